//! A replay buffer on disk, so that a named session's replay survives a restart (Reverb checkpoints
//! its tables for the same reason; the format here is radserve's own).
//!
//! A snapshot is a directory:
//! - `seg-NNNNNNNN.rsnap`: append-only segments. Each holds, per env, the frames (with their
//!   transitions' metadata) written since the previous segment, in blocks of consecutive frames, each
//!   block with its own CRC-32. A segment costs the transitions recorded since the last one, not the
//!   buffer. When the segments reach twice the buffer's size (or [`MAX_SEGMENTS`]), the next one is
//!   *full*: every frame the buffer holds, after which the older segments are deleted.
//! - `prio-NNNNNNNN.rsnap` (format 2), once a prioritized stream sampled the buffer: every held
//!   transition's priority (key and value) and the largest priority set, written whole with each
//!   segment (priorities change anywhere in the buffer, not only where frames were added). A
//!   snapshot of format 1 has none: its transitions start at priority 1, as in a buffer no
//!   prioritized stream has sampled.
//! - `MANIFEST`: which segments (and which priorities file) make the snapshot, in order, and the
//!   buffer's state at the end of the last one (frames written per env, counters). It is written to `MANIFEST.tmp`, synced and renamed
//!   over the old one: a crash at any point leaves the previous snapshot whole (a segment the manifest
//!   does not list is ignored and removed).
//!
//! Frames are copied under the buffer's read lock a block at a time, so acting (which takes the write
//! lock to record) waits at most for one block's copy. If acting laps the copy (an env writes a whole
//! ring of frames while its blocks are written), the lost frames are skipped: the reader sees a gap
//! and the restored buffer samples nothing that reaches below it.
//!
//! Reading trusts nothing: files are opened relative to the directory's descriptor, never through a
//! symlink, and read only when they are regular files (`dir.rs`); sizes are checked against the
//! layout the session was created with (its memory already reserved) and the format's own limits
//! before anything is read, the counters against the frames the segments hold, every block's CRC
//! before it is applied, and any failure leaves the buffer empty with an error that names the file.

use std::io;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::buffer::ReplayLayout;

mod dir;
mod read;
mod write;

pub use dir::SnapshotPath;
pub use read::{restore, RestoreReport};
pub use write::{SnapshotReport, SnapshotWriter, Throttle};

/// The on-disk format this build writes: 2 adds the priorities file. It reads 1 and 2.
pub const FORMAT_VERSION: u32 = 2;
/// The oldest format this build reads.
pub const OLDEST_READABLE_VERSION: u32 = 1;
/// Segments a snapshot may list before the next one is full.
pub const MAX_SEGMENTS: usize = 256;
const MANIFEST: &str = "MANIFEST";
const MANIFEST_TMP: &str = "MANIFEST.tmp";
const MANIFEST_MAGIC: &[u8; 8] = b"RSNPMANI";
const SEGMENT_MAGIC: &[u8; 8] = b"RSNPSEGM";
const PRIORITIES_MAGIC: &[u8; 8] = b"RSNPPRIO";
/// magic, version, transitions, the largest priority set.
const PRIORITIES_HEADER_BYTES: usize = 8 + 4 + 8 + 8;
/// A transition's key and its priority.
const PRIORITY_RECORD_BYTES: usize = 8 + 8;
/// A manifest lists at most MAX_SEGMENTS segments and one count per env: far below this.
const MAX_MANIFEST_BYTES: u64 = 1 << 20;
/// The largest value a counter of a snapshot may hold (frames per env, inserts, samples, steps):
/// 2^48 is ~9,000 years of a million env steps per second, and far enough below 2^64 that nothing
/// restored from a forged manifest can wrap when the session counts on.
const MAX_COUNTER: u64 = 1 << 48;
/// Bytes of the frames and metadata of one block (at least one record, whatever its size).
const BLOCK_BYTES: usize = 4 << 20;
/// magic, version, sequence, num_envs, frame_bytes, action_bytes, CRC.
const SEGMENT_HEADER_BYTES: usize = 8 + 4 + 8 + 4 + 4 + 4 + 4;
/// env, count, first frame.
const BLOCK_HEADER_BYTES: usize = 4 + 4 + 8;

/// What a snapshot could not do, and the file it was about.
#[derive(Debug, thiserror::Error)]
#[error("snapshot file {}: {message}", file.display())]
pub struct SnapshotError {
    pub file: PathBuf,
    pub message: String,
}

impl SnapshotError {
    fn new(file: &Path, message: impl Into<String>) -> Self {
        SnapshotError { file: file.to_path_buf(), message: message.into() }
    }

    fn io(file: &Path, error: io::Error) -> Self {
        Self::new(file, error.to_string())
    }
}

type Result<T> = std::result::Result<T, SnapshotError>;

/// The session's own counters, kept with its replay so a restored session continues them.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionCounters {
    /// Step calls (the step index recorded with each transition).
    pub step_calls: u64,
    pub total_env_steps: u64,
    pub episodes_completed: u64,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SavedCounters {
    inserts: u64,
    samples: u64,
    batches: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct SegmentEntry {
    sequence: u64,
    bytes: u64,
}

/// The priorities file of a snapshot (format 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PriorityEntry {
    sequence: u64,
    bytes: u64,
}

#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    /// What the session was created as (env id, options, envs...), as its creator described it.
    identity: String,
    capacity: u64,
    num_envs: u64,
    frame_stack: u64,
    frame_bytes: u64,
    action_bytes: u64,
    segments: Vec<SegmentEntry>,
    /// Per env: one past the last frame the segments hold.
    written: Vec<u64>,
    counters: SavedCounters,
    session: SessionCounters,
    /// When the last segment was written (seconds since the Unix epoch).
    unix_time_s: u64,
    /// The buffer's priorities, once a prioritized stream sampled it (format 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    priorities: Option<PriorityEntry>,
}

impl Manifest {
    fn empty(identity: &str, layout: &ReplayLayout) -> Self {
        Manifest {
            identity: identity.to_string(),
            capacity: layout.capacity as u64,
            num_envs: layout.num_envs as u64,
            frame_stack: layout.frame_stack as u64,
            frame_bytes: layout.frame_bytes as u64,
            action_bytes: layout.action_bytes as u64,
            segments: Vec::new(),
            written: vec![0; layout.num_envs],
            counters: SavedCounters::default(),
            session: SessionCounters::default(),
            unix_time_s: 0,
            priorities: None,
        }
    }

    fn bytes(&self) -> u64 {
        self.segments.iter().map(|segment| segment.bytes).sum::<u64>() + self.priorities.map_or(0, |entry| entry.bytes)
    }
}

fn segment_name(sequence: u64) -> String {
    format!("seg-{sequence:08}.rsnap")
}

fn priorities_name(sequence: u64) -> String {
    format!("prio-{sequence:08}.rsnap")
}

/// Whether this build reads snapshot files of `version`.
fn readable(version: u32) -> bool {
    (OLDEST_READABLE_VERSION..=FORMAT_VERSION).contains(&version)
}

fn unreadable(version: u32) -> String {
    format!("snapshot format version {version}; this server reads versions {OLDEST_READABLE_VERSION} to {FORMAT_VERSION}")
}

/// Records of one block: as many as fit in [`BLOCK_BYTES`], at least one.
fn block_records(layout: &ReplayLayout) -> usize {
    (BLOCK_BYTES / layout.snapshot_record_bytes().max(1)).max(1)
}

/// Moves a snapshot that could not be used out of the way (`<dir>.rejected-<unix time>`), so a new one
/// can start in its place and nothing is deleted; the new path. A symlink planted as the snapshot's
/// directory is moved itself, never what it points to.
pub fn set_aside(dir: &SnapshotPath) -> io::Result<PathBuf> {
    let stamp = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_nanos());
    let name = format!("{}.rejected-{stamp}", dir.name());
    let parent = dir.open_parent(false)?.ok_or_else(|| io::Error::new(io::ErrorKind::NotFound, "the snapshot's directory is gone"))?;
    parent.rename(dir.name(), &name)?;
    Ok(parent.path().join(name))
}

#[cfg(test)]
mod tests;
