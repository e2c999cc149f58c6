//! Leases: any call on a session renews its lease, an open stream holds it while it moves (a stream
//! whose client takes nothing for `limits.unread_stream_timeout_s` no longer does), and the reaper
//! closes a session whose lease expired.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::watch;

use super::{Entry, SessionManager};
use crate::error::CoreError;
use crate::principal::Principal;

/// When a session was last used, and what keeps it in use now: any call on it renews the lease, an
/// open stream or shared-stepping channel holds it.
#[derive(Debug)]
pub struct Lease {
    /// Milliseconds after the manager's start.
    pub(super) last_used_ms: AtomicU64,
    pub(super) holds: AtomicUsize,
    /// When a holder last moved (a batch taken by its client), milliseconds after the manager's start.
    pub(super) progress_ms: AtomicU64,
    /// Turns true when the session is closed, for what holds the lease (streams, shared-stepping channels).
    pub(super) closed: watch::Sender<bool>,
}

impl Lease {
    pub(super) fn new(now_ms: u64) -> Lease {
        Lease {
            last_used_ms: AtomicU64::new(now_ms),
            holds: AtomicUsize::new(0),
            progress_ms: AtomicU64::new(now_ms),
            closed: watch::Sender::new(false),
        }
    }
}

/// A stream's hold on its session's lease: the session is not reaped while one exists.
#[derive(Debug)]
pub struct LeaseHold {
    lease: Arc<Lease>,
    clock: Instant,
}

impl LeaseHold {
    /// Resolves once the session is closed (by its client, its lease or shutdown): what holds it
    /// should end and free what it has.
    /// The future owns its subscription: a long-lived holder makes it once and polls it again and
    /// again (a shared-stepping channel, between requests).
    pub fn session_closed(&self) -> impl std::future::Future<Output = ()> + Send + 'static {
        let mut closed = self.lease.closed.subscribe();
        async move {
            // An error means the lease is gone, which only happens once the session is.
            let _ = closed.wait_for(|closed| *closed).await;
        }
    }

    /// A handle that marks this hold's progress (a batch taken), for the part of a stream that
    /// sends; a hold whose progress stops for `limits.unread_stream_timeout_s` stops holding.
    pub fn progress(&self) -> Progress {
        Progress { lease: self.lease.clone(), clock: self.clock }
    }
}

/// Marks a lease hold's progress; see [`LeaseHold::progress`].
#[derive(Clone, Debug)]
pub struct Progress {
    lease: Arc<Lease>,
    clock: Instant,
}

impl Progress {
    pub fn mark(&self) {
        self.lease.progress_ms.store(elapsed_ms(self.clock), Ordering::Relaxed);
    }
}

impl Drop for LeaseHold {
    fn drop(&mut self) {
        self.lease.last_used_ms.store(elapsed_ms(self.clock), Ordering::Relaxed);
        self.lease.holds.fetch_sub(1, Ordering::AcqRel);
    }
}

pub(super) fn elapsed_ms(clock: Instant) -> u64 {
    clock.elapsed().as_millis() as u64
}

impl SessionManager {
    /// Keep the session's lease alive for as long as the returned hold lives (a stream on it).
    pub fn hold(&self, caller: &Principal, session_id: &str) -> Result<LeaseHold, CoreError> {
        let registry = self.sessions.lock().expect("registry lock");
        let entry = self.touch(&registry, caller, session_id)?;
        entry.lease.progress_ms.store(elapsed_ms(self.clock), Ordering::Relaxed);
        entry.lease.holds.fetch_add(1, Ordering::AcqRel);
        Ok(LeaseHold { lease: entry.lease.clone(), clock: self.clock })
    }

    /// The idle time after which a session is reaped (None: never).
    pub fn idle_timeout(&self) -> Option<Duration> {
        (self.limits.session_idle_timeout_s > 0).then(|| Duration::from_secs(self.limits.session_idle_timeout_s))
    }

    /// Closes every session whose lease expired: no open stream, and no call for longer than the
    /// idle timeout. Returns the ids closed.
    pub async fn reap_idle(&self) -> Vec<String> {
        let Some(timeout) = self.idle_timeout() else { return Vec::new() };
        // Chosen and removed under one lock: a call cannot renew a lease between the two.
        let expired: Vec<(String, Entry, Duration)> = {
            let mut registry = self.sessions.lock().expect("registry lock");
            let ids: Vec<String> =
                registry.sessions.iter().filter(|(_, entry)| self.idle(entry) > timeout).map(|(id, _)| id.clone()).collect();
            ids.into_iter()
                .filter_map(|id| {
                    let entry = registry.sessions.remove(&id)?;
                    let idle = self.idle(&entry);
                    Some((id, entry, idle))
                })
                .collect()
        };
        let mut reaped = Vec::new();
        for (id, entry, idle) in expired {
            let reason = format!(
                "its lease expired: no call and no stream read for {} s (limits.session_idle_timeout_s = {})",
                idle.as_secs(),
                timeout.as_secs()
            );
            self.close_entry(&id, entry, &reason, false).await;
            reaped.push(id);
        }
        reaped
    }

    /// Reaps idle sessions until the manager is dropped or shut down, checking a few times per
    /// timeout.
    pub async fn run_reaper(self: Arc<Self>) {
        let Some(timeout) = self.idle_timeout() else { return };
        let period = (timeout / 4).clamp(Duration::from_millis(100), Duration::from_secs(10));
        loop {
            tokio::time::sleep(period).await;
            if self.sessions.lock().expect("registry lock").closing {
                return;
            }
            self.reap_idle().await;
        }
    }

    /// How long nothing has used the session: zero while a stream holds it and moved within
    /// `limits.unread_stream_timeout_s`; a held session whose holders stalled longer than that is
    /// idle since its last call or its holders' last progress, whichever came later.
    pub(super) fn idle(&self, entry: &Entry) -> Duration {
        let now = elapsed_ms(self.clock);
        let used = entry.lease.last_used_ms.load(Ordering::Relaxed);
        let mut since = used;
        if entry.lease.holds.load(Ordering::Acquire) > 0 {
            let progress = entry.lease.progress_ms.load(Ordering::Relaxed);
            let unread_bound = self.limits.unread_stream_timeout_s.saturating_mul(1000);
            if unread_bound == 0 || now.saturating_sub(progress) <= unread_bound {
                return Duration::ZERO;
            }
            since = used.max(progress);
        }
        Duration::from_millis(now.saturating_sub(since))
    }
}
