use std::fmt;

/// The shape of one sample of an image batch: `frames` stacked frames of `channels` planes each,
/// channel-first, so a sample is `[frames * channels, height, width]` uint8 and a batch is
/// `[batch, frames * channels, height, width]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct FrameShape {
    pub frames: usize,
    pub channels: usize,
    pub height: usize,
    pub width: usize,
}

impl FrameShape {
    pub const fn new(frames: usize, channels: usize, height: usize, width: usize) -> Self {
        Self { frames, channels, height, width }
    }

    /// Pixels in one plane.
    pub const fn plane_len(&self) -> usize {
        self.height * self.width
    }

    /// Bytes in one frame (all of its channels).
    pub const fn frame_len(&self) -> usize {
        self.channels * self.plane_len()
    }

    /// Bytes in one sample (the whole stack).
    pub const fn sample_len(&self) -> usize {
        self.frames * self.frame_len()
    }

    /// Planes in one sample.
    pub const fn planes(&self) -> usize {
        self.frames * self.channels
    }

    pub(crate) const fn with_size(&self, height: usize, width: usize) -> Self {
        Self { height, width, ..*self }
    }
}

impl fmt::Display for FrameShape {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} frame(s) of {}x{}x{} (channel-first)",
            self.frames, self.channels, self.height, self.width
        )
    }
}
