//! Memory that radserve shares with another process: a worker writing its envs' frames, a learner
//! reading minibatches where the producer augmented them, a learner acting through arrays both sides
//! map. All three are one kind of object, a [`MemFile`].
//!
//! A `MemFile` is an anonymous memory file (`memfd_create`): nothing is left in `/dev/shm` when either
//! process dies, its pages are allocated when first written, and a peer's mapping stays valid after
//! the server drops its own. The peer maps it through `/proc/<server pid>/fd/<fd>` ([`MemFile::proc_path`]),
//! which only a process of the same user can open. Regions handed to clients start with a
//! [`Header`]: 16 bytes that say what the memory is, then a random token the client checks, so that
//! it knows it mapped the memory it was told of.

use std::ffi::CStr;
use std::fs::{File, OpenOptions};
use std::io;
use std::os::fd::{AsRawFd, FromRawFd};

use memmap2::MmapMut;

/// Bytes of a region's header: the 16-byte magic, then the 16-byte token.
pub const HEADER_BYTES: usize = 32;

/// What a region is (its magic) and the token a client must find after it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    pub magic: [u8; 16],
    pub token: [u8; 16],
}

/// A mapped memory file, created here or opened from a peer's path.
pub struct MemFile {
    file: File,
    map: MmapMut,
}

impl MemFile {
    /// A zeroed memory file of `len` bytes (at least one), named `name` in `/proc/<pid>/fd` listings.
    pub fn create(name: &CStr, len: usize) -> io::Result<MemFile> {
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

    /// Creates a memory file of `len` bytes whose first [`HEADER_BYTES`] hold `magic` and a fresh
    /// random token.
    pub fn create_with_header(name: &CStr, len: usize, magic: &[u8; 16]) -> io::Result<(MemFile, Header)> {
        assert!(len >= HEADER_BYTES, "a region with a header holds at least {HEADER_BYTES} bytes, asked {len}");
        let mut memory = MemFile::create(name, len)?;
        let header = Header { magic: *magic, token: random_token()? };
        memory.as_mut_slice()[..16].copy_from_slice(&header.magic);
        memory.as_mut_slice()[16..HEADER_BYTES].copy_from_slice(&header.token);
        Ok((memory, header))
    }

    /// Maps a memory file created by another process, from the path that process gave.
    pub fn open(path: &str) -> io::Result<MemFile> {
        let file = OpenOptions::new().read(true).write(true).open(path)?;
        Self::map(file)
    }

    fn map(file: File) -> io::Result<MemFile> {
        // SAFETY: every user of a MemFile agrees with its peer on who writes which bytes when: a
        // worker writes a group's frames only while it handles a request for that group and the
        // server reads them after the reply; a batch slot is written by the producer that owns it
        // and read by the learner after its descriptor was sent; acting arrays are written by one
        // side between doorbells. The server never trusts what it reads back (it copies and checks).
        let map = unsafe { MmapMut::map_mut(&file)? };
        Ok(MemFile { file, map })
    }

    /// The path another process of the same user opens to map this memory.
    pub fn proc_path(&self) -> String {
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

    /// The start of the mapping, for owners that hand disjoint parts of it to several writers.
    pub fn as_mut_ptr(&mut self) -> *mut u8 {
        self.map.as_mut_ptr()
    }
}

/// 16 random bytes from the kernel.
pub fn random_token() -> io::Result<[u8; 16]> {
    let mut token = [0u8; 16];
    // SAFETY: writes at most 16 bytes into `token`.
    let written = unsafe { libc::getrandom(token.as_mut_ptr().cast(), token.len(), 0) };
    if written != token.len() as isize {
        return Err(io::Error::last_os_error());
    }
    Ok(token)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_mapping_sees_the_first_ones_writes() {
        let mut owner = MemFile::create(c"radserve-test", 4096).unwrap();
        let peer = MemFile::open(&owner.proc_path()).unwrap();
        owner.as_mut_slice()[100] = 42;
        assert_eq!(peer.as_slice()[100], 42);
        assert_eq!(peer.len(), 4096);
        assert!(!peer.is_empty());
    }

    #[test]
    fn headers_carry_the_magic_and_a_fresh_token() {
        let (first, header) = MemFile::create_with_header(c"radserve-test", 64, b"radserve-testing").unwrap();
        let (_, other) = MemFile::create_with_header(c"radserve-test", 64, b"radserve-testing").unwrap();
        let peer = MemFile::open(&first.proc_path()).unwrap();
        assert_eq!(&peer.as_slice()[..16], b"radserve-testing");
        assert_eq!(peer.as_slice()[16..32], header.token);
        assert_ne!(header.token, other.token);
    }

    #[test]
    fn an_empty_request_still_maps_one_byte() {
        assert_eq!(MemFile::create(c"radserve-test", 0).unwrap().len(), 1);
    }
}
