//! Handing a memory file to the learner on the same host: the client connects to a Unix socket in
//! the abstract namespace whose name is random (it says nothing about the server or the token),
//! the server checks who connected (SO_PEERCRED: a uid it allows) and waits for the 16-byte token
//! the client learned over gRPC (authenticated, possibly TLS), then sends the descriptor itself
//! (SCM_RIGHTS). No path to the memory exists anywhere: the server is non-dumpable, so
//! `/proc/<pid>/fd` is closed to other processes, and only the client that passed both checks
//! holds a descriptor.
//!
//! Connections are checked concurrently: one that connects first and stays silent does not hold up
//! the rightful client (each has `TOKEN_TIMEOUT`, and at most `MAX_PENDING` wait at once).

use std::io;
use std::os::fd::BorrowedFd;
use std::os::linux::net::SocketAddrExt;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::AsyncReadExt;
use tokio::net::{UnixListener, UnixStream};
use tokio::time::{timeout_at, Instant};

/// How long a client has to connect and present the token after the server described the memory.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one connection has to present the token once connected.
const TOKEN_TIMEOUT: Duration = Duration::from_secs(2);
/// Connections that have not presented the token yet, at most, per socket.
const MAX_PENDING: usize = 32;
/// The byte sent with the descriptor.
const HANDED_OVER: u8 = 1;

/// Which local users may receive shared memory: the server's own uid, and those configured
/// (`server.shared_memory_uids`).
#[derive(Clone, Debug)]
pub struct PeerPolicy(Arc<Vec<u32>>);

impl PeerPolicy {
    /// The server's own user and `extra`.
    pub fn new(extra: &[u32]) -> PeerPolicy {
        // SAFETY: geteuid has no arguments and cannot fail.
        let mut uids = vec![unsafe { libc::geteuid() }];
        uids.extend_from_slice(extra);
        PeerPolicy(Arc::new(uids))
    }

    fn allows(&self, uid: u32) -> bool {
        self.0.contains(&uid)
    }
}

/// A socket waiting for the one client that may have a memory file.
pub struct HandoffSocket {
    listener: UnixListener,
    name: String,
}

impl HandoffSocket {
    /// Binds `radserve-<32 random hex digits>` in the abstract namespace (nothing on disk; the name
    /// is listed in /proc/net/unix for anyone on the host, so it carries no secret).
    pub fn bind() -> io::Result<HandoffSocket> {
        let name = format!("radserve-{}", crate::auth::hex(&radserve_shm::random_token()?));
        let address = std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes())?;
        let listener = std::os::unix::net::UnixListener::bind_addr(&address)?;
        listener.set_nonblocking(true)?;
        Ok(HandoffSocket { listener: UnixListener::from_std(listener)?, name })
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// Waits (at most `CONNECT_TIMEOUT`) for a connection from an allowed user that presents
    /// `token`, sends it `memory`, and returns the connection (an acting channel goes on using it).
    /// None: nobody rightful came in time.
    pub async fn hand_over(&self, token: [u8; 16], memory: BorrowedFd<'_>, peers: &PeerPolicy) -> Option<UnixStream> {
        let deadline = Instant::now() + CONNECT_TIMEOUT;
        let mut pending = tokio::task::JoinSet::new();
        loop {
            tokio::select! {
                accepted = self.listener.accept() => {
                    let Ok((stream, _)) = accepted else {
                        // Out of descriptors, say: try again shortly instead of spinning.
                        tokio::time::sleep(Duration::from_millis(10)).await;
                        continue;
                    };
                    // Another user's process: dropped at once, before it can send anything.
                    let Ok(credentials) = stream.peer_cred() else { continue };
                    if !peers.allows(credentials.uid()) || pending.len() >= MAX_PENDING {
                        continue;
                    }
                    pending.spawn(async move {
                        let mut stream = stream;
                        let mut presented = [0u8; 16];
                        let limit = Instant::now() + TOKEN_TIMEOUT;
                        match timeout_at(limit, stream.read_exact(&mut presented)).await {
                            Ok(Ok(_)) if presented == token => Some(stream),
                            _ => None,
                        }
                    });
                }
                Some(presented) = pending.join_next(), if !pending.is_empty() => {
                    if let Ok(Some(stream)) = presented {
                        // The rest of `pending` is dropped, and their connections with it.
                        return send(stream, memory).await;
                    }
                }
                () = tokio::time::sleep_until(deadline) => return None,
            }
        }
    }
}

async fn send(stream: UnixStream, memory: BorrowedFd<'_>) -> Option<UnixStream> {
    // One byte and one descriptor into an empty socket buffer: writable at once, but wait for it
    // rather than assume.
    loop {
        if stream.writable().await.is_err() {
            return None;
        }
        match stream.try_io(tokio::io::Interest::WRITABLE, || radserve_shm::send_fd(&stream, memory, HANDED_OVER)) {
            Ok(()) => return Some(stream),
            Err(error) if error.kind() == io::ErrorKind::WouldBlock => continue,
            Err(_) => return None,
        }
    }
}
