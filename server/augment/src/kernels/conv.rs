//! RAD's random convolution: a 3x3 RGB-to-RGB filter with zero padding.

use super::color::round_byte;
use super::multiversion;

const LANES: usize = 32;

/// Round a convolution output to a byte: clamp to [0, 255] (RAD's reference leaves unbounded
/// floats; a uint8 batch cannot), then round to nearest, ties to even.
#[inline(always)]
fn quantize_conv(value: f32) -> u8 {
    round_byte(value.clamp(0.0, 255.0))
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
    let plane_len = height * width;
    let (out_red, rest) = dst.split_at_mut(plane_len);
    let (out_green, out_blue) = rest.split_at_mut(plane_len);
    let mut out_planes = [out_red, out_green, &mut out_blue[..plane_len]];
    for y in 0..height {
        // The 27 taps' source rows, in [in][ky] order; tap kx reads the row shifted by kx.
        let rows: [&[f32]; 9] = std::array::from_fn(|index| {
            let (in_channel, ky) = (index / 3, index % 3);
            let start = in_channel * padded_plane + (y + ky) * padded_width;
            &padded[start..start + padded_width]
        });
        let row_range = y * width..(y + 1) * width;
        if width < LANES {
            for (out_channel, out_plane) in out_planes.iter_mut().enumerate() {
                let kernel = &weights[out_channel * 27..(out_channel + 1) * 27];
                for (x, out) in out_plane[row_range.clone()].iter_mut().enumerate() {
                    let mut accumulator = 0.0f32;
                    for (row_index, row) in rows.iter().enumerate() {
                        for kx in 0..3 {
                            accumulator += kernel[row_index * 3 + kx] * row[x + kx];
                        }
                    }
                    *out = quantize_conv(accumulator);
                }
            }
            continue;
        }
        // Chunks of LANES pixels for all three output channels at once: each source load feeds
        // three independent accumulation chains. The last chunk overlaps the one before when the
        // width is not a multiple, recomputing a few pixels with the same arithmetic (same bytes).
        // Every pixel still sums its 27 taps in the reference's order.
        let last_start = width - LANES;
        for x in (0..last_start).step_by(LANES).chain(std::iter::once(last_start)) {
            let (mut red, mut green, mut blue) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
            for (row_index, row) in rows.iter().enumerate() {
                for kx in 0..3 {
                    let tap = row_index * 3 + kx;
                    let source: &[f32; LANES] = row[x + kx..x + kx + LANES].try_into().unwrap();
                    let (weight_red, weight_green, weight_blue) = (weights[tap], weights[27 + tap], weights[54 + tap]);
                    for lane in 0..LANES {
                        red[lane] += weight_red * source[lane];
                        green[lane] += weight_green * source[lane];
                        blue[lane] += weight_blue * source[lane];
                    }
                }
            }
            let accumulators = [red, green, blue];
            for (accumulator, out_plane) in accumulators.iter().zip(out_planes.iter_mut()) {
                let start = row_range.start + x;
                let out: &mut [u8; LANES] = (&mut out_plane[start..start + LANES]).try_into().unwrap();
                for lane in 0..LANES {
                    out[lane] = quantize_conv(accumulator[lane]);
                }
            }
        }
    }
}

multiversion! {
    /// Convolve one RGB frame; `padded` is 3 x (H + 2) x (W + 2) float scratch.
    fn conv_frame(src: &[u8], dst: &mut [u8], height: usize, width: usize, weights: &[f32; 81], padded: &mut [f32]) => conv_body
}
