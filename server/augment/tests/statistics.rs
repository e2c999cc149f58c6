//! The empirical rates and ranges of every random parameter match the specification. Tolerances
//! are five standard errors, so a correct sampler fails about once in a few million runs; draws are
//! seeded, so these tests are deterministic anyway.

#![allow(clippy::wildcard_enum_match_arm, reason = "a test's match names what it expects; anything else fails the test")]

use std::collections::HashMap;

use radserve_augment::{Draws, FrameShape, ImagePlan, JitterOp, Pipeline, StageParams, StatePlan, CONV_WEIGHT_STD};

const DRAWS: u64 = 20_000;

fn params(text: &str, shape: FrameShape) -> Vec<StageParams> {
    let plan = ImagePlan::new(&Pipeline::parse(text).unwrap(), shape).unwrap();
    let draws = Draws::new(2020);
    (0..DRAWS).map(|key| plan.draw(&draws, key).remove(0)).collect()
}

fn assert_rate(label: &str, hits: usize, trials: usize, p: f64) {
    let rate = hits as f64 / trials as f64;
    let standard_error = (p * (1.0 - p) / trials as f64).sqrt();
    assert!((rate - p).abs() <= 5.0 * standard_error, "{label}: rate {rate:.4}, expected {p}");
}

/// Each value of `low..=high` appears at its uniform rate, and nothing outside.
fn assert_uniform_integers(label: &str, values: &[usize], low: usize, high: usize) {
    let mut counts: HashMap<usize, usize> = HashMap::new();
    for value in values {
        *counts.entry(*value).or_default() += 1;
    }
    assert!(counts.keys().all(|v| (low..=high).contains(v)), "{label}: values outside [{low}, {high}]: {counts:?}");
    let p = 1.0 / (high - low + 1) as f64;
    for value in low..=high {
        assert_rate(&format!("{label} = {value}"), counts.get(&value).copied().unwrap_or(0), values.len(), p);
    }
}

fn assert_uniform_reals(label: &str, values: &[f32], low: f32, high: f32) {
    assert!(values.iter().all(|v| (low..=high).contains(v)), "{label}: outside [{low}, {high}]");
    let n = values.len() as f64;
    let mean = values.iter().map(|v| f64::from(*v)).sum::<f64>() / n;
    let spread = f64::from(high - low);
    let expected_mean = f64::from(low + high) / 2.0;
    assert!((mean - expected_mean).abs() <= 5.0 * spread / (12.0 * n).sqrt(), "{label}: mean {mean}");
    // Each decile of the range holds a tenth of the draws.
    let deciles: Vec<usize> = (0..10)
        .map(|d| values.iter().filter(|v| ((f64::from(**v - low) / spread * 10.0) as usize).min(9) == d).count())
        .collect();
    for (decile, count) in deciles.iter().enumerate() {
        assert_rate(&format!("{label} decile {decile}"), *count, values.len(), 0.1);
    }
}

const FRAME: FrameShape = FrameShape::new(3, 3, 100, 100);

#[test]
fn probabilities_fire_at_their_rate() {
    for (text, p) in [("grayscale", 0.3), ("flip", 0.2), ("grayscale(p=0.9)", 0.9), ("flip(p=0)", 0.0), ("flip(p=1)", 1.0)] {
        let fired = params(text, FRAME).iter().filter(|p| **p == StageParams::Apply(true)).count();
        assert_rate(text, fired, DRAWS as usize, p);
    }
    let quarters: Vec<usize> = params("rotate", FRAME)
        .iter()
        .map(|p| match p {
            StageParams::Quarters(q) => usize::from(*q),
            other => panic!("{other:?}"),
        })
        .collect();
    assert_rate("rotate fires", quarters.iter().filter(|q| **q > 0).count(), quarters.len(), 0.3);
    let turned: Vec<usize> = quarters.into_iter().filter(|q| *q > 0).collect();
    assert_uniform_integers("rotate quarters", &turned, 1, 3);
}

fn offsets(text: &str) -> (Vec<usize>, Vec<usize>) {
    params(text, FRAME)
        .iter()
        .map(|p| match p {
            StageParams::Offset { top, left } => (*top, *left),
            other => panic!("{other:?}"),
        })
        .unzip()
}

#[test]
fn offsets_are_uniform_over_every_position() {
    for (text, high) in [("crop(84)", 16), ("translate(108)", 8), ("window(84)", 16), ("crop(99)", 1), ("shift(4)", 8)] {
        let (tops, lefts) = offsets(text);
        assert_uniform_integers(&format!("{text} top"), &tops, 0, high);
        assert_uniform_integers(&format!("{text} left"), &lefts, 0, high);
        let same = tops.iter().zip(&lefts).filter(|(t, l)| t == l).count();
        assert_rate(&format!("{text} top == left"), same, tops.len(), 1.0 / (high + 1) as f64);
    }
    assert_eq!(offsets("center_crop(84)").0[0], 8);
    assert_eq!(offsets("center_translate(108)").1[0], 4);
}

#[test]
fn cutout_sizes_and_positions_are_uniform_where_they_fit() {
    for text in ["cutout", "cutout_color(5, 12)"] {
        let rects: Vec<[usize; 4]> = params(text, FRAME)
            .iter()
            .map(|p| match p {
                StageParams::Rect { top, left, height, width, .. } => [*top, *left, *height, *width],
                other => panic!("{other:?}"),
            })
            .collect();
        let (min, max) = if text == "cutout" { (10, 30) } else { (5, 12) };
        let heights: Vec<usize> = rects.iter().map(|r| r[2]).collect();
        let widths: Vec<usize> = rects.iter().map(|r| r[3]).collect();
        assert_uniform_integers(&format!("{text} height"), &heights, min, max);
        assert_uniform_integers(&format!("{text} width"), &widths, min, max);
        // Given its size, the position is uniform over where it fits: top / (H - h) is uniform on [0, 1].
        assert!(rects.iter().all(|[top, left, h, w]| top + h <= 100 && left + w <= 100));
        let relative: Vec<f32> = rects.iter().map(|[top, _, h, _]| (*top as f32 + 0.5) / (101 - h) as f32).collect();
        assert_uniform_reals(&format!("{text} relative top"), &relative, 0.0, 1.0);
    }
    let fills: Vec<f32> = params("cutout_color", FRAME)
        .iter()
        .flat_map(|p| match p {
            StageParams::Rect { fill, .. } => fill.map(f32::from),
            other => panic!("{other:?}"),
        })
        .collect();
    assert_uniform_reals("cutout_color fill", &fills, 0.0, 255.0);
    assert!(params("cutout", FRAME).iter().all(|p| matches!(p, StageParams::Rect { fill: [0, 0, 0], .. })));
}

#[test]
fn intensity_factors_are_a_clipped_normal() {
    // DrQ's `Intensity(scale=0.05)`: 1 + 0.05 * clamp(N(0, 1), -2, 2).
    let factors: Vec<f64> = params("intensity", FRAME)
        .iter()
        .map(|p| match p {
            StageParams::Factor(factor) => f64::from(*factor),
            other => panic!("{other:?}"),
        })
        .collect();
    let n = factors.len() as f64;
    let z: Vec<f64> = factors.iter().map(|f| (f - 1.0) / 0.05).collect();
    assert!(z.iter().all(|z| (-2.0 - 1e-4..=2.0 + 1e-4).contains(z)), "factors outside 1 +- 2 * scale");
    let mean = z.iter().sum::<f64>() / n;
    assert!(mean.abs() < 5.0 / n.sqrt(), "mean {mean}");
    // The clipped tails hold P(|N| > 2) = 4.55% of the draws, at the bounds exactly.
    let clipped = z.iter().filter(|z| z.abs() > 2.0 - 1e-4).count();
    assert_rate("clipped", clipped, z.len(), 0.045_500);
    let within = z.iter().filter(|z| z.abs() < 1.0).count();
    assert_rate("|z| < 1", within, z.len(), 0.682_689);
}

#[test]
fn conv_weights_are_xavier_normal() {
    let weights: Vec<f64> = params("conv", FRAME)
        .iter()
        .take(2000)
        .flat_map(|p| match p {
            StageParams::Conv(weights) => weights.map(f64::from),
            other => panic!("{other:?}"),
        })
        .collect();
    let n = weights.len() as f64;
    let mean = weights.iter().sum::<f64>() / n;
    let std = (weights.iter().map(|w| (w - mean).powi(2)).sum::<f64>() / n).sqrt();
    let expected = f64::from(CONV_WEIGHT_STD);
    assert!(mean.abs() < 5.0 * expected / n.sqrt(), "mean {mean}");
    assert!((std / expected - 1.0).abs() < 5.0 / (2.0 * n).sqrt(), "std {std}, expected {expected}");
    // Normal, not uniform: about 68.3% within one standard deviation.
    let within = weights.iter().filter(|w| w.abs() < expected).count();
    assert_rate("|w| < std", within, weights.len(), 0.682_689);
    let expected_sqrt = (2.0f64 / 54.0).sqrt();
    assert!((expected - expected_sqrt).abs() < 1e-7);
}

#[test]
fn jitter_factors_hue_and_order() {
    let jitters: Vec<_> = params("color_jitter", FRAME)
        .iter()
        .map(|p| match p {
            StageParams::Jitter(jitter) => *jitter,
            other => panic!("{other:?}"),
        })
        .collect();
    let collect = |f: fn(&radserve_augment::JitterParams) -> f32| jitters.iter().map(f).collect::<Vec<f32>>();
    assert_uniform_reals("brightness", &collect(|j| j.brightness), 0.6, 1.4);
    assert_uniform_reals("contrast", &collect(|j| j.contrast), 0.6, 1.4);
    assert_uniform_reals("saturation", &collect(|j| j.saturation), 0.6, 1.4);
    assert_uniform_reals("hue", &collect(|j| j.hue), -0.5, 0.5);
    let mut orders: HashMap<[JitterOp; 4], usize> = HashMap::new();
    for jitter in &jitters {
        *orders.entry(jitter.order).or_default() += 1;
    }
    assert_eq!(orders.len(), 24, "every order of the four operations appears");
    for count in orders.values() {
        assert_rate("an order", *count, jitters.len(), 1.0 / 24.0);
    }
}

#[test]
fn state_factors_and_noise() {
    let dim = 4;
    let input = vec![1.0f32; DRAWS as usize * dim];
    let mut output = vec![0.0; input.len()];
    for (text, per_dimension) in [("ras_s", false), ("ras_m(0.5, 2)", true)] {
        let plan = StatePlan::new(&Pipeline::parse(text).unwrap(), dim).unwrap();
        plan.apply(&input, &mut output, &Draws::new(3)).unwrap();
        let (low, high) = if per_dimension { (0.5, 2.0) } else { (0.6, 1.4) };
        let factors: Vec<f32> = output.chunks(dim).map(|row| row[1]).collect();
        assert_uniform_reals(text, &factors, low, high);
    }
    let plan = StatePlan::new(&Pipeline::parse("noise(std=0.5)").unwrap(), dim).unwrap();
    plan.apply(&input, &mut output, &Draws::new(4)).unwrap();
    let noise: Vec<f64> = output.iter().map(|v| f64::from(*v) - 1.0).collect();
    let n = noise.len() as f64;
    let mean = noise.iter().sum::<f64>() / n;
    let std = (noise.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    assert!(mean.abs() < 5.0 * 0.5 / n.sqrt(), "noise mean {mean}");
    assert!((std / 0.5 - 1.0).abs() < 5.0 / (2.0 * n).sqrt(), "noise std {std}");
}
