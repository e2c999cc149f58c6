//! A replay buffer on disk, so that a named session's replay survives a restart (Reverb checkpoints
//! its tables for the same reason; the format here is radserve's own).
//!
//! A snapshot is a directory:
//! - `seg-NNNNNNNN.rsnap`: append-only segments. Each holds, per env, the frames (with their
//!   transitions' metadata) written since the previous segment, in blocks of consecutive frames, each
//!   block with its own CRC-32. A segment costs the transitions recorded since the last one, not the
//!   buffer. When the segments reach twice the buffer's size (or [`MAX_SEGMENTS`]), the next one is
//!   *full*: every frame the buffer holds, after which the older segments are deleted.
//! - `MANIFEST`: which segments make the snapshot, in order, and the buffer's state at the end of the
//!   last one (frames written per env, counters). It is written to `MANIFEST.tmp`, synced and renamed
//!   over the old one: a crash at any point leaves the previous snapshot whole (a segment the manifest
//!   does not list is ignored and removed).
//!
//! Frames are copied under the buffer's read lock a block at a time, so acting (which takes the write
//! lock to record) waits at most for one block's copy. If acting laps the copy (an env writes a whole
//! ring of frames while its blocks are written), the lost frames are skipped: the reader sees a gap
//! and the restored buffer samples nothing that reaches below it.
//!
//! Reading trusts nothing: sizes are checked against the layout the session was created with (its
//! memory already reserved) before anything is read, every block's CRC before it is applied, and any
//! failure leaves the buffer empty with an error that names the file.

use std::fs::{self, File};
use std::io::{self, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use crate::buffer::{BufferKind, ReplayBuffer, ReplayCounters, ReplayLayout, FIRST_OF_EPISODE, TERMINATED, TRUNCATED};

/// The on-disk format this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
/// Segments a snapshot may list before the next one is full.
pub const MAX_SEGMENTS: usize = 256;
const MANIFEST: &str = "MANIFEST";
const MANIFEST_TMP: &str = "MANIFEST.tmp";
const MANIFEST_MAGIC: &[u8; 8] = b"RSNPMANI";
const SEGMENT_MAGIC: &[u8; 8] = b"RSNPSEGM";
/// A manifest lists at most MAX_SEGMENTS segments and one count per env: far below this.
const MAX_MANIFEST_BYTES: u64 = 1 << 20;
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
        }
    }

    fn bytes(&self) -> u64 {
        self.segments.iter().map(|segment| segment.bytes).sum()
    }
}

fn segment_name(sequence: u64) -> String {
    format!("seg-{sequence:08}.rsnap")
}

/// Records of one block: as many as fit in [`BLOCK_BYTES`], at least one.
fn block_records(layout: &ReplayLayout) -> usize {
    (BLOCK_BYTES / layout.slot_bytes().max(1)).max(1)
}

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
    /// Bytes of the new segment.
    pub bytes: u64,
    /// Transitions (frames) it holds.
    pub frames: u64,
    /// Whether it was full (every frame the buffer holds; older segments deleted).
    pub full: bool,
    /// Bytes the snapshot takes on disk now (every listed segment).
    pub disk_bytes: u64,
    pub duration: Duration,
}

/// What a restore read.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RestoreReport {
    /// Transitions that can be sampled from the restored buffer.
    pub transitions: usize,
    /// Bytes of segments read.
    pub bytes: u64,
    /// Episodes that were in progress when the snapshot was taken, now ended as truncated.
    pub truncated_episodes: usize,
    pub session: SessionCounters,
    /// How old the snapshot was when restored.
    pub age: Duration,
    pub duration: Duration,
}

/// Writes the snapshots of one buffer into its directory, each after the last.
#[derive(Debug)]
pub struct SnapshotWriter {
    dir: PathBuf,
    layout: ReplayLayout,
    manifest: Manifest,
    next_sequence: u64,
}

impl SnapshotWriter {
    /// A writer for a buffer with no snapshot yet in `dir` (created on the first write). Only replay
    /// buffers are snapshotted: a rollout is on-policy data of the policy of its last update, which a
    /// learner collects again after a restart anyway.
    pub fn new(dir: &Path, identity: &str, layout: ReplayLayout) -> Result<Self> {
        if layout.kind != BufferKind::Replay {
            return Err(SnapshotError::new(dir, "only replay buffers are snapshotted, not rollouts"));
        }
        Ok(SnapshotWriter { dir: dir.to_path_buf(), layout, manifest: Manifest::empty(identity, &layout), next_sequence: 1 })
    }

    pub fn dir(&self) -> &Path {
        &self.dir
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
        fs::create_dir_all(&self.dir).map_err(|error| SnapshotError::io(&self.dir, error))?;
        let full = self.manifest.segments.is_empty()
            || self.manifest.segments.len() >= MAX_SEGMENTS
            || self.manifest.bytes() > 2 * self.layout.memory_bytes() as u64;
        let sequence = self.next_sequence;
        let path = self.dir.join(segment_name(sequence));
        let written = match self.write_segment(&path, sequence, buffer, full, throttle) {
            Ok(written) => written,
            Err(error) => {
                let _ = fs::remove_file(&path);
                return Err(SnapshotError::io(&path, error));
            }
        };
        let (bytes, frames, hi) = written;
        let mut manifest = self.manifest.clone();
        if full {
            manifest.segments.clear();
        }
        manifest.segments.push(SegmentEntry { sequence, bytes });
        manifest.written = hi;
        let counters = buffer.read().expect("replay lock").counters;
        manifest.counters = SavedCounters { inserts: counters.inserts, samples: counters.samples, batches: counters.batches };
        manifest.session = session;
        manifest.unix_time_s = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_secs());
        if let Err(error) = write_manifest(&self.dir, &manifest) {
            let _ = fs::remove_file(&path);
            return Err(error);
        }
        if full {
            for old in &self.manifest.segments {
                let _ = fs::remove_file(self.dir.join(segment_name(old.sequence)));
            }
        }
        self.manifest = manifest;
        self.next_sequence += 1;
        Ok(SnapshotReport { bytes, frames, full, disk_bytes: self.manifest.bytes(), duration: started.elapsed() })
    }

    /// Writes one segment; (its bytes, the frames in it, one past the last frame covered per env).
    fn write_segment(
        &self,
        path: &Path,
        sequence: u64,
        buffer: &RwLock<ReplayBuffer>,
        full: bool,
        throttle: &mut Throttle,
    ) -> io::Result<(u64, u64, Vec<u64>)> {
        let layout = &self.layout;
        let mut out = BufWriter::with_capacity(1 << 20, File::create(path)?);
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
        let mut block = Vec::with_capacity(BLOCK_HEADER_BYTES + per_block as usize * layout.slot_bytes() + 4);
        for (env, hi) in hi.iter_mut().enumerate() {
            let (mut first, target) = {
                let replay = buffer.read().expect("replay lock");
                (if full { replay.held_from(env) } else { *hi }, replay.written[env])
            };
            loop {
                block.clear();
                let count = {
                    let replay = buffer.read().expect("replay lock");
                    // Lapped by acting: what was overwritten is gone; continue from what is held.
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

    /// Remove the snapshot (its directory and everything in it).
    pub fn discard(&self) -> io::Result<()> {
        match fs::remove_dir_all(&self.dir) {
            Err(error) if error.kind() == io::ErrorKind::NotFound => Ok(()),
            other => other,
        }
    }
}

fn write_manifest(dir: &Path, manifest: &Manifest) -> Result<()> {
    let body = serde_json::to_vec(manifest).expect("a manifest serializes");
    let mut contents = Vec::with_capacity(body.len() + 20);
    contents.extend_from_slice(MANIFEST_MAGIC);
    contents.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    contents.extend_from_slice(&(body.len() as u32).to_le_bytes());
    contents.extend_from_slice(&body);
    contents.extend_from_slice(&crc32fast::hash(&body).to_le_bytes());
    let tmp = dir.join(MANIFEST_TMP);
    let write = || -> io::Result<()> {
        let mut file = File::create(&tmp)?;
        file.write_all(&contents)?;
        file.sync_all()?;
        fs::rename(&tmp, dir.join(MANIFEST))?;
        // The rename itself must reach the disk before the old segments are deleted.
        File::open(dir)?.sync_all()
    };
    write().map_err(|error| {
        let _ = fs::remove_file(&tmp);
        SnapshotError::io(&dir.join(MANIFEST), error)
    })
}

/// Moves a snapshot that could not be used out of the way (`<dir>.rejected-<unix time>`), so a new one
/// can start in its place and nothing is deleted; the new path.
pub fn set_aside(dir: &Path) -> io::Result<PathBuf> {
    let stamp = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_nanos());
    let mut name = dir.file_name().unwrap_or_default().to_os_string();
    name.push(format!(".rejected-{stamp}"));
    let target = dir.with_file_name(name);
    fs::rename(dir, &target)?;
    Ok(target)
}

/// Whether `dir` holds a snapshot (a manifest).
pub fn exists(dir: &Path) -> bool {
    dir.join(MANIFEST).is_file()
}

/// Fill `buffer` (new, empty, made with the layout the snapshot must have) from the snapshot in
/// `dir`; None when there is none. Episodes in progress when it was taken end as truncated. On an
/// error the buffer is left empty.
pub fn restore(dir: &Path, identity: &str, buffer: &mut ReplayBuffer) -> Result<Option<(RestoreReport, SnapshotWriter)>> {
    let started = Instant::now();
    let manifest_path = dir.join(MANIFEST);
    if !manifest_path.is_file() {
        return Ok(None);
    }
    let result = read_manifest(&manifest_path, identity, &buffer.layout).and_then(|manifest| {
        let (bytes, truncated_episodes) = read_segments(dir, &manifest, buffer)?;
        Ok((manifest, bytes, truncated_episodes))
    });
    let (manifest, bytes, truncated_episodes) = match result {
        Ok(read) => read,
        Err(error) => {
            buffer.clear();
            return Err(error);
        }
    };
    remove_strays(dir, &manifest);
    let now = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |since| since.as_secs());
    let report = RestoreReport {
        transitions: buffer.len(),
        bytes,
        truncated_episodes,
        session: manifest.session,
        age: Duration::from_secs(now.saturating_sub(manifest.unix_time_s)),
        duration: started.elapsed(),
    };
    let next_sequence = manifest.segments.last().map_or(1, |last| last.sequence + 1);
    let writer = SnapshotWriter { dir: dir.to_path_buf(), layout: buffer.layout, manifest, next_sequence };
    Ok(Some((report, writer)))
}

/// Segments a crash left behind unlisted, and a half-written manifest.
fn remove_strays(dir: &Path, manifest: &Manifest) {
    let Ok(entries) = fs::read_dir(dir) else { return };
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let listed = manifest.segments.iter().any(|segment| segment_name(segment.sequence) == name);
        if (name.starts_with("seg-") && name.ends_with(".rsnap") && !listed) || name == MANIFEST_TMP {
            let _ = fs::remove_file(entry.path());
        }
    }
}

fn read_manifest(path: &Path, identity: &str, layout: &ReplayLayout) -> Result<Manifest> {
    let invalid = |message: String| SnapshotError::new(path, message);
    let length = fs::metadata(path).map_err(|error| SnapshotError::io(path, error))?.len();
    if length > MAX_MANIFEST_BYTES {
        return Err(invalid(format!("{length} bytes, more than a manifest can be ({MAX_MANIFEST_BYTES})")));
    }
    let contents = fs::read(path).map_err(|error| SnapshotError::io(path, error))?;
    let manifest = parse_manifest(&contents).map_err(invalid)?;
    let expected = Manifest::empty(identity, layout);
    if manifest.identity != expected.identity {
        return Err(invalid(format!(
            "it is the snapshot of a session created as {}, not as {}: create the session as it was, or under \
             another name",
            manifest.identity, expected.identity
        )));
    }
    let saved = (manifest.capacity, manifest.num_envs, manifest.frame_stack, manifest.frame_bytes, manifest.action_bytes);
    let wanted = (expected.capacity, expected.num_envs, expected.frame_stack, expected.frame_bytes, expected.action_bytes);
    if saved != wanted {
        return Err(invalid(format!(
            "it holds a buffer of (capacity, envs, frame stack, frame bytes, action bytes) {saved:?}; this session's \
             is {wanted:?}"
        )));
    }
    if manifest.written.len() != layout.num_envs {
        return Err(invalid(format!("it counts frames for {} envs, not {}", manifest.written.len(), layout.num_envs)));
    }
    if manifest.segments.is_empty() || manifest.segments.len() > MAX_SEGMENTS {
        return Err(invalid(format!("it lists {} segments; a snapshot has 1 to {MAX_SEGMENTS}", manifest.segments.len())));
    }
    if manifest.segments.windows(2).any(|pair| pair[0].sequence >= pair[1].sequence) {
        return Err(invalid("its segments are not in ascending order".into()));
    }
    Ok(manifest)
}

/// The manifest in `contents`, checked for what it is, its version and its checksum.
fn parse_manifest(contents: &[u8]) -> std::result::Result<Manifest, String> {
    if contents.len() < 20 || &contents[..8] != MANIFEST_MAGIC {
        return Err("not a radserve snapshot manifest".into());
    }
    let version = u32::from_le_bytes(contents[8..12].try_into().expect("4 bytes"));
    if version != FORMAT_VERSION {
        return Err(format!("snapshot format version {version}; this server reads version {FORMAT_VERSION}"));
    }
    let length = u32::from_le_bytes(contents[12..16].try_into().expect("4 bytes")) as usize;
    if contents.len() != 16 + length + 4 {
        return Err(format!("{} bytes where the header announces {}: truncated or extended", contents.len(), 16 + length + 4));
    }
    let (body, crc) = contents[16..].split_at(length);
    if crc32fast::hash(body).to_le_bytes() != crc {
        return Err("checksum mismatch: the manifest is corrupted".into());
    }
    serde_json::from_slice(body).map_err(|error| format!("unreadable manifest: {error}"))
}

/// A little-endian integer at `at` of `bytes` (the caller checked the length).
fn le_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4 bytes"))
}

fn le_u64(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"))
}

/// Apply every segment of `manifest` to `buffer`; (bytes read, episodes ended as truncated).
fn read_segments(dir: &Path, manifest: &Manifest, buffer: &mut ReplayBuffer) -> Result<(u64, usize)> {
    let layout = buffer.layout;
    let (num_envs, slots) = (layout.num_envs, buffer.slots as u64);
    let record_bytes = layout.slot_bytes();
    let per_block = block_records(&layout);
    // Per env: the first frame of the last run of consecutive frames, and one past its end.
    let (mut lo, mut hi) = (vec![0u64; num_envs], vec![0u64; num_envs]);
    let mut block = vec![0u8; per_block * record_bytes + 4];
    let mut total = 0u64;
    for segment in &manifest.segments {
        let path = dir.join(segment_name(segment.sequence));
        let invalid = |message: String| SnapshotError::new(&path, message);
        let mut file = File::open(&path).map_err(|error| SnapshotError::io(&path, error))?;
        let length = file.metadata().map_err(|error| SnapshotError::io(&path, error))?.len();
        if length != segment.bytes {
            return Err(invalid(format!("{length} bytes, the manifest says {}: truncated or replaced", segment.bytes)));
        }
        let mut read_exact = |into: &mut [u8], what: &str| {
            file.read_exact(into).map_err(|error| {
                if error.kind() == io::ErrorKind::UnexpectedEof {
                    invalid(format!("ends inside {what}"))
                } else {
                    SnapshotError::io(&path, error)
                }
            })
        };
        let mut header = [0u8; SEGMENT_HEADER_BYTES];
        read_exact(&mut header, "its header")?;
        if &header[..8] != SEGMENT_MAGIC {
            return Err(invalid("not a radserve snapshot segment".into()));
        }
        if le_u32(&header, SEGMENT_HEADER_BYTES - 4) != crc32fast::hash(&header[..SEGMENT_HEADER_BYTES - 4]) {
            return Err(invalid("header checksum mismatch: corrupted".into()));
        }
        let version = le_u32(&header, 8);
        if version != FORMAT_VERSION {
            return Err(invalid(format!("snapshot format version {version}; this server reads version {FORMAT_VERSION}")));
        }
        let described = (le_u64(&header, 12), le_u32(&header, 20) as usize, le_u32(&header, 24) as usize, le_u32(&header, 28) as usize);
        let expected = (segment.sequence, num_envs, layout.frame_bytes, layout.action_bytes);
        if described != expected {
            return Err(invalid(format!(
                "header says (sequence, envs, frame bytes, action bytes) {described:?}, the manifest {expected:?}"
            )));
        }
        let mut offset = SEGMENT_HEADER_BYTES as u64;
        while offset < length {
            let mut head = [0u8; BLOCK_HEADER_BYTES];
            read_exact(&mut head, "a block header")?;
            let (env, count, first) = (le_u32(&head, 0) as usize, le_u32(&head, 4) as usize, le_u64(&head, 8));
            if env >= num_envs || count == 0 || count > per_block {
                return Err(invalid(format!(
                    "a block at byte {offset} of env {env} with {count} frames (envs: {num_envs}, frames per block: 1 to \
                     {per_block})"
                )));
            }
            let end = first.checked_add(count as u64).filter(|&end| end <= manifest.written[env]);
            let Some(end) = end.filter(|_| first >= hi[env]) else {
                return Err(invalid(format!(
                    "a block at byte {offset} holds frames {first}.. of env {env}, outside {}..{} (after what is read, \
                     within what the manifest counts)",
                    hi[env], manifest.written[env]
                )));
            };
            let data = &mut block[..count * record_bytes + 4];
            read_exact(data, "a block")?;
            let mut hasher = crc32fast::Hasher::new();
            hasher.update(&head);
            hasher.update(&data[..count * record_bytes]);
            if hasher.finalize() != le_u32(data, count * record_bytes) {
                return Err(invalid(format!("block at byte {offset} of env {env}: checksum mismatch: corrupted")));
            }
            if first > hi[env] {
                lo[env] = first;
            }
            let keep_from = manifest.written[env].saturating_sub(slots);
            for (index, record) in data[..count * record_bytes].chunks_exact(record_bytes).enumerate() {
                let frame = first + index as u64;
                buffer.import_record(env, frame, record, frame >= keep_from).map_err(|message| {
                    invalid(format!("block at byte {offset}, frame {frame} of env {env}: {message}"))
                })?;
            }
            hi[env] = end;
            offset += (BLOCK_HEADER_BYTES + count * record_bytes + 4) as u64;
        }
        total += length;
    }
    if let Some(env) = (0..num_envs).find(|&env| hi[env] != manifest.written[env]) {
        return Err(SnapshotError::new(
            &dir.join(MANIFEST),
            format!("it counts {} frames of env {env}; its segments hold {}", manifest.written[env], hi[env]),
        ));
    }
    let counters = ReplayCounters {
        inserts: manifest.counters.inserts,
        samples: manifest.counters.samples,
        batches: manifest.counters.batches,
    };
    let truncated = buffer.finish_restore(&lo, &hi, counters);
    Ok((total, truncated))
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

    /// Check one record read from a snapshot and, when `keep` (its frame is among the last the ring
    /// holds), store it. An episode that did not end before an episode's first frame ends as truncated.
    fn import_record(&mut self, env: usize, frame: u64, record: &[u8], keep: bool) -> std::result::Result<(), String> {
        let (frame_bytes, action_bytes) = (self.layout.frame_bytes, self.layout.action_bytes);
        let at = frame_bytes + action_bytes;
        let reward = f32::from_le_bytes(record[at..at + 4].try_into().expect("4 bytes"));
        let flags = record[at + 4];
        let (episode_start, step_index) = (le_u64(record, at + 5), le_u64(record, at + 13));
        if flags & !(FIRST_OF_EPISODE | TERMINATED | TRUNCATED) != 0 || (flags & FIRST_OF_EPISODE != 0 && flags != FIRST_OF_EPISODE) {
            return Err(format!("flags {flags:#04b} are not a transition's"));
        }
        if episode_start > frame || (flags & FIRST_OF_EPISODE != 0 && episode_start != frame) {
            return Err(format!("its episode starts at frame {episode_start}"));
        }
        if step_index == u64::MAX {
            return Err("its step index is out of range".into());
        }
        if flags & FIRST_OF_EPISODE != 0 && frame > 0 && self.written[env] == frame {
            // The previous frame's episode never ended (the snapshot was taken mid-episode, or its
            // worker died): it ends as truncated.
            let previous = self.slot(env, frame - 1);
            if self.flags[previous] & (FIRST_OF_EPISODE | TERMINATED | TRUNCATED) == 0 {
                self.flags[previous] |= TRUNCATED;
            }
        }
        self.written[env] = frame + 1;
        if !keep {
            return Ok(());
        }
        let slot = self.slot(env, frame);
        self.frames[slot * frame_bytes..(slot + 1) * frame_bytes].copy_from_slice(&record[..frame_bytes]);
        self.actions[slot * action_bytes..(slot + 1) * action_bytes].copy_from_slice(&record[frame_bytes..at]);
        self.rewards[slot] = reward;
        self.flags[slot] = flags;
        self.episode_starts[slot] = episode_start;
        self.step_indices[slot] = step_index;
        self.steps_recorded = self.steps_recorded.max(step_index + 1);
        Ok(())
    }

    /// After the last record: each env's runs, the episodes still open end as truncated, the counters
    /// as saved. The number of episodes ended.
    fn finish_restore(&mut self, lo: &[u64], hi: &[u64], counters: ReplayCounters) -> usize {
        let mut truncated = 0;
        for env in 0..self.layout.num_envs {
            self.written[env] = hi[env];
            self.floors[env] = lo[env];
            self.in_episode[env] = false;
            if hi[env] > self.held_from(env) {
                let last = self.slot(env, hi[env] - 1);
                if self.flags[last] & (FIRST_OF_EPISODE | TERMINATED | TRUNCATED) == 0 {
                    self.flags[last] |= TRUNCATED;
                    truncated += 1;
                }
            }
        }
        self.counters = counters;
        truncated
    }

    /// Forget everything recorded (a restore that failed part way).
    fn clear(&mut self) {
        self.written.fill(0);
        self.floors.fill(0);
        self.in_episode.fill(false);
        self.steps_recorded = 0;
        self.counters = ReplayCounters::default();
    }
}

#[cfg(test)]
#[path = "snapshot_tests.rs"]
mod tests;
