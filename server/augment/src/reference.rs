//! Plain scalar implementations, one pixel at a time with explicit indices, written for obvious
//! correctness rather than speed. The fast kernels are tested against them: equal bytes for the
//! integer kernels and random convolution, within one level for colour jitter (its contrast mean
//! is summed in a different order). Parameters come from [`crate::ImagePlan::draw`].

use crate::draw::{JitterOp, JitterParams, StageParams};
use crate::kernels::LUMA_FIXED;
use crate::shape::FrameShape;
use crate::spec::{Augmentation, LUMA_WEIGHTS};

fn at(shape: &FrameShape, plane: usize, y: usize, x: usize) -> usize {
    (plane * shape.height + y) * shape.width + x
}

/// Apply one stage to one sample; `output` is the stage's output shape.
pub fn apply_stage(
    augmentation: &Augmentation,
    params: &StageParams,
    input: &FrameShape,
    output: &FrameShape,
    src: &[u8],
) -> Vec<u8> {
    assert_eq!(src.len(), input.sample_len());
    let mut dst = vec![0u8; output.sample_len()];
    let (height, width) = (output.height, output.width);
    let each_pixel = |dst: &mut Vec<u8>, value: &dyn Fn(usize, usize, usize) -> u8| {
        for plane in 0..output.planes() {
            for y in 0..height {
                for x in 0..width {
                    dst[at(output, plane, y, x)] = value(plane, y, x);
                }
            }
        }
    };
    match (augmentation, params) {
        (Augmentation::Crop { .. } | Augmentation::CenterCrop { .. }, &StageParams::Offset { top, left }) => {
            each_pixel(&mut dst, &|plane, y, x| src[at(input, plane, y + top, x + left)])
        }
        (Augmentation::Translate { .. } | Augmentation::CenterTranslate { .. }, &StageParams::Offset { top, left }) => {
            each_pixel(&mut dst, &|plane, y, x| {
                let inside = (top..top + input.height).contains(&y) && (left..left + input.width).contains(&x);
                if inside { src[at(input, plane, y - top, x - left)] } else { 0 }
            })
        }
        (&Augmentation::Window { size }, &StageParams::Offset { top, left }) => each_pixel(&mut dst, &|plane, y, x| {
            let inside = (top..top + size).contains(&y) && (left..left + size).contains(&x);
            if inside { src[at(input, plane, y, x)] } else { 0 }
        }),
        (&Augmentation::Shift { pad }, &StageParams::Offset { top, left }) => each_pixel(&mut dst, &|plane, y, x| {
            // The padded frame repeats its edge: a coordinate outside the frame takes the nearest one.
            let source_y = (y + top).saturating_sub(pad).min(input.height - 1);
            let source_x = (x + left).saturating_sub(pad).min(input.width - 1);
            src[at(input, plane, source_y, source_x)]
        }),
        (Augmentation::Intensity { .. }, &StageParams::Factor(factor)) => each_pixel(&mut dst, &|plane, y, x| {
            (f32::from(src[at(input, plane, y, x)]) * factor).clamp(0.0, 255.0).round_ties_even() as u8
        }),
        (Augmentation::Flip { .. }, &StageParams::Apply(fires)) => each_pixel(&mut dst, &|plane, y, x| {
            src[at(input, plane, y, if fires { width - 1 - x } else { x })]
        }),
        (Augmentation::Rotate { .. }, &StageParams::Quarters(quarters)) => {
            // One counter-clockwise quarter turn at a time: out[y][x] = in[x][side - 1 - y].
            let mut current = src.to_vec();
            for _ in 0..quarters {
                let previous = current.clone();
                for plane in 0..input.planes() {
                    for y in 0..height {
                        for x in 0..width {
                            current[at(input, plane, y, x)] = previous[at(input, plane, x, width - 1 - y)];
                        }
                    }
                }
            }
            dst = current;
        }
        (Augmentation::Cutout { .. } | Augmentation::CutoutColor { .. }, &StageParams::Rect { top, left, height: rect_height, width: rect_width, fill }) => {
            each_pixel(&mut dst, &|plane, y, x| {
                let inside = (top..top + rect_height).contains(&y) && (left..left + rect_width).contains(&x);
                if inside { fill[plane % input.channels % 3] } else { src[at(input, plane, y, x)] }
            })
        }
        (Augmentation::Grayscale { .. }, &StageParams::Apply(fires)) => each_pixel(&mut dst, &|plane, y, x| {
            if !fires {
                return src[at(input, plane, y, x)];
            }
            let first = plane / 3 * 3;
            let [red, green, blue] = [0, 1, 2].map(|channel| u32::from(src[at(input, first + channel, y, x)]));
            ((LUMA_FIXED[0] * red + LUMA_FIXED[1] * green + LUMA_FIXED[2] * blue + 32768) >> 16) as u8
        }),
        (Augmentation::RandomConv, StageParams::Conv(weights)) => each_pixel(&mut dst, &|plane, y, x| {
            let (frame, out_channel) = (plane / 3, plane % 3);
            let mut sum = 0.0f32;
            for in_channel in 0..3 {
                for ky in 0..3 {
                    for kx in 0..3 {
                        let (source_y, source_x) = (y + ky, x + kx); // shifted by the one-pixel zero padding
                        if source_y == 0 || source_x == 0 || source_y > height || source_x > width {
                            continue;
                        }
                        let value = f32::from(src[at(input, frame * 3 + in_channel, source_y - 1, source_x - 1)]);
                        sum += weights[((out_channel * 3 + in_channel) * 3 + ky) * 3 + kx] * value;
                    }
                }
            }
            sum.clamp(0.0, 255.0).round_ties_even() as u8
        }),
        (Augmentation::ColorJitter { .. }, StageParams::Jitter(jitter)) => {
            for frame in 0..input.frames {
                jitter_frame(&src[frame * input.frame_len()..][..input.frame_len()], &mut dst[frame * input.frame_len()..][..input.frame_len()], input, jitter);
            }
        }
        (augmentation, params) => panic!("{augmentation:?} cannot take {params:?}"),
    }
    dst
}

fn jitter_frame(src: &[u8], dst: &mut [u8], shape: &FrameShape, params: &JitterParams) {
    let plane = shape.plane_len();
    let mut pixels: Vec<[f32; 3]> =
        (0..plane).map(|index| [0, 1, 2].map(|channel| f32::from(src[channel * plane + index]) / 255.0)).collect();
    let luma = |[red, green, blue]: [f32; 3]| LUMA_WEIGHTS[0] * red + LUMA_WEIGHTS[1] * green + LUMA_WEIGHTS[2] * blue;
    let blend = |value: f32, ratio: f32, other: f32| (ratio * value + (1.0 - ratio) * other).clamp(0.0, 1.0);
    for op in params.order {
        match op {
            JitterOp::Brightness => {
                for pixel in &mut pixels {
                    *pixel = pixel.map(|value| blend(value, params.brightness, 0.0));
                }
            }
            JitterOp::Contrast => {
                let mean = (pixels.iter().map(|&pixel| f64::from(luma(pixel))).sum::<f64>() / plane as f64) as f32;
                for pixel in &mut pixels {
                    *pixel = pixel.map(|value| blend(value, params.contrast, mean));
                }
            }
            JitterOp::Saturation => {
                for pixel in &mut pixels {
                    let gray = luma(*pixel);
                    *pixel = pixel.map(|value| blend(value, params.saturation, gray));
                }
            }
            JitterOp::Hue => {
                for pixel in &mut pixels {
                    *pixel = shift_hue(*pixel, params.hue);
                }
            }
        }
    }
    for (index, pixel) in pixels.iter().enumerate() {
        for channel in 0..3 {
            dst[channel * plane + index] = (pixel[channel].clamp(0.0, 1.0) * 255.0).round_ties_even() as u8;
        }
    }
}

/// RGB -> HSV -> RGB with the hue rotated, written with branches as a textbook would.
fn shift_hue([red, green, blue]: [f32; 3], shift: f32) -> [f32; 3] {
    let max = red.max(green).max(blue);
    let min = red.min(green).min(blue);
    let delta = max - min;
    let saturation = if max > 0.0 { delta / max } else { 0.0 };
    let sextant = if delta == 0.0 {
        0.0
    } else if max == red {
        (green - blue) / delta
    } else if max == green {
        2.0 + (blue - red) / delta
    } else {
        4.0 + (red - green) / delta
    };
    let mut hue = sextant / 6.0 + shift;
    if hue < 0.0 {
        hue += 1.0;
    }
    if hue >= 1.0 {
        hue -= 1.0;
    }
    let scaled = hue * 6.0;
    let sector = (scaled.floor() as i32).min(5);
    let fraction = scaled - sector as f32;
    let value = max;
    let p = value * (1.0 - saturation);
    let q = value * (1.0 - saturation * fraction);
    let t = value * (1.0 - saturation * (1.0 - fraction));
    match sector {
        0 => [value, t, p],
        1 => [q, value, p],
        2 => [p, value, t],
        3 => [p, q, value],
        4 => [t, p, value],
        _ => [value, p, q],
    }
}

/// Apply a whole pipeline to one sample, stage by stage.
pub fn apply_sample(stages: &[Augmentation], params: &[StageParams], shapes: &[FrameShape], src: &[u8]) -> Vec<u8> {
    let mut current = src.to_vec();
    for (index, (augmentation, stage_params)) in stages.iter().zip(params).enumerate() {
        current = apply_stage(augmentation, stage_params, &shapes[index], &shapes[index + 1], &current);
    }
    current
}
