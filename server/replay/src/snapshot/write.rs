//! Writing snapshots: a segment of the frames recorded since the last one (or every frame held, for
//! a full one), copied a block at a time under the buffer's read lock and paced, the priorities
//! (whole, once a prioritized stream sampled the buffer), then the manifest.

use std::io::{self, BufWriter, Write};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use super::dir::{SnapshotDir, SnapshotPath};
use super::{
    block_records, priorities_name, segment_name, Manifest, PriorityEntry, Result, SavedCounters, SegmentEntry,
    SessionCounters, SnapshotError, BLOCK_HEADER_BYTES, FORMAT_VERSION, MANIFEST, MANIFEST_MAGIC, MANIFEST_TMP,
    MAX_SEGMENTS, PRIORITIES_HEADER_BYTES, PRIORITIES_MAGIC, SEGMENT_HEADER_BYTES, SEGMENT_MAGIC,
};
use crate::buffer::{BufferKind, ReplayBuffer, ReplayLayout};

/// Paces a writer to a rate, unless told to hurry (a final snapshot at shutdown).
pub struct Throttle {
    bytes_per_second: u64,
    start: Instant,
    bytes: u64,
    hurry: Option<Arc<AtomicBool>>,
}

impl Throttle {
    /// At most `bytes_per_second` (0: as fast as the disk takes it); `hurry`, once set, lifts the limit.
    pub fn new(bytes_per_second: u64, hurry: Option<Arc<AtomicBool>>) -> Self {
        Throttle { bytes_per_second, start: Instant::now(), bytes: 0, hurry }
    }

    fn account(&mut self, bytes: usize) {
        self.bytes += bytes as u64;
        if self.bytes_per_second == 0 {
            return;
        }
        let due = Duration::from_secs_f64(self.bytes as f64 / self.bytes_per_second as f64);
        // Sleep in short steps so that a hurry is noticed.
        while self.start.elapsed() < due && !self.hurry.as_ref().is_some_and(|hurry| hurry.load(Ordering::Relaxed)) {
            std::thread::sleep((due - self.start.elapsed()).min(Duration::from_millis(50)));
        }
    }
}

/// What one snapshot wrote.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SnapshotReport {
    /// Bytes of the new segment, and of the priorities file written with it.
    pub bytes: u64,
    /// Transitions (frames) it holds.
    pub frames: u64,
    /// Whether it was full (every frame the buffer holds; older segments deleted).
    pub full: bool,
    /// Bytes the snapshot takes on disk now (every listed segment and the priorities file).
    pub disk_bytes: u64,
    pub duration: Duration,
}

/// Writes the snapshots of one buffer into its directory, each after the last.
#[derive(Debug)]
pub struct SnapshotWriter {
    pub(super) dir: SnapshotPath,
    pub(super) layout: ReplayLayout,
    pub(super) manifest: Manifest,
    pub(super) next_sequence: u64,
}

impl SnapshotWriter {
    /// A writer for a buffer with no snapshot yet in `dir` (created on the first write). Only replay
    /// buffers are snapshotted: a rollout is on-policy data of the policy of its last update, which a
    /// learner collects again after a restart anyway.
    pub fn new(dir: &SnapshotPath, identity: &str, layout: ReplayLayout) -> Result<Self> {
        if layout.kind != BufferKind::Replay {
            return Err(SnapshotError::new(&dir.path(), "only replay buffers are snapshotted, not rollouts"));
        }
        Ok(SnapshotWriter { dir: dir.clone(), layout, manifest: Manifest::empty(identity, &layout), next_sequence: 1 })
    }

    /// The snapshot's directory, for messages.
    pub fn dir(&self) -> PathBuf {
        self.dir.path()
    }

    /// Bytes the snapshot takes on disk (its listed segments).
    pub fn disk_bytes(&self) -> u64 {
        self.manifest.bytes()
    }

    /// Frames the snapshot on disk holds or skipped, over all envs: once the buffer's
    /// `frames_written` equals it, the snapshot holds everything recorded.
    pub fn covered_frames(&self) -> u64 {
        self.manifest.written.iter().sum()
    }

    /// Whether a snapshot was ever written (a manifest exists).
    pub fn written(&self) -> bool {
        !self.manifest.segments.is_empty()
    }

    /// Frames recorded since the last snapshot that the buffer still holds (what the next snapshot
    /// writes, unless it is a full one).
    pub fn pending_frames(&self, buffer: &ReplayBuffer) -> u64 {
        (0..self.layout.num_envs)
            .map(|env| buffer.written[env].saturating_sub(self.manifest.written[env].max(buffer.held_from(env))))
            .sum()
    }

    /// Write the frames recorded since the last snapshot (or every frame, when it is time for a full
    /// one) and a manifest that includes them. On any error (a full disk), the new segment is removed
    /// and the previous snapshot stays as it was: the next call writes the same frames again.
    pub fn write(&mut self, buffer: &RwLock<ReplayBuffer>, session: SessionCounters, throttle: &mut Throttle) -> Result<SnapshotReport> {
        let started = Instant::now();
        let dir = match self.dir.open(true) {
            Ok(Some(dir)) => dir,
            Ok(None) => return Err(SnapshotError::new(&self.dir.path(), "could not be created")),
            Err(error) => return Err(SnapshotError::io(&self.dir.path(), error)),
        };
        let full = self.manifest.segments.is_empty()
            || self.manifest.segments.len() >= MAX_SEGMENTS
            || self.manifest.bytes() > 2 * self.layout.memory_bytes() as u64;
        let sequence = self.next_sequence;
        let name = segment_name(sequence);
        let path = dir.path().join(&name);
        let written = match self.write_segment(&dir, &name, sequence, buffer, full, throttle) {
            Ok(written) => written,
            Err(error) => {
                let _ = dir.remove(&name);
                return Err(SnapshotError::io(&path, error));
            }
        };
        let (bytes, frames, hi) = written;
        // The priorities, whole (copied under the read lock in one go: 16 bytes per transition).
        let exported = buffer.read().expect("replay lock").export_priorities();
        let priorities = match exported.map(|contents| write_priorities(&dir, sequence, &contents)).transpose() {
            Ok(entry) => entry,
            Err(error) => {
                let _ = dir.remove(&name);
                let _ = dir.remove(&priorities_name(sequence));
                return Err(SnapshotError::io(&dir.path().join(priorities_name(sequence)), error));
            }
        };
        let mut manifest = self.manifest.clone();
        manifest.priorities = priorities;
        if full {
            manifest.segments.clear();
        }
        manifest.segments.push(SegmentEntry { sequence, bytes });
        manifest.written = hi;
        let counters = buffer.read().expect("replay lock").counters;
        manifest.counters = SavedCounters { inserts: counters.inserts, samples: counters.samples, batches: counters.batches };
        manifest.session = session;
        manifest.unix_time_s = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_secs());
        if let Err(error) = write_manifest(&dir, &manifest) {
            let _ = dir.remove(&name);
            let _ = dir.remove(&priorities_name(sequence));
            return Err(error);
        }
        if let Some(old) = self.manifest.priorities {
            let _ = dir.remove(&priorities_name(old.sequence));
        }
        if full {
            for old in &self.manifest.segments {
                let _ = dir.remove(&segment_name(old.sequence));
            }
        }
        self.manifest = manifest;
        self.next_sequence += 1;
        let bytes = bytes + priorities.map_or(0, |entry| entry.bytes);
        Ok(SnapshotReport { bytes, frames, full, disk_bytes: self.manifest.bytes(), duration: started.elapsed() })
    }

    /// Writes one segment; (its bytes, the frames in it, one past the last frame covered per env).
    fn write_segment(
        &self,
        dir: &SnapshotDir,
        name: &str,
        sequence: u64,
        buffer: &RwLock<ReplayBuffer>,
        full: bool,
        throttle: &mut Throttle,
    ) -> io::Result<(u64, u64, Vec<u64>)> {
        let layout = &self.layout;
        let mut out = BufWriter::with_capacity(1 << 20, dir.create_exclusive(name)?);
        let mut header = Vec::with_capacity(SEGMENT_HEADER_BYTES);
        header.extend_from_slice(SEGMENT_MAGIC);
        header.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
        header.extend_from_slice(&sequence.to_le_bytes());
        for value in [layout.num_envs, layout.frame_bytes, layout.action_bytes] {
            header.extend_from_slice(&(value as u32).to_le_bytes());
        }
        header.extend_from_slice(&crc32fast::hash(&header).to_le_bytes());
        out.write_all(&header)?;
        let mut bytes = header.len() as u64;
        let (mut frames, per_block) = (0u64, block_records(layout) as u64);
        let mut hi = if full { vec![0; layout.num_envs] } else { self.manifest.written.clone() };
        let mut block = Vec::with_capacity(BLOCK_HEADER_BYTES + per_block as usize * layout.snapshot_record_bytes() + 4);
        for (env, hi) in hi.iter_mut().enumerate() {
            let (mut first, target) = {
                let replay = buffer.read().expect("replay lock");
                (if full { replay.held_from(env) } else { *hi }, replay.written[env])
            };
            loop {
                block.clear();
                let count = {
                    let replay = buffer.read().expect("replay lock");
                    // Lapped by stepping: what was overwritten is gone; continue from what is held.
                    first = first.max(replay.held_from(env));
                    if first >= target {
                        break;
                    }
                    let count = per_block.min(target - first);
                    block.extend_from_slice(&(env as u32).to_le_bytes());
                    block.extend_from_slice(&(count as u32).to_le_bytes());
                    block.extend_from_slice(&first.to_le_bytes());
                    for frame in first..first + count {
                        replay.export_record(env, frame, &mut block);
                    }
                    count
                };
                block.extend_from_slice(&crc32fast::hash(&block).to_le_bytes());
                out.write_all(&block)?;
                throttle.account(block.len());
                bytes += block.len() as u64;
                frames += count;
                first += count;
                *hi = first;
            }
        }
        let file = out.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()?;
        Ok((bytes, frames, hi))
    }

    /// Remove the snapshot (its directory and the files in it; a symlink in it is removed, never
    /// followed).
    pub fn discard(&self) -> io::Result<()> {
        match self.dir.open_parent(false)? {
            Some(parent) => parent.remove_tree(self.dir.name()),
            None => Ok(()),
        }
    }
}

/// Writes a priorities file (`contents` without its header and checksum) for segment `sequence`.
fn write_priorities(dir: &SnapshotDir, sequence: u64, records: &[u8]) -> io::Result<PriorityEntry> {
    let name = priorities_name(sequence);
    let mut file = BufWriter::new(dir.create_exclusive(&name)?);
    let mut hasher = crc32fast::Hasher::new();
    let mut put = |bytes: &[u8]| -> io::Result<()> {
        hasher.update(bytes);
        file.write_all(bytes)
    };
    let (max, pairs) = records.split_at(8);
    put(PRIORITIES_MAGIC)?;
    put(&FORMAT_VERSION.to_le_bytes())?;
    put(&((pairs.len() / 16) as u64).to_le_bytes())?;
    put(max)?;
    put(pairs)?;
    let crc = hasher.finalize();
    file.write_all(&crc.to_le_bytes())?;
    file.into_inner().map_err(|error| error.into_error())?.sync_all()?;
    Ok(PriorityEntry { sequence, bytes: (PRIORITIES_HEADER_BYTES + pairs.len() + 4) as u64 })
}

pub(super) fn write_manifest(dir: &SnapshotDir, manifest: &Manifest) -> Result<()> {
    let body = serde_json::to_vec(manifest).expect("a manifest serializes");
    let mut contents = Vec::with_capacity(body.len() + 20);
    contents.extend_from_slice(MANIFEST_MAGIC);
    contents.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    contents.extend_from_slice(&(body.len() as u32).to_le_bytes());
    contents.extend_from_slice(&body);
    contents.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
    let write = || -> io::Result<()> {
        let mut file = dir.create_exclusive(MANIFEST_TMP)?;
        file.write_all(&contents)?;
        file.sync_all()?;
        dir.rename(MANIFEST_TMP, MANIFEST)?;
        // The rename itself must reach the disk before the old segments are deleted.
        dir.sync()
    };
    write().map_err(|error| {
        let _ = dir.remove(MANIFEST_TMP);
        SnapshotError::io(&dir.path().join(MANIFEST), error)
    })
}

impl ReplayBuffer {
    /// Append the record of `frame` of `env` (held: `held_from(env)..written`) to `out`: the frame, its
    /// transition's action, reward, flags, episode start and step index.
    fn export_record(&self, env: usize, frame: u64, out: &mut Vec<u8>) {
        let slot = self.slot(env, frame);
        let (frame_bytes, action_bytes) = (self.layout.frame_bytes, self.layout.action_bytes);
        out.extend_from_slice(&self.frames[slot * frame_bytes..(slot + 1) * frame_bytes]);
        out.extend_from_slice(&self.actions[slot * action_bytes..(slot + 1) * action_bytes]);
        out.extend_from_slice(&self.rewards[slot].to_le_bytes());
        out.push(self.flags[slot]);
        out.extend_from_slice(&self.episode_starts[slot].to_le_bytes());
        out.extend_from_slice(&self.step_indices[slot].to_le_bytes());
    }
}
