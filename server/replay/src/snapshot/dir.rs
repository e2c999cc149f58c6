//! The snapshot directory opened as what it must be. Whatever is found below `snapshot_dir` may have
//! been planted there (a symlink to `/etc/shadow`, a FIFO, a session directory that is a link to
//! somewhere else), so every name is resolved relative to a directory descriptor with `openat` and
//! `O_NOFOLLOW` (a symlink is an error, never followed), files are opened non-blocking and used only
//! when `fstat` says they are regular files, and new files are created exclusively (`O_EXCL`: a name
//! planted in between is removed, never written through). `snapshot_dir` itself is the operator's
//! path and is opened as configured.
//!
//! rustix (already in the tree through tempfile) gives these system calls without hand-written
//! `unsafe`.

use std::ffi::OsStr;
use std::fs::File;
use std::io::{self, Read};
use std::os::fd::OwnedFd;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};

use rustix::fs::{AtFlags, FileType, Mode, OFlags};

/// Where a snapshot lives: the directory `parts` below `root` (`snapshot_dir`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SnapshotPath {
    root: PathBuf,
    parts: Vec<String>,
}

impl SnapshotPath {
    /// `root/parts[0]/parts[1]/...`; each part is one plain name (no `/`, not `.` or `..`).
    pub fn new(root: &Path, parts: &[&str]) -> io::Result<SnapshotPath> {
        if parts.is_empty() {
            return Err(io::Error::new(io::ErrorKind::InvalidInput, "a snapshot path names at least one directory below its root"));
        }
        if let Some(bad) = parts.iter().find(|part| part.is_empty() || **part == "." || **part == ".." || part.contains(['/', '\0'])) {
            return Err(io::Error::new(io::ErrorKind::InvalidInput, format!("'{bad}' is not a plain directory name")));
        }
        Ok(SnapshotPath { root: root.to_path_buf(), parts: parts.iter().map(|part| part.to_string()).collect() })
    }

    /// The path, for messages.
    pub fn path(&self) -> PathBuf {
        self.parts.iter().fold(self.root.clone(), |path, part| path.join(part))
    }

    /// The last directory's name.
    pub fn name(&self) -> &str {
        self.parts.last().expect("at least one part")
    }

    /// The directory that holds the snapshot's directory (created when `create`), and the snapshot
    /// directory's name in it; None when a part is missing and `create` is off.
    pub(super) fn open_parent(&self, create: bool) -> io::Result<Option<SnapshotDir>> {
        let root = match rustix::fs::open(&self.root, OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC, Mode::empty()) {
            Ok(fd) => fd,
            Err(rustix::io::Errno::NOENT) if create => {
                std::fs::create_dir_all(&self.root)?;
                rustix::fs::open(&self.root, OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC, Mode::empty())?
            }
            Err(rustix::io::Errno::NOENT) => return Ok(None),
            Err(error) => return Err(error.into()),
        };
        let mut dir = SnapshotDir { fd: root, path: self.root.clone() };
        for part in &self.parts[..self.parts.len() - 1] {
            match dir.subdir(part, create)? {
                Some(next) => dir = next,
                None => return Ok(None),
            }
        }
        Ok(Some(dir))
    }

    /// The snapshot's directory (created when `create`); None when it does not exist and `create` is
    /// off. A part that is a symlink or not a directory is an error.
    pub(super) fn open(&self, create: bool) -> io::Result<Option<SnapshotDir>> {
        match self.open_parent(create)? {
            Some(parent) => parent.subdir(self.name(), create),
            None => Ok(None),
        }
    }
}

/// An open directory under `snapshot_dir`: every name in it is opened relative to it.
#[derive(Debug)]
pub(super) struct SnapshotDir {
    fd: OwnedFd,
    path: PathBuf,
}

fn not_regular(kind: FileType) -> &'static str {
    match kind {
        FileType::RegularFile => "a regular file",
        FileType::Directory => "a directory",
        FileType::Symlink => "a symlink",
        FileType::Fifo => "a FIFO",
        FileType::Socket => "a socket",
        FileType::CharacterDevice => "a character device",
        FileType::BlockDevice => "a block device",
        FileType::Unknown => "of an unknown type",
    }
}

impl SnapshotDir {
    pub(super) fn path(&self) -> &Path {
        &self.path
    }

    /// `name` in this directory, created when missing and `create`; a symlink or anything but a
    /// directory is refused.
    fn subdir(&self, name: &str, create: bool) -> io::Result<Option<SnapshotDir>> {
        let path = self.path.join(name);
        let flags = OFlags::RDONLY | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC;
        let fd = match rustix::fs::openat(&self.fd, name, flags, Mode::empty()) {
            Ok(fd) => fd,
            Err(rustix::io::Errno::NOENT) if create => {
                match rustix::fs::mkdirat(&self.fd, name, Mode::from_raw_mode(0o700)) {
                    Ok(()) | Err(rustix::io::Errno::EXIST) => {}
                    Err(error) => return Err(error.into()),
                }
                rustix::fs::openat(&self.fd, name, flags, Mode::empty()).map_err(|error| refused(&path, error))?
            }
            Err(rustix::io::Errno::NOENT) => return Ok(None),
            // O_DIRECTORY on a symlink says ENOTDIR: tell a link from a file.
            Err(rustix::io::Errno::NOTDIR) => {
                let link = rustix::fs::statat(&self.fd, name, AtFlags::SYMLINK_NOFOLLOW)
                    .is_ok_and(|stat| FileType::from_raw_mode(stat.st_mode) == FileType::Symlink);
                return Err(refused(&path, if link { rustix::io::Errno::LOOP } else { rustix::io::Errno::NOTDIR }));
            }
            Err(error) => return Err(refused(&path, error)),
        };
        Ok(Some(SnapshotDir { fd, path }))
    }

    /// Opens `name` for reading if it is a regular file: never through a symlink, never blocking on
    /// a FIFO or a device (opened non-blocking, checked with fstat before any read). None when it
    /// does not exist.
    pub(super) fn open_regular(&self, name: &str) -> io::Result<Option<(File, u64)>> {
        let flags = OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::NONBLOCK | OFlags::CLOEXEC | OFlags::NOCTTY;
        let fd = match rustix::fs::openat(&self.fd, name, flags, Mode::empty()) {
            Ok(fd) => fd,
            Err(rustix::io::Errno::NOENT) => return Ok(None),
            Err(error) => return Err(refused(&self.path.join(name), error)),
        };
        let stat = rustix::fs::fstat(&fd)?;
        let kind = FileType::from_raw_mode(stat.st_mode);
        if kind != FileType::RegularFile {
            return Err(io::Error::new(io::ErrorKind::InvalidData, format!("{} is {}, not a regular file", name, not_regular(kind))));
        }
        // Regular files never block; the flag is cleared so reads behave as usual.
        rustix::fs::fcntl_setfl(&fd, OFlags::empty())?;
        Ok(Some((File::from(fd), stat.st_size as u64)))
    }

    /// Reads all of regular file `name`, refusing one longer than `limit` bytes (read with a bound:
    /// a file's claimed length is not trusted). None when it does not exist.
    pub(super) fn read_bounded(&self, name: &str, limit: u64) -> io::Result<Option<Vec<u8>>> {
        let Some((file, length)) = self.open_regular(name)? else { return Ok(None) };
        if length > limit {
            return Err(io::Error::new(io::ErrorKind::InvalidData, format!("{length} bytes, more than it can be ({limit})")));
        }
        let mut contents = Vec::with_capacity(length as usize);
        file.take(limit + 1).read_to_end(&mut contents)?;
        if contents.len() as u64 > limit {
            return Err(io::Error::new(io::ErrorKind::InvalidData, format!("more than {limit} bytes, more than it can be")));
        }
        Ok(Some(contents))
    }

    /// Creates `name` for writing, exclusively: whatever holds the name (a stray of a crash, or a
    /// symlink or FIFO planted there) is removed first, and the create fails rather than open
    /// something that appeared in between.
    pub(super) fn create_exclusive(&self, name: &str) -> io::Result<File> {
        let flags = OFlags::WRONLY | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC;
        let mode = Mode::from_raw_mode(0o600);
        match rustix::fs::openat(&self.fd, name, flags, mode) {
            Ok(fd) => Ok(File::from(fd)),
            Err(rustix::io::Errno::EXIST) => {
                self.remove(name)?;
                Ok(File::from(rustix::fs::openat(&self.fd, name, flags, mode)?))
            }
            Err(error) => Err(error.into()),
        }
    }

    /// Renames `from` to `to` within this directory (a symlink at `to` is replaced, not followed).
    pub(super) fn rename(&self, from: &str, to: &str) -> io::Result<()> {
        Ok(rustix::fs::renameat(&self.fd, from, &self.fd, to)?)
    }

    /// Removes the entry `name` (a symlink itself, never its target); a missing one is not an error.
    pub(super) fn remove(&self, name: &str) -> io::Result<()> {
        match rustix::fs::unlinkat(&self.fd, name, AtFlags::empty()) {
            Ok(()) | Err(rustix::io::Errno::NOENT) => Ok(()),
            Err(rustix::io::Errno::ISDIR) => Err(io::Error::new(io::ErrorKind::InvalidData, format!("{name} is a directory"))),
            Err(error) => Err(error.into()),
        }
    }

    /// Removes the empty-of-subdirectories directory `name` in this one and every entry in it.
    pub(super) fn remove_tree(&self, name: &str) -> io::Result<()> {
        let Some(child) = self.subdir(name, false)? else { return Ok(()) };
        for entry in child.names()? {
            child.remove(&entry)?;
        }
        match rustix::fs::unlinkat(&self.fd, name, AtFlags::REMOVEDIR) {
            Ok(()) | Err(rustix::io::Errno::NOENT) => Ok(()),
            Err(error) => Err(error.into()),
        }
    }

    /// The names in this directory (without `.` and `..`); names that are not UTF-8 are left out
    /// (nothing radserve writes has one).
    pub(super) fn names(&self) -> io::Result<Vec<String>> {
        let fd = rustix::fs::openat(&self.fd, ".", OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC, Mode::empty())?;
        let mut names = Vec::new();
        for entry in rustix::fs::Dir::read_from(&fd)? {
            let entry = entry?;
            let name = OsStr::from_bytes(entry.file_name().to_bytes());
            if name == "." || name == ".." {
                continue;
            }
            if let Some(name) = name.to_str() {
                names.push(name.to_string());
            }
        }
        Ok(names)
    }

    /// Makes the directory's entries (a rename) durable.
    pub(super) fn sync(&self) -> io::Result<()> {
        Ok(rustix::fs::fsync(&self.fd)?)
    }
}

/// An `openat` that failed: a symlink (ELOOP under O_NOFOLLOW) or a non-directory is named as such.
fn refused(path: &Path, error: rustix::io::Errno) -> io::Error {
    match error {
        rustix::io::Errno::LOOP => io::Error::new(io::ErrorKind::InvalidData, format!("{} is a symlink, which is never followed", path.display())),
        rustix::io::Errno::NOTDIR => io::Error::new(io::ErrorKind::InvalidData, format!("{} is not a directory", path.display())),
        other => io::Error::new(io::Error::from(other).kind(), format!("{}: {}", path.display(), io::Error::from(other))),
    }
}
