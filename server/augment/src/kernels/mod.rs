//! The fast kernels. Each one transforms one sample (a whole frame stack) out of place, from `src`
//! in the stage's input shape to `dst` in its output shape, and writes every output byte.
//! Hot loops are written over fixed-size chunks so that LLVM vectorizes them, and compiled twice:
//! for the baseline target and, chosen at run time, for AVX2 and AVX-512 (see [`Isa`]).

mod color;
pub(crate) use color::LUMA_FIXED;
mod conv;
mod geometry;

use crate::draw::StageParams;
use crate::shape::FrameShape;
use crate::spec::Augmentation;

/// The instruction set the kernels run with. Only constructed after run-time detection, so the
/// AVX2 path is never taken on a CPU without it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Isa(IsaKind);

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum IsaKind {
    Baseline,
    Avx2,
    Avx512,
}

impl Isa {
    /// The target's baseline (SSE2 on x86-64): always available.
    pub const fn baseline() -> Self {
        Self(IsaKind::Baseline)
    }

    /// AVX2, when this CPU has it.
    pub fn avx2() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            return Some(Self(IsaKind::Avx2));
        }
        None
    }

    /// AVX-512 (F and BW, with AVX2), when this CPU has it.
    pub fn avx512() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx512f")
            && std::arch::is_x86_feature_detected!("avx512bw")
            && std::arch::is_x86_feature_detected!("avx2")
        {
            return Some(Self(IsaKind::Avx512));
        }
        None
    }

    /// The best instruction set this CPU offers.
    pub fn detect() -> Self {
        Self::avx512().or_else(Self::avx2).unwrap_or(Self::baseline())
    }

    /// Every instruction set this CPU offers (tests run each of them against the reference).
    pub fn available() -> Vec<Self> {
        std::iter::once(Self::baseline()).chain(Self::avx2()).chain(Self::avx512()).collect()
    }

    pub fn name(&self) -> &'static str {
        match self.0 {
            IsaKind::Baseline => "baseline",
            IsaKind::Avx2 => "avx2",
            IsaKind::Avx512 => "avx512",
        }
    }
}

/// Defines `$name(isa, args...)`, which runs the `#[inline(always)]` body `$body` compiled either
/// for the baseline or, when `isa` says so, inside an `avx2` function so that LLVM vectorizes it
/// with 256-bit registers (the fast_image_resize way of multiversioning).
macro_rules! multiversion {
    ($(#[$meta:meta])* fn $name:ident($($arg:ident: $ty:ty),* $(,)?) => $body:path) => {
        $(#[$meta])*
        pub(crate) fn $name(isa: $crate::kernels::Isa, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn avx2($($arg: $ty),*) {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2,avx512f,avx512bw")]
                fn avx512($($arg: $ty),*) {
                    $body($($arg),*)
                }
                // SAFETY: an `Isa` naming an instruction set only exists after run-time detection
                // of it (`Isa::avx2`, `Isa::avx512`).
                if isa == $crate::kernels::Isa::unchecked(true) {
                    return unsafe { avx512($($arg),*) };
                }
                if isa == $crate::kernels::Isa::unchecked(false) {
                    return unsafe { avx2($($arg),*) };
                }
            }
            let _ = isa;
            $body($($arg),*)
        }
    };
}
pub(crate) use multiversion;

impl Isa {
    /// For comparisons in [`multiversion`] only; never handed out.
    pub(crate) const fn unchecked(avx512: bool) -> Self {
        Self(if avx512 { IsaKind::Avx512 } else { IsaKind::Avx2 })
    }
}

/// Per-thread scratch that kernels needing floats reuse from sample to sample.
#[derive(Default)]
pub(crate) struct FloatScratch {
    floats: Vec<f32>,
}

impl FloatScratch {
    pub(crate) fn take(&mut self, len: usize) -> &mut [f32] {
        if self.floats.len() < len {
            self.floats.resize(len, 0.0);
        }
        &mut self.floats[..len]
    }
}

/// Run one stage on one sample.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run_stage(
    augmentation: &Augmentation,
    params: &StageParams,
    input: &FrameShape,
    output: &FrameShape,
    src: &[u8],
    dst: &mut [u8],
    scratch: &mut FloatScratch,
    isa: Isa,
) {
    debug_assert_eq!(src.len(), input.sample_len());
    debug_assert_eq!(dst.len(), output.sample_len());
    match (augmentation, params) {
        (Augmentation::Crop { .. } | Augmentation::CenterCrop { .. }, StageParams::Offset { top, left }) => {
            geometry::crop(src, input, dst, output, *top, *left)
        }
        (Augmentation::Translate { .. } | Augmentation::CenterTranslate { .. }, StageParams::Offset { top, left }) => {
            geometry::translate(src, input, dst, output, *top, *left)
        }
        (Augmentation::Window { size }, StageParams::Offset { top, left }) => {
            geometry::window(src, input, dst, *top, *left, *size)
        }
        (&Augmentation::Shift { pad }, StageParams::Offset { top, left }) => geometry::shift(src, input, dst, pad, *top, *left),
        (Augmentation::Intensity { .. }, StageParams::Factor(factor)) => color::intensity(isa, src, dst, *factor),
        (Augmentation::Flip { .. }, StageParams::Apply(fires)) => {
            if *fires {
                geometry::flip(isa, src, input, dst)
            } else {
                dst.copy_from_slice(src)
            }
        }
        (Augmentation::Rotate { .. }, StageParams::Quarters(quarters)) => geometry::rotate(isa, src, input, dst, *quarters),
        (Augmentation::Cutout { .. } | Augmentation::CutoutColor { .. }, StageParams::Rect { top, left, height, width, fill }) => {
            geometry::cutout(src, input, dst, [*top, *left, *height, *width], *fill)
        }
        (Augmentation::Grayscale { .. }, StageParams::Apply(fires)) => {
            if *fires {
                for (frame_src, frame_dst) in src.chunks_exact(input.frame_len()).zip(dst.chunks_exact_mut(input.frame_len())) {
                    color::grayscale_frame(isa, frame_src, frame_dst)
                }
            } else {
                dst.copy_from_slice(src)
            }
        }
        (Augmentation::RandomConv, StageParams::Conv(weights)) => {
            let padded = scratch.take(3 * (input.height + 2) * (input.width + 2));
            for (frame_src, frame_dst) in src.chunks_exact(input.frame_len()).zip(dst.chunks_exact_mut(input.frame_len())) {
                conv::conv_frame(isa, frame_src, frame_dst, input.height, input.width, weights, padded)
            }
        }
        (Augmentation::ColorJitter { .. }, StageParams::Jitter(jitter)) => {
            let planes = scratch.take(3 * input.plane_len());
            for (frame_src, frame_dst) in src.chunks_exact(input.frame_len()).zip(dst.chunks_exact_mut(input.frame_len())) {
                color::jitter_frame(isa, frame_src, frame_dst, jitter, planes)
            }
        }
        (augmentation, params) => unreachable!("{augmentation:?} drawn with {params:?}"),
    }
}
