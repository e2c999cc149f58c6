//! The augmentations of RAD (Laskin et al., NeurIPS 2020, section 4 and appendix), as a typed
//! structure with the paper's defaults, validated independently of any observation shape.

use std::fmt;

use crate::error::{AugmentError, Result};

/// Luma weights of ITU-R BT.601 as RAD's grayscale and torchvision's `rgb_to_grayscale` use them.
pub const LUMA_WEIGHTS: [f32; 3] = [0.2989, 0.587, 0.114];

/// One augmentation with its parameters. Every random parameter is drawn once per sample and
/// applied identically to every frame of that sample's stack.
#[derive(Clone, Debug, PartialEq)]
pub enum Augmentation {
    /// A random `size x size` window, offsets uniform in `[0, H - size]` and `[0, W - size]`.
    Crop { size: usize },
    /// The whole frame placed at a random offset in a zero canvas of `size x size`, offsets
    /// uniform in `[0, size - H]` and `[0, size - W]`.
    Translate { size: usize },
    /// Keep a random `size x size` window (crop-like offsets), zero the rest; shape unchanged.
    Window { size: usize },
    /// DrQ's and DrQ-v2's random shift (Kostrikov et al. 2020; Yarats et al. 2021, `RandomShiftsAug`):
    /// the frame padded by `pad` pixels that repeat its edge, then cropped back to its own size at
    /// offsets uniform in `[0, 2 * pad]`; shape unchanged.
    Shift { pad: usize },
    /// DrQ's and SPR's intensity augmentation on Atari: every pixel multiplied by
    /// `1 + scale * clip(N(0, 1), -2, 2)`, one draw per sample, rounded to the nearest byte.
    Intensity { scale: f32 },
    /// The centre `size x size` window: the evaluation view matching `Crop`.
    CenterCrop { size: usize },
    /// The frame centred in a zero canvas of `size x size`: the evaluation view matching `Translate`.
    CenterTranslate { size: usize },
    /// With probability `p`, every frame becomes its luma copied to the three channels.
    Grayscale { p: f32 },
    /// Zero one rectangle with sides uniform in `[min, max]`, uniformly placed where it fits.
    Cutout { min: usize, max: usize },
    /// Like `Cutout`, filled with a random RGB colour.
    CutoutColor { min: usize, max: usize },
    /// With probability `p`, mirror the width axis.
    Flip { p: f32 },
    /// With probability `p`, rotate by 90, 180 or 270 degrees counter-clockwise (uniform).
    Rotate { p: f32 },
    /// A random 3x3 RGB-to-RGB convolution (Xavier-normal weights, no bias, zero padding), clamped
    /// to [0, 255].
    RandomConv,
    /// Brightness, contrast and saturation factors uniform in `[1 - x, 1 + x]` and a hue shift
    /// uniform in `[-hue, hue]` turns, applied in a random order (torchvision's `ColorJitter`).
    ColorJitter { brightness: f32, contrast: f32, saturation: f32, hue: f32 },
    /// State vectors: random amplitude scaling, one factor per sample (RAS-S) or one per dimension
    /// (RAS-M), uniform in `[alpha, beta]`.
    AmplitudeScale { per_dimension: bool, alpha: f32, beta: f32 },
    /// State vectors: additive Gaussian noise with standard deviation `std`.
    GaussianNoise { std: f32 },
}

/// What an augmentation applies to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Domain {
    Image,
    State,
}

/// Every name the text form accepts, canonical first; RAD's own names are accepted as aliases.
pub(crate) const NAMES: &[(&str, &[&str])] = &[
    ("crop", &["random_crop"]),
    ("translate", &[]),
    ("window", &[]),
    ("shift", &["random_shift"]),
    ("intensity", &[]),
    ("center_crop", &[]),
    ("center_translate", &[]),
    ("grayscale", &["gray"]),
    ("cutout", &[]),
    ("cutout_color", &[]),
    ("flip", &[]),
    ("rotate", &[]),
    ("conv", &["rand_conv", "random_conv"]),
    ("color_jitter", &["jitter"]),
    ("ras_s", &[]),
    ("ras_m", &[]),
    ("noise", &["gaussian_noise"]),
];

impl Augmentation {
    /// The canonical name in the text form.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Crop { .. } => "crop",
            Self::Translate { .. } => "translate",
            Self::Window { .. } => "window",
            Self::Shift { .. } => "shift",
            Self::Intensity { .. } => "intensity",
            Self::CenterCrop { .. } => "center_crop",
            Self::CenterTranslate { .. } => "center_translate",
            Self::Grayscale { .. } => "grayscale",
            Self::Cutout { .. } => "cutout",
            Self::CutoutColor { .. } => "cutout_color",
            Self::Flip { .. } => "flip",
            Self::Rotate { .. } => "rotate",
            Self::RandomConv => "conv",
            Self::ColorJitter { .. } => "color_jitter",
            Self::AmplitudeScale { per_dimension: false, .. } => "ras_s",
            Self::AmplitudeScale { per_dimension: true, .. } => "ras_m",
            Self::GaussianNoise { .. } => "noise",
        }
    }

    pub fn domain(&self) -> Domain {
        match self {
            Self::AmplitudeScale { .. } | Self::GaussianNoise { .. } => Domain::State,
            // Listed one by one: a new augmentation must say which observations it applies to.
            Self::Crop { .. }
            | Self::Translate { .. }
            | Self::Window { .. }
            | Self::Shift { .. }
            | Self::Intensity { .. }
            | Self::CenterCrop { .. }
            | Self::CenterTranslate { .. }
            | Self::Grayscale { .. }
            | Self::Cutout { .. }
            | Self::CutoutColor { .. }
            | Self::Flip { .. }
            | Self::Rotate { .. }
            | Self::RandomConv
            | Self::ColorJitter { .. } => Domain::Image,
        }
    }

    /// Whether transitions share this augmentation's draws between obs and next_obs by default.
    /// RAD's reference code shares them for translate and the state augmentations and draws crop
    /// (and every other image augmentation) independently for the two; DrQ and DrQ-v2 shift obs
    /// and next_obs independently.
    pub fn shares_draws_by_default(&self) -> bool {
        matches!(
            self,
            Self::Translate { .. }
                | Self::CenterCrop { .. }
                | Self::CenterTranslate { .. }
                | Self::AmplitudeScale { .. }
                | Self::GaussianNoise { .. }
        )
    }

    /// Whether the augmentation needs RGB frames (three channels).
    pub(crate) fn needs_rgb(&self) -> bool {
        matches!(self, Self::Grayscale { .. } | Self::CutoutColor { .. } | Self::RandomConv | Self::ColorJitter { .. })
    }

    /// Check the parameters on their own (sizes positive, probabilities in [0, 1], ranges ordered).
    pub fn validate(&self) -> Result<()> {
        let name = self.name();
        let invalid = |message: String| Err(AugmentError::InvalidParameter { augmentation: name, message });
        match *self {
            Self::Crop { size } | Self::Translate { size } | Self::Window { size } | Self::CenterCrop { size }
            | Self::CenterTranslate { size } => {
                if size == 0 {
                    return invalid("size must be at least 1, got 0".into());
                }
            }
            Self::Grayscale { p } | Self::Flip { p } | Self::Rotate { p } => {
                if !(0.0..=1.0).contains(&p) {
                    return invalid(format!("p must be a probability in [0, 1], got {p}"));
                }
            }
            Self::Cutout { min, max } | Self::CutoutColor { min, max } => {
                if min == 0 {
                    return invalid("min must be at least 1 (a cutout removes a rectangle), got 0".into());
                }
                if min > max {
                    return invalid(format!("min must not exceed max, got min={min} max={max}"));
                }
            }
            Self::Shift { pad } => {
                if pad == 0 {
                    return invalid("pad must be at least 1 pixel (DrQ's is 4), got 0".into());
                }
            }
            Self::Intensity { scale } => {
                if !(0.0..=0.5).contains(&scale) {
                    return invalid(format!(
                        "scale must be in [0, 0.5] (factors are 1 + scale * clip(N(0, 1), -2, 2)), got {scale}"
                    ));
                }
            }
            Self::RandomConv => {}
            Self::ColorJitter { brightness, contrast, saturation, hue } => {
                for (label, value) in [("brightness", brightness), ("contrast", contrast), ("saturation", saturation)] {
                    if !(0.0..=1.0).contains(&value) {
                        return invalid(format!(
                            "{label} must be in [0, 1] (factors are drawn from [1 - {label}, 1 + {label}]), got {value}"
                        ));
                    }
                }
                if !(0.0..=0.5).contains(&hue) {
                    return invalid(format!("hue must be in [0, 0.5] turns, got {hue}"));
                }
            }
            Self::AmplitudeScale { alpha, beta, .. } => {
                if !(alpha.is_finite() && beta.is_finite()) || alpha > beta {
                    return invalid(format!("alpha and beta must be finite with alpha <= beta, got alpha={alpha} beta={beta}"));
                }
            }
            Self::GaussianNoise { std } => {
                if !(std.is_finite() && std >= 0.0) {
                    return invalid(format!("std must be finite and non-negative, got {std}"));
                }
            }
        }
        Ok(())
    }
}

impl fmt::Display for Augmentation {
    /// The canonical text form, which `Pipeline::parse` reads back to the same value.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = self.name();
        match *self {
            Self::Crop { size } | Self::Translate { size } | Self::Window { size } | Self::CenterCrop { size }
            | Self::CenterTranslate { size } => write!(f, "{name}({size})"),
            Self::Shift { pad } => write!(f, "{name}({pad})"),
            Self::Intensity { scale } => write!(f, "{name}(scale={scale})"),
            Self::Grayscale { p } | Self::Flip { p } | Self::Rotate { p } => write!(f, "{name}(p={p})"),
            Self::Cutout { min, max } | Self::CutoutColor { min, max } => write!(f, "{name}(min={min},max={max})"),
            Self::RandomConv => write!(f, "{name}"),
            Self::ColorJitter { brightness, contrast, saturation, hue } => write!(
                f,
                "{name}(brightness={brightness},contrast={contrast},saturation={saturation},hue={hue})"
            ),
            Self::AmplitudeScale { alpha, beta, .. } => write!(f, "{name}(alpha={alpha},beta={beta})"),
            Self::GaussianNoise { std } => write!(f, "{name}(std={std})"),
        }
    }
}

/// An ordered sequence of augmentations (the paper ablates every ordered pair). Empty means no
/// augmentation. Parameters are validated on construction; shapes are checked when a plan is made.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Pipeline {
    stages: Vec<Augmentation>,
}

/// The most stages a pipeline may have. RAD's and DrQ's pipelines have one or two; the cap bounds the
/// work one sample can ask of the augmentation threads, which every stream shares.
pub const MAX_STAGES: usize = 8;

impl Pipeline {
    pub fn new(stages: Vec<Augmentation>) -> Result<Self> {
        if stages.len() > MAX_STAGES {
            return Err(AugmentError::TooLong {
                message: format!("a pipeline has at most {MAX_STAGES} stages, got {}", stages.len()),
            });
        }
        stages.iter().try_for_each(Augmentation::validate)?;
        Ok(Self { stages })
    }

    pub fn identity() -> Self {
        Self::default()
    }

    pub fn stages(&self) -> &[Augmentation] {
        &self.stages
    }

    pub fn is_empty(&self) -> bool {
        self.stages.is_empty()
    }
}

impl fmt::Display for Pipeline {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.stages.is_empty() {
            return write!(f, "none");
        }
        for (index, stage) in self.stages.iter().enumerate() {
            if index > 0 {
                write!(f, "|")?;
            }
            write!(f, "{stage}")?;
        }
        Ok(())
    }
}
