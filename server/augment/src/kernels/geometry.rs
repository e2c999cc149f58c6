//! Crop, translate, window, flip, rotate and cutout: pure data movement, row by row.

use super::multiversion;
use crate::shape::FrameShape;

/// Copy a short row without a call into `memcpy` (whose per-call cost dominates 84-byte rows):
/// 32-byte blocks, the last one overlapping its neighbour when the length is not a multiple.
#[inline(always)]
fn copy_row(dst: &mut [u8], src: &[u8]) {
    const BLOCK: usize = 32;
    let len = dst.len();
    debug_assert_eq!(len, src.len());
    if len < BLOCK {
        dst.copy_from_slice(src);
        return;
    }
    let mut copy_block = |start: usize| {
        let from: &[u8; BLOCK] = src[start..start + BLOCK].try_into().unwrap();
        let to: &mut [u8; BLOCK] = (&mut dst[start..start + BLOCK]).try_into().unwrap();
        *to = *from;
    };
    for start in (0..len - BLOCK).step_by(BLOCK) {
        copy_block(start);
    }
    copy_block(len - BLOCK);
}

/// RAD's random crop (section 4): the output window starting at (top, left) of every plane.
pub(super) fn crop(src: &[u8], input: &FrameShape, dst: &mut [u8], output: &FrameShape, top: usize, left: usize) {
    for (plane_src, plane_dst) in src.chunks_exact(input.plane_len()).zip(dst.chunks_exact_mut(output.plane_len())) {
        let rows_src = plane_src[top * input.width..].chunks_exact(input.width);
        for (row_src, row_dst) in rows_src.zip(plane_dst.chunks_exact_mut(output.width)) {
            copy_row(row_dst, &row_src[left..left + output.width]);
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
            copy_row(&mut row_dst[left..left + input.width], row_src);
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
            copy_row(&mut row_dst[left..left + size], &row_src[left..left + size]);
            row_dst[left + size..].fill(0);
        }
    }
}

/// DrQ's random shift: the frame padded by `pad` repeated edge pixels, cropped back to its own size
/// at (top, left) of the padded frame. Each output row is a source row (clamped to the frame)
/// moved by `left - pad` columns, its ends filled with the row's edge pixel.
pub(super) fn shift(src: &[u8], shape: &FrameShape, dst: &mut [u8], pad: usize, top: usize, left: usize) {
    let (height, width) = (shape.height, shape.width);
    // Columns of the output taken from the left edge, from the row itself, from the right edge.
    let moved = left as isize - pad as isize;
    let (left_fill, start) = if moved < 0 { ((-moved) as usize, 0) } else { (0, moved as usize) };
    let left_fill = left_fill.min(width);
    let copied = (width - left_fill).min(width.saturating_sub(start));
    for (plane_src, plane_dst) in src.chunks_exact(shape.plane_len()).zip(dst.chunks_exact_mut(shape.plane_len())) {
        for (y, row_dst) in plane_dst.chunks_exact_mut(width).enumerate() {
            let source_y = (y + top).saturating_sub(pad).min(height - 1);
            let row_src = &plane_src[source_y * width..(source_y + 1) * width];
            row_dst[..left_fill].fill(row_src[0]);
            copy_row(&mut row_dst[left_fill..left_fill + copied], &row_src[start..start + copied]);
            row_dst[left_fill + copied..].fill(row_src[width - 1]);
        }
    }
}

multiversion! {
    /// Mirror the width axis of every row.
    fn flip(src: &[u8], shape: &FrameShape, dst: &mut [u8]) => flip_body
}

#[inline(always)]
fn flip_body(src: &[u8], shape: &FrameShape, dst: &mut [u8]) {
    for (row_src, row_dst) in src.chunks_exact(shape.width).zip(dst.chunks_exact_mut(shape.width)) {
        for (out, value) in row_dst.iter_mut().zip(row_src.iter().rev()) {
            *out = *value;
        }
    }
}

multiversion! {
    /// Rotate every (square) plane by `quarters` counter-clockwise quarter turns, as `np.rot90` does.
    fn rotate(src: &[u8], shape: &FrameShape, dst: &mut [u8], quarters: u8) => rotate_body
}

#[inline(always)]
fn rotate_body(src: &[u8], shape: &FrameShape, dst: &mut [u8], quarters: u8) {
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
            1 | 3 if side < 8 => {
                for y in 0..side {
                    for x in 0..side {
                        let source = if quarters == 1 { x * side + (side - 1 - y) } else { (side - 1 - x) * side + y };
                        plane_dst[y * side + x] = plane_src[source];
                    }
                }
            }
            #[cfg(target_arch = "x86_64")]
            1 | 3 if side >= 16 => sse2::rotate_blocks_16(plane_src, plane_dst, side, quarters == 1),
            1 | 3 => rotate_blocks(plane_src, plane_dst, side, quarters == 1),
            _ => unreachable!("quarters are drawn in 0..=3"),
        }
    }
}

/// Starts of `width`-wide blocks covering `0..side` (side >= width); the last one overlaps its
/// neighbour when `side` is not a multiple, rewriting a few bytes with the same values.
#[inline(always)]
fn block_starts_of(side: usize, width: usize) -> impl Iterator<Item = usize> + Clone {
    (0..side / width).map(move |block| block * width).chain((!side.is_multiple_of(width)).then_some(side - width))
}

#[inline(always)]
fn block_starts(side: usize) -> impl Iterator<Item = usize> + Clone {
    block_starts_of(side, 8)
}

/// Quarter turns 16x16 bytes at a time in SSE2 registers (part of every x86-64 CPU).
#[cfg(target_arch = "x86_64")]
mod sse2 {
    use std::arch::x86_64::{
        __m128i, _mm_loadu_si128, _mm_storeu_si128, _mm_unpackhi_epi16, _mm_unpackhi_epi32, _mm_unpackhi_epi64,
        _mm_unpackhi_epi8, _mm_unpacklo_epi16, _mm_unpacklo_epi32, _mm_unpacklo_epi64, _mm_unpacklo_epi8,
    };

    /// Transpose 16 rows of 16 bytes: four rounds interleave row pairs at 1, 2, 4 and 8 bytes.
    /// Tracking the index bits through the rounds, register `n` ends up holding column
    /// `bit_reverse4(n)`, so column `c` is `rows[bit_reverse4(c)]`.
    #[inline(always)]
    fn transpose_16x16(rows: [__m128i; 16]) -> [__m128i; 16] {
        macro_rules! round {
            ($rows:expr, $low:ident, $high:ident) => {{
                let rows: [__m128i; 16] = $rows;
                let mut next = rows;
                for pair in 0..8 {
                    let (a, b) = (rows[2 * pair], rows[2 * pair + 1]);
                    // SAFETY: SSE2 is part of the x86-64 baseline, so these intrinsics are always available.
                    unsafe {
                        next[pair] = $low(a, b);
                        next[pair + 8] = $high(a, b);
                    }
                }
                next
            }};
        }
        let rows = round!(rows, _mm_unpacklo_epi8, _mm_unpackhi_epi8);
        let rows = round!(rows, _mm_unpacklo_epi16, _mm_unpackhi_epi16);
        let rows = round!(rows, _mm_unpacklo_epi32, _mm_unpackhi_epi32);
        round!(rows, _mm_unpacklo_epi64, _mm_unpackhi_epi64)
    }

    /// `bit_reverse4(column)`: the register of [`transpose_16x16`]'s result holding each column.
    const REGISTER_OF_COLUMN: [usize; 16] = [0, 8, 4, 12, 2, 10, 6, 14, 1, 9, 5, 13, 3, 11, 7, 15];

    /// As `super::rotate_blocks`, with 16x16 blocks (side >= 16).
    #[inline(always)]
    pub(super) fn rotate_blocks_16(src: &[u8], dst: &mut [u8], side: usize, ccw: bool) {
        assert!(side >= 16 && src.len() >= side * side && dst.len() >= side * side);
        #[inline(always)]
        fn load_at(src: &[u8], offset: usize) -> __m128i {
            let bytes = &src[offset..offset + 16];
            // SAFETY: `bytes` is 16 readable bytes; the load is unaligned.
            unsafe { _mm_loadu_si128(bytes.as_ptr().cast()) }
        }
        let load = |offset: usize| load_at(src, offset);
        for block_y in super::block_starts_of(side, 16) {
            for block_x in super::block_starts_of(side, 16) {
                // Row j of the block is 16 contiguous input bytes (see super::rotate_blocks).
                let mut rows = [load(0); 16];
                for (j, row) in rows.iter_mut().enumerate() {
                    *row = if ccw {
                        load((block_x + j) * side + (side - 16 - block_y))
                    } else {
                        load((side - 1 - block_x - j) * side + block_y)
                    };
                }
                let columns = transpose_16x16(rows);
                let mut store = |i: usize, register: __m128i| {
                    let offset = (block_y + i) * side + block_x;
                    let out = &mut dst[offset..offset + 16];
                    // SAFETY: `out` is 16 writable bytes; the store is unaligned.
                    unsafe { _mm_storeu_si128(out.as_mut_ptr().cast(), register) };
                };
                // Output row i is column 15 - i (counter-clockwise) or column i (clockwise).
                if ccw {
                    for i in 0..16 {
                        store(i, columns[REGISTER_OF_COLUMN[15 - i]]);
                    }
                } else {
                    for i in 0..16 {
                        store(i, columns[REGISTER_OF_COLUMN[i]]);
                    }
                }
            }
        }
    }
}

/// Transpose an 8x8 byte matrix held as eight little-endian rows: three rounds of swapping
/// 1-, 2- and 4-byte sub-blocks between row pairs (the recursive block transpose).
#[inline(always)]
fn transpose_8x8(rows: &mut [u64; 8]) {
    #[inline(always)]
    fn swap<const SHIFT: u32, const LOW: u64>(rows: &mut [u64; 8], first: usize, second: usize) {
        let (a, b) = (rows[first], rows[second]);
        rows[first] = (a & LOW) | ((b << SHIFT) & !LOW);
        rows[second] = ((a >> SHIFT) & LOW) | (b & !LOW);
    }
    const BYTES: u64 = 0x00FF_00FF_00FF_00FF;
    const PAIRS: u64 = 0x0000_FFFF_0000_FFFF;
    const QUADS: u64 = 0x0000_0000_FFFF_FFFF;
    for first in [0, 2, 4, 6] {
        swap::<8, BYTES>(rows, first, first + 1);
    }
    for first in [0, 1, 4, 5] {
        swap::<16, PAIRS>(rows, first, first + 2);
    }
    for first in [0, 1, 2, 3] {
        swap::<32, QUADS>(rows, first, first + 4);
    }
}

/// Quarter turns of a square plane, 8x8 blocks at a time. Counter-clockwise (`ccw`):
/// out[y][x] = in[x][side-1-y]; clockwise: out[y][x] = in[side-1-x][y].
#[inline(always)]
fn rotate_blocks(src: &[u8], dst: &mut [u8], side: usize, ccw: bool) {
    let load = |offset: usize| u64::from_le_bytes(src[offset..offset + 8].try_into().unwrap());
    for block_y in block_starts(side) {
        for block_x in block_starts(side) {
            // Row j of the block is 8 contiguous input bytes; after the transpose, byte j of
            // matrix row k is byte k of input row j.
            let mut rows: [u64; 8] = if ccw {
                std::array::from_fn(|j| load((block_x + j) * side + (side - 8 - block_y)))
            } else {
                std::array::from_fn(|j| load((side - 1 - block_x - j) * side + block_y))
            };
            transpose_8x8(&mut rows);
            for i in 0..8 {
                // ccw: out row block_y + i reads input column side-1-block_y-i, byte 7 - i of a row.
                let row = if ccw { rows[7 - i] } else { rows[i] };
                let offset = (block_y + i) * side + block_x;
                dst[offset..offset + 8].copy_from_slice(&row.to_le_bytes());
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
