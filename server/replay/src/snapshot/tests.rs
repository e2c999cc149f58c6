//! Snapshots written while the buffer fills, restored into a new buffer: every transition the new
//! buffer can sample equals the original's, episodes in progress end truncated, and any damage to the
//! files is refused with the file named and the buffer left empty.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::RwLock;

use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::read::parse_manifest;
use super::write::write_manifest;
use super::*;
use crate::buffer::{
    BufferKind, RecordedStep, ReplayBuffer, ReplayCounters, TransitionMetadata, TransitionRef, FIRST_OF_EPISODE,
};

const IDENTITY: &str = "{\"env\":\"test/Pixels-v0\",\"num_envs\":3}";

fn layout(capacity: usize) -> ReplayLayout {
    ReplayLayout { kind: BufferKind::Replay, capacity, num_envs: 3, frame_stack: 3, frame_bytes: 48, action_bytes: 8 }
}

/// Records `steps` steps of every env: frames and actions from the rng, episodes that end (terminated
/// or truncated) now and then.
fn record(buffer: &RwLock<ReplayBuffer>, rng: &mut ChaCha8Rng, steps: usize, step_calls: &mut u64) {
    let mut replay = buffer.write().unwrap();
    let layout = replay.layout;
    let mut frame = vec![0u8; layout.frame_bytes];
    let mut action = vec![0u8; layout.action_bytes];
    for _ in 0..steps {
        for env in 0..layout.num_envs {
            rng.fill(&mut frame[..]);
            if !replay.in_episode[env] {
                replay.record_first_frame(env, &frame, *step_calls);
                continue;
            }
            rng.fill(&mut action[..]);
            let end: u8 = rng.random_range(0..20);
            let step = RecordedStep {
                action: &action,
                reward: rng.random_range(-1.0..1.0),
                terminated: end == 0,
                truncated: end == 1,
                next_frame: &frame,
                step_index: *step_calls,
                acted: None,
            };
            replay.record_step(env, &step);
        }
        *step_calls += 1;
    }
}

/// Every transition `restored` can sample, checked against `original`: frames, next frames and
/// metadata equal, except that the last transition of an episode in progress ends truncated.
fn assert_same_transitions(original: &ReplayBuffer, restored: &ReplayBuffer) -> usize {
    let layout = original.layout;
    let mut checked = 0;
    for env in 0..layout.num_envs {
        assert_eq!(restored.written[env], original.written[env], "env {env}");
        for frame in restored.oldest_sampleable(env)..restored.written[env] {
            let transition = TransitionRef { env, frame };
            if restored.flags[restored.slot(env, frame)] & FIRST_OF_EPISODE != 0 {
                continue;
            }
            let size = (layout.frame_stack + 1) * layout.frame_bytes;
            let (mut a, mut b) = (vec![0u8; size], vec![0u8; size]);
            original.copy_transition(transition, &mut a);
            restored.copy_transition(transition, &mut b);
            assert_eq!(a, b, "frames of env {env} frame {frame}");
            let (mut left, mut right) = (TransitionMetadata::default(), TransitionMetadata::default());
            original.gather_metadata(&[transition], &mut left);
            restored.gather_metadata(&[transition], &mut right);
            let open_end = frame + 1 == original.written[env] && original.in_episode[env];
            if open_end {
                assert_eq!(right.truncated, vec![1], "the open episode of env {env} ends truncated");
                right.truncated = left.truncated.clone();
            }
            assert_eq!(left, right, "metadata of env {env} frame {frame}");
            checked += 1;
        }
    }
    checked
}


/// The snapshot directory `path` (a child of a temporary directory, which is its root).
fn at(path: &Path) -> SnapshotPath {
    SnapshotPath::new(path.parent().unwrap(), &[path.file_name().unwrap().to_str().unwrap()]).unwrap()
}

fn session(step_calls: u64) -> SessionCounters {
    SessionCounters { step_calls, total_env_steps: step_calls * 3, episodes_completed: step_calls / 7 }
}

#[test]
fn a_restored_buffer_samples_what_the_original_held() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("alice").join("run-1");
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let original = RwLock::new(ReplayBuffer::new(layout(300)).unwrap());
    let mut writer = SnapshotWriter::new(&at(&path), IDENTITY, layout(300)).unwrap();
    let mut step_calls = 0;
    let mut reports = Vec::new();
    // Fill past the ring several times, with a snapshot after each chunk: the first is full, the
    // next ones append, and a full one comes back once the segments pass twice the buffer.
    for chunk in [40, 17, 1, 90, 33, 120, 64, 5] {
        record(&original, &mut rng, chunk, &mut step_calls);
        let pending = writer.pending_frames(&original.read().unwrap());
        let report = writer.write(&original, session(step_calls), &mut Throttle::new(0, None)).unwrap();
        let slots = (original.read().unwrap().slots * 3) as u64;
        assert!(if report.full { report.frames <= slots } else { report.frames == pending }, "{report:?}");
        reports.push(report);
    }
    assert!(reports[0].full);
    assert!(!reports[1].full && reports[1].frames == 17 * 3, "an increment holds the new frames: {:?}", reports[1]);
    assert!(reports[2..].iter().any(|report| report.full), "compaction happened: {reports:?}");
    let segments = fs::read_dir(&path).unwrap().filter(|entry| entry.as_ref().unwrap().file_name().to_string_lossy().starts_with("seg-")).count();
    assert_eq!(segments, writer.manifest.segments.len(), "a full snapshot deletes the segments before it");
    assert_eq!(writer.disk_bytes(), fs::read_dir(&path).unwrap().map(|entry| {
        let entry = entry.unwrap();
        if entry.file_name() == MANIFEST { 0 } else { entry.metadata().unwrap().len() }
    }).sum::<u64>());

    let mut restored = ReplayBuffer::new(layout(300)).unwrap();
    let (report, mut resumed) = restore(&at(&path), IDENTITY, &mut restored).unwrap().expect("a snapshot");
    let original = original.into_inner().unwrap();
    assert_eq!(report.transitions, original.len(), "{report:?}");
    assert_eq!(report.session, session(step_calls));
    assert_eq!(restored.counters, original.counters);
    assert_eq!(restored.steps_recorded, original.steps_recorded);
    let open = original.in_episode.iter().filter(|&&open| open).count();
    assert_eq!(report.truncated_episodes, open);
    assert!(assert_same_transitions(&original, &restored) > 200);
    assert!(restored.in_episode.iter().all(|&open| !open), "every env starts with a first frame");

    // The restored buffer goes on: its writer appends after the restored segments.
    let restored = RwLock::new(restored);
    record(&restored, &mut rng, 25, &mut step_calls);
    let report = resumed.write(&restored, session(step_calls), &mut Throttle::new(0, None)).unwrap();
    assert_eq!(report.frames, 25 * 3);
    let mut again = ReplayBuffer::new(layout(300)).unwrap();
    restore(&at(&path), IDENTITY, &mut again).unwrap().expect("a snapshot");
    assert!(assert_same_transitions(&restored.into_inner().unwrap(), &again) > 200);
}

#[test]
fn no_snapshot_is_none_and_a_rollout_has_none() {
    let dir = tempfile::tempdir().unwrap();
    let mut buffer = ReplayBuffer::new(layout(30)).unwrap();
    assert!(restore(&at(&dir.path().join("absent")), IDENTITY, &mut buffer).unwrap().is_none());
    let rollout = ReplayLayout::rollout(8, 3, 1, 4, 4);
    assert!(SnapshotWriter::new(&at(&dir.path().join("rollout")), IDENTITY, rollout).unwrap_err().to_string().contains("only replay buffers"));
}

/// A buffer being recorded and its snapshots, in a temporary directory.
struct Recording {
    _dir: tempfile::TempDir,
    path: PathBuf,
    rng: ChaCha8Rng,
    buffer: RwLock<ReplayBuffer>,
    writer: SnapshotWriter,
    step_calls: u64,
}

impl Recording {
    fn new(seed: u64, capacity: usize) -> Recording {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run");
        let writer = SnapshotWriter::new(&at(&path), IDENTITY, layout(capacity)).unwrap();
        let buffer = RwLock::new(ReplayBuffer::new(layout(capacity)).unwrap());
        Recording { _dir: dir, path, rng: ChaCha8Rng::seed_from_u64(seed), buffer, writer, step_calls: 0 }
    }

    fn record(&mut self, steps: usize) {
        record(&self.buffer, &mut self.rng, steps, &mut self.step_calls);
    }

    fn snapshot(&mut self) -> Result<SnapshotReport> {
        self.writer.write(&self.buffer, session(self.step_calls), &mut Throttle::new(0, None))
    }

    /// A new buffer restored from the snapshot on disk.
    fn restored(&self) -> ReplayBuffer {
        let mut restored = ReplayBuffer::new(self.buffer.read().unwrap().layout).unwrap();
        restore(&at(&self.path), IDENTITY, &mut restored).unwrap().expect("a snapshot");
        restored
    }
}

/// A buffer of 120 transitions with a snapshot of it in two segments, in a temporary directory.
fn snapshot_on_disk() -> Recording {
    let mut recording = Recording::new(11, 150);
    for chunk in [25, 15] {
        recording.record(chunk);
        recording.snapshot().unwrap();
    }
    recording
}

#[test]
fn another_session_or_layout_is_refused_naming_the_manifest() {
    let recording = snapshot_on_disk();
    let path = &recording.path;
    let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
    let error = restore(&at(path), "{\"env\":\"other\"}", &mut buffer).unwrap_err();
    assert_eq!(error.file, path.join(MANIFEST));
    assert!(error.to_string().contains("created as"), "{error}");
    let mut bigger = ReplayBuffer::new(layout(151)).unwrap();
    let error = restore(&at(path), IDENTITY, &mut bigger).unwrap_err();
    assert!(error.to_string().contains("this session's is (151, 3, 3, 48, 8)"), "{error}");
    assert!(bigger.is_empty() && buffer.is_empty());
}

#[test]
fn a_foreign_file_or_another_format_version_is_named_as_such() {
    let recording = snapshot_on_disk();
    let manifest = recording.path.join(MANIFEST);
    let mut bytes = fs::read(&manifest).unwrap();
    bytes[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
    fs::write(&manifest, &bytes).unwrap();
    let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
    let error = restore(&at(&recording.path), IDENTITY, &mut buffer).unwrap_err();
    assert!(error.to_string().contains("snapshot format version 3; this server reads versions 1 to 2"), "{error}");
    fs::write(&manifest, b"{\"identity\": \"someone else's JSON\"}").unwrap();
    let error = restore(&at(&recording.path), IDENTITY, &mut buffer).unwrap_err();
    assert!(error.to_string().contains("not a radserve snapshot manifest") && error.file == manifest, "{error}");
}

#[test]
fn a_crash_mid_write_leaves_the_previous_snapshot() {
    let recording = snapshot_on_disk();
    let path = &recording.path;
    // A segment written but never listed, and a manifest never renamed: what a kill leaves.
    fs::write(path.join(segment_name(3)), b"RSNPSEGM half a segment").unwrap();
    fs::write(path.join(MANIFEST_TMP), b"RSNPMANI half a manifest").unwrap();
    let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
    let (report, _) = restore(&at(path), IDENTITY, &mut buffer).unwrap().unwrap();
    assert_eq!(report.transitions, recording.buffer.read().unwrap().len());
    assert!(!path.join(segment_name(3)).exists() && !path.join(MANIFEST_TMP).exists(), "strays are removed");
}

#[test]
fn a_failed_write_keeps_the_previous_snapshot_and_retries_the_same_frames() {
    let mut recording = Recording::new(3, 150);
    recording.record(10);
    recording.snapshot().unwrap();
    recording.record(10);
    // The next segment's path is taken by a directory: creating the file fails, as a full disk would.
    let taken = recording.path.join(segment_name(2));
    fs::create_dir(&taken).unwrap();
    assert_eq!(recording.snapshot().unwrap_err().file, taken);
    assert_eq!(recording.restored().written, vec![10; 3], "the previous snapshot is whole");
    fs::remove_dir(&taken).unwrap();
    let report = recording.snapshot().unwrap();
    assert_eq!(report.frames, 30, "the frames of the failed write are written again");
    assert_same_transitions(&recording.buffer.read().unwrap(), &recording.restored());
}

#[test]
fn a_writer_lapped_by_stepping_skips_what_was_overwritten() {
    // Frames overwritten between the snapshot's blocks: simulated by writing a snapshot of a buffer
    // whose ring has moved on since the last one (the increment starts below what is held).
    let mut recording = Recording::new(5, 30);
    recording.record(5);
    recording.snapshot().unwrap();
    recording.record(40);
    recording.snapshot().unwrap();
    let (original, restored) = (recording.buffer.read().unwrap(), recording.restored());
    assert!(restored.floors.iter().all(|&floor| floor > 0), "a gap: {:?}", restored.floors);
    assert!(assert_same_transitions(&original, &restored) > 0);
    assert!(restored.len() <= original.len());
}

/// Every file of a snapshot, by name.
fn files(path: &Path) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = fs::read_dir(path).unwrap().map(|entry| entry.unwrap().path()).collect();
    files.sort();
    files
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(std::env::var("PROPTEST_CASES").ok().and_then(|cases| cases.parse().ok()).unwrap_or(256)))]

    /// Any byte changed, any file cut short or extended: refused, naming a file of the snapshot, the
    /// buffer left empty, nothing panics.
    #[test]
    fn damaged_files_are_refused(file in 0usize..3, index in any::<prop::sample::Index>(), xor in 1u8..=255, cut in any::<bool>(), extra in prop::collection::vec(any::<u8>(), 0..16)) {
        let recording = snapshot_on_disk();
        let path = &recording.path;
        let target = &files(path)[file];
        let mut bytes = fs::read(target).unwrap();
        let offset = index.index(bytes.len());
        if cut {
            bytes.truncate(offset);
        } else if extra.is_empty() {
            bytes[offset] ^= xor;
        } else {
            bytes.extend_from_slice(&extra);
        }
        fs::write(target, &bytes).unwrap();
        let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
        let error = restore(&at(path), IDENTITY, &mut buffer).unwrap_err();
        prop_assert!(error.file.starts_with(path), "{error}");
        prop_assert!(buffer.is_empty() && buffer.counters == ReplayCounters::default());
    }

    /// Manifests with a valid checksum and any numbers in them: refused or restored, never a panic
    /// or an allocation beyond the buffer made for the session.
    #[test]
    fn any_manifest_is_read_safely(
        written in prop::collection::vec(prop_oneof![0u64..200, any::<u64>()], 0..5),
        sequences in prop::collection::vec(prop_oneof![1u64..4, any::<u64>()], 0..4),
        bytes in prop_oneof![0u64..100_000, any::<u64>()],
        capacity in prop_oneof![Just(150u64), any::<u64>()],
    ) {
        let recording = snapshot_on_disk();
        let path = &recording.path;
        let mut manifest = parse_manifest(&fs::read(path.join(MANIFEST)).unwrap()).unwrap();
        let sizes: Vec<u64> = manifest.segments.iter().map(|segment| segment.bytes).collect();
        manifest.written = written;
        manifest.capacity = capacity;
        manifest.segments = sequences.iter().enumerate().map(|(index, &sequence)| {
            SegmentEntry { sequence, bytes: sizes.get(index).copied().unwrap_or(bytes) }
        }).collect();
        write_manifest(&at(path).open(false).unwrap().unwrap(), &manifest).unwrap();
        let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
        match restore(&at(path), IDENTITY, &mut buffer) {
            Ok(restored) => prop_assert!(restored.is_some()),
            Err(error) => prop_assert!(buffer.is_empty() && error.file.starts_with(path), "{error}"),
        }
    }
}

/// A restore of `recording`'s snapshot into a new buffer: its error (the buffer left empty).
fn restore_error(recording: &Recording) -> SnapshotError {
    let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
    let error = restore(&at(&recording.path), IDENTITY, &mut buffer).expect_err("refused");
    assert!(buffer.is_empty() && buffer.counters == ReplayCounters::default());
    error
}

#[test]
fn a_symlinked_manifest_or_segment_is_refused_without_being_read() {
    // /proc/self/pagemap claims 0 bytes and reads without end: it must not be opened at all.
    let recording = snapshot_on_disk();
    let manifest = recording.path.join(MANIFEST);
    fs::remove_file(&manifest).unwrap();
    std::os::unix::fs::symlink("/proc/self/pagemap", &manifest).unwrap();
    let error = restore_error(&recording);
    assert!(error.to_string().contains("is a symlink, which is never followed") && error.file == manifest, "{error}");

    let recording = snapshot_on_disk();
    let outside = recording._dir.path().join("secret");
    fs::write(&outside, b"not the server's to read").unwrap();
    let segment = recording.path.join(segment_name(1));
    fs::remove_file(&segment).unwrap();
    std::os::unix::fs::symlink(&outside, &segment).unwrap();
    let error = restore_error(&recording);
    assert!(error.to_string().contains("symlink") && error.file == segment, "{error}");
}

#[test]
fn a_fifo_or_a_directory_in_place_of_a_file_is_refused_at_once() {
    for (file, make) in [(MANIFEST, "fifo"), ("seg-00000002.rsnap", "fifo"), ("seg-00000001.rsnap", "dir")] {
        let recording = snapshot_on_disk();
        let path = recording.path.join(file);
        fs::remove_file(&path).unwrap();
        if make == "fifo" {
            rustix::fs::mknodat(rustix::fs::CWD, &path, rustix::fs::FileType::Fifo, rustix::fs::Mode::from_raw_mode(0o600), 0).unwrap();
        } else {
            fs::create_dir(&path).unwrap();
        }
        // Opening a FIFO for reading would wait for a writer for ever: this returns.
        let error = restore_error(&recording);
        let expected = if make == "fifo" { "is a FIFO, not a regular file" } else { "a directory" };
        assert!(error.to_string().contains(expected) && error.file == path, "{file}: {error}");
    }
}

#[test]
fn a_symlinked_session_directory_is_refused_and_set_aside_without_touching_its_target() {
    let recording = snapshot_on_disk();
    let elsewhere = recording._dir.path().join("elsewhere");
    fs::rename(&recording.path, &elsewhere).unwrap();
    std::os::unix::fs::symlink(&elsewhere, &recording.path).unwrap();
    // A stray the restore would remove, were it followed.
    fs::write(elsewhere.join(MANIFEST_TMP), b"outside").unwrap();
    let before = files(&elsewhere);
    let error = restore_error(&recording);
    assert!(error.to_string().contains("is a symlink, which is never followed"), "{error}");
    let aside = set_aside(&at(&recording.path)).unwrap();
    assert!(fs::symlink_metadata(&aside).unwrap().file_type().is_symlink(), "the link itself was moved");
    assert_eq!(files(&elsewhere), before, "nothing of the target was removed");
    // A writer there now creates a real directory.
    let mut writer = SnapshotWriter::new(&at(&recording.path), IDENTITY, layout(150)).unwrap();
    writer.write(&recording.buffer, session(recording.step_calls), &mut Throttle::new(0, None)).unwrap();
    assert!(fs::symlink_metadata(&recording.path).unwrap().is_dir());
    assert_eq!(files(&elsewhere), before);
    writer.discard().unwrap();
    assert!(!recording.path.exists() && files(&elsewhere) == before, "discard removes the directory, not the target");
}

#[test]
fn names_planted_while_writing_are_replaced_never_written_through() {
    let mut recording = snapshot_on_disk();
    let outside = recording._dir.path().join("victim");
    fs::write(&outside, b"precious").unwrap();
    // The next segment's name and the manifest's temporary name, planted as links to the victim, and
    // a FIFO at the segment after (opening it for writing would wait for a reader).
    std::os::unix::fs::symlink(&outside, recording.path.join(segment_name(3))).unwrap();
    std::os::unix::fs::symlink(&outside, recording.path.join(MANIFEST_TMP)).unwrap();
    let fifo = recording.path.join(segment_name(4));
    rustix::fs::mknodat(rustix::fs::CWD, &fifo, rustix::fs::FileType::Fifo, rustix::fs::Mode::from_raw_mode(0o600), 0).unwrap();
    for _ in 0..2 {
        recording.record(7);
        recording.snapshot().unwrap();
    }
    assert_eq!(fs::read(&outside).unwrap(), b"precious");
    assert!(files(&recording.path).iter().all(|file| fs::symlink_metadata(file).unwrap().is_file()), "{:?}", files(&recording.path));
    assert_same_transitions(&recording.buffer.read().unwrap(), &recording.restored());
}

#[test]
fn forged_counters_with_a_valid_checksum_are_a_bad_snapshot() {
    type Forge = fn(&mut Manifest);
    let forgeries: [(&str, Forge); 5] = [
        ("inserts counter is 18446744073709551615", |manifest| manifest.counters.inserts = u64::MAX),
        ("step calls counter", |manifest| manifest.session.step_calls = u64::MAX),
        ("env steps counter", |manifest| manifest.session.total_env_steps = 1 << 60),
        ("transitions inserted but only", |manifest| manifest.counters.inserts = manifest.written.iter().sum::<u64>() + 1),
        ("batches but", |manifest| manifest.counters.batches = manifest.counters.samples + 1),
    ];
    for (expected, forge) in forgeries {
        let recording = snapshot_on_disk();
        let path = &recording.path;
        let mut manifest = parse_manifest(&fs::read(path.join(MANIFEST)).unwrap()).unwrap();
        forge(&mut manifest);
        write_manifest(&at(path).open(false).unwrap().unwrap(), &manifest).unwrap();
        let error = restore_error(&recording);
        assert!(error.to_string().contains(expected) && error.to_string().contains("forged"), "{expected}: {error}");
    }
}

/// What a file of a snapshot is replaced with in `other_file_types_are_refused`.
#[derive(Clone, Copy, Debug)]
enum Planted {
    SymlinkToFile,
    SymlinkToDir,
    DanglingSymlink,
    Fifo,
    Directory,
    Socket,
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// The reader's fuzzer over file types: any file of a snapshot replaced by a symlink (to a file, a
    /// directory, nowhere), a FIFO, a directory or a socket is refused, naming that file, at once.
    #[test]
    fn other_file_types_are_refused(file in 0usize..3, planted in prop_oneof![
        Just(Planted::SymlinkToFile), Just(Planted::SymlinkToDir), Just(Planted::DanglingSymlink),
        Just(Planted::Fifo), Just(Planted::Directory), Just(Planted::Socket),
    ]) {
        let recording = snapshot_on_disk();
        let target = files(&recording.path)[file].clone();
        let copy = recording._dir.path().join("copy");
        fs::rename(&target, &copy).unwrap();
        let _listener;
        match planted {
            Planted::SymlinkToFile => std::os::unix::fs::symlink(&copy, &target).unwrap(),
            Planted::SymlinkToDir => std::os::unix::fs::symlink(recording._dir.path(), &target).unwrap(),
            Planted::DanglingSymlink => std::os::unix::fs::symlink("/nonexistent/radserve", &target).unwrap(),
            Planted::Fifo => rustix::fs::mknodat(rustix::fs::CWD, &target, rustix::fs::FileType::Fifo, rustix::fs::Mode::from_raw_mode(0o600), 0).unwrap(),
            Planted::Directory => fs::create_dir(&target).unwrap(),
            Planted::Socket => _listener = std::os::unix::net::UnixListener::bind(&target).unwrap(),
        }
        let error = restore_error(&recording);
        prop_assert!(error.file == target, "{planted:?} at {}: {error}", target.display());
    }
}

/// The transitions `buffer` can sample.
fn held(buffer: &ReplayBuffer) -> Vec<TransitionRef> {
    (0..buffer.layout.num_envs)
        .flat_map(|env| (buffer.oldest_sampleable(env)..buffer.written[env]).map(move |frame| TransitionRef { env, frame }))
        .filter(|transition| buffer.flags[buffer.slot(transition.env, transition.frame)] & FIRST_OF_EPISODE == 0)
        .collect()
}

/// A snapshot taken before any prioritized stream, then priorities set (some to 0) and a second
/// snapshot with them, then steps the snapshot does not have.
fn prioritized_on_disk() -> Recording {
    let mut recording = Recording::new(13, 150);
    recording.record(25);
    recording.snapshot().unwrap();
    {
        let mut buffer = recording.buffer.write().unwrap();
        buffer.acquire_priorities(0.5).unwrap();
        let keys: Vec<u64> = held(&buffer).iter().map(|transition| transition.key()).collect();
        let values: Vec<f64> = (0..keys.len()).map(|index| (index % 5) as f64 * 1.5).collect();
        buffer.update_priorities(&keys, &values).unwrap();
    }
    recording.record(15);
    recording.snapshot().unwrap();
    recording.record(5);
    recording
}

#[test]
fn priorities_survive_a_snapshot() {
    let recording = prioritized_on_disk();
    let restored = recording.restored();
    let original = recording.buffer.read().unwrap();
    let transitions = held(&restored);
    assert!(transitions.len() > 80);
    for transition in &transitions {
        assert_eq!(restored.priority(*transition), original.priority(*transition), "{transition:?}");
    }
    assert!(transitions.iter().any(|transition| restored.priority(*transition) == Some(0.0)));
    assert_eq!(restored.max_priority(), Some(6.0));
    // One priorities file on disk, the last snapshot's, counted in the snapshot's bytes.
    let names: Vec<String> = files(&recording.path).iter().map(|file| file.file_name().unwrap().to_string_lossy().into()).collect();
    assert_eq!(names.iter().filter(|name| name.starts_with("prio-")).collect::<Vec<_>>(), ["prio-00000002.rsnap"]);
    let on_disk: u64 = files(&recording.path).iter().filter(|file| !file.ends_with(MANIFEST)).map(|file| fs::metadata(file).unwrap().len()).sum();
    assert_eq!(recording.writer.disk_bytes(), on_disk);
}

#[test]
fn a_snapshot_of_format_1_still_reads_without_priorities() {
    let recording = snapshot_on_disk();
    let open = at(&recording.path).open(false).unwrap().unwrap();
    // As a format 1 build wrote it: the version in the manifest's header and in each segment's
    // (under the segment header's checksum).
    let manifest = parse_manifest(&fs::read(recording.path.join(MANIFEST)).unwrap()).unwrap();
    write_manifest(&open, &manifest).unwrap();
    let mut bytes = fs::read(recording.path.join(MANIFEST)).unwrap();
    bytes[8..12].copy_from_slice(&1u32.to_le_bytes());
    fs::write(recording.path.join(MANIFEST), &bytes).unwrap();
    for segment in &manifest.segments {
        let path = recording.path.join(segment_name(segment.sequence));
        let mut bytes = fs::read(&path).unwrap();
        bytes[8..12].copy_from_slice(&1u32.to_le_bytes());
        let crc = crc32fast::hash(&bytes[..SEGMENT_HEADER_BYTES - 4]);
        bytes[SEGMENT_HEADER_BYTES - 4..SEGMENT_HEADER_BYTES].copy_from_slice(&crc.to_le_bytes());
        fs::write(&path, &bytes).unwrap();
    }
    let restored = recording.restored();
    assert!(assert_same_transitions(&recording.buffer.read().unwrap(), &restored) > 80);
    assert_eq!(restored.max_priority(), None, "no priorities until a prioritized stream samples it");
}

#[test]
fn a_damaged_or_forged_priorities_file_is_refused_naming_it() {
    const HEADER: usize = PRIORITIES_HEADER_BYTES;
    type Damage = fn(&mut Vec<u8>);
    let damages: [(&str, Damage); 4] = [
        ("checksum mismatch", |bytes| bytes[HEADER + 3] ^= 1),
        ("the manifest says", |bytes| bytes.truncate(bytes.len() - 16)),
        ("not a radserve snapshot priorities file", |bytes| bytes[0] = b'X'),
        ("not a priority of this buffer", |bytes| {
            // A negative priority under a valid checksum.
            bytes[HEADER + 8..HEADER + 16].copy_from_slice(&(-1.0f64).to_le_bytes());
            let end = bytes.len() - 4;
            let crc = crc32fast::hash(&bytes[..end]);
            bytes[end..].copy_from_slice(&crc.to_le_bytes());
        }),
    ];
    for (expected, damage) in damages {
        let recording = prioritized_on_disk();
        let path = recording.path.join(priorities_name(2));
        let mut bytes = fs::read(&path).unwrap();
        damage(&mut bytes);
        fs::write(&path, &bytes).unwrap();
        let mut buffer = ReplayBuffer::new(layout(150)).unwrap();
        let error = restore(&at(&recording.path), IDENTITY, &mut buffer).expect_err("refused");
        assert!(error.to_string().contains(expected) && error.file == path, "{expected}: {error}");
        assert!(buffer.is_empty() && buffer.max_priority().is_none());
    }
}

#[test]
fn a_symlink_or_fifo_in_place_of_the_priorities_file_is_refused_without_being_read() {
    let recording = prioritized_on_disk();
    let path = recording.path.join(priorities_name(2));
    fs::remove_file(&path).unwrap();
    std::os::unix::fs::symlink("/proc/self/pagemap", &path).unwrap();
    let error = restore_error(&recording);
    assert!(error.to_string().contains("symlink") && error.file == path, "{error}");

    let recording = prioritized_on_disk();
    let path = recording.path.join(priorities_name(2));
    fs::remove_file(&path).unwrap();
    rustix::fs::mknodat(rustix::fs::CWD, &path, rustix::fs::FileType::Fifo, rustix::fs::Mode::from_raw_mode(0o600), 0).unwrap();
    let error = restore_error(&recording);
    assert!(error.to_string().contains("is a FIFO, not a regular file") && error.file == path, "{error}");
}
