//! Every fast kernel, on every instruction set this CPU has, against the plain scalar reference at
//! awkward shapes: batch 1, odd widths, widths that are not a multiple of the vector width, k = 1
//! and k = 3 stacks, translate from inputs smaller than the canvas.

use radserve_augment::speed::noise;
use radserve_augment::{reference, Draws, FrameShape, ImagePlan, Isa, Pipeline};

/// Run `text` on `batch` samples of `shape` through the plan (every ISA) and the reference; the
/// largest per-byte difference must not exceed `tolerance`.
fn check(text: &str, shape: FrameShape, batch: usize, tolerance: u8) {
    let pipeline = Pipeline::parse(text).unwrap();
    let input = noise(batch * shape.sample_len(), batch as u64 + shape.width as u64);
    for isa in Isa::available() {
        let plan = ImagePlan::new(&pipeline, shape).unwrap().with_isa(isa);
        let output_len = plan.output_shape().sample_len();
        let mut fast = vec![0xAB; batch * output_len];
        let draws = Draws::new(1234);
        plan.apply(&input, &mut fast, &draws).unwrap();
        for sample in 0..batch {
            let params = plan.draw(&draws, sample as u64);
            let src = &input[sample * shape.sample_len()..][..shape.sample_len()];
            let expected = reference::apply_sample(plan.stages(), &params, plan.shapes(), src);
            let actual = &fast[sample * output_len..][..output_len];
            let worst = expected.iter().zip(actual).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
            assert!(
                worst <= tolerance,
                "{text} on {shape} ({}), sample {sample} with {params:?}: differs by {worst} from the reference",
                isa.name()
            );
        }
    }
}

const SHAPES: [FrameShape; 6] = [
    FrameShape::new(3, 3, 100, 100),
    FrameShape::new(1, 3, 91, 91),
    FrameShape::new(1, 3, 37, 37),
    FrameShape::new(3, 3, 33, 33),
    FrameShape::new(2, 3, 17, 17),
    FrameShape::new(1, 3, 1, 1),
];

fn fits(text: &str, shape: FrameShape) -> bool {
    ImagePlan::new(&Pipeline::parse(text).unwrap(), shape).is_ok()
}

fn check_everywhere(texts: &[&str], tolerance: u8) {
    for text in texts {
        let mut ran = 0;
        for shape in SHAPES {
            if !fits(text, shape) {
                continue;
            }
            for batch in [1, 5] {
                check(text, shape, batch, tolerance);
            }
            ran += 1;
        }
        assert!(ran >= 2, "{text} ran on only {ran} shape(s)");
    }
}

#[test]
fn geometric_kernels_equal_the_reference() {
    check_everywhere(
        &[
            "crop(84)", "crop(31)", "crop(1)", "crop(17)", "center_crop(15)", "translate(108)", "translate(41)",
            "translate(17)", "center_translate(45)", "center_translate(120)", "window(84)", "window(13)",
            "flip(p=1)", "flip(p=0.5)", "rotate(p=1)", "rotate(p=0.6)", "shift(4)", "shift(1)", "shift(16)",
        ],
        0,
    );
}

#[test]
fn rectangle_kernels_equal_the_reference() {
    check_everywhere(&["cutout(min=1,max=1)", "cutout(min=3,max=9)", "cutout", "cutout_color(min=2,max=15)", "cutout_color"], 0);
}

#[test]
fn colour_kernels_equal_the_reference() {
    check_everywhere(&["grayscale(p=1)", "grayscale(p=0.5)", "conv", "intensity", "intensity(0.5)"], 0);
    // Colour jitter's contrast mean is summed in another order than the reference: one level.
    check_everywhere(&["color_jitter", "color_jitter(0.9,0.9,0.9,0.5)"], 1);
}

#[test]
fn non_rgb_stacks_take_the_channel_agnostic_kernels() {
    for text in ["crop(9)", "translate(16)", "window(5)", "flip(p=1)", "rotate(p=1)", "cutout(2,4)", "shift(3)", "intensity"] {
        check(text, FrameShape::new(4, 1, 11, 11), 3, 0);
        check(text, FrameShape::new(2, 2, 13, 13), 2, 0);
    }
}

#[test]
fn pipelines_equal_the_reference_stage_by_stage() {
    for text in [
        "crop(84)|grayscale(p=0.5)",
        "translate(108)|flip(p=0.5)|rotate(p=0.5)",
        "crop(90)|cutout_color|conv",
        "crop(64)|translate(72)|window(50)",
        "cutout|color_jitter|crop(70)",
        "shift(4)|intensity",
        "crop(84)|shift(4)|conv",
    ] {
        let tolerance = if text.contains("jitter") { 1 } else { 0 };
        check(text, FrameShape::new(3, 3, 100, 100), 4, tolerance);
    }
    check("center_crop(15)|center_translate(21)|flip(p=1)|rotate(p=1)", FrameShape::new(3, 3, 17, 17), 2, 0);
}

#[test]
fn the_empty_pipeline_copies() {
    check("none", FrameShape::new(3, 3, 10, 10), 3, 0);
}
