//! Per-sample random parameters. Each (seed, stage, sample key) has its own ChaCha8 stream, so a
//! batch is reproducible from its seed whatever the thread count, and a sample's parameters do not
//! depend on the other samples of the batch.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::shape::FrameShape;
use crate::spec::Augmentation;

/// Which observation of a transition is being augmented.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum TransitionPart {
    #[default]
    Obs,
    NextObs,
}

/// Whether obs and next_obs of a transition get the same random parameters.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Sharing {
    /// RAD's reference behaviour: translate, the centre views and the state augmentations share
    /// their draws; crop and the other image augmentations draw independently.
    #[default]
    Reference,
    /// Every stage uses the same parameters for obs and next_obs.
    Shared,
    /// Every stage draws obs and next_obs independently.
    Independent,
}

/// The randomness of one call: a seed, which observation, the sharing policy, and the stream of
/// draws (outputs with the same stream and part share their parameters stage by stage; a sample
/// request's named views each get a stream of their own unless they share one).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Draws {
    pub seed: u64,
    pub part: TransitionPart,
    pub sharing: Sharing,
    pub stream: u32,
}

impl Draws {
    pub fn new(seed: u64) -> Self {
        Self { seed, ..Self::default() }
    }

    pub fn with_part(self, part: TransitionPart) -> Self {
        Self { part, ..self }
    }

    pub fn with_sharing(self, sharing: Sharing) -> Self {
        Self { sharing, ..self }
    }

    pub fn with_stream(self, stream: u32) -> Self {
        Self { stream, ..self }
    }

    /// The generator of one stage for one sample. `key` names the sample: its index in the batch
    /// by default, or anything the caller wants to hold parameters fixed for (an environment index
    /// across a rollout, say).
    pub(crate) fn rng(&self, stage_index: usize, augmentation: &Augmentation, key: u64) -> ChaCha8Rng {
        let shared = match self.sharing {
            Sharing::Reference => augmentation.shares_draws_by_default(),
            Sharing::Shared => true,
            Sharing::Independent => false,
        };
        let separate_next = self.part == TransitionPart::NextObs && !shared;
        let mut seed = [0u8; 32];
        seed[..8].copy_from_slice(&self.seed.to_le_bytes());
        seed[8..16].copy_from_slice(&(stage_index as u64).to_le_bytes());
        seed[16] = u8::from(separate_next);
        seed[20..24].copy_from_slice(&self.stream.to_le_bytes());
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(key);
        rng
    }
}

/// A standard normal draw (Box-Muller; one of the pair is enough here).
pub(crate) fn standard_normal(rng: &mut impl Rng) -> f32 {
    let u1 = 1.0 - rng.random::<f64>(); // (0, 1]: the logarithm stays finite
    let u2 = rng.random::<f64>();
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

/// One of the four colour-jitter operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum JitterOp {
    Brightness,
    Contrast,
    Saturation,
    Hue,
}

/// The per-sample parameters of colour jitter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JitterParams {
    pub brightness: f32,
    pub contrast: f32,
    pub saturation: f32,
    /// In turns: 0.5 is half-way round the colour wheel.
    pub hue: f32,
    pub order: [JitterOp; 4],
}

/// The parameters one stage uses for one sample.
#[derive(Clone, Debug, PartialEq)]
pub enum StageParams {
    /// Where the output window starts in the input (crop, window; for shift, in the padded input) or
    /// where the input lands in the output canvas (translate); also the fixed offsets of the centre
    /// views.
    Offset { top: usize, left: usize },
    /// A factor every pixel is multiplied by (intensity).
    Factor(f32),
    /// Whether a probabilistic augmentation fires (grayscale, flip).
    Apply(bool),
    /// Counter-clockwise quarter turns, 0 when rotate does not fire.
    Quarters(u8),
    /// The cutout rectangle and its fill (zero for cutout, a random colour for cutout-color).
    Rect { top: usize, left: usize, height: usize, width: usize, fill: [u8; 3] },
    /// Convolution weights indexed `[out][in][ky][kx]`.
    Conv(Box<[f32; 81]>),
    Jitter(JitterParams),
}

/// The standard deviation of Xavier-normal weights for a 3x3 conv from 3 to 3 channels:
/// gain * sqrt(2 / (fan_in + fan_out)) with fan_in = fan_out = 3 * 3 * 3 (Glorot & Bengio 2010,
/// as `torch.nn.init.xavier_normal_` computes it).
pub const CONV_WEIGHT_STD: f32 = 0.192_450_09; // sqrt(2 / 54)

/// Draw one stage's parameters for one sample. `input` is the shape the stage receives.
pub(crate) fn draw(augmentation: &Augmentation, input: &FrameShape, rng: &mut ChaCha8Rng) -> StageParams {
    let (height, width) = (input.height, input.width);
    match *augmentation {
        Augmentation::Crop { size } | Augmentation::Window { size } => {
            StageParams::Offset { top: rng.random_range(0..=height - size), left: rng.random_range(0..=width - size) }
        }
        // Offsets into the padded frame: 0 shows its top (left) `pad` rows of repeated edge.
        Augmentation::Shift { pad } => {
            StageParams::Offset { top: rng.random_range(0..=2 * pad), left: rng.random_range(0..=2 * pad) }
        }
        // DrQ's `Intensity`: `1 + scale * clamp(randn, -2, 2)`.
        Augmentation::Intensity { scale } => {
            StageParams::Factor(1.0 + scale * standard_normal(rng).clamp(-2.0, 2.0))
        }
        Augmentation::Translate { size } => {
            StageParams::Offset { top: rng.random_range(0..=size - height), left: rng.random_range(0..=size - width) }
        }
        // RAD's centre views floor the half-difference (center_crop_image, center_translate).
        Augmentation::CenterCrop { size } => StageParams::Offset { top: (height - size) / 2, left: (width - size) / 2 },
        Augmentation::CenterTranslate { size } => {
            StageParams::Offset { top: (size - height) / 2, left: (size - width) / 2 }
        }
        Augmentation::Grayscale { p } | Augmentation::Flip { p } => StageParams::Apply(rng.random::<f32>() < p),
        Augmentation::Rotate { p } => {
            let fires = rng.random::<f32>() < p;
            StageParams::Quarters(if fires { rng.random_range(1..=3) } else { 0 })
        }
        Augmentation::Cutout { min, max } | Augmentation::CutoutColor { min, max } => {
            let rect_height = rng.random_range(min..=max);
            let rect_width = rng.random_range(min..=max);
            let top = rng.random_range(0..=height - rect_height);
            let left = rng.random_range(0..=width - rect_width);
            let fill = if matches!(augmentation, Augmentation::CutoutColor { .. }) { rng.random() } else { [0; 3] };
            StageParams::Rect { top, left, height: rect_height, width: rect_width, fill }
        }
        Augmentation::RandomConv => {
            let mut weights = Box::new([0.0; 81]);
            for weight in weights.iter_mut() {
                *weight = standard_normal(rng) * CONV_WEIGHT_STD;
            }
            StageParams::Conv(weights)
        }
        Augmentation::ColorJitter { brightness, contrast, saturation, hue } => {
            let mut factor = |spread: f32| 1.0 - spread + 2.0 * spread * rng.random::<f32>();
            let brightness = factor(brightness);
            let contrast = factor(contrast);
            let saturation = factor(saturation);
            let hue = -hue + 2.0 * hue * rng.random::<f32>();
            // torchvision's ColorJitter applies the four in a random order; we draw it per sample.
            let mut order = [JitterOp::Brightness, JitterOp::Contrast, JitterOp::Saturation, JitterOp::Hue];
            for index in (1..order.len()).rev() {
                order.swap(index, rng.random_range(0..=index));
            }
            StageParams::Jitter(JitterParams { brightness, contrast, saturation, hue, order })
        }
        Augmentation::AmplitudeScale { .. } | Augmentation::GaussianNoise { .. } => {
            unreachable!("state augmentations are drawn by the state plan")
        }
    }
}
