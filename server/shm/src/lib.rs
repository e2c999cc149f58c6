//! Memory that radserve shares with another process: a worker writing its envs' frames, a learner
//! reading minibatches where the producer augmented them, a learner acting through arrays both sides
//! map. All three are one kind of object, a [`MemFile`].
//!
//! A `MemFile` is an anonymous memory file (`memfd_create`): nothing is left in `/dev/shm` when either
//! process dies, its pages are allocated when first written, and a peer's mapping stays valid after
//! the server drops its own. It has no name anywhere: a peer gets the descriptor itself over a Unix
//! socket (SCM_RIGHTS, [`send_fd`] and [`receive_fd`]) from the process that decided it may have
//! it, and the server makes itself non-dumpable so that `/proc/<pid>/fd` does not hand it to any
//! other process of its user. Its size is sealed (`F_SEAL_SHRINK | F_SEAL_GROW`): a peer cannot
//! truncate it under the server's mapping (which would kill the server with SIGBUS). Regions handed
//! to clients start with a [`Header`]: 16 bytes that say what the memory is, then a random token
//! the client checks, so that it knows it mapped the memory it was told of.

use std::ffi::CStr;
use std::fs::File;
use std::io;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, FromRawFd, OwnedFd};
use std::os::unix::net::UnixStream;

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
    /// A zeroed memory file of `len` bytes (at least one), named `name` in `/proc/<pid>/fd` listings,
    /// its size sealed.
    pub fn create(name: &CStr, len: usize) -> io::Result<MemFile> {
        // SAFETY: `name` is a valid C string; the returned descriptor is checked and then owned by `File`.
        let fd = unsafe { libc::memfd_create(name.as_ptr(), libc::MFD_CLOEXEC | libc::MFD_ALLOW_SEALING) };
        if fd < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: `fd` is a fresh descriptor that nothing else owns.
        let file = unsafe { File::from_raw_fd(fd) };
        file.set_len(len.max(1) as u64)?;
        let seals = libc::F_SEAL_SHRINK | libc::F_SEAL_GROW | libc::F_SEAL_SEAL;
        // SAFETY: F_ADD_SEALS takes an int of seal flags on a descriptor this function owns.
        if unsafe { libc::fcntl(file.as_raw_fd(), libc::F_ADD_SEALS, seals) } != 0 {
            return Err(io::Error::last_os_error());
        }
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

    /// Maps a memory file another process passed (its descriptor, received with [`receive_fd`]).
    pub fn from_fd(fd: OwnedFd) -> io::Result<MemFile> {
        Self::map(File::from(fd))
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

    /// The descriptor, to pass to a peer with [`send_fd`].
    pub fn fd(&self) -> BorrowedFd<'_> {
        self.file.as_fd()
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

/// Sends `fd` over `socket` with one byte of data (`byte`), as SCM_RIGHTS: the peer gets its own
/// descriptor of the same file.
pub fn send_fd(socket: &impl AsRawFd, fd: BorrowedFd<'_>, byte: u8) -> io::Result<()> {
    let mut data = [byte];
    let mut iov = libc::iovec { iov_base: data.as_mut_ptr().cast(), iov_len: 1 };
    // An aligned buffer for one cmsghdr carrying one int.
    let mut control = [0u64; 4];
    // SAFETY: CMSG_SPACE is a pure size computation.
    let space = unsafe { libc::CMSG_SPACE(std::mem::size_of::<libc::c_int>() as u32) } as usize;
    assert!(space <= std::mem::size_of_val(&control));
    // SAFETY: msghdr is plain data; every pointer set below points at live locals for the call, and
    // the control buffer is large enough and aligned for the one header CMSG_FIRSTHDR returns.
    unsafe {
        let mut message: libc::msghdr = std::mem::zeroed();
        message.msg_iov = &mut iov;
        message.msg_iovlen = 1;
        message.msg_control = control.as_mut_ptr().cast();
        message.msg_controllen = space as _;
        let header = libc::CMSG_FIRSTHDR(&message);
        (*header).cmsg_level = libc::SOL_SOCKET;
        (*header).cmsg_type = libc::SCM_RIGHTS;
        (*header).cmsg_len = libc::CMSG_LEN(std::mem::size_of::<libc::c_int>() as u32) as _;
        std::ptr::write_unaligned(libc::CMSG_DATA(header).cast::<libc::c_int>(), fd.as_raw_fd());
        if libc::sendmsg(socket.as_raw_fd(), &message, libc::MSG_NOSIGNAL) != 1 {
            return Err(io::Error::last_os_error());
        }
    }
    Ok(())
}

/// Receives one byte and, if the peer sent one, a descriptor (the counterpart of [`send_fd`]);
/// blocks. Ok((byte, None)) when data came without a descriptor; an error at end of stream.
pub fn receive_fd(socket: &UnixStream) -> io::Result<(u8, Option<OwnedFd>)> {
    let mut data = [0u8];
    let mut iov = libc::iovec { iov_base: data.as_mut_ptr().cast(), iov_len: 1 };
    let mut control = [0u64; 4];
    // SAFETY: as in `send_fd`; the kernel writes at most `msg_controllen` bytes of control data, and
    // a descriptor it passed is owned here from then on (MSG_CMSG_CLOEXEC).
    unsafe {
        let mut message: libc::msghdr = std::mem::zeroed();
        message.msg_iov = &mut iov;
        message.msg_iovlen = 1;
        message.msg_control = control.as_mut_ptr().cast();
        message.msg_controllen = std::mem::size_of_val(&control) as _;
        let received = libc::recvmsg(socket.as_raw_fd(), &mut message, libc::MSG_CMSG_CLOEXEC);
        if received < 0 {
            return Err(io::Error::last_os_error());
        }
        if received == 0 {
            return Err(io::Error::new(io::ErrorKind::UnexpectedEof, "the peer closed the socket"));
        }
        let header = libc::CMSG_FIRSTHDR(&message);
        let fd = if !header.is_null() && (*header).cmsg_level == libc::SOL_SOCKET && (*header).cmsg_type == libc::SCM_RIGHTS {
            let raw = std::ptr::read_unaligned(libc::CMSG_DATA(header).cast::<libc::c_int>());
            Some(OwnedFd::from_raw_fd(raw))
        } else {
            None
        };
        Ok((data[0], fd))
    }
}

/// Makes this process non-dumpable: `/proc/<pid>/fd`, `/proc/<pid>/mem` and ptrace are then closed
/// to every other process without CAP_SYS_PTRACE, the same user's included, so the memory files
/// this process holds reach only the peers it sends them to. Also no core dumps (they would hold
/// tokens and observations).
pub fn make_undumpable() -> io::Result<()> {
    // SAFETY: prctl(PR_SET_DUMPABLE) reads one integer argument.
    if unsafe { libc::prctl(libc::PR_SET_DUMPABLE, 0, 0, 0, 0) } != 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
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

    /// The memory as a peer maps it: its descriptor passed over a socket pair.
    fn passed(memory: &MemFile) -> MemFile {
        let (server, client) = UnixStream::pair().unwrap();
        send_fd(&server, memory.fd(), 7).unwrap();
        let (byte, fd) = receive_fd(&client).unwrap();
        assert_eq!(byte, 7);
        MemFile::from_fd(fd.expect("a descriptor came")).unwrap()
    }

    #[test]
    fn a_passed_mapping_sees_the_first_ones_writes() {
        let mut owner = MemFile::create(c"radserve-test", 4096).unwrap();
        let peer = passed(&owner);
        owner.as_mut_slice()[100] = 42;
        assert_eq!(peer.as_slice()[100], 42);
        assert_eq!(peer.len(), 4096);
        assert!(!peer.is_empty());
    }

    #[test]
    fn a_peer_cannot_resize_the_memory() {
        let owner = MemFile::create(c"radserve-test", 4096).unwrap();
        let peer = passed(&owner);
        assert!(peer.file.set_len(0).is_err(), "shrinking would SIGBUS the owner");
        assert!(peer.file.set_len(1 << 20).is_err());
        assert_eq!(owner.as_slice().len(), 4096);
    }

    #[test]
    fn data_without_a_descriptor_is_told_apart() {
        let (server, client) = UnixStream::pair().unwrap();
        std::io::Write::write_all(&mut &server, &[1]).unwrap();
        assert_eq!(receive_fd(&client).unwrap().0, 1);
        drop(server);
        assert!(receive_fd(&client).is_err());
    }

    #[test]
    fn headers_carry_the_magic_and_a_fresh_token() {
        let (first, header) = MemFile::create_with_header(c"radserve-test", 64, b"radserve-testing").unwrap();
        let (_, other) = MemFile::create_with_header(c"radserve-test", 64, b"radserve-testing").unwrap();
        let peer = passed(&first);
        assert_eq!(&peer.as_slice()[..16], b"radserve-testing");
        assert_eq!(peer.as_slice()[16..32], header.token);
        assert_ne!(header.token, other.token);
    }

    #[test]
    fn an_empty_request_still_maps_one_byte() {
        assert_eq!(MemFile::create(c"radserve-test", 0).unwrap().len(), 1);
    }
}
