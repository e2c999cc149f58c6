//! Grayscale and colour jitter, one RGB frame (three planes) at a time.

use super::multiversion;
use crate::draw::{JitterOp, JitterParams};
use crate::spec::LUMA_WEIGHTS;

/// Luma in 16-bit fixed point, rounded to nearest: the BT.601 weights scaled by 2^16 (they sum to
/// 65530, so white stays 255). Exact integer arithmetic, so every path gives the same bytes.
pub(crate) const LUMA_FIXED: [u32; 3] = [19589, 38470, 7471];

#[inline(always)]
pub(crate) fn luma_u8(red: u8, green: u8, blue: u8) -> u8 {
    ((LUMA_FIXED[0] * u32::from(red) + LUMA_FIXED[1] * u32::from(green) + LUMA_FIXED[2] * u32::from(blue) + 32768) >> 16)
        as u8
}

#[inline(always)]
fn grayscale_body(src: &[u8], dst: &mut [u8]) {
    let plane = src.len() / 3;
    let (red, rest) = src.split_at(plane);
    let (green, blue) = rest.split_at(plane);
    let (out_red, rest) = dst.split_at_mut(plane);
    let (out_green, out_blue) = rest.split_at_mut(plane);
    let (green, blue, out_green, out_blue) = (&green[..plane], &blue[..plane], &mut out_green[..plane], &mut out_blue[..plane]);
    for index in 0..plane {
        let luma = luma_u8(red[index], green[index], blue[index]);
        out_red[index] = luma;
        out_green[index] = luma;
        out_blue[index] = luma;
    }
}

multiversion! {
    /// RAD's grayscale: every channel of the frame becomes its luma.
    fn grayscale_frame(src: &[u8], dst: &mut [u8]) => grayscale_body
}

multiversion! {
    /// DrQ's intensity: every byte times `factor`, clamped to [0, 255] and rounded to nearest.
    fn intensity(src: &[u8], dst: &mut [u8], factor: f32) => intensity_body
}

#[inline(always)]
fn intensity_body(src: &[u8], dst: &mut [u8], factor: f32) {
    for (out, value) in dst.iter_mut().zip(src) {
        *out = round_byte((f32::from(*value) * factor).clamp(0.0, 255.0));
    }
}

/// Round a float already clamped to [0, 255] to the nearest byte, ties to even. Adding 1.5 * 2^23
/// leaves the rounded integer in the low mantissa bits; unlike `as u8` (a saturating conversion
/// LLVM scalarizes), this vectorizes. Equal to `value.round_ties_even() as u8`.
#[inline(always)]
pub(crate) fn round_byte(clamped: f32) -> u8 {
    debug_assert!((0.0..=255.0).contains(&clamped));
    (clamped + 12_582_912.0).to_bits() as u8
}

/// Quantize a value in [0, 1] to a byte: clamp, scale by 255, round to nearest (ties to even).
#[inline(always)]
pub(crate) fn quantize_unit(value: f32) -> u8 {
    round_byte(value.clamp(0.0, 1.0) * 255.0)
}

/// torchvision's `_blend` on a plane: `ratio * x + (1 - ratio) * other`, clamped to [0, 1].
#[inline(always)]
fn blend_towards_constant(plane: &mut [f32], ratio: f32, other: f32) {
    let offset = (1.0 - ratio) * other;
    for value in plane {
        *value = (ratio * *value + offset).clamp(0.0, 1.0);
    }
}

/// The hue of (r, g, b) rotated by `shift` turns, through HSV as torchvision's `_rgb2hsv` and
/// `_hsv2rgb` define it; branch-free so that it vectorizes.
#[inline(always)]
pub(crate) fn shift_hue(red: f32, green: f32, blue: f32, shift: f32) -> (f32, f32, f32) {
    let max = red.max(green).max(blue);
    let min = red.min(green).min(blue);
    let delta = max - min;
    let saturation = if max > 0.0 { delta / max } else { 0.0 };
    let divisor = if delta > 0.0 { delta } else { 1.0 };
    let sextant_red = (green - blue) / divisor;
    let sextant_green = 2.0 + (blue - red) / divisor;
    let sextant_blue = 4.0 + (red - green) / divisor;
    let sextant = if max == red { sextant_red } else if max == green { sextant_green } else { sextant_blue };
    let sextant = if delta > 0.0 { sextant } else { 0.0 };
    // Hue in turns, shifted, wrapped into [0, 1): sextant / 6 is in [-1/6, 1), shift in [-1/2, 1/2].
    let hue = sextant / 6.0 + shift;
    let hue = if hue < 0.0 { hue + 1.0 } else { hue };
    let hue = if hue >= 1.0 { hue - 1.0 } else { hue };
    let scaled = hue * 6.0;
    let sector = (scaled as i32).min(5); // scaled >= 0, so truncation is floor
    let fraction = scaled - sector as f32;
    let value = max;
    let p = value * (1.0 - saturation);
    let q = value * (1.0 - saturation * fraction);
    let t = value * (1.0 - saturation * (1.0 - fraction));
    let out_red = if sector == 0 || sector == 5 { value } else if sector == 1 { q } else if sector == 4 { t } else { p };
    let out_green = if sector == 1 || sector == 2 { value } else if sector == 0 { t } else if sector == 3 { q } else { p };
    let out_blue = if sector == 3 || sector == 4 { value } else if sector == 2 { t } else if sector == 5 { q } else { p };
    (out_red, out_green, out_blue)
}

const CHUNK: usize = 16;

#[inline(always)]
fn luma_sum(red: &[f32], green: &[f32], blue: &[f32]) -> f64 {
    let mut partial = [0.0f32; CHUNK];
    let chunks = red.len() / CHUNK * CHUNK;
    for start in (0..chunks).step_by(CHUNK) {
        let (r, g, b) = (&red[start..start + CHUNK], &green[start..start + CHUNK], &blue[start..start + CHUNK]);
        for lane in 0..CHUNK {
            partial[lane] += LUMA_WEIGHTS[0] * r[lane] + LUMA_WEIGHTS[1] * g[lane] + LUMA_WEIGHTS[2] * b[lane];
        }
    }
    let mut total: f64 = partial.iter().map(|&value| f64::from(value)).sum();
    for index in chunks..red.len() {
        total += f64::from(LUMA_WEIGHTS[0] * red[index] + LUMA_WEIGHTS[1] * green[index] + LUMA_WEIGHTS[2] * blue[index]);
    }
    total
}

#[inline(always)]
fn jitter_body(src: &[u8], dst: &mut [u8], params: &JitterParams, planes: &mut [f32]) {
    let plane = src.len() / 3;
    for (value, byte) in planes.iter_mut().zip(src) {
        *value = f32::from(*byte) / 255.0;
    }
    for op in params.order {
        match op {
            JitterOp::Brightness => blend_towards_constant(planes, params.brightness, 0.0),
            JitterOp::Contrast => {
                let (red, rest) = planes.split_at(plane);
                let (green, blue) = rest.split_at(plane);
                let mean = (luma_sum(red, &green[..plane], &blue[..plane]) / plane as f64) as f32;
                blend_towards_constant(planes, params.contrast, mean);
            }
            JitterOp::Saturation => {
                let ratio = params.saturation;
                let (red, rest) = planes.split_at_mut(plane);
                let (green, blue) = rest.split_at_mut(plane);
                let (green, blue) = (&mut green[..plane], &mut blue[..plane]);
                for index in 0..plane {
                    let (r, g, b) = (red[index], green[index], blue[index]);
                    let gray = (1.0 - ratio) * (LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b);
                    red[index] = (ratio * r + gray).clamp(0.0, 1.0);
                    green[index] = (ratio * g + gray).clamp(0.0, 1.0);
                    blue[index] = (ratio * b + gray).clamp(0.0, 1.0);
                }
            }
            JitterOp::Hue => {
                let (red, rest) = planes.split_at_mut(plane);
                let (green, blue) = rest.split_at_mut(plane);
                let (green, blue) = (&mut green[..plane], &mut blue[..plane]);
                for index in 0..plane {
                    (red[index], green[index], blue[index]) = shift_hue(red[index], green[index], blue[index], params.hue);
                }
            }
        }
    }
    for (byte, value) in dst.iter_mut().zip(planes.iter()) {
        *byte = quantize_unit(*value);
    }
}

multiversion! {
    /// Colour jitter of one frame through float planes in `planes` (3 x H x W scratch).
    fn jitter_frame(src: &[u8], dst: &mut [u8], params: &JitterParams, planes: &mut [f32]) => jitter_body
}
