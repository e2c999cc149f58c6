//! Fuzzing of the pipeline text parser and of the plans it feeds: any text, well-formed or not,
//! parses to an error or to a valid pipeline, and any valid pipeline either refuses a frame shape or
//! augments it without panicking, deterministically. Bounded here (`cargo test`: PROPTEST_CASES,
//! default 2048 per property); `make fuzz` runs the same properties with many more cases.

use proptest::prelude::*;
use radserve_augment::{Domain, Draws, FrameShape, ImagePlan, Pipeline, Sharing, StatePlan, TransitionPart, MAX_PIPELINE_TEXT_BYTES, MAX_STAGES};

fn config() -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES").ok().and_then(|value| value.parse().ok()).unwrap_or(2048);
    ProptestConfig { cases, ..ProptestConfig::default() }
}

/// Names the parser knows (canonical, aliases, other spellings), near misses and garbage.
fn name() -> impl Strategy<Value = String> {
    prop_oneof![
        4 => prop::sample::select(vec![
            "crop", "random_crop", "translate", "window", "center_crop", "center_translate", "grayscale", "gray",
            "cutout", "cutout_color", "flip", "rotate", "conv", "rand_conv", "random_conv", "color_jitter", "jitter",
            "ras_s", "ras_m", "noise", "gaussian_noise", "shift", "random_shift", "intensity", "Center-Crop", "CROP",
            "none", "no_aug",
        ])
        .prop_map(str::to_owned),
        1 => "[a-z_-]{0,12}",
        1 => "\\PC{0,40}",
    ]
}

/// Argument values: plausible numbers, edge cases and garbage.
fn number() -> impl Strategy<Value = String> {
    prop_oneof![
        3 => (0u32..300).prop_map(|n| n.to_string()),
        2 => any::<f64>().prop_map(|x| x.to_string()),
        1 => prop::sample::select(vec![
            "-1", "-0", "0.5", "1e6", "1000001", "1e309", "NaN", "inf", "-inf", "0x10", "", " ", "1_0", "2.", ".5",
            "18446744073709551616", "84.0000001",
        ])
        .prop_map(str::to_owned),
        1 => "\\PC{0,8}",
    ]
}

fn argument() -> impl Strategy<Value = String> {
    prop_oneof![
        3 => number(),
        2 => (prop::sample::select(vec!["size", "p", "min", "max", "brightness", "contrast", "saturation", "hue", "alpha", "beta", "std", "pad", "scale", "x", ""]), number())
            .prop_map(|(key, value)| format!("{key}={value}")),
    ]
}

fn stage() -> impl Strategy<Value = String> {
    (name(), prop::option::of(prop::collection::vec(argument(), 0..5)), " {0,2}").prop_map(|(name, arguments, pad)| match arguments {
        None => format!("{pad}{name}{pad}"),
        Some(arguments) => format!("{pad}{name}({}){pad}", arguments.join(",")),
    })
}

/// A stage with arguments in its valid range (sizes near the small frames used below), so that
/// plans get built and run.
fn valid_stage() -> impl Strategy<Value = String> {
    let p = 0.0f64..=1.0;
    prop_oneof![
        // Frames below are mostly 40 to 47 pixels a side: crops inside that, translations around it.
        (prop::sample::select(vec!["crop", "window", "center_crop"]), 1u32..40).prop_map(|(name, size)| format!("{name}({size})")),
        (prop::sample::select(vec!["translate", "center_translate"]), 48u32..96).prop_map(|(name, size)| format!("{name}({size})")),
        (prop::sample::select(vec!["grayscale", "flip", "rotate"]), p.clone()).prop_map(|(name, p)| format!("{name}(p={p})")),
        (prop::sample::select(vec!["cutout", "cutout_color"]), 0u32..20, 0u32..20)
            .prop_map(|(name, a, b)| format!("{name}({},{})", a.min(b), a.max(b))),
        Just("conv".to_owned()),
        (1u32..40).prop_map(|pad| format!("shift({pad})")),
        (0.0f64..=0.5).prop_map(|scale| format!("intensity({scale})")),
        (p.clone(), p.clone(), p.clone(), 0.0f64..=0.5).prop_map(|(b, c, s, h)| format!("color_jitter({b},{c},{s},{h})")),
        (prop::sample::select(vec!["ras_s", "ras_m"]), 0.0f64..2.0, 0.0f64..2.0)
            .prop_map(|(name, a, b)| format!("{name}(alpha={},beta={})", a.min(b), a.max(b))),
        (0.0f64..3.0).prop_map(|std| format!("noise({std})")),
    ]
}

/// Text shaped like a pipeline (mostly), or anything at all.
fn pipeline_text() -> impl Strategy<Value = String> {
    prop_oneof![
        6 => prop::collection::vec(stage(), 0..10).prop_map(|stages| stages.join("|")),
        1 => any::<String>(),
        1 => "[a-z(),=|0-9. ]{0,64}",
    ]
}

fn shape() -> impl Strategy<Value = FrameShape> {
    let side = || prop_oneof![3 => 40usize..48, 1 => 1usize..48];
    (1usize..4, prop::sample::select(vec![1usize, 3]), side(), side())
        .prop_map(|(frames, channels, height, width)| FrameShape::new(frames, channels, height, width))
}

fn sharing() -> impl Strategy<Value = Sharing> {
    prop::sample::select(vec![Sharing::Reference, Sharing::Shared, Sharing::Independent])
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn any_text_parses_to_an_error_or_a_valid_pipeline(text in pipeline_text()) {
        match Pipeline::parse(&text) {
            Ok(pipeline) => {
                prop_assert!(text.len() <= MAX_PIPELINE_TEXT_BYTES);
                prop_assert!(pipeline.stages().len() <= MAX_STAGES);
                for stage in pipeline.stages() {
                    prop_assert!(stage.validate().is_ok(), "{stage} passed the parser but not validation");
                }
            }
            Err(error) => {
                // Messages quote the text, never an unbounded amount of it.
                prop_assert!(error.to_string().len() <= 2 * MAX_PIPELINE_TEXT_BYTES + 1024, "message of {} bytes", error.to_string().len());
            }
        }
    }

    #[test]
    fn text_over_the_limit_is_refused(repeat in 1usize..4, filler in "[a-z|(),0-9]{1,8}") {
        let text = filler.repeat(MAX_PIPELINE_TEXT_BYTES / filler.len() + repeat);
        prop_assert!(Pipeline::parse(&text).is_err());
    }

    #[test]
    fn valid_pipelines_refuse_a_shape_or_augment_it_deterministically(
        text in prop::collection::vec(prop_oneof![4 => valid_stage(), 1 => stage()], 1..4).prop_map(|stages| stages.join("|")),
        shape in shape(),
        batch in 1usize..4,
        seed in any::<u64>(),
        sharing in sharing(),
        next in any::<bool>(),
    ) {
        let Ok(pipeline) = Pipeline::parse(&text) else { return Ok(()) };
        let draws = Draws::new(seed).with_sharing(sharing).with_part(if next { TransitionPart::NextObs } else { TransitionPart::Obs });
        if pipeline.stages().iter().all(|stage| stage.domain() == Domain::State) && !pipeline.is_empty() {
            let dim = shape.sample_len() % 17 + 1;
            let plan = StatePlan::new(&pipeline, dim).expect("state pipelines take any dimension");
            let input: Vec<f32> = (0..batch * dim).map(|i| i as f32 - 3.5).collect();
            let mut first = vec![0.0; input.len()];
            let mut second = vec![0.0; input.len()];
            plan.apply(&input, &mut first, &draws).unwrap();
            plan.apply(&input, &mut second, &draws).unwrap();
            prop_assert_eq!(first.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), second.iter().map(|x| x.to_bits()).collect::<Vec<_>>());
            return Ok(());
        }
        let Ok(plan) = ImagePlan::new(&pipeline, shape) else { return Ok(()) };
        let input: Vec<u8> = (0..batch * shape.sample_len()).map(|i| (i.wrapping_mul(2_654_435_761) >> 7) as u8).collect();
        let output_len = batch * plan.output_shape().sample_len();
        let mut first = vec![0u8; output_len];
        let mut second = vec![1u8; output_len];
        plan.apply(&input, &mut first, &draws).unwrap();
        plan.apply(&input, &mut second, &draws).unwrap();
        prop_assert!(first == second, "the same draws gave different bytes for {}", text);
        // A buffer of the wrong size is an error, never a panic or an out-of-bounds write.
        let mut short = vec![0u8; output_len.saturating_sub(1)];
        prop_assert!(plan.apply(&input, &mut short, &draws).is_err());
    }
}
