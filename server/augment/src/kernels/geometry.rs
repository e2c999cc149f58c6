//! Crop, translate, window, flip, rotate and cutout: pure data movement, row by row.

use crate::shape::FrameShape;

/// RAD's random crop (section 4): the output window starting at (top, left) of every plane.
pub(super) fn crop(src: &[u8], input: &FrameShape, dst: &mut [u8], output: &FrameShape, top: usize, left: usize) {
    for (plane_src, plane_dst) in src.chunks_exact(input.plane_len()).zip(dst.chunks_exact_mut(output.plane_len())) {
        let rows_src = plane_src[top * input.width..].chunks_exact(input.width);
        for (row_src, row_dst) in rows_src.zip(plane_dst.chunks_exact_mut(output.width)) {
            row_dst.copy_from_slice(&row_src[left..left + output.width]);
        }
    }
}

/// RAD's random translate: the input plane placed at (top, left) of a zero canvas.
pub(super) fn translate(src: &[u8], input: &FrameShape, dst: &mut [u8], output: &FrameShape, top: usize, left: usize) {
    let right = output.width - left - input.width;
    for (plane_src, plane_dst) in src.chunks_exact(input.plane_len()).zip(dst.chunks_exact_mut(output.plane_len())) {
        let (above, rest) = plane_dst.split_at_mut(top * output.width);
        above.fill(0);
        let (middle, below) = rest.split_at_mut(input.height * output.width);
        below.fill(0);
        for (row_src, row_dst) in plane_src.chunks_exact(input.width).zip(middle.chunks_exact_mut(output.width)) {
            row_dst[..left].fill(0);
            row_dst[left..left + input.width].copy_from_slice(row_src);
            row_dst[output.width - right..].fill(0);
        }
    }
}

/// RAD's window: keep the `size x size` window at (top, left), zero everything else.
pub(super) fn window(src: &[u8], shape: &FrameShape, dst: &mut [u8], top: usize, left: usize, size: usize) {
    let width = shape.width;
    for (plane_src, plane_dst) in src.chunks_exact(shape.plane_len()).zip(dst.chunks_exact_mut(shape.plane_len())) {
        let (above, rest) = plane_dst.split_at_mut(top * width);
        above.fill(0);
        let (middle, below) = rest.split_at_mut(size * width);
        below.fill(0);
        let rows_src = plane_src[top * width..].chunks_exact(width);
        for (row_src, row_dst) in rows_src.zip(middle.chunks_exact_mut(width)) {
            row_dst[..left].fill(0);
            row_dst[left..left + size].copy_from_slice(&row_src[left..left + size]);
            row_dst[left + size..].fill(0);
        }
    }
}

/// Mirror the width axis of every row.
pub(super) fn flip(src: &[u8], shape: &FrameShape, dst: &mut [u8]) {
    for (row_src, row_dst) in src.chunks_exact(shape.width).zip(dst.chunks_exact_mut(shape.width)) {
        for (out, value) in row_dst.iter_mut().zip(row_src.iter().rev()) {
            *out = *value;
        }
    }
}

/// Rotate every (square) plane by `quarters` counter-clockwise quarter turns, as `np.rot90` does.
pub(super) fn rotate(src: &[u8], shape: &FrameShape, dst: &mut [u8], quarters: u8) {
    let side = shape.width;
    debug_assert_eq!(shape.height, side);
    for (plane_src, plane_dst) in src.chunks_exact(shape.plane_len()).zip(dst.chunks_exact_mut(shape.plane_len())) {
        match quarters {
            0 => plane_dst.copy_from_slice(plane_src),
            2 => {
                for (out, value) in plane_dst.iter_mut().zip(plane_src.iter().rev()) {
                    *out = *value;
                }
            }
            // One quarter: out[y][x] = in[x][side-1-y]; three: out[y][x] = in[side-1-x][y].
            1 => transpose_tiles(plane_src, plane_dst, side, |y, x| x * side + (side - 1 - y)),
            3 => transpose_tiles(plane_src, plane_dst, side, |y, x| (side - 1 - x) * side + y),
            _ => unreachable!("quarters are drawn in 0..=3"),
        }
    }
}

/// Fill `dst[y][x] = src[source(y, x)]` for a transposing `source`, in tiles that stay in L1 so
/// the column-wise reads hit cache.
#[inline(always)]
fn transpose_tiles(src: &[u8], dst: &mut [u8], side: usize, source: impl Fn(usize, usize) -> usize) {
    const TILE: usize = 16;
    let src = &src[..side * side];
    for tile_y in (0..side).step_by(TILE) {
        for tile_x in (0..side).step_by(TILE) {
            for y in tile_y..(tile_y + TILE).min(side) {
                let row = &mut dst[y * side..(y + 1) * side];
                for x in tile_x..(tile_x + TILE).min(side) {
                    row[x] = src[source(y, x)];
                }
            }
        }
    }
}

/// Copy the sample and fill one rectangle (`[top, left, height, width]`) of every frame with
/// `fill[channel]` (cutout and cutout-color).
pub(super) fn cutout(src: &[u8], shape: &FrameShape, dst: &mut [u8], rect: [usize; 4], fill: [u8; 3]) {
    let [top, left, height, width] = rect;
    dst.copy_from_slice(src);
    for (plane_index, plane) in dst.chunks_exact_mut(shape.plane_len()).enumerate() {
        let value = fill[(plane_index % shape.channels).min(2)];
        for row in plane.chunks_exact_mut(shape.width).skip(top).take(height) {
            row[left..left + width].fill(value);
        }
    }
}
