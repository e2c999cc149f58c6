//! The server-wide memory budget: every allocation a request causes (a session's envs and frame
//! buffers, replay, sample streams, shared-stepping channels) is reserved here before it is made, and
//! refused with RESOURCE_EXHAUSTED and the numbers when the budget cannot hold it. A reservation is
//! returned when it is dropped (the session closed, the stream ended).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use crate::catalog::{EnvId, Family, OptionValue, Options};
use crate::error::CoreError;

const MIB: u64 = 1 << 20;

/// What one environment costs in a worker beyond its frames, by family: what `bench/env_memory.py`
/// prints (a worker's RSS after N envs minus after one, over N), rounded up. A dm_control pixel env
/// is its physics, a GL context and MuJoCo's render buffers, which grow with the frame.
pub fn env_cost_bytes(env: &EnvId, options: &Options) -> u64 {
    match env.family {
        Family::Dmc => match options.get("pixels") {
            Some(OptionValue::Bool(false)) => 16 * MIB,
            // Render buffers grow with the frame: MuJoCo's offscreen buffer and the GL surfaces.
            _ => 96 * MIB + 16 * pixel_bytes(options),
        },
        Family::Gym => 2 * MIB,
        Family::Procgen => MIB,
    }
}

fn pixel_bytes(options: &Options) -> u64 {
    let side = |name: &str| options.get(name).and_then(OptionValue::as_int).unwrap_or(100).max(0) as u64;
    side("height") * side("width") * 3
}

/// Each worker's own memory before any env (an interpreter with the simulators imported, the
/// "first env" `bench/env_memory.py` prints), rounded up and kept out of the derived budget.
pub const WORKER_BASELINE_BYTES: u64 = 512 * MIB;

/// The default budget: three quarters of the memory this process may use (the host's, or its
/// cgroup's limit when lower), less every worker's baseline, and at least 1 GiB.
pub fn default_budget_bytes(workers: usize) -> u64 {
    let usable = available_memory_bytes() / 4 * 3;
    usable.saturating_sub(WORKER_BASELINE_BYTES * workers as u64).max(1 << 30)
}

/// The host's memory (MemTotal), or the cgroup's limit when one is set and lower (containers).
pub fn available_memory_bytes() -> u64 {
    let host = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|text| {
            let line = text.lines().find(|line| line.starts_with("MemTotal:"))?;
            line.split_whitespace().nth(1)?.parse::<u64>().ok()
        })
        .map_or(8 << 30, |kib| kib * 1024);
    let cgroup = ["/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"]
        .iter()
        .filter_map(|path| read_limit(Path::new(path)))
        .min();
    cgroup.map_or(host, |limit| limit.min(host))
}

fn read_limit(path: &Path) -> Option<u64> {
    std::fs::read_to_string(path).ok()?.trim().parse().ok()
}

#[derive(Debug)]
pub struct MemoryBudget {
    limit: u64,
    used: AtomicU64,
    /// Whose budget this is, for messages: None for the server's, a principal's name for its quota.
    owner: Option<Arc<str>>,
}

/// Bytes held against the budget until dropped (and against a principal's quota too, when the
/// reservation was made for one).
#[derive(Debug)]
pub struct Reservation {
    budget: Arc<MemoryBudget>,
    bytes: u64,
    quota: Option<Box<Reservation>>,
}

impl Reservation {
    pub fn bytes(&self) -> u64 {
        self.bytes
    }
}

impl Drop for Reservation {
    fn drop(&mut self) {
        self.budget.used.fetch_sub(self.bytes, Ordering::AcqRel);
    }
}

impl MemoryBudget {
    pub fn new(limit: u64) -> Arc<MemoryBudget> {
        Arc::new(MemoryBudget { limit, used: AtomicU64::new(0), owner: None })
    }

    /// A principal's memory quota (`memory_bytes` in its entry of the tokens file).
    pub fn quota(limit: u64, principal: Arc<str>) -> Arc<MemoryBudget> {
        Arc::new(MemoryBudget { limit, used: AtomicU64::new(0), owner: Some(principal) })
    }

    pub fn limit(&self) -> u64 {
        self.limit
    }

    pub fn used(&self) -> u64 {
        self.used.load(Ordering::Acquire)
    }

    /// Reserve `bytes` for `what` (a phrase such as "8 envs of dmc/cheetah-run at 96 MiB each"), or
    /// say why not. Check and reservation are one atomic step.
    pub fn try_reserve(self: &Arc<Self>, bytes: u64, what: &str) -> Result<Reservation, CoreError> {
        let limit = self.limit;
        self.used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |used| used.checked_add(bytes).filter(|&total| total <= limit))
            .map(|_| Reservation { budget: self.clone(), bytes, quota: None })
            .map_err(|used| {
                // What is left of the server's budget is memory (OutOfMemory); of a principal's
                // quota, a configured limit (OverLimit).
                let (owner, budget, setting, short): (String, &str, &str, fn(String) -> CoreError) = match &self.owner {
                    None => ("this server's".into(), "memory budget", "limits.memory_bytes", CoreError::OutOfMemory),
                    Some(principal) => {
                        (format!("principal '{principal}'s"), "memory quota", "memory_bytes in its tokens file entry", CoreError::OverLimit)
                    }
                };
                let needs = format!("{what} needs {} of memory", human(bytes));
                if bytes > limit {
                    return CoreError::TooLarge(format!("{needs}, more than {owner} whole {budget} of {} ({setting})", human(limit)));
                }
                short(format!("{needs}; {} of {owner} {budget} of {} is reserved already ({setting})", human(used), human(limit)))
            })
    }

    /// Reserve `bytes` against `quota` (a principal's, if it has one) and this budget, both or
    /// neither.
    pub fn try_reserve_within(
        self: &Arc<Self>,
        quota: Option<&Arc<MemoryBudget>>,
        bytes: u64,
        what: &str,
    ) -> Result<Reservation, CoreError> {
        let quota = quota.map(|quota| quota.try_reserve(bytes, what)).transpose()?;
        let mut reservation = self.try_reserve(bytes, what)?;
        reservation.quota = quota.map(Box::new);
        Ok(reservation)
    }
}

/// Bytes for a message: "1.50 GiB", "96.0 MiB", "512 bytes".
pub fn human(bytes: u64) -> String {
    if bytes >= 1 << 30 {
        format!("{:.2} GiB", bytes as f64 / (1u64 << 30) as f64)
    } else if bytes >= MIB {
        format!("{:.1} MiB", bytes as f64 / MIB as f64)
    } else {
        format!("{bytes} bytes")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reservations_fit_the_limit_and_return_when_dropped() {
        let budget = MemoryBudget::new(100 * MIB);
        let first = budget.try_reserve(60 * MIB, "a").unwrap();
        let refused = budget.try_reserve(50 * MIB, "8 envs of dmc/cheetah-run").unwrap_err().to_string();
        assert_eq!(
            refused,
            "8 envs of dmc/cheetah-run needs 50.0 MiB of memory; 60.0 MiB of this server's memory budget of 100.0 MiB \
             is reserved already (limits.memory_bytes)"
        );
        assert!(budget.try_reserve(u64::MAX, "everything").is_err(), "no overflow");
        let second = budget.try_reserve(40 * MIB, "b").unwrap();
        assert_eq!(budget.used(), 100 * MIB);
        drop((first, second));
        assert_eq!(budget.used(), 0);
    }

    #[test]
    fn pixel_envs_cost_more_and_grow_with_the_frame() {
        let cheetah = EnvId { family: Family::Dmc, name: "cheetah-run".into() };
        let defaults = crate::catalog::default_options(&cheetah);
        let mut large = defaults.clone();
        large.insert("height".into(), OptionValue::Int(1024));
        large.insert("width".into(), OptionValue::Int(1024));
        let mut state = defaults.clone();
        state.insert("pixels".into(), OptionValue::Bool(false));
        assert!(env_cost_bytes(&cheetah, &large) > env_cost_bytes(&cheetah, &defaults));
        assert!(env_cost_bytes(&cheetah, &defaults) > env_cost_bytes(&cheetah, &state));
        assert!(available_memory_bytes() > 0);
        assert!(default_budget_bytes(2) >= 1 << 30);
    }
}
