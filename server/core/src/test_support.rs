//! What core's tests share: a manager over the fake simulators with a small budget, and the calls
//! they make of it (create, reset, step).

use std::sync::Arc;

use crate::error::CoreError;
use crate::fake::{self, FakeSimulators, FAKE_ENV};
use crate::manager::{Limits, SessionExtras, SessionManager};
use crate::principal::Principal;
use crate::session::StepOutcome;
use crate::space::DType;

/// A small memory budget, so that budget tests need few sessions (the fake's envs cost 2 MiB each).
pub(crate) const BUDGET: u64 = 64 << 20;

pub(crate) fn limits() -> Limits {
    Limits { memory_bytes: BUDGET, session_idle_timeout_s: 0, ..Limits::default() }
}

pub(crate) fn local() -> Principal {
    Principal::local()
}

pub(crate) fn manager(processes: usize, limits: Limits) -> (Arc<FakeSimulators>, SessionManager) {
    let simulators = FakeSimulators::new(processes);
    (simulators.clone(), SessionManager::new(simulators, limits))
}

pub(crate) async fn create(manager: &SessionManager, num_envs: usize, seed: u64, frame_stack: i64, extras: SessionExtras) -> String {
    let info = manager.create_session(&local(), FAKE_ENV, num_envs, seed, &fake::fake_options(frame_stack), &extras).await.unwrap();
    info.session_id
}

pub(crate) fn actions(values: &[i64]) -> Vec<u8> {
    values.iter().flat_map(|value| value.to_le_bytes()).collect()
}

pub(crate) async fn step(manager: &SessionManager, id: &str, values: &[i64]) -> Result<StepOutcome, CoreError> {
    let session = manager.get(&local(), id).unwrap();
    let mut session = session.lock().await;
    session.step(DType::Int64, &[values.len()], &actions(values)).await
}

pub(crate) async fn reset(manager: &SessionManager, id: &str, seed: Option<u64>) -> Vec<u8> {
    manager.get(&local(), id).unwrap().lock().await.reset(seed).await.unwrap()
}

