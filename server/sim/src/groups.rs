//! The worker pool as the core's [`Simulators`]: a session's envs in contiguous groups on the least
//! loaded workers, each group's frames in a [`MemFile`] its worker maps, and the catalog asked of a
//! transient worker at the lowest CPU priority.

use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};

use async_trait::async_trait;
use radserve_core::catalog::{engine_is_envpool, native_async_groups, OptionValue};
use radserve_core::{
    EnvGroup, EnvId, EnvNames, EnvSpec, FrameLayout, Infos, Options, PendingStep, SimulatorError, Simulators, StepResult,
};
use radserve_shm::MemFile;

use crate::pool::{await_generation, WorkerFault, WorkerHandle, WorkerPool};
use crate::protocol::{GroupConfig, PassedFd, Request, Response};

/// Group ids are unique in the server (a worker hosts groups of many sessions).
static NEXT_GROUP: AtomicU64 = AtomicU64::new(1);

/// One group of a session's envs in one worker.
pub struct WorkerGroup {
    worker: WorkerHandle,
    id: u64,
    envs: Range<usize>,
    frames: MemFile,
    /// The worker process generation whose envs this group's session follows: a step is refused by
    /// a newer process (which rebuilt the group unreset), and the session ends those episodes.
    generation: u64,
}

#[async_trait]
impl EnvGroup for WorkerGroup {
    fn envs(&self) -> Range<usize> {
        self.envs.clone()
    }

    fn frames(&self) -> &[u8] {
        self.frames.as_slice()
    }

    async fn reset(&mut self, seeds: Option<Vec<u64>>, mask: Option<Vec<bool>>) -> Result<Infos, SimulatorError> {
        match await_generation(self.worker.submit(Request::Reset { group: self.id, seeds, mask }).await).await {
            Ok((Response::Reset(infos), generation)) => {
                self.generation = generation;
                Ok(infos)
            }
            other => Err(unexpected(other)),
        }
    }

    async fn async_reset(&mut self, seeds: Option<Vec<u64>>) -> Result<(), SimulatorError> {
        match await_generation(self.worker.submit(Request::AsyncReset { group: self.id, seeds }).await).await {
            Ok((Response::Sent, generation)) => {
                self.generation = generation;
                Ok(())
            }
            other => Err(unexpected(other)),
        }
    }

    async fn send(&mut self, actions: Vec<u8>, sent: Vec<bool>) -> Result<(), SimulatorError> {
        // A newer process rebuilt the group unreset: its envs' steps in flight are gone (lost group).
        let request = Request::Send { group: self.id, actions, sent };
        match await_generation(self.worker.submit_in(request, self.generation).await).await {
            Ok((Response::Sent, _)) => Ok(()),
            other => Err(unexpected(other)),
        }
    }

    async fn send_recv(&mut self, actions: Vec<u8>, sent: Vec<bool>) -> Result<(Vec<bool>, StepResult), SimulatorError> {
        let request = Request::SendRecv { group: self.id, actions, sent };
        match await_generation(self.worker.submit_in(request, self.generation).await).await {
            Ok((Response::Received { ready, result }, _)) => Ok((ready, result)),
            other => Err(unexpected(other)),
        }
    }

    async fn recv(&mut self) -> Result<(Vec<bool>, StepResult), SimulatorError> {
        match await_generation(self.worker.submit_in(Request::Recv { group: self.id }, self.generation).await).await {
            Ok((Response::Received { ready, result }, _)) => Ok((ready, result)),
            other => Err(unexpected(other)),
        }
    }

    async fn step(&mut self, actions: Vec<u8>, skip: Option<Vec<bool>>) -> Result<StepResult, SimulatorError> {
        // Refused by a newer process of the worker: the group was rebuilt there (another session's
        // step crashed it, or it was stuck), which the session sees as a lost group.
        let request = Request::Step { group: self.id, actions, skip };
        match await_generation(self.worker.submit_in(request, self.generation).await).await {
            Ok((Response::Stepped(result), _)) => Ok(result),
            other => Err(unexpected(other)),
        }
    }

    async fn start_step(&mut self, actions: Vec<u8>) -> PendingStep {
        // Queued to the worker now; the answer is awaited by whoever polls the returned future.
        let request = Request::Step { group: self.id, actions, skip: None };
        let answer = self.worker.submit_in(request, self.generation).await;
        Box::pin(async move {
            match await_generation(answer).await {
                Ok((Response::Stepped(result), _)) => Ok(result),
                other => Err(unexpected(other)),
            }
        })
    }

    async fn close(&mut self) {
        let _ = self.worker.call(Request::CloseGroup { group: self.id }).await;
        self.worker.remove_hosted_envs(self.envs.len());
    }
}

/// A worker's answer that is not the one asked for, as the core sees it.
fn unexpected(reply: Result<(Response, u64), WorkerFault>) -> SimulatorError {
    match reply {
        Ok((Response::Failed(message), _)) => SimulatorError::Failed(message),
        Ok((other, _)) => SimulatorError::Failed(format!("unexpected worker response {other:?}")),
        Err(WorkerFault::Crashed(message)) => SimulatorError::Lost(message),
        Err(WorkerFault::Unavailable(message)) => SimulatorError::Unavailable(message),
    }
}

/// `total` items over `parts` contiguous ranges whose sizes differ by at most one.
fn split_evenly(total: usize, parts: usize) -> Vec<Range<usize>> {
    let parts = parts.clamp(1, total.max(1));
    let (base, extra) = (total / parts, total % parts);
    let mut start = 0;
    (0..parts)
        .map(|part| {
            let len = base + usize::from(part < extra);
            let range = start..start + len;
            start += len;
            range
        })
        .collect()
}

impl WorkerPool {
    /// A request to a transient worker (the catalog's), which is killed after it answered.
    async fn transient_call(&self, request: Request) -> Result<Response, SimulatorError> {
        let mut worker = self
            .spawn_transient()
            .await
            .map_err(|err| SimulatorError::Unavailable(format!("cannot start a catalog worker: {err}")))?;
        match worker.call_within(&request, self.create_timeout()).await {
            Ok(Response::Failed(message)) => Err(SimulatorError::Failed(message)),
            Ok(response) => Ok(response),
            Err(err) => Err(SimulatorError::Unavailable(format!("catalog worker failed: {err}"))),
        }
    }

    /// Closes groups built for a session that could not be completed.
    async fn close_all(groups: Vec<(WorkerHandle, u64)>) {
        for (worker, group) in groups {
            let _ = worker.call(Request::CloseGroup { group }).await;
        }
    }
}

#[async_trait]
impl Simulators for WorkerPool {
    fn processes(&self) -> usize {
        self.len()
    }

    fn overdue(&self, after: std::time::Duration) -> Vec<usize> {
        self.overdue_workers(after)
    }

    async fn env_names(&self) -> Result<EnvNames, SimulatorError> {
        let response = self.transient_call(Request::ListNames).await?;
        if let Response::Names(names) = response {
            return Ok(names);
        }
        Err(unexpected(Ok((response, 0))))
    }

    async fn env_specs(&self, envs: Vec<(EnvId, Options)>) -> Result<Vec<Result<EnvSpec, String>>, SimulatorError> {
        let entries = envs.into_iter().map(|(id, options)| (id.family, id.name, options)).collect();
        let response = self.transient_call(Request::Specs { entries }).await?;
        if let Response::Specs(specs) = response {
            return Ok(specs);
        }
        Err(unexpected(Ok((response, 0))))
    }

    async fn create_groups(
        &self,
        env: &EnvId,
        options: &Options,
        seeds: Vec<u64>,
    ) -> Result<(EnvSpec, Vec<Box<dyn EnvGroup>>), SimulatorError> {
        // engine="envpool": one worker hosts the session and EnvPool's own threads, one per worker process
        // of the pool, step its envs in parallel (radserve_worker/envpool_engine.py reads `envpool_threads`). One pipe
        // round trip per step instead of one per worker: HalfCheetah x16 ran 20-30% faster than split
        // over two workers of one EnvPool thread each (docs/performance.md, "The EnvPool engine").
        let envpool = engine_is_envpool(options);
        let mut options = options.clone();
        if envpool {
            options.insert("envpool_threads".into(), OptionValue::Int(self.len() as i64));
        }
        // The native engine's asynchronous mode steps groups of batch_size envs whole (the session
        // keeps one in flight while it reads another): the groups go round the least loaded workers.
        let groups = native_async_groups(&options, seeds.len());
        let workers = self.least_loaded(match &groups {
            _ if envpool => 1,
            Some(groups) => groups.len(),
            None => seeds.len(),
        });
        let ranges = groups.unwrap_or_else(|| split_evenly(seeds.len(), workers.len()));
        let mut pending = Vec::new();
        for (worker, envs) in workers.iter().cycle().zip(&ranges) {
            let group = NEXT_GROUP.fetch_add(1, Ordering::Relaxed);
            let request = Request::CreateGroup(GroupConfig {
                group,
                family: env.family,
                name: env.name.clone(),
                options: options.clone(),
                seeds: seeds[envs.clone()].to_vec(),
            });
            pending.push((worker.clone(), group, envs.clone(), worker.submit(request).await));
        }
        let mut created = Vec::new();
        let mut failure = None;
        let mut spec = None;
        for (worker, group, envs, receiver) in pending {
            match await_generation(receiver).await {
                Ok((Response::Created(group_spec), generation)) => {
                    spec.get_or_insert(group_spec);
                    created.push((worker, group, envs, generation));
                }
                Ok((Response::Failed(message), _)) => {
                    failure.get_or_insert(SimulatorError::Refused(message));
                }
                other => {
                    failure.get_or_insert(unexpected(other));
                }
            }
        }
        let built = || created.iter().map(|(worker, group, ..)| (worker.clone(), *group)).collect::<Vec<_>>();
        if let Some(error) = failure {
            WorkerPool::close_all(built()).await;
            return Err(error);
        }
        let spec = spec.expect("at least one group");
        let layout = FrameLayout { frame_bytes: spec.observation.num_bytes() };

        let mut groups = Vec::new();
        for (worker, id, envs, generation) in &created {
            match MemFile::create(c"radserve-frames", layout.memory_len(envs.len())) {
                Ok(frames) => groups.push(WorkerGroup {
                    worker: worker.clone(),
                    id: *id,
                    envs: envs.clone(),
                    frames,
                    generation: *generation,
                }),
                Err(err) => {
                    WorkerPool::close_all(built()).await;
                    return Err(SimulatorError::allocation("allocating the session's shared frames", &err));
                }
            }
        }
        let mut attached = Vec::new();
        for group in &groups {
            let memory = match group.frames.fd().try_clone_to_owned() {
                Ok(fd) => PassedFd::new(fd),
                Err(err) => {
                    WorkerPool::close_all(built()).await;
                    return Err(SimulatorError::allocation("passing the session's shared frames", &err));
                }
            };
            let request = Request::Attach { group: group.id, shm_len: group.frames.len(), memory };
            attached.push(group.worker.submit(request).await);
        }
        for group in &groups {
            group.worker.add_hosted_envs(group.envs.len());
        }
        let mut groups: Vec<Box<dyn EnvGroup>> = groups.into_iter().map(|group| Box::new(group) as Box<dyn EnvGroup>).collect();
        for receiver in attached {
            match await_generation(receiver).await {
                Ok((Response::Attached, _)) => {}
                other => {
                    for group in &mut groups {
                        group.close().await;
                    }
                    return Err(unexpected(other));
                }
            }
        }
        Ok((spec, groups))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn envs_split_evenly_over_workers() {
        assert_eq!(split_evenly(5, 2), vec![0..3, 3..5]);
        assert_eq!(split_evenly(1, 4), vec![0..1]);
        assert_eq!(split_evenly(4, 4), vec![0..1, 1..2, 2..3, 3..4]);
    }
}
