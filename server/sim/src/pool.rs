//! Worker processes as seen from the server: each is driven by one actor task that owns its pipes,
//! handles requests in order, and replaces the process when it dies.

use std::collections::{BTreeMap, HashSet};
use std::io;
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::process::{Child, ChildStdin, ChildStdout, Command};
use tokio::sync::{mpsc, oneshot};
use tracing::{info, warn};

use crate::protocol::{self, Request, Response};
use crate::worker::GlBackend;

/// How to start a worker: the same binary in its `worker` mode.
#[derive(Clone, Debug)]
pub struct WorkerLauncher {
    pub program: PathBuf,
    pub venv: PathBuf,
    pub gl: GlBackend,
}

/// The niceness of the catalog worker: the catalog is built in the background at start-up (about 14 s
/// of one core: every task is loaded once for its spaces), and on a small host it must not take CPU
/// from the workers that serve sessions. At niceness 19 it gets what they leave.
const BACKGROUND_NICENESS: libc::c_int = 19;

impl WorkerLauncher {
    pub async fn spawn(&self) -> io::Result<WorkerProcess> {
        let mut child = Command::new(&self.program)
            .arg("worker")
            .arg("--venv")
            .arg(&self.venv)
            .arg("--gl")
            .arg(self.gl.name())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true)
            .spawn()?;
        let stdin = child.stdin.take().expect("stdin is piped");
        let stdout = child.stdout.take().expect("stdout is piped");
        Ok(WorkerProcess { child, stdin, stdout, registration: None })
    }
}

pub struct WorkerProcess {
    child: Child,
    stdin: ChildStdin,
    stdout: ChildStdout,
    /// A transient worker's entry among the pool's, removed when the process is dropped (killed).
    registration: Option<Registration>,
}

/// Pids of the transient workers alive now, for `WorkerPool::kill_all`.
type TransientPids = Arc<std::sync::Mutex<HashSet<u32>>>;

struct Registration {
    pids: TransientPids,
    pid: u32,
}

impl Drop for Registration {
    fn drop(&mut self) {
        self.pids.lock().expect("transient pid lock").remove(&self.pid);
    }
}

impl WorkerProcess {
    /// Sends one request and waits for its response. An I/O error means the worker is gone.
    pub async fn call(&mut self, request: &Request) -> io::Result<Response> {
        self.stdin.write_all(&protocol::encode(request)?).await?;
        self.stdin.flush().await?;
        let mut header = [0u8; 4];
        self.stdout.read_exact(&mut header).await?;
        let mut body = vec![0u8; protocol::check_length(header)?];
        self.stdout.read_exact(&mut body).await?;
        protocol::decode(&body)
    }

    pub fn pid(&self) -> Option<u32> {
        self.child.id()
    }

    /// Kills the process if it still runs and says how it ended.
    async fn reap(mut self) -> String {
        let _ = self.child.start_kill();
        match self.child.wait().await {
            Ok(status) => status.to_string(),
            Err(err) => format!("unknown status ({err})"),
        }
    }
}

/// Why a request got no response from a worker.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WorkerFault {
    /// The worker died while handling the request. It has been replaced, and the groups it hosted were
    /// built again (unreset) in the new process.
    Crashed(String),
    /// No worker process could be started.
    Unavailable(String),
}

struct Job {
    request: Request,
    reply: oneshot::Sender<Result<Response, WorkerFault>>,
}

/// A handle on one worker's actor; cheap to clone.
#[derive(Clone)]
pub struct WorkerHandle {
    index: usize,
    jobs: mpsc::Sender<Job>,
    state: Arc<WorkerState>,
}

#[derive(Default)]
struct WorkerState {
    hosted_envs: AtomicUsize,
    pid: AtomicU32,
    restarts: AtomicU64,
}

impl WorkerHandle {
    pub fn index(&self) -> usize {
        self.index
    }

    /// Queues a request; the returned receiver resolves when the worker has answered. Queue requests to
    /// several workers before awaiting any of them to run them in parallel.
    pub async fn submit(&self, request: Request) -> oneshot::Receiver<Result<Response, WorkerFault>> {
        let (reply, receiver) = oneshot::channel();
        if let Err(mpsc::error::SendError(job)) = self.jobs.send(Job { request, reply }).await {
            let _ = job.reply.send(Err(WorkerFault::Unavailable("the worker pool has stopped".into())));
        }
        receiver
    }

    pub async fn call(&self, request: Request) -> Result<Response, WorkerFault> {
        await_reply(self.submit(request).await).await
    }

    pub fn hosted_envs(&self) -> usize {
        self.state.hosted_envs.load(Ordering::Relaxed)
    }

    pub fn add_hosted_envs(&self, count: usize) {
        self.state.hosted_envs.fetch_add(count, Ordering::Relaxed);
    }

    pub fn remove_hosted_envs(&self, count: usize) {
        self.state.hosted_envs.fetch_sub(count, Ordering::Relaxed);
    }

    /// The current process id (0 before the first start).
    pub fn pid(&self) -> u32 {
        self.state.pid.load(Ordering::Relaxed)
    }

    pub fn restarts(&self) -> u64 {
        self.state.restarts.load(Ordering::Relaxed)
    }
}

pub async fn await_reply(receiver: oneshot::Receiver<Result<Response, WorkerFault>>) -> Result<Response, WorkerFault> {
    receiver.await.unwrap_or_else(|_| Err(WorkerFault::Unavailable("the worker pool has stopped".into())))
}

pub struct WorkerPool {
    workers: Vec<WorkerHandle>,
    launcher: WorkerLauncher,
    transient: TransientPids,
}

impl WorkerPool {
    /// Starts `count` workers (at least one) in the background; requests wait for their start.
    pub fn start(launcher: WorkerLauncher, count: usize) -> WorkerPool {
        let workers = (0..count.max(1))
            .map(|index| {
                let (jobs, receiver) = mpsc::channel(256);
                let state = Arc::new(WorkerState::default());
                tokio::spawn(run_actor(index, launcher.clone(), receiver, state.clone()));
                WorkerHandle { index, jobs, state }
            })
            .collect();
        WorkerPool { workers, launcher, transient: TransientPids::default() }
    }

    pub fn len(&self) -> usize {
        self.workers.len()
    }

    pub fn is_empty(&self) -> bool {
        self.workers.is_empty()
    }

    pub fn workers(&self) -> &[WorkerHandle] {
        &self.workers
    }

    /// Kills every worker process now (SIGKILL), for an exit that cannot wait for them.
    pub fn kill_all(&self) {
        let transient: Vec<u32> = self.transient.lock().expect("transient pid lock").iter().copied().collect();
        for pid in self.workers.iter().map(WorkerHandle::pid).chain(transient) {
            if pid > 0 {
                // SAFETY: kill only reads its integer arguments; the pid is this pool's child (a
                // process that already exited and was reaped makes it fail with ESRCH).
                unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
            }
        }
    }

    /// The `count` workers hosting the fewest environments, least loaded first.
    pub fn least_loaded(&self, count: usize) -> Vec<WorkerHandle> {
        let mut workers = self.workers.clone();
        workers.sort_by_key(|worker| (worker.hosted_envs(), worker.index));
        workers.truncate(count.clamp(1, self.workers.len()));
        workers
    }

    /// A worker outside the pool for a one-off background job (the catalog), at the lowest CPU priority;
    /// dropped (killed) when done.
    pub async fn spawn_transient(&self) -> io::Result<WorkerProcess> {
        let mut worker = self.launcher.spawn().await?;
        if let Some(pid) = worker.pid() {
            self.transient.lock().expect("transient pid lock").insert(pid);
            worker.registration = Some(Registration { pids: self.transient.clone(), pid });
            // SAFETY: setpriority only reads its integer arguments. The worker was just spawned and is
            // owned (kill_on_drop) by `worker`, so the pid names it. Python threads it starts later
            // inherit the niceness.
            let failed = unsafe { libc::setpriority(libc::PRIO_PROCESS, pid, BACKGROUND_NICENESS) } != 0;
            if failed {
                warn!(pid, error = %io::Error::last_os_error(), "could not lower the catalog worker's priority");
            }
        }
        Ok(worker)
    }
}

async fn run_actor(index: usize, launcher: WorkerLauncher, mut jobs: mpsc::Receiver<Job>, state: Arc<WorkerState>) {
    // The requests that built each hosted group, replayed into a replacement process.
    let mut replay: BTreeMap<u64, Vec<Request>> = BTreeMap::new();
    let mut process = start(index, &launcher, &state, &replay).await.ok();
    while let Some(job) = jobs.recv().await {
        if process.is_none() {
            match start(index, &launcher, &state, &replay).await {
                Ok(started) => process = Some(started),
                Err(err) => {
                    let _ = job.reply.send(Err(WorkerFault::Unavailable(format!("cannot start worker {index}: {err}"))));
                    continue;
                }
            }
        }
        let worker = process.as_mut().expect("started above");
        match worker.call(&job.request).await {
            Ok(response) => {
                remember(&mut replay, &job.request, &response);
                let _ = job.reply.send(Ok(response));
            }
            Err(err) => {
                let status = process.take().expect("present").reap().await;
                warn!(worker = index, error = %err, status = %status, "worker died, replacing it");
                state.restarts.fetch_add(1, Ordering::Relaxed);
                if let Request::CloseGroup { group } = &job.request {
                    replay.remove(group);
                }
                process = start(index, &launcher, &state, &replay).await.ok();
                let fault = format!("simulator worker {index} died ({status}); it was restarted");
                let _ = job.reply.send(Err(WorkerFault::Crashed(fault)));
            }
        }
    }
}

async fn start(
    index: usize,
    launcher: &WorkerLauncher,
    state: &WorkerState,
    replay: &BTreeMap<u64, Vec<Request>>,
) -> io::Result<WorkerProcess> {
    let mut process = launcher.spawn().await.inspect_err(|err| warn!(worker = index, error = %err, "cannot start worker"))?;
    state.pid.store(process.pid().unwrap_or(0), Ordering::Relaxed);
    info!(worker = index, pid = process.pid().unwrap_or(0), groups = replay.len(), "worker started");
    for (group, requests) in replay {
        for request in requests {
            match process.call(request).await {
                Ok(Response::Failed(message)) => warn!(worker = index, group, %message, "could not rebuild group"),
                Ok(_) => {}
                Err(err) => return Err(err),
            }
        }
    }
    Ok(process)
}

fn remember(replay: &mut BTreeMap<u64, Vec<Request>>, request: &Request, response: &Response) {
    match (request, response) {
        (Request::CreateGroup(config), Response::Created(_)) => {
            replay.insert(config.group, vec![request.clone()]);
        }
        (Request::Attach { group, .. }, Response::Attached) => {
            if let Some(requests) = replay.get_mut(group) {
                requests.truncate(1);
                requests.push(request.clone());
            }
        }
        (Request::CloseGroup { group }, _) => {
            replay.remove(group);
        }
        _ => {}
    }
}
