//! Simulators in plain Rust, for tests of everything above them: sessions, stacking, autoreset,
//! replay recording, recovery, limits, and the transports.
//!
//! One env id, `gym/Fake-v0`: a 2x2 single-channel uint8 image whose bytes say where the env is, so a
//! test can tell which frame it is looking at ([`frame`]): byte 0 is the env's seed (mod 256), byte 1
//! its episode, byte 2 the step within the episode, byte 3 [`MARK`]. Actions are `Discrete(3)`; the
//! reward of action a is a + 1. Env j of seed s ends its episode after `3 + s % 3` steps, as
//! terminated in even episodes and truncated in odd ones, so a few steps see both kinds of end at
//! different times in different envs. Autoreset is the same-step kind the core expects: the ending
//! step writes the episode's last frame as the final frame and the next episode's first frame as
//! the current one, as the workers do.
//!
//! Faults are injected through [`FakeSimulators`]: a create the simulator refuses, a step whose
//! group is lost (its process died: the envs are rebuilt unreset), an env whose simulator raises.

use std::collections::BTreeMap;
use std::ops::Range;
use std::sync::{Arc, Mutex};

use async_trait::async_trait;

use crate::catalog::{EnvId, EnvNames, Family, Options};
use crate::infos::{InfoColumn, Infos};
use crate::simulators::{EnvGroup, EnvSpec, FrameLayout, SimulatorError, Simulators, StepResult};
use crate::space::{DType, Space};

/// The fake env's id.
pub const FAKE_ENV: &str = "gym/Fake-v0";
/// Byte 3 of every fake frame (a zeroed frame never passes for one).
pub const MARK: u8 = 0xA5;
/// Bytes of one fake frame.
pub const FRAME_BYTES: usize = 4;

/// The frame of an env of seed `seed` at step `t` of episode `episode`.
pub fn frame(seed: u64, episode: u64, t: u64) -> [u8; FRAME_BYTES] {
    [seed as u8, episode as u8, t as u8, MARK]
}

/// How many steps the episodes of an env seeded `seed` last.
pub fn episode_length(seed: u64) -> u64 {
    3 + seed % 3
}

/// Whether episode `episode` ends as terminated (else truncated).
pub fn ends_terminated(episode: u64) -> bool {
    episode.is_multiple_of(2)
}

fn spec() -> EnvSpec {
    EnvSpec {
        observation: Space::Box { dtype: DType::Uint8, shape: vec![1, 2, 2], low: vec![0.0], high: vec![255.0] },
        action: Space::Discrete { n: 3 },
    }
}

/// Faults to inject, shared by the simulators and every group they built.
#[derive(Debug, Default)]
struct Faults {
    refuse_create: Option<String>,
    /// Session env indices whose group loses its process in its next step.
    lose_group_of: Vec<usize>,
    /// Session env indices whose simulator raises in its next step.
    raise_in: Vec<usize>,
    fail_next_step: Option<String>,
    /// Processes reported as stuck in a call (`overdue`).
    overdue: Vec<usize>,
    groups_alive: usize,
    /// env_names waits on this until it is closed (a server still listing its envs).
    catalog_gate: Option<Arc<tokio::sync::Semaphore>>,
    /// env_names fails this many more times.
    fail_env_names: usize,
    /// create_groups calls that reached the simulators (refused ones included).
    creates: usize,
    steps: u64,
}

/// The fake simulators: `processes` groups at most per session.
#[derive(Clone)]
pub struct FakeSimulators {
    processes: usize,
    faults: Arc<Mutex<Faults>>,
}

impl FakeSimulators {
    pub fn new(processes: usize) -> Arc<FakeSimulators> {
        Arc::new(FakeSimulators { processes: processes.max(1), faults: Arc::default() })
    }

    fn faults(&self) -> std::sync::MutexGuard<'_, Faults> {
        self.faults.lock().expect("fake faults lock")
    }

    /// Reports these processes as stuck in a call (a worker that stopped answering), or none.
    pub fn set_overdue(&self, processes: Vec<usize>) {
        self.faults().overdue = processes;
    }

    /// The next create is refused with `message` (as a simulator refuses bad options).
    pub fn refuse_next_create(&self, message: &str) {
        self.faults().refuse_create = Some(message.to_string());
    }

    /// The group hosting session env `env` loses its process in its next step.
    pub fn lose_group_of(&self, env: usize) {
        self.faults().lose_group_of.push(env);
    }

    /// Session env `env`'s simulator raises in its next step.
    pub fn raise_in(&self, env: usize) {
        self.faults().raise_in.push(env);
    }

    /// The next step of any group fails (the simulator answered nonsense).
    pub fn fail_next_step(&self, message: &str) {
        self.faults().fail_next_step = Some(message.to_string());
    }

    /// Listing the env names (the start of the catalog) waits until `release_catalog`.
    pub fn hold_catalog(&self) {
        self.faults().catalog_gate = Some(Arc::new(tokio::sync::Semaphore::new(0)));
    }

    /// Lets a held env listing go on.
    pub fn release_catalog(&self) {
        if let Some(gate) = self.faults().catalog_gate.take() {
            gate.close();
        }
    }

    /// The next `times` env listings fail (the workers could not import their simulators).
    pub fn fail_env_names(&self, times: usize) {
        self.faults().fail_env_names = times;
    }

    /// Groups built and not closed.
    pub fn groups_alive(&self) -> usize {
        self.faults().groups_alive
    }

    /// How often the core asked the simulators to build envs (refused requests included).
    pub fn creates(&self) -> usize {
        self.faults().creates
    }

    /// Group steps taken so far.
    pub fn steps(&self) -> u64 {
        self.faults().steps
    }
}

#[async_trait]
impl Simulators for FakeSimulators {
    fn processes(&self) -> usize {
        self.processes
    }

    fn overdue(&self, _after: std::time::Duration) -> Vec<usize> {
        self.faults().overdue.clone()
    }

    async fn env_names(&self) -> Result<EnvNames, SimulatorError> {
        let gate = self.faults().catalog_gate.clone();
        if let Some(gate) = gate {
            let _closed = gate.acquire().await;
        }
        {
            let mut faults = self.faults();
            if faults.fail_env_names > 0 {
                faults.fail_env_names -= 1;
                return Err(SimulatorError::Unavailable("fake: the workers could not list their envs".into()));
            }
        }
        let mut names = EnvNames::default();
        for family in Family::ALL {
            names.by_family.insert(family, Vec::new());
        }
        names.by_family.insert(Family::Gym, vec!["Fake-v0".to_string()]);
        Ok(names)
    }

    async fn env_specs(&self, envs: Vec<(EnvId, Options)>) -> Result<Vec<Result<EnvSpec, String>>, SimulatorError> {
        Ok(envs.iter().map(|_| Ok(spec())).collect())
    }

    async fn create_groups(
        &self,
        _env: &EnvId,
        options: &Options,
        seeds: Vec<u64>,
    ) -> Result<(EnvSpec, Vec<Box<dyn EnvGroup>>), SimulatorError> {
        let batch = crate::catalog::async_batch(options, seeds.len()).unwrap_or(0);
        let native_groups = crate::catalog::native_async_groups(options, seeds.len());
        self.faults().creates += 1;
        if let Some(message) = self.faults().refuse_create.take() {
            return Err(SimulatorError::Refused(message));
        }
        let mut groups: Vec<Box<dyn EnvGroup>> = Vec::new();
        if let Some(ranges) = native_groups {
            // The native engine's asynchronous mode: synchronous groups of `batch` envs, as groups.rs builds.
            for envs in ranges {
                groups.push(Box::new(FakeGroup::new(envs.clone(), seeds[envs].to_vec(), self.faults.clone(), 0)));
            }
            self.faults().groups_alive += groups.len();
            return Ok((spec(), groups));
        }
        let parts = self.processes.min(seeds.len()).max(1);
        let (base, extra) = (seeds.len() / parts, seeds.len() % parts);
        let mut start = 0;
        for part in 0..parts {
            let envs = start..start + base + usize::from(part < extra);
            start = envs.end;
            groups.push(Box::new(FakeGroup::new(envs.clone(), seeds[envs].to_vec(), self.faults.clone(), batch)));
        }
        self.faults().groups_alive += groups.len();
        Ok((spec(), groups))
    }
}

#[derive(Clone, Copy, Debug)]
struct FakeEnv {
    seed: u64,
    episode: u64,
    t: u64,
    /// Reset since it was built: an unseeded reset starts the next episode (before the first one,
    /// episode 0 of the seed it was built with).
    started: bool,
}

struct FakeGroup {
    envs: Range<usize>,
    state: Vec<FakeEnv>,
    frames: Vec<u8>,
    layout: FrameLayout,
    /// Lost since its last reset: steps are refused until the core resets it.
    lost: bool,
    faults: Arc<Mutex<Faults>>,
    /// Asynchronous mode (option batch_size below the envs; 0: synchronous): envs a recv returns.
    batch: usize,
    /// Asynchronous mode: envs reset (None) or sent an action, in order; recv takes from the front.
    in_flight: Vec<(usize, Option<i64>)>,
}

impl FakeGroup {
    fn new(envs: Range<usize>, seeds: Vec<u64>, faults: Arc<Mutex<Faults>>, batch: usize) -> FakeGroup {
        let layout = FrameLayout { frame_bytes: FRAME_BYTES };
        FakeGroup {
            frames: vec![0; layout.memory_len(envs.len())],
            state: seeds.into_iter().map(|seed| FakeEnv { seed, episode: 0, t: 0, started: false }).collect(),
            envs,
            layout,
            lost: false,
            faults,
            batch,
            in_flight: Vec::new(),
        }
    }

    fn write(&mut self, local: usize, final_frame: bool, bytes: [u8; FRAME_BYTES]) {
        let range = if final_frame { self.layout.final_frame(local) } else { self.layout.frame(local) };
        self.frames[range].copy_from_slice(&bytes);
    }

    /// Env `local` takes a step with `action`: reward action + 1, its episode ends at its seed's
    /// length (the last frame in the final slot, the next episode's first in the current one).
    fn step_env(&mut self, local: usize, action: i64, result: &mut StepResult) {
        result.rewards[local] = action as f64 + 1.0;
        self.state[local].t += 1;
        let env = self.state[local];
        fake_info(&mut result.step_infos, local, "t", env.t);
        if env.t == episode_length(env.seed) {
            result.terminated[local] = ends_terminated(env.episode);
            result.truncated[local] = !ends_terminated(env.episode);
            let last = self.current(local);
            self.write(local, true, last);
            self.state[local] = FakeEnv { episode: env.episode + 1, t: 0, ..env };
            fake_info(&mut result.reset_infos, local, "episode", env.episode + 1);
        }
        let current = self.current(local);
        self.write(local, false, current);
    }

    fn current(&self, local: usize) -> [u8; FRAME_BYTES] {
        let env = self.state[local];
        frame(env.seed, env.episode, env.t)
    }
}

#[async_trait]
impl EnvGroup for FakeGroup {
    fn envs(&self) -> Range<usize> {
        self.envs.clone()
    }

    fn frames(&self) -> &[u8] {
        &self.frames
    }

    async fn reset(&mut self, seeds: Option<Vec<u64>>, mask: Option<Vec<bool>>) -> Result<Infos, SimulatorError> {
        let mut infos = Infos::default();
        for local in 0..self.state.len() {
            if mask.as_ref().is_some_and(|mask| !mask[local]) {
                continue;
            }
            let env = &mut self.state[local];
            match &seeds {
                Some(seeds) => *env = FakeEnv { seed: seeds[local], episode: 0, t: 0, started: true },
                None if !env.started => *env = FakeEnv { episode: 0, t: 0, started: true, ..*env },
                // An unseeded reset continues the env's stream: a new episode.
                None => *env = FakeEnv { episode: env.episode + 1, t: 0, ..*env },
            }
            let current = self.current(local);
            self.write(local, false, current);
            fake_info(&mut infos, local, "episode", self.state[local].episode);
        }
        self.lost = false;
        Ok(infos)
    }

    async fn step(&mut self, actions: Vec<u8>, skip: Option<Vec<bool>>) -> Result<StepResult, SimulatorError> {
        let (lose, raise, fail) = {
            let mut faults = self.faults.lock().expect("fake faults lock");
            faults.steps += 1;
            let envs = self.envs.clone();
            let lose = faults.lose_group_of.iter().any(|env| envs.contains(env));
            faults.lose_group_of.retain(|env| !envs.contains(env));
            let raise: Vec<usize> = faults.raise_in.iter().filter(|env| envs.contains(env)).map(|env| env - envs.start).collect();
            faults.raise_in.retain(|env| !envs.contains(env));
            (lose, raise, faults.fail_next_step.take())
        };
        if let Some(message) = fail {
            return Err(SimulatorError::Failed(message));
        }
        if lose || self.lost {
            // The process is gone; a new one rebuilt the envs from their seeds, not reset.
            for env in &mut self.state {
                *env = FakeEnv { episode: 0, t: 0, started: false, ..*env };
            }
            self.lost = true;
            return Err(SimulatorError::Lost("fake worker died".to_string()));
        }
        let n = self.state.len();
        assert_eq!(actions.len(), n * 8, "the core sends one int64 action per env");
        let mut result = StepResult {
            rewards: vec![0.0; n],
            terminated: vec![false; n],
            truncated: vec![false; n],
            ..StepResult::default()
        };
        for local in 0..n {
            if skip.as_ref().is_some_and(|skip| skip[local]) {
                continue;
            }
            let action = i64::from_le_bytes(actions[local * 8..][..8].try_into().expect("8 bytes"));
            if raise.contains(&local) {
                result.errors.push((local as u32, "FakeError: the simulator raised".to_string()));
                result.truncated[local] = true;
                let last = self.current(local);
                self.write(local, true, last);
                let env = &mut self.state[local];
                *env = FakeEnv { episode: env.episode + 1, t: 0, ..*env };
                let first = self.current(local);
                self.write(local, false, first);
                continue;
            }
            self.step_env(local, action, &mut result);
        }
        Ok(result)
    }

    async fn async_reset(&mut self, seeds: Option<Vec<u64>>) -> Result<(), SimulatorError> {
        if self.batch == 0 {
            return Err(SimulatorError::Refused("this fake group steps synchronously".into()));
        }
        self.reset(seeds, None).await?;
        // The first frames are written now and returned by recv, last env first.
        self.in_flight = (0..self.state.len()).rev().map(|local| (local, None)).collect();
        Ok(())
    }

    async fn send(&mut self, actions: Vec<u8>, sent: Vec<bool>) -> Result<(), SimulatorError> {
        for (local, _) in sent.iter().enumerate().filter(|(_, &sent)| sent) {
            let action = i64::from_le_bytes(actions[local * 8..][..8].try_into().expect("8 bytes"));
            self.in_flight.push((local, Some(action)));
        }
        Ok(())
    }

    async fn recv(&mut self) -> Result<(Vec<bool>, StepResult), SimulatorError> {
        let n = self.state.len();
        let mut ready = vec![false; n];
        let mut result =
            StepResult { rewards: vec![0.0; n], terminated: vec![false; n], truncated: vec![false; n], ..StepResult::default() };
        // First sent, first done; after an async reset the last env first: envs come back in another
        // order than the session's, as EnvPool's do.
        for (local, action) in self.in_flight.drain(..self.batch.min(self.in_flight.len())).collect::<Vec<_>>() {
            ready[local] = true;
            if let Some(action) = action {
                self.step_env(local, action, &mut result);
            }
        }
        Ok((ready, result))
    }

    async fn close(&mut self) {
        self.faults.lock().expect("fake faults lock").groups_alive -= 1;
    }
}

/// Adds env `local`'s info `{"fake_<name>": value}` (a Python int) to `infos`, as a worker reports
/// it; envs are added in ascending order.
fn fake_info(infos: &mut Infos, local: usize, name: &str, value: u64) {
    let column = InfoColumn::python_ints(&[&format!("fake_{name}")], vec![local as u32], &[value as i64]);
    infos.append(&Infos { columns: vec![column] }, 0, |_| true);
}

/// Options for a fake session: `frame_stack` frames per observation.
pub fn fake_options(frame_stack: i64) -> Options {
    BTreeMap::from([(crate::catalog::FRAME_STACK.to_string(), crate::catalog::OptionValue::Int(frame_stack))])
}
