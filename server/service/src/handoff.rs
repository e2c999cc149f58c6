//! Handing a memory file to the learner on the same host: the client connects to a Unix socket in
//! the abstract namespace whose name is random (it says nothing about the server or the token),
//! the server checks who connected (SO_PEERCRED: a uid it allows) and waits for the 16-byte token
//! the client learned over gRPC (authenticated, possibly TLS), then sends the descriptor itself
//! (SCM_RIGHTS). No path to the memory exists anywhere: the server is non-dumpable, so
//! `/proc/<pid>/fd` is closed to other processes, and only the client that passed both checks
//! holds a descriptor.
//!
//! Connections are checked concurrently: one that connects first and stays silent does not hold up
//! the rightful client (each has `TOKEN_TIMEOUT`). At most `MAX_PENDING` wait at once, and at most
//! `MAX_PENDING_PER_PROCESS` of one process: a new connection beyond either makes room by dropping
//! the oldest waiting one (of its own process first), so a process that keeps silent connections
//! open cannot keep the rightful client out, which connects and presents its token at once. The
//! listener is closed once the memory is handed over (the socket is consumed).

use std::collections::VecDeque;
use std::io;
use std::os::fd::BorrowedFd;
use std::os::linux::net::SocketAddrExt;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::AsyncReadExt;
use tokio::net::{UnixListener, UnixStream};
use tokio::task::{AbortHandle, JoinSet};
use tokio::time::{timeout_at, Instant};

/// How long a client has to connect and present the token after the server described the memory.
pub const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// How long one connection has to present the token once connected.
const TOKEN_TIMEOUT: Duration = Duration::from_secs(2);
/// Connections that have not presented the token yet, at most, per socket.
const MAX_PENDING: usize = 32;
/// Of those, at most, from one process (SO_PEERCRED's pid).
const MAX_PENDING_PER_PROCESS: usize = 4;
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
    /// `token`, sends it `memory`, and returns the connection (a shared-stepping channel goes on using it).
    /// None: nobody rightful came in time. The listener closes when this returns.
    pub async fn hand_over(self, token: [u8; 16], memory: BorrowedFd<'_>, peers: &PeerPolicy) -> Option<UnixStream> {
        let deadline = Instant::now() + CONNECT_TIMEOUT;
        let mut pending = Pending::default();
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
                    if !peers.allows(credentials.uid()) {
                        continue;
                    }
                    pending.admit(credentials.pid().unwrap_or(0), stream, token);
                }
                Some(presented) = pending.checks.join_next_with_id(), if !pending.checks.is_empty() => {
                    if let Ok((id, found)) = presented {
                        pending.waiting.retain(|waiting| waiting.abort.id() != id);
                        if let Some(stream) = found {
                            // The rest of `pending` is dropped, and their connections with it.
                            return send(stream, memory).await;
                        }
                    }
                }
                () = tokio::time::sleep_until(deadline) => return None,
            }
        }
    }
}

/// Connections that have not presented the token yet: each is read by a task of `checks`, and
/// `waiting` lists them oldest first with the process that made them.
#[derive(Default)]
struct Pending {
    checks: JoinSet<Option<UnixStream>>,
    waiting: VecDeque<Waiting>,
}

struct Waiting {
    pid: i32,
    abort: AbortHandle,
}

impl Pending {
    /// Starts reading `stream`'s token (at most `TOKEN_TIMEOUT`), first dropping the oldest
    /// connection of `pid` when it has `MAX_PENDING_PER_PROCESS` waiting, else the oldest of all
    /// when `MAX_PENDING` wait.
    fn admit(&mut self, pid: i32, stream: UnixStream, token: [u8; 16]) {
        let own = self.waiting.iter().filter(|waiting| waiting.pid == pid).count();
        let oldest = if own >= MAX_PENDING_PER_PROCESS {
            self.waiting.iter().position(|waiting| waiting.pid == pid)
        } else if self.waiting.len() >= MAX_PENDING {
            Some(0)
        } else {
            None
        };
        if let Some(dropped) = oldest.and_then(|index| self.waiting.remove(index)) {
            dropped.abort.abort();
        }
        let abort = self.checks.spawn(async move {
            let mut stream = stream;
            let mut presented = [0u8; 16];
            let limit = Instant::now() + TOKEN_TIMEOUT;
            match timeout_at(limit, stream.read_exact(&mut presented)).await {
                Ok(Ok(_)) if presented == token => Some(stream),
                _ => None,
            }
        });
        self.waiting.push_back(Waiting { pid, abort });
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

#[cfg(test)]
mod tests {
    use std::io::Write;
    use std::os::unix::net::UnixStream as StdStream;

    use super::*;

    fn connect(name: &str) -> io::Result<StdStream> {
        StdStream::connect_addr(&std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes())?)
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn silent_connections_cannot_keep_the_rightful_client_out_and_the_socket_closes_after() {
        let socket = HandoffSocket::bind().unwrap();
        let name = socket.name().to_string();
        let token = radserve_shm::random_token().unwrap();
        let memory = radserve_shm::MemFile::create(c"radserve-handoff-test", 4096).unwrap();
        let peers = PeerPolicy::new(&[]);
        let client_name = name.clone();
        let client = tokio::task::spawn_blocking(move || {
            // More silent connections than may wait at once, then the rightful client.
            let squatters: Vec<StdStream> = (0..MAX_PENDING * 2).map(|_| connect(&client_name).unwrap()).collect();
            std::thread::sleep(Duration::from_millis(200));
            let mut rightful = connect(&client_name).unwrap();
            rightful.write_all(&token).unwrap();
            let received = radserve_shm::receive_fd(&rightful);
            (squatters, received)
        });
        let handed = socket.hand_over(token, memory.fd(), &peers).await;
        assert!(handed.is_some(), "the rightful client was handed the memory");
        let (_squatters, received) = client.await.unwrap();
        let (byte, fd) = received.unwrap();
        assert_eq!((byte, fd.is_some()), (HANDED_OVER, true));
        let refused = connect(&name).expect_err("the listener is closed once the memory was handed over");
        assert_eq!(refused.kind(), io::ErrorKind::ConnectionRefused, "{refused}");
    }

    #[tokio::test]
    async fn a_full_queue_drops_the_oldest_connection_of_the_same_process_first() {
        let mut pending = Pending::default();
        let mut peers = Vec::new();
        let mut admit = |pending: &mut Pending, pid: i32| {
            let (ours, theirs) = UnixStream::pair().unwrap();
            peers.push(theirs);
            pending.admit(pid, ours, [0; 16]);
        };
        let pids = |pending: &Pending| pending.waiting.iter().map(|waiting| waiting.pid).collect::<Vec<_>>();
        for _ in 0..MAX_PENDING_PER_PROCESS + 2 {
            admit(&mut pending, 7);
        }
        assert_eq!(pids(&pending), vec![7; MAX_PENDING_PER_PROCESS], "one process keeps at most its share waiting");
        for pid in 100..100 + MAX_PENDING as i32 {
            admit(&mut pending, pid);
        }
        assert_eq!(pending.waiting.len(), MAX_PENDING);
        let waiting = pids(&pending);
        assert_eq!(waiting.iter().filter(|&&pid| pid == 7).count(), 0, "the oldest went first: {waiting:?}");
        assert_eq!(waiting.last(), Some(&(100 + MAX_PENDING as i32 - 1)), "the newest waits");
    }
}
