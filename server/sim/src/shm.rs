//! Shared memory through which workers hand frames to the server without copying them into a pipe.
//!
//! The server creates an anonymous memory file (`memfd_create`) per group of environments; the worker
//! maps the same file through `/proc/<server pid>/fd/<fd>`. Nothing is left behind in `/dev/shm` when
//! either process dies, and a restarted worker can map the group again.

use std::fs::{File, OpenOptions};
use std::io;
use std::os::fd::{AsRawFd, FromRawFd};

use memmap2::MmapMut;

pub struct SharedFrames {
    file: File,
    map: MmapMut,
}

impl SharedFrames {
    /// Creates a zeroed segment of `len` bytes owned by this process.
    pub fn create(len: usize) -> io::Result<SharedFrames> {
        let name = c"radserve-frames";
        // SAFETY: `name` is a valid C string; the returned descriptor is checked and then owned by `File`.
        let fd = unsafe { libc::memfd_create(name.as_ptr(), libc::MFD_CLOEXEC) };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: `fd` is a fresh descriptor that nothing else owns.
        let file = unsafe { File::from_raw_fd(fd) };
        file.set_len(len.max(1) as u64)?;
        Self::map(file)
    }

    /// Maps a segment created by another process, from the path that process gave.
    pub fn open(path: &str) -> io::Result<SharedFrames> {
        let file = OpenOptions::new().read(true).write(true).open(path)?;
        Self::map(file)
    }

    fn map(file: File) -> io::Result<SharedFrames> {
        // SAFETY: the mapping is shared with exactly one worker, which writes a group's frames only while
        // it handles a request for that group; the server reads them only after the reply (see session.rs).
        let map = unsafe { MmapMut::map_mut(&file)? };
        Ok(SharedFrames { file, map })
    }

    /// The path a child process opens to map this segment.
    pub fn child_path(&self) -> String {
        format!("/proc/{}/fd/{}", std::process::id(), self.file.as_raw_fd())
    }

    pub fn len(&self) -> usize {
        self.map.len()
    }

    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }

    pub fn as_slice(&self) -> &[u8] {
        &self.map
    }

    pub fn as_mut_slice(&mut self) -> &mut [u8] {
        &mut self.map
    }

    pub fn as_mut_ptr(&mut self) -> *mut u8 {
        self.map.as_mut_ptr()
    }
}

/// Where environment `index` of a group keeps its frames: its current frame, then the last frame of
/// its previous episode (written only in the step that ends an episode).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameLayout {
    pub frame_bytes: usize,
}

impl FrameLayout {
    pub fn segment_len(&self, num_envs: usize) -> usize {
        2 * self.frame_bytes * num_envs
    }

    pub fn frame(&self, index: usize) -> std::ops::Range<usize> {
        let start = 2 * self.frame_bytes * index;
        start..start + self.frame_bytes
    }

    pub fn final_frame(&self, index: usize) -> std::ops::Range<usize> {
        let start = 2 * self.frame_bytes * index + self.frame_bytes;
        start..start + self.frame_bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_mapping_sees_the_first_ones_writes() {
        let mut owner = SharedFrames::create(4096).unwrap();
        let peer = SharedFrames::open(&owner.child_path()).unwrap();
        // SAFETY: in bounds of the 4096-byte mapping.
        unsafe { owner.as_mut_ptr().add(100).write(42) };
        assert_eq!(peer.as_slice()[100], 42);
        assert_eq!(peer.len(), 4096);
    }

    #[test]
    fn frames_and_final_frames_do_not_overlap() {
        let layout = FrameLayout { frame_bytes: 10 };
        assert_eq!(layout.frame(1), 20..30);
        assert_eq!(layout.final_frame(1), 30..40);
        assert_eq!(layout.segment_len(2), 40);
    }
}
