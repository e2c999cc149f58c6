//! Properties of the semantics, checked on the output bytes (not on the drawn parameters).

use radserve_augment::{Augmentation, Draws, FrameShape, ImagePlan, Pipeline, Sharing, StageParams, StatePlan, TransitionPart};

const SHAPE: FrameShape = FrameShape::new(3, 3, 100, 100);

/// Bytes in 1..=255 (no zeros, so zeroed regions are visible).
fn nonzero_batch(len: usize, seed: u64) -> Vec<u8> {
    radserve_augment::speed::noise(len, seed).into_iter().map(|byte| 1 + byte % 255).collect()
}

fn plan(text: &str, shape: FrameShape) -> ImagePlan {
    ImagePlan::new(&Pipeline::parse(text).unwrap(), shape).unwrap()
}

fn run(plan: &ImagePlan, input: &[u8], draws: &Draws) -> Vec<u8> {
    let batch = input.len() / plan.input_shape().sample_len();
    let mut output = vec![0; batch * plan.output_shape().sample_len()];
    plan.apply(input, &mut output, draws).unwrap();
    output
}

fn plane<'a>(sample: &'a [u8], shape: &FrameShape, index: usize) -> &'a [u8] {
    &sample[index * shape.plane_len()..(index + 1) * shape.plane_len()]
}

fn window_of(plane: &[u8], width: usize, top: usize, left: usize, height: usize, window_width: usize) -> Vec<u8> {
    (top..top + height).flat_map(|y| plane[y * width + left..y * width + left + window_width].to_vec()).collect()
}

#[test]
fn a_crop_is_a_sub_window_at_one_offset_for_the_whole_stack() {
    let crop = plan("crop(84)", SHAPE);
    let input = nonzero_batch(16 * SHAPE.sample_len(), 1);
    let output = run(&crop, &input, &Draws::new(5));
    let out_shape = crop.output_shape();
    let mut offsets = std::collections::HashSet::new();
    for (src, dst) in input.chunks(SHAPE.sample_len()).zip(output.chunks(out_shape.sample_len())) {
        let first = plane(dst, &out_shape, 0);
        let found: Vec<(usize, usize)> = (0..=16)
            .flat_map(|top| (0..=16).map(move |left| (top, left)))
            .filter(|&(top, left)| window_of(plane(src, &SHAPE, 0), 100, top, left, 84, 84) == first)
            .collect();
        assert_eq!(found.len(), 1, "the first plane is exactly one window of its input");
        let (top, left) = found[0];
        for index in 0..SHAPE.planes() {
            assert_eq!(window_of(plane(src, &SHAPE, index), 100, top, left, 84, 84), plane(dst, &out_shape, index));
        }
        offsets.insert((top, left));
    }
    assert!(offsets.len() >= 12, "offsets differ across the batch: {offsets:?}");
}

#[test]
fn a_shift_moves_the_whole_stack_by_at_most_pad_and_repeats_the_edge() {
    let shift = plan("shift(4)", SHAPE);
    let input = nonzero_batch(16 * SHAPE.sample_len(), 9);
    let output = run(&shift, &input, &Draws::new(3));
    assert_eq!(shift.output_shape(), SHAPE);
    let mut moves = std::collections::HashSet::new();
    for (src, dst) in input.chunks(SHAPE.sample_len()).zip(output.chunks(SHAPE.sample_len())) {
        // The inner 92x92 of the output is the input moved by (dy, dx) in [-4, 4]^2.
        let found: Vec<(usize, usize)> = (0..=8)
            .flat_map(|top| (0..=8).map(move |left| (top, left)))
            .filter(|&(top, left)| {
                window_of(plane(src, &SHAPE, 0), 100, top, left, 92, 92) == window_of(plane(dst, &SHAPE, 0), 100, 4, 4, 92, 92)
            })
            .collect();
        assert_eq!(found.len(), 1, "the inside is the input at one offset");
        let (top, left) = found[0];
        for index in 0..SHAPE.planes() {
            let (source, shifted) = (plane(src, &SHAPE, index), plane(dst, &SHAPE, index));
            for y in 0..100 {
                for x in 0..100 {
                    let source_y = (y + top).clamp(4, 103) - 4;
                    let source_x = (x + left).clamp(4, 103) - 4;
                    assert_eq!(shifted[y * 100 + x], source[source_y * 100 + source_x], "plane {index} at ({y}, {x})");
                }
            }
        }
        moves.insert((top, left));
    }
    assert!(moves.len() >= 10, "moves differ across the batch: {moves:?}");
}

#[test]
fn intensity_scales_every_pixel_of_a_sample_by_one_factor() {
    let intensity = plan("intensity(0.5)", SHAPE);
    let input = nonzero_batch(8 * SHAPE.sample_len(), 4);
    let output = run(&intensity, &input, &Draws::new(8));
    let mut factors = Vec::new();
    for (sample, (src, dst)) in input.chunks(SHAPE.sample_len()).zip(output.chunks(SHAPE.sample_len())).enumerate() {
        let StageParams::Factor(factor) = intensity.draw(&Draws::new(8), sample as u64)[0] else { panic!() };
        assert!((0.0..=2.0).contains(&factor), "{factor}");
        for (a, b) in src.iter().zip(dst) {
            let exact = f32::from(*a) * factor;
            assert!((f32::from(*b) - exact.min(255.0)).abs() <= 0.5, "{a} * {factor} gave {b}");
        }
        factors.push(factor);
    }
    factors.dedup();
    assert!(factors.len() > 4, "one factor per sample, varying: {factors:?}");
}

#[test]
fn a_translate_holds_its_input_exactly_inside_zeros() {
    let translate = plan("translate(108)", SHAPE);
    let input = nonzero_batch(8 * SHAPE.sample_len(), 2);
    let output = run(&translate, &input, &Draws::new(6));
    let out_shape = translate.output_shape();
    for (src, dst) in input.chunks(SHAPE.sample_len()).zip(output.chunks(out_shape.sample_len())) {
        let nonzero: Vec<usize> = plane(dst, &out_shape, 0).iter().enumerate().filter(|(_, v)| **v != 0).map(|(i, _)| i).collect();
        let (top, left) = (nonzero[0] / 108, nonzero[0] % 108);
        assert_eq!(nonzero.len(), 100 * 100);
        for index in 0..SHAPE.planes() {
            let out_plane = plane(dst, &out_shape, index);
            assert_eq!(window_of(out_plane, 108, top, left, 100, 100), plane(src, &SHAPE, index));
            assert_eq!(out_plane.iter().filter(|v| **v == 0).count(), 108 * 108 - 100 * 100);
        }
    }
}

#[test]
fn flip_twice_and_four_quarter_turns_are_identity() {
    let input = nonzero_batch(4 * SHAPE.sample_len(), 3);
    assert_eq!(run(&plan("flip(p=1)|flip(p=1)", SHAPE), &input, &Draws::new(1)), input);
    assert_ne!(run(&plan("flip(p=1)", SHAPE), &input, &Draws::new(1)), input);
    let square = FrameShape::new(3, 3, 37, 37);
    let input = nonzero_batch(square.sample_len(), 4);
    for quarters in 1..=3u8 {
        let rotate = plan("rotate(p=1)", square);
        let mut current = input.clone();
        for turn in 1..=4 {
            let mut next = vec![0; square.sample_len()];
            rotate.apply_sample(&current, &mut next, &[StageParams::Quarters(quarters)]);
            current = next;
            assert_eq!(current == input, turn * u32::from(quarters) % 4 == 0, "{quarters} quarter(s), {turn} time(s)");
        }
    }
}

#[test]
fn every_frame_of_a_sample_gets_the_same_parameters() {
    // A stack of three identical frames must come out as three identical frames.
    let frame = nonzero_batch(SHAPE.frame_len(), 7);
    let input = frame.repeat(2 * SHAPE.frames); // 2 samples of 3 frames
    for text in ["crop(84)", "translate(108)", "window(70)", "grayscale(p=0.5)", "cutout", "cutout_color", "flip(p=0.5)",
        "rotate(p=0.7)", "conv", "color_jitter", "crop(84)|color_jitter|rotate(p=1)", "shift(4)", "intensity"]
    {
        let augment = plan(text, SHAPE);
        let out_shape = augment.output_shape();
        for seed in 0..4 {
            let output = run(&augment, &input, &Draws::new(seed));
            for sample in output.chunks(out_shape.sample_len()) {
                let frames: Vec<&[u8]> = sample.chunks(out_shape.frame_len()).collect();
                assert!(frames.iter().all(|f| *f == frames[0]), "{text}: frames of one sample differ (seed {seed})");
            }
        }
    }
}

#[test]
fn grayscale_makes_the_channels_equal_and_leaves_the_others_alone() {
    let input = nonzero_batch(64 * SHAPE.sample_len(), 8);
    let output = run(&plan("grayscale(p=0.5)", SHAPE), &input, &Draws::new(9));
    let mut fired = 0;
    for (src, dst) in input.chunks(SHAPE.sample_len()).zip(output.chunks(SHAPE.sample_len())) {
        if src == dst {
            continue;
        }
        fired += 1;
        for frame in dst.chunks(SHAPE.frame_len()) {
            let plane_len = SHAPE.plane_len();
            assert_eq!(frame[..plane_len], frame[plane_len..2 * plane_len]);
            assert_eq!(frame[..plane_len], frame[2 * plane_len..]);
        }
    }
    assert!((16..=48).contains(&fired), "{fired} of 64 turned gray at p=0.5");
}

#[test]
fn cutout_zeroes_exactly_one_rectangle() {
    let input = nonzero_batch(32 * SHAPE.sample_len(), 10);
    for text in ["cutout", "cutout(1,1)", "cutout(30,30)"] {
        let output = run(&plan(text, SHAPE), &input, &Draws::new(11));
        for (src, dst) in input.chunks(SHAPE.sample_len()).zip(output.chunks(SHAPE.sample_len())) {
            let zeros: Vec<usize> = plane(dst, &SHAPE, 0).iter().enumerate().filter(|(_, v)| **v == 0).map(|(i, _)| i).collect();
            let (rows, cols): (Vec<usize>, Vec<usize>) = zeros.iter().map(|i| (i / 100, i % 100)).unzip();
            let (top, bottom) = (*rows.iter().min().unwrap(), *rows.iter().max().unwrap());
            let (left, right) = (*cols.iter().min().unwrap(), *cols.iter().max().unwrap());
            let (height, width) = (bottom - top + 1, right - left + 1);
            assert_eq!(zeros.len(), height * width, "{text}: the zeros form one filled rectangle");
            let Ok(Some(Augmentation::Cutout { min, max })) = Pipeline::parse(text).map(|p| p.stages().first().cloned()) else { panic!() };
            assert!((min..=max).contains(&height) && (min..=max).contains(&width));
            for index in 0..SHAPE.planes() {
                let (src_plane, dst_plane) = (plane(src, &SHAPE, index), plane(dst, &SHAPE, index));
                for (pixel, (a, b)) in src_plane.iter().zip(dst_plane).enumerate() {
                    let inside = (top..=bottom).contains(&(pixel / 100)) && (left..=right).contains(&(pixel % 100));
                    assert_eq!(*b, if inside { 0 } else { *a });
                }
            }
        }
    }
}


#[test]
fn the_same_seed_gives_the_same_batch_whatever_the_threads() {
    let augment = plan("crop(84)|cutout_color|conv|color_jitter|flip(p=0.5)", SHAPE);
    let input = nonzero_batch(24 * SHAPE.sample_len(), 12);
    let in_pool = |threads: usize, seed: u64| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| run(&augment, &input, &Draws::new(seed)))
    };
    let reference = in_pool(1, 77);
    assert_eq!(in_pool(2, 77), reference);
    assert_eq!(in_pool(3, 77), reference);
    assert_ne!(in_pool(2, 78), reference, "another seed gives another batch");
}

#[test]
fn transitions_share_draws_as_configured() {
    let input = nonzero_batch(16 * SHAPE.sample_len(), 13);
    let draws = Draws::new(21);
    for (text, sharing, same) in [
        ("translate(108)", Sharing::Reference, true),
        ("crop(84)", Sharing::Reference, false),
        ("crop(84)", Sharing::Shared, true),
        ("translate(108)", Sharing::Independent, false),
        ("crop(84)|translate(108)", Sharing::Shared, true),
    ] {
        let augment = plan(text, SHAPE);
        let obs = run(&augment, &input, &draws.with_sharing(sharing));
        let next = run(&augment, &input, &draws.with_sharing(sharing).with_part(TransitionPart::NextObs));
        assert_eq!(obs == next, same, "{text} with {sharing:?}");
    }
}

#[test]
fn keys_hold_parameters_fixed() {
    let augment = plan("crop(84)|rotate(p=0.5)", SHAPE);
    let frame = nonzero_batch(SHAPE.sample_len(), 14);
    let input = frame.repeat(6);
    let mut output = vec![0; 6 * augment.output_shape().sample_len()];
    augment.apply_keyed(&input, &mut output, &Draws::new(3), Some(&[4, 9, 4, 9, 4, 9])).unwrap();
    let samples: Vec<&[u8]> = output.chunks(augment.output_shape().sample_len()).collect();
    assert_eq!(samples[0], samples[2]);
    assert_eq!(samples[1], samples[5]);
    assert_ne!(samples[0], samples[1]);
    let error = augment.apply_keyed(&input, &mut output, &Draws::new(3), Some(&[1, 2])).unwrap_err();
    assert!(error.to_string().contains("2 draw keys for 6 samples"), "{error}");
}

#[test]
fn shapes_that_do_not_fit_are_refused_before_any_batch() {
    let message = |text: &str, shape: FrameShape| ImagePlan::new(&Pipeline::parse(text).unwrap(), shape).unwrap_err().to_string();
    assert!(message("crop(120)", SHAPE).contains("needs frames of at least 120x120, got 100x100"));
    assert!(message("translate(90)", SHAPE).contains("use crop to shrink"));
    assert!(message("rotate", FrameShape::new(3, 3, 84, 100)).contains("needs square frames, got 84x100"));
    assert!(message("grayscale", FrameShape::new(3, 1, 84, 84)).contains("needs RGB frames (3 channels per frame), got 1"));
    assert!(message("cutout(10, 40)", FrameShape::new(1, 3, 32, 32)).contains("must fit in the 32x32 frame"));
    assert!(message("shift(32)", FrameShape::new(1, 3, 32, 32)).contains("must be less than the 32x32 frame's sides"));
    assert!(message("ras_s", SHAPE).contains("applies to state vectors, not images"));
    assert!(message("crop(84)|crop(90)", SHAPE).contains("needs frames of at least 90x90, got 84x84"));
    assert!(message("translate(1000000)", SHAPE).contains("the most allowed is 67108864"));
    let state = StatePlan::new(&Pipeline::parse("crop(84)").unwrap(), 17).unwrap_err().to_string();
    assert!(state.contains("applies to images, not state vectors"), "{state}");
    let augment = plan("crop(84)", SHAPE);
    let mut output = vec![0; 84 * 84 * 9];
    let error = augment.apply(&[0; 100], &mut output, &Draws::new(0)).unwrap_err().to_string();
    assert!(error.contains("not a whole number of 90000-element samples"), "{error}");
    let error = augment.apply(&vec![0; 2 * 90000], &mut output, &Draws::new(0)).unwrap_err().to_string();
    assert!(error.contains("2 samples of 63504 need 127008"), "{error}");
}

#[test]
fn state_augmentations_scale_and_perturb_as_specified() {
    let dim = 17;
    let input: Vec<f32> = (0..64 * dim).map(|i| 1.0 + (i % dim) as f32).collect();
    let mut output = vec![0.0; input.len()];
    let scalar = StatePlan::new(&Pipeline::parse("ras_s").unwrap(), dim).unwrap();
    scalar.apply(&input, &mut output, &Draws::new(1)).unwrap();
    let mut factors = Vec::new();
    for (src, dst) in input.chunks(dim).zip(output.chunks(dim)) {
        let factor = dst[0] / src[0];
        assert!((0.6..=1.4).contains(&factor));
        assert!(src.iter().zip(dst).all(|(a, b)| (b / a - factor).abs() < 1e-5), "one factor per sample");
        factors.push(factor);
    }
    assert!(factors.windows(2).any(|w| w[0] != w[1]));
    let multi = StatePlan::new(&Pipeline::parse("ras_m").unwrap(), dim).unwrap();
    multi.apply(&input, &mut output, &Draws::new(1)).unwrap();
    for (src, dst) in input.chunks(dim).zip(output.chunks(dim)) {
        let ratios: Vec<f32> = src.iter().zip(dst).map(|(a, b)| b / a).collect();
        assert!(ratios.iter().all(|r| (0.6..=1.4).contains(r)));
        assert!(ratios.windows(2).any(|w| (w[0] - w[1]).abs() > 1e-4), "one factor per dimension");
    }
    // Transitions share state draws by default.
    let mut next = vec![0.0; input.len()];
    let draws = Draws::new(5);
    let noise = StatePlan::new(&Pipeline::parse("noise(std=0.1)").unwrap(), dim).unwrap();
    noise.apply(&input, &mut output, &draws).unwrap();
    noise.apply(&input, &mut next, &draws.with_part(TransitionPart::NextObs)).unwrap();
    assert_eq!(output, next);
    noise.apply(&input, &mut next, &draws.with_part(TransitionPart::NextObs).with_sharing(Sharing::Independent)).unwrap();
    assert_ne!(output, next);
}
