//! Reverb's `SampleToInsertRatio` rate limiter, one for both sides of a buffer: a sample stream
//! waits in [`RateLimiter::can_sample`], the server-side actor in [`RateLimiter::can_insert`], and
//! both are woken by the buffer's [`Activity`] (each insert and each sampled batch), never by a timer.
//!
//! The semantics follow Reverb (`reverb/rate_limiters.py` `SampleToInsertRatio`, `reverb/cc/
//! rate_limiter.cc` `CanInsert`/`CanSample`): below `min_size` transitions inserts are free and
//! sampling waits; from there on the error `inserts * samples_per_insert - samples` is kept within
//! `samples_per_insert * min_size ± error_buffer`, so that only the operations after the warm-up
//! count towards the ratio. Reverb inserts and samples one item per call; here an actor's step inserts
//! one transition per env and a stream samples a batch, so each check takes a count.
//!
//! Neither side can hold the other for ever when `2 * error_buffer >= batch_size + num_envs *
//! samples_per_insert` (Reverb's `error_buffer >= max(1, samples_per_insert)` for one-item calls);
//! with less, an actor and a stream may both wait, each for the other.

use std::sync::{Condvar, Mutex};
use std::time::Duration;

use crate::buffer::ReplayCounters;

/// Reverb's `SampleToInsertRatio`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RateLimiter {
    /// Transitions the buffer holds before sampling may start (inserts are free until then).
    pub min_size: u64,
    /// The average number of times each transition is sampled.
    pub samples_per_insert: f64,
    /// How far samples and inserts may drift from the ratio before either side waits.
    pub error_buffer: f64,
}

/// What the limiter reads from a buffer: its counters and the transitions it holds now.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Occupancy {
    pub inserts: u64,
    pub samples: u64,
    /// Transitions held (Reverb's `inserts - deletes`).
    pub size: u64,
}

impl Occupancy {
    pub fn of(counters: ReplayCounters, size: usize) -> Occupancy {
        Occupancy { inserts: counters.inserts, samples: counters.samples, size: size as u64 }
    }
}

impl RateLimiter {
    /// Checks the settings: a positive ratio, an error buffer of at least 0.
    pub fn new(min_size: u64, samples_per_insert: f64, error_buffer: f64) -> Result<RateLimiter, String> {
        if !(samples_per_insert.is_finite() && samples_per_insert > 0.0 && error_buffer.is_finite() && error_buffer >= 0.0) {
            return Err(format!(
                "samples_per_insert must be a positive number and error_buffer at least 0; got {samples_per_insert} and {error_buffer}"
            ));
        }
        Ok(RateLimiter { min_size, samples_per_insert, error_buffer })
    }

    /// The band the error `inserts * samples_per_insert - samples` is kept in.
    fn band(&self) -> (f64, f64) {
        let offset = self.samples_per_insert * self.min_size as f64;
        (offset - self.error_buffer, offset + self.error_buffer)
    }

    /// Whether `count` more inserts keep within the limit.
    pub fn can_insert(&self, now: Occupancy, count: u64) -> bool {
        if now.size + count <= self.min_size {
            return true;
        }
        let error = (now.inserts + count) as f64 * self.samples_per_insert - now.samples as f64;
        error <= self.band().1
    }

    /// Whether `count` more samples keep within the limit (and the buffer holds `min_size`).
    pub fn can_sample(&self, now: Occupancy, count: u64) -> bool {
        if now.size < self.min_size.max(1) {
            return false;
        }
        let error = now.inserts as f64 * self.samples_per_insert - now.samples as f64 - count as f64;
        error >= self.band().0
    }
}

/// What a buffer signals to the waiters on its rate limiter: a generation bumped by every insert and
/// every sampled batch, for threads (a condition variable) and tasks (a `Notify`) alike.
#[derive(Debug, Default)]
pub struct Activity {
    generation: Mutex<u64>,
    changed: Condvar,
    notify: tokio::sync::Notify,
}

impl Activity {
    /// Something changed the buffer's counters: wake every waiter to check again.
    pub fn bump(&self) {
        *self.generation.lock().expect("activity lock") += 1;
        self.changed.notify_all();
        self.notify.notify_waiters();
    }

    /// Blocks the thread until `ready()` holds (true), or until `keep_going()` turns false (false),
    /// which is looked at every `check_every` and after every change.
    pub fn wait_blocking(&self, mut ready: impl FnMut() -> bool, keep_going: impl Fn() -> bool, check_every: Duration) -> bool {
        loop {
            let seen = *self.generation.lock().expect("activity lock");
            if ready() {
                return true;
            }
            if !keep_going() {
                return false;
            }
            let generation = self.generation.lock().expect("activity lock");
            // Woken by a change, or after `check_every` to look at keep_going.
            drop(self.changed.wait_timeout_while(generation, check_every, |now| *now == seen).expect("activity lock"));
        }
    }

    /// Waits until `ready()` holds; a caller that must stop meanwhile drops the future.
    pub async fn wait(&self, mut ready: impl FnMut() -> bool) {
        loop {
            let notified = self.notify.notified();
            tokio::pin!(notified);
            // Registered before the check: a change between the check and the await still wakes it.
            notified.as_mut().enable();
            if ready() {
                return;
            }
            notified.await;
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::sync::{Arc, Mutex};
    use std::time::Duration;

    use super::{Activity, Occupancy, RateLimiter};

    fn at(inserts: u64, samples: u64) -> Occupancy {
        Occupancy { inserts, samples, size: inserts }
    }

    #[test]
    fn settings_are_checked() {
        assert!(RateLimiter::new(10, 0.0, 1.0).unwrap_err().contains("samples_per_insert must be a positive number"));
        assert!(RateLimiter::new(10, f64::NAN, 1.0).is_err());
        assert!(RateLimiter::new(10, 1.0, -1.0).is_err());
        assert!(RateLimiter::new(10, 1.0, f64::INFINITY).is_err());
        assert!(RateLimiter::new(0, 0.5, 0.0).is_ok());
    }

    #[test]
    fn inserts_are_free_until_min_size_and_sampling_waits_for_it() {
        let limiter = RateLimiter::new(100, 4.0, 8.0).unwrap();
        assert!(limiter.can_insert(at(0, 0), 100));
        assert!(!limiter.can_sample(at(99, 0), 1));
        // At min_size the error is the offset: 8 of slack for samples, 8 for inserts (2 of them).
        assert!(limiter.can_sample(at(100, 0), 8));
        assert!(!limiter.can_sample(at(100, 0), 9));
        assert!(limiter.can_insert(at(100, 0), 2));
        assert!(!limiter.can_insert(at(100, 0), 3));
    }

    #[test]
    fn the_ratio_counts_only_what_follows_min_size() {
        // Reverb's offset: 1,000 warm-up inserts at 2 samples per insert give no credit of 2,000
        // samples; 10 inserts after them give 20 (with no slack).
        let limiter = RateLimiter::new(1000, 2.0, 0.0).unwrap();
        assert!(!limiter.can_sample(at(1000, 0), 1));
        assert!(limiter.can_sample(at(1010, 0), 20));
        assert!(!limiter.can_sample(at(1010, 0), 21));
        // With no slack the next insert waits until the learner has sampled its 2 ahead.
        assert!(!limiter.can_insert(at(1010, 20), 1));
        assert!(limiter.can_insert(at(1010, 22), 1));
    }

    #[test]
    fn size_not_inserts_decides_the_stage() {
        // A buffer that dropped transitions (a rollout cleared, a small capacity) is back in the
        // warm-up while it holds fewer than min_size, as Reverb's inserts - deletes.
        let limiter = RateLimiter::new(50, 1.0, 0.0).unwrap();
        let refilling = Occupancy { inserts: 500, samples: 10_000, size: 10 };
        assert!(limiter.can_insert(refilling, 40));
        assert!(!limiter.can_sample(refilling, 1));
    }

    #[test]
    fn a_blocking_waiter_wakes_on_a_bump_and_leaves_when_told() {
        let activity = Arc::new(Activity::default());
        let value = Arc::new(AtomicU64::new(0));
        let waiter = {
            let (activity, value) = (activity.clone(), value.clone());
            // An hour between looks at keep_going: only a bump can wake it in time.
            std::thread::spawn(move || activity.wait_blocking(|| value.load(Ordering::SeqCst) == 3, || true, Duration::from_secs(3600)))
        };
        for _ in 0..3 {
            std::thread::sleep(Duration::from_millis(20));
            value.fetch_add(1, Ordering::SeqCst);
            activity.bump();
        }
        assert!(waiter.join().unwrap());
        let leave = Arc::new(AtomicBool::new(false));
        let waiter = {
            let (activity, leave) = (activity.clone(), leave.clone());
            std::thread::spawn(move || activity.wait_blocking(|| false, || !leave.load(Ordering::SeqCst), Duration::from_millis(5)))
        };
        leave.store(true, Ordering::SeqCst);
        assert!(!waiter.join().unwrap());
    }

    #[tokio::test]
    async fn an_async_waiter_wakes_on_a_bump() {
        let activity = Arc::new(Activity::default());
        let value = Arc::new(AtomicU64::new(0));
        let waiter = {
            let (activity, value) = (activity.clone(), value.clone());
            tokio::spawn(async move { activity.wait(|| value.load(Ordering::SeqCst) == 2).await })
        };
        for _ in 0..2 {
            tokio::time::sleep(Duration::from_millis(10)).await;
            value.fetch_add(1, Ordering::SeqCst);
            activity.bump();
        }
        tokio::time::timeout(Duration::from_secs(60), waiter).await.expect("woken").unwrap();
    }

    /// An actor inserting `num_envs` at a time and a learner sampling batches, each on a thread of
    /// its own, each waiting on the other through the limiter: the error never leaves its band,
    /// neither side stalls, and the ratio holds over the run.
    #[test]
    fn the_bound_holds_under_concurrent_insert_and_sample() {
        let (num_envs, batch, ratio, slack) = (4u64, 32u64, 8.0, 64.0);
        assert!(2.0 * slack >= batch as f64 + num_envs as f64 * ratio, "a setting that cannot deadlock");
        let limiter = RateLimiter::new(200, ratio, slack).unwrap();
        let counters = Arc::new(Mutex::new(at(0, 0)));
        let activity = Arc::new(Activity::default());
        let (low, high) = limiter.band();
        let check = move |now: Occupancy| {
            if now.size >= limiter.min_size {
                let error = now.inserts as f64 * ratio - now.samples as f64;
                assert!(error >= low - 1e-9 && error <= high + 1e-9, "error {error} left [{low}, {high}] at {now:?}");
            }
        };
        let inserter = {
            let (counters, activity) = (counters.clone(), activity.clone());
            std::thread::spawn(move || {
                for _ in 0..2_000 {
                    assert!(activity.wait_blocking(|| limiter.can_insert(*counters.lock().unwrap(), num_envs), || true, Duration::from_secs(60)));
                    let mut now = counters.lock().unwrap();
                    assert!(limiter.can_insert(*now, num_envs), "only this thread inserts");
                    now.inserts += num_envs;
                    now.size += num_envs;
                    check(*now);
                    drop(now);
                    activity.bump();
                }
            })
        };
        loop {
            // The learner also looks every 10 ms at whether the actor has finished.
            let ready = || limiter.can_sample(*counters.lock().unwrap(), batch) || inserter.is_finished();
            assert!(activity.wait_blocking(ready, || true, Duration::from_millis(10)));
            let mut now = counters.lock().unwrap();
            if !limiter.can_sample(*now, batch) {
                break; // the actor is done and the learner has drawn its share
            }
            now.samples += batch;
            check(*now);
            drop(now);
            activity.bump();
        }
        inserter.join().unwrap();
        let now = *counters.lock().unwrap();
        assert_eq!(now.inserts, 8_000);
        let after_warmup = (now.inserts - limiter.min_size) as f64 * ratio;
        assert!((now.samples as f64 - after_warmup).abs() <= slack + batch as f64, "{now:?}");
    }
}
