//! RAD's random convolution: a 3x3 RGB-to-RGB filter with zero padding.

use super::multiversion;

const LANES: usize = 16;

/// Round a convolution output to a byte: clamp to [0, 255] (RAD's reference leaves unbounded
/// floats; a uint8 batch cannot), then round half up.
#[inline(always)]
pub(crate) fn quantize_conv(value: f32) -> u8 {
    (value.clamp(0.0, 255.0) + 0.5) as u8
}

#[inline(always)]
fn conv_body(src: &[u8], dst: &mut [u8], height: usize, width: usize, weights: &[f32; 81], padded: &mut [f32]) {
    let padded_width = width + 2;
    let padded_plane = (height + 2) * padded_width;
    // Zero border, pixel values inside (no scaling: the filter runs on 0..255).
    padded.fill(0.0);
    for channel in 0..3 {
        let plane_src = &src[channel * height * width..(channel + 1) * height * width];
        let plane_pad = &mut padded[channel * padded_plane..(channel + 1) * padded_plane];
        for (row_src, row_pad) in plane_src.chunks_exact(width).zip(plane_pad[padded_width..].chunks_exact_mut(padded_width)) {
            for (value, byte) in row_pad[1..=width].iter_mut().zip(row_src) {
                *value = f32::from(*byte);
            }
        }
    }
    let padded: &[f32] = padded;
    for out_channel in 0..3 {
        let kernel = &weights[out_channel * 27..(out_channel + 1) * 27];
        for y in 0..height {
            // The 27 taps' source rows, in [in][ky] order; tap kx reads the row shifted by kx.
            let rows: [&[f32]; 9] = std::array::from_fn(|index| {
                let (in_channel, ky) = (index / 3, index % 3);
                let start = in_channel * padded_plane + (y + ky) * padded_width;
                &padded[start..start + padded_width]
            });
            let out_row = &mut dst[(out_channel * height + y) * width..][..width];
            let mut x = 0;
            while x + LANES <= width {
                let mut accumulator = [0.0f32; LANES];
                for (row_index, row) in rows.iter().enumerate() {
                    for kx in 0..3 {
                        let weight = kernel[row_index * 3 + kx];
                        let source: &[f32; LANES] = row[x + kx..x + kx + LANES].try_into().unwrap();
                        for lane in 0..LANES {
                            accumulator[lane] += weight * source[lane];
                        }
                    }
                }
                for lane in 0..LANES {
                    out_row[x + lane] = quantize_conv(accumulator[lane]);
                }
                x += LANES;
            }
            for x in x..width {
                let mut accumulator = 0.0f32;
                for (row_index, row) in rows.iter().enumerate() {
                    for kx in 0..3 {
                        accumulator += kernel[row_index * 3 + kx] * row[x + kx];
                    }
                }
                out_row[x] = quantize_conv(accumulator);
            }
        }
    }
}

multiversion! {
    /// Convolve one RGB frame; `padded` is 3 x (H + 2) x (W + 2) float scratch.
    fn conv_frame(src: &[u8], dst: &mut [u8], height: usize, width: usize, weights: &[f32; 81], padded: &mut [f32]) => conv_body
}
