//! radserve's augmentation engine: the image and state augmentations of RAD ("Reinforcement
//! Learning with Augmented Data", Laskin et al., NeurIPS 2020) as native kernels.
//!
//! Every random parameter is drawn once per sample and applied identically to all frames of that
//! sample's stack; a seed makes a batch reproducible whatever the thread count. Kernels write into
//! buffers the caller provides and run in parallel over the batch on the current rayon pool.
//!
//! ```
//! use radserve_augment::{Draws, FrameShape, ImagePlan, Pipeline};
//!
//! let pipeline: Pipeline = "crop(84)|grayscale(p=0.3)".parse().unwrap();
//! let plan = ImagePlan::new(&pipeline, FrameShape::new(3, 3, 100, 100)).unwrap();
//! let batch = vec![0u8; 2 * plan.input_shape().sample_len()];
//! let mut out = vec![0u8; 2 * plan.output_shape().sample_len()];
//! plan.apply(&batch, &mut out, &Draws::new(7)).unwrap();
//! ```
//!
//! No tokio, no tonic and no Python here: the service calls this crate.

mod draw;
mod error;
mod kernels;
mod parse;
mod plan;
pub mod reference;
mod shape;
pub mod speed;
mod spec;

pub use draw::{Draws, JitterOp, JitterParams, Sharing, StageParams, TransitionPart, CONV_WEIGHT_STD};
pub use error::{AugmentError, Result};
pub use kernels::Isa;
pub use plan::{ImagePlan, StatePlan, MAX_SAMPLE_BYTES};
pub use shape::FrameShape;
pub use parse::MAX_TEXT_BYTES as MAX_PIPELINE_TEXT_BYTES;
pub use spec::{Augmentation, Domain, Pipeline, LUMA_WEIGHTS, MAX_STAGES};
