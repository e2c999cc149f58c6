//! Reading a snapshot back into a new buffer, trusting nothing: files opened as regular files only,
//! never through a symlink; sizes checked against the session's layout and the format's limits
//! before anything is read, the counters against the frames, every block's CRC before it is applied.

use std::io::{self, Read};
use std::path::Path;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use super::dir::{SnapshotDir, SnapshotPath};
use super::{
    block_records, priorities_name, readable, segment_name, unreadable, Manifest, Result, SessionCounters, SnapshotError,
    SnapshotWriter, BLOCK_HEADER_BYTES, MANIFEST, MANIFEST_MAGIC, MANIFEST_TMP, MAX_COUNTER, MAX_MANIFEST_BYTES, MAX_SEGMENTS,
    PRIORITIES_HEADER_BYTES, PRIORITIES_MAGIC, PRIORITY_RECORD_BYTES, SEGMENT_HEADER_BYTES, SEGMENT_MAGIC,
};
use crate::buffer::{ReplayBuffer, ReplayCounters, ReplayLayout, FIRST_OF_EPISODE, TERMINATED, TRUNCATED};

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

/// Fill `buffer` (new, empty, made with the layout the snapshot must have) from the snapshot in
/// `dir`; None when there is none. Episodes in progress when it was taken end as truncated. On an
/// error the buffer is left empty.
pub fn restore(dir: &SnapshotPath, identity: &str, buffer: &mut ReplayBuffer) -> Result<Option<(RestoreReport, SnapshotWriter)>> {
    let started = Instant::now();
    let Some(open) = dir.open(false).map_err(|error| SnapshotError::io(&dir.path(), error))? else { return Ok(None) };
    let manifest_path = open.path().join(MANIFEST);
    let contents = match open.read_bounded(MANIFEST, MAX_MANIFEST_BYTES) {
        Ok(Some(contents)) => contents,
        Ok(None) => return Ok(None),
        Err(error) => return Err(SnapshotError::io(&manifest_path, error)),
    };
    let result = read_manifest(&manifest_path, &contents, identity, &buffer.layout, buffer.slots as u64).and_then(|manifest| {
        let (bytes, truncated_episodes) = read_segments(&open, &manifest, buffer)?;
        let priority_bytes = read_priorities(&open, &manifest, buffer)?;
        Ok((manifest, bytes + priority_bytes, truncated_episodes))
    });
    let (manifest, bytes, truncated_episodes) = match result {
        Ok(read) => read,
        Err(error) => {
            buffer.clear();
            return Err(error);
        }
    };
    remove_strays(&open, &manifest);
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
    let writer = SnapshotWriter { dir: dir.clone(), layout: buffer.layout, manifest, next_sequence };
    Ok(Some((report, writer)))
}

/// Segments a crash left behind unlisted, and a half-written manifest.
fn remove_strays(dir: &SnapshotDir, manifest: &Manifest) {
    let Ok(names) = dir.names() else { return };
    for name in names {
        let listed = manifest.segments.iter().any(|segment| segment_name(segment.sequence) == name)
            || manifest.priorities.is_some_and(|entry| priorities_name(entry.sequence) == name);
        let ours = (name.starts_with("seg-") || name.starts_with("prio-")) && name.ends_with(".rsnap");
        if (ours && !listed) || name == MANIFEST_TMP {
            let _ = dir.remove(&name);
        }
    }
}

/// The most bytes one segment of `layout` can take: every frame the ring holds (`slots` per env),
/// each in a block of its own.
fn max_segment_bytes(layout: &ReplayLayout, slots: u64) -> u64 {
    let record = (layout.snapshot_record_bytes() + BLOCK_HEADER_BYTES + 4) as u64;
    (SEGMENT_HEADER_BYTES as u64).saturating_add(slots.saturating_mul(layout.num_envs as u64).saturating_mul(record))
}

fn read_manifest(path: &Path, contents: &[u8], identity: &str, layout: &ReplayLayout, slots: u64) -> Result<Manifest> {
    let invalid = |message: String| SnapshotError::new(path, message);
    let manifest = parse_manifest(contents).map_err(invalid)?;
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
    let most = max_segment_bytes(layout, slots);
    if let Some(segment) = manifest.segments.iter().find(|segment| segment.bytes > most || segment.sequence >= MAX_COUNTER) {
        return Err(invalid(format!(
            "it lists segment {} of {} bytes; a segment of this buffer has at most {most} bytes and a sequence below {MAX_COUNTER}",
            segment.sequence, segment.bytes
        )));
    }
    if let Some(entry) = manifest.priorities {
        let most = max_priorities_bytes(slots * layout.num_envs as u64);
        if entry.bytes > most || entry.sequence >= MAX_COUNTER {
            return Err(invalid(format!(
                "it lists priorities file {} of {} bytes; this buffer's has at most {most} bytes",
                entry.sequence, entry.bytes
            )));
        }
    }
    check_counters(&manifest).map_err(invalid)?;
    Ok(manifest)
}

/// The most bytes a priorities file of a buffer of `slots` slots can take.
fn max_priorities_bytes(slots: u64) -> u64 {
    (PRIORITIES_HEADER_BYTES as u64 + 4).saturating_add(slots.saturating_mul(PRIORITY_RECORD_BYTES as u64))
}

/// The priorities the manifest lists, checked whole (magic, version, length, checksum, every key
/// and value) before `buffer` takes them; the bytes read.
fn read_priorities(dir: &SnapshotDir, manifest: &Manifest, buffer: &mut ReplayBuffer) -> Result<u64> {
    let Some(entry) = manifest.priorities else { return Ok(0) };
    let name = priorities_name(entry.sequence);
    let path = dir.path().join(&name);
    let invalid = |message: String| SnapshotError::new(&path, message);
    let contents = match dir.read_bounded(&name, entry.bytes) {
        Ok(Some(contents)) => contents,
        Ok(None) => return Err(invalid("missing: the manifest lists it".into())),
        Err(error) => return Err(SnapshotError::io(&path, error)),
    };
    if contents.len() as u64 != entry.bytes || contents.len() < PRIORITIES_HEADER_BYTES + 4 {
        return Err(invalid(format!("{} bytes, the manifest says {}: truncated or replaced", contents.len(), entry.bytes)));
    }
    if &contents[..8] != PRIORITIES_MAGIC {
        return Err(invalid("not a radserve snapshot priorities file".into()));
    }
    let (body, crc) = contents.split_at(contents.len() - 4);
    if crc32fast::hash(body).to_le_bytes() != crc {
        return Err(invalid("checksum mismatch: corrupted".into()));
    }
    let version = le_u32(body, 8);
    if !readable(version) {
        return Err(invalid(unreadable(version)));
    }
    let count = le_u64(body, 12);
    let max = f64::from_le_bytes(body[20..28].try_into().expect("8 bytes"));
    if (body.len() - PRIORITIES_HEADER_BYTES) as u64 != count.saturating_mul(PRIORITY_RECORD_BYTES as u64) {
        return Err(invalid(format!("it counts {count} priorities in {} bytes", body.len() - PRIORITIES_HEADER_BYTES)));
    }
    let pairs: Vec<(u64, f64)> = body[PRIORITIES_HEADER_BYTES..]
        .chunks_exact(PRIORITY_RECORD_BYTES)
        .map(|record| (le_u64(record, 0), f64::from_le_bytes(record[8..16].try_into().expect("8 bytes"))))
        .collect();
    buffer.restore_priorities(max, &pairs).map_err(invalid)?;
    Ok(entry.bytes)
}

/// The manifest's counters against the frames it counts: none past [`MAX_COUNTER`] (so none can
/// wrap as the session counts on), no more transitions inserted than frames written, no more
/// batches than samples, no more episodes ended than env steps.
fn check_counters(manifest: &Manifest) -> std::result::Result<(), String> {
    let session = &manifest.session;
    let counters = &manifest.counters;
    let named = [
        ("frames written of an env", manifest.written.iter().copied().max().unwrap_or(0)),
        ("inserts", counters.inserts),
        ("samples", counters.samples),
        ("batches", counters.batches),
        ("step calls", session.step_calls),
        ("env steps", session.total_env_steps),
        ("episodes", session.episodes_completed),
    ];
    if let Some((name, value)) = named.iter().find(|(_, value)| *value > MAX_COUNTER) {
        return Err(format!("its {name} counter is {value}, past what a snapshot can count ({MAX_COUNTER}): forged or corrupted"));
    }
    let frames: u64 = manifest.written.iter().sum();
    if counters.inserts > frames {
        return Err(format!("it counts {} transitions inserted but only {frames} frames written: forged or corrupted", counters.inserts));
    }
    if counters.batches > counters.samples {
        return Err(format!("it counts {} batches but {} samples: forged or corrupted", counters.batches, counters.samples));
    }
    if session.episodes_completed > session.total_env_steps {
        return Err(format!(
            "it counts {} episodes ended in {} env steps: forged or corrupted",
            session.episodes_completed, session.total_env_steps
        ));
    }
    Ok(())
}

/// The manifest in `contents`, checked for what it is, its version and its checksum.
pub(super) fn parse_manifest(contents: &[u8]) -> std::result::Result<Manifest, String> {
    if contents.len() < 20 || &contents[..8] != MANIFEST_MAGIC {
        return Err("not a radserve snapshot manifest".into());
    }
    let version = u32::from_le_bytes(contents[8..12].try_into().expect("4 bytes"));
    if !readable(version) {
        return Err(unreadable(version));
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
fn read_segments(dir: &SnapshotDir, manifest: &Manifest, buffer: &mut ReplayBuffer) -> Result<(u64, usize)> {
    let layout = buffer.layout;
    let (num_envs, slots) = (layout.num_envs, buffer.slots as u64);
    let record_bytes = layout.snapshot_record_bytes();
    let per_block = block_records(&layout);
    // Per env: the first frame of the last run of consecutive frames, and one past its end.
    let (mut lo, mut hi) = (vec![0u64; num_envs], vec![0u64; num_envs]);
    let mut block = vec![0u8; per_block * record_bytes + 4];
    let mut total = 0u64;
    for segment in &manifest.segments {
        let name = segment_name(segment.sequence);
        let path = dir.path().join(&name);
        let invalid = |message: String| SnapshotError::new(&path, message);
        let (file, length) = match dir.open_regular(&name) {
            Ok(Some(opened)) => opened,
            Ok(None) => return Err(invalid("missing: the manifest lists it".into())),
            Err(error) => return Err(SnapshotError::io(&path, error)),
        };
        // Reads stop at the length the manifest records (bounded by the layout), whatever the file
        // grows to meanwhile.
        let mut file = file.take(segment.bytes);
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
        if !readable(version) {
            return Err(invalid(unreadable(version)));
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
            &dir.path().join(MANIFEST),
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
        self.stamp(slot, None);
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
        for env in 0..self.layout.num_envs {
            self.first_frames[env] = self.count_first_frames(env);
        }
        truncated
    }

    /// Forget everything recorded (a restore that failed part way).
    fn clear(&mut self) {
        self.written.fill(0);
        self.floors.fill(0);
        self.in_episode.fill(false);
        self.first_frames.fill(0);
        self.steps_recorded = 0;
        self.counters = ReplayCounters::default();
        self.priorities = None;
    }
}
