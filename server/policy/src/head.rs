//! The action heads: what turns a model's outputs into actions, sampled in the server with the
//! actor's seeded generator (the model itself stays deterministic).
//!
//! - `gaussian_tanh` (SAC, RAD-SAC, DrQ): outputs `mean` and `log_std` [B, A]; the action is
//!   tanh(mean + std * eps) scaled to the action bounds; evaluation acts with tanh(mean). The
//!   log-probability has the tanh correction of Haarnoja et al. 2018 (appendix C). log_std is
//!   clamped to [-20, 2], as the SAC references do, so that exp() stays finite.
//! - `categorical` (PPO, discrete SAC): output `logits` [B, n] and optionally `value` [B] or [B, 1];
//!   the action is drawn from softmax(logits); evaluation takes the argmax.
//! - `deterministic_noise` (DrQ-v2, TD3): output `action` [B, A] in [-1, 1]; the action adds
//!   Gaussian noise of a linearly scheduled std clipped to +-clip (DrQ-v2's `stddev_schedule` and
//!   `stddev_clip`), clamped to [-1, 1] and scaled to the bounds; evaluation acts without noise.

use rand::Rng;

/// log_std's range, as SAC's references clamp it.
pub const LOG_STD_RANGE: (f32, f32) = (-20.0, 2.0);

/// How a model's outputs become actions.
#[derive(Clone, Debug, PartialEq)]
pub enum Head {
    GaussianTanh,
    Categorical,
    /// The noise's std goes linearly from `std_start` to `std_end` over `std_steps` env steps of the
    /// session, then stays at `std_end`; each draw is clipped to +-`clip`.
    DeterministicNoise { std_start: f32, std_end: f32, std_steps: u64, clip: f32 },
}

impl Head {
    pub fn name(&self) -> &'static str {
        match self {
            Head::GaussianTanh => "gaussian_tanh",
            Head::Categorical => "categorical",
            Head::DeterministicNoise { .. } => "deterministic_noise",
        }
    }

    /// The outputs the model must have, in order, and the optional one after them.
    pub fn outputs(&self) -> (&'static [&'static str], Option<&'static str>) {
        match self {
            Head::GaussianTanh => (&["mean", "log_std"], None),
            Head::Categorical => (&["logits"], Some("value")),
            Head::DeterministicNoise { .. } => (&["action"], None),
        }
    }

    /// The noise std of the deterministic head after `steps` env steps.
    pub fn noise_std(&self, steps: u64) -> f32 {
        match self {
            Head::DeterministicNoise { std_start, std_end, std_steps, .. } => {
                let mix = if *std_steps == 0 { 1.0 } else { (steps as f64 / *std_steps as f64).min(1.0) as f32 };
                std_start + (std_end - std_start) * mix
            }
            Head::GaussianTanh | Head::Categorical => 0.0,
        }
    }
}

/// A standard normal draw (Box-Muller; two uniforms per draw keeps the stream simple to replay).
pub fn normal(rng: &mut impl Rng) -> f32 {
    let u1: f64 = rng.random::<f64>().max(f64::MIN_POSITIVE);
    let u2: f64 = rng.random::<f64>();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

const HALF_LN_TAU: f32 = 0.918_938_5;

/// One env's tanh-squashed Gaussian action in [-1, 1] and its log-probability.
pub fn gaussian_tanh(mean: &[f32], log_std: &[f32], rng: &mut impl Rng, eval: bool, out: &mut [f32]) -> f32 {
    let mut log_prob = 0.0;
    for (i, slot) in out.iter_mut().enumerate() {
        let log_std = log_std[i].clamp(LOG_STD_RANGE.0, LOG_STD_RANGE.1);
        let eps = if eval { 0.0 } else { normal(rng) };
        let action = (mean[i] + log_std.exp() * eps).tanh();
        *slot = action;
        log_prob += -0.5 * eps * eps - log_std - HALF_LN_TAU - (1.0 - action * action + 1e-6).ln();
    }
    log_prob
}

/// One env's categorical action and its log-probability.
pub fn categorical(logits: &[f32], rng: &mut impl Rng, eval: bool) -> (usize, f32) {
    let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let total: f32 = logits.iter().map(|logit| (logit - max).exp()).sum();
    let log_total = total.ln() + max;
    let choice = if eval {
        logits.iter().enumerate().fold(0, |best, (i, logit)| if *logit > logits[best] { i } else { best })
    } else {
        let mut draw = rng.random::<f32>() * total;
        let mut choice = logits.len() - 1;
        for (i, logit) in logits.iter().enumerate() {
            draw -= (logit - max).exp();
            if draw < 0.0 {
                choice = i;
                break;
            }
        }
        choice
    };
    (choice, logits[choice] - log_total)
}

/// One env's deterministic action with clipped Gaussian noise, in [-1, 1].
pub fn deterministic_noise(action: &[f32], std: f32, clip: f32, rng: &mut impl Rng, eval: bool, out: &mut [f32]) {
    for (slot, mean) in out.iter_mut().zip(action) {
        let noise = if eval { 0.0 } else { (normal(rng) * std).clamp(-clip, clip) };
        *slot = (mean + noise).clamp(-1.0, 1.0);
    }
}

/// A value in [-1, 1] mapped onto [low, high].
pub fn scale(unit: f32, low: f64, high: f64) -> f64 {
    low + (f64::from(unit) + 1.0) * 0.5 * (high - low)
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand_chacha::ChaCha8Rng;

    use super::*;

    #[test]
    fn tanh_gaussian_matches_its_density() {
        // Monte-Carlo check of the log-probability: E[exp(-log_prob)] over samples is the volume of
        // the support (2 for one dimension in [-1, 1]).
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut out = [0.0f32];
        let n = 200_000;
        let mut volume = 0.0f64;
        for _ in 0..n {
            let log_prob = gaussian_tanh(&[0.3], &[-0.5], &mut rng, false, &mut out);
            assert!((-1.0..=1.0).contains(&out[0]));
            volume += f64::from((-log_prob).exp());
        }
        let volume = volume / n as f64;
        assert!((volume - 2.0).abs() < 0.05, "estimated support volume {volume}");
        assert!(gaussian_tanh(&[0.3], &[-0.5], &mut rng, true, &mut out).is_finite());
        assert!((out[0] - 0.3f32.tanh()).abs() < 1e-6);
    }

    #[test]
    fn log_std_is_clamped() {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let mut out = [0.0f32; 2];
        let log_prob = gaussian_tanh(&[0.0, 0.0], &[1e9, -1e9], &mut rng, false, &mut out);
        assert!(!log_prob.is_nan());
        assert!(out.iter().all(|a| a.is_finite()));
    }

    #[test]
    fn categorical_draws_follow_the_softmax() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let logits = [0.0f32, 1.0, 2.0];
        let mut counts = [0usize; 3];
        for _ in 0..60_000 {
            let (choice, log_prob) = categorical(&logits, &mut rng, false);
            counts[choice] += 1;
            let expected = logits[choice] - logits.iter().map(|l| l.exp()).sum::<f32>().ln();
            assert!((log_prob - expected).abs() < 1e-5);
        }
        let total: f32 = logits.iter().map(|l| l.exp()).sum();
        for (i, count) in counts.iter().enumerate() {
            let share = *count as f32 / 60_000.0;
            assert!((share - logits[i].exp() / total).abs() < 0.01, "action {i}: {share}");
        }
        assert_eq!(categorical(&[0.5, 3.0, -1.0], &mut rng, true).0, 1);
    }

    #[test]
    fn noise_follows_the_schedule_and_the_clip() {
        let head = Head::DeterministicNoise { std_start: 1.0, std_end: 0.1, std_steps: 100, clip: 0.3 };
        assert_eq!(head.noise_std(0), 1.0);
        assert!((head.noise_std(50) - 0.55).abs() < 1e-6);
        assert!((head.noise_std(1000) - 0.1).abs() < 1e-6);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let mut out = [0.0f32; 1];
        let mut largest = 0.0f32;
        for _ in 0..10_000 {
            deterministic_noise(&[0.0], 1.0, 0.3, &mut rng, false, &mut out);
            largest = largest.max(out[0].abs());
        }
        assert!((largest - 0.3).abs() < 1e-6, "noise reached {largest}");
        deterministic_noise(&[0.9], 1.0, 0.3, &mut rng, false, &mut out);
        assert!(out[0] <= 1.0);
        deterministic_noise(&[0.25], 1.0, 0.3, &mut rng, true, &mut out);
        assert_eq!(out[0], 0.25);
    }

    #[test]
    fn scaling_maps_the_unit_interval_onto_the_bounds() {
        assert_eq!(scale(-1.0, -2.0, 4.0), -2.0);
        assert_eq!(scale(1.0, -2.0, 4.0), 4.0);
        assert_eq!(scale(0.0, -2.0, 4.0), 1.0);
    }
}
