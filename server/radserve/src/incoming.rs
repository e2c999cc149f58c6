//! The server's connections: at most `max_connections` open at once, each closed once its peer has
//! sent nothing for `idle_timeout`, and an accept loop that backs off instead of spinning when the
//! process runs out of file descriptors.
//!
//! tonic's own `TcpIncoming` accepts without limit and keeps a TCP connection that never speaks
//! HTTP/2 forever (HTTP/2 keepalive pings start only after the handshake), and at EMFILE it retries
//! `accept` at once, at 100 % of a core. Live clients are never idle here: the server's keepalive
//! pings (`http2_keepalive_interval`, shorter than the idle timeout) are answered, and readers of a
//! stream send window updates.

use std::io;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, OwnedSemaphorePermit, Semaphore};
use tokio::time::{Instant, Sleep};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::{Connected, TcpConnectInfo};
use tracing::warn;

/// How often the same warning (refused connections, no file descriptors) is logged at most.
const WARN_EVERY: Duration = Duration::from_secs(10);

#[derive(Clone, Copy, Debug)]
pub struct ConnectionLimits {
    pub max_connections: usize,
    pub idle_timeout: Duration,
}

/// Accepts on `listener` in a task of its own until the returned stream is dropped.
pub fn incoming(listener: TcpListener, limits: ConnectionLimits) -> ReceiverStream<io::Result<Connection>> {
    let (sender, receiver) = mpsc::channel(16);
    tokio::spawn(accept_loop(listener, limits, sender));
    ReceiverStream::new(receiver)
}

async fn accept_loop(listener: TcpListener, limits: ConnectionLimits, sender: mpsc::Sender<io::Result<Connection>>) {
    let permits = Arc::new(Semaphore::new(limits.max_connections));
    let mut last_warning: Option<Instant> = None;
    let mut refused = 0u64;
    let warn_now = |last: &mut Option<Instant>| {
        let now = Instant::now();
        let due = last.is_none_or(|at| now.duration_since(at) >= WARN_EVERY);
        if due {
            *last = Some(now);
        }
        due
    };
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            () = sender.closed() => return,
        };
        match accepted {
            Ok((stream, peer)) => match permits.clone().try_acquire_owned() {
                Ok(permit) => {
                    // Small request/response pairs (acting) stall ~40 ms on Nagle + delayed ACK.
                    let _ = stream.set_nodelay(true);
                    let connection = Connection::new(stream, permit, limits.idle_timeout);
                    if sender.send(Ok(connection)).await.is_err() {
                        return;
                    }
                }
                Err(_) => {
                    // Closed at once: the client sees the connection reset (UNAVAILABLE), not a hang.
                    refused += 1;
                    if warn_now(&mut last_warning) {
                        warn!(%peer, refused, limit = limits.max_connections, "refusing connections: server.max_connections are open");
                    }
                }
            },
            Err(error) if matches!(error.raw_os_error(), Some(libc::EMFILE | libc::ENFILE)) => {
                if warn_now(&mut last_warning) {
                    warn!(%error, "out of file descriptors: not accepting connections for 100 ms");
                }
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            // The peer went away before the accept (ECONNABORTED...): nothing to serve.
            Err(_) => {}
        }
    }
}

/// An accepted connection, counted against the limit until dropped, that fails its reads once the
/// peer has been silent for the idle timeout (hyper then closes it).
pub struct Connection {
    stream: TcpStream,
    _permit: OwnedSemaphorePermit,
    idle_timeout: Duration,
    last_read: Instant,
    idle: Pin<Box<Sleep>>,
}

impl Connection {
    fn new(stream: TcpStream, permit: OwnedSemaphorePermit, idle_timeout: Duration) -> Connection {
        let now = Instant::now();
        Connection { stream, _permit: permit, idle_timeout, last_read: now, idle: Box::pin(tokio::time::sleep_until(now + idle_timeout)) }
    }
}

impl AsyncRead for Connection {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = &mut *self;
        let before = buf.filled().len();
        match Pin::new(&mut this.stream).poll_read(cx, buf) {
            Poll::Ready(result) => {
                if buf.filled().len() > before {
                    this.last_read = Instant::now();
                }
                return Poll::Ready(result);
            }
            Poll::Pending => {}
        }
        loop {
            let expires = this.last_read + this.idle_timeout;
            if this.idle.deadline() != expires {
                this.idle.as_mut().reset(expires);
            }
            match this.idle.as_mut().poll(cx) {
                Poll::Pending => return Poll::Pending,
                Poll::Ready(()) if Instant::now() >= this.last_read + this.idle_timeout => {
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("the peer sent nothing for {} s", this.idle_timeout.as_secs_f64()),
                    )));
                }
                Poll::Ready(()) => {}
            }
        }
    }
}

impl AsyncWrite for Connection {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(mut self: Pin<&mut Self>, cx: &mut Context<'_>, bufs: &[io::IoSlice<'_>]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.stream).poll_shutdown(cx)
    }
}

impl Connected for Connection {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.stream.connect_info()
    }
}

/// The fewest connections a server starts with: below it the open-file limit is a mistake to fix,
/// not a size to serve at.
pub const MIN_CONNECTIONS: usize = 8;

/// How many connections fit `limit` open files once `open` descriptors are in use: half of what is
/// left, the other half kept for what sessions open as they come (memory files, acting and hand-over
/// sockets, sample streams' rings), at most `configured`. An error, saying what to raise, when that
/// is below `MIN_CONNECTIONS`.
pub fn connections_within(configured: usize, limit: u64, open: u64) -> anyhow::Result<usize> {
    let room = usize::try_from(limit.saturating_sub(open) / 2).unwrap_or(usize::MAX);
    if room < MIN_CONNECTIONS.min(configured) {
        anyhow::bail!(
            "the open-file limit ({limit}) leaves room for {room} connections once the server's {open} open descriptors \
             and as many for sessions are counted; at least {MIN_CONNECTIONS} are needed: raise it to at least {} \
             (ulimit -n, systemd's LimitNOFILE, docker run --ulimit nofile=..., or the pod's runtime default)",
            open + 2 * MIN_CONNECTIONS as u64
        );
    }
    Ok(room.min(configured))
}

/// `connections_within` for this process: its open-file limit (the soft one raised to the hard one
/// first) and the descriptors it has open now.
pub fn connection_capacity(configured: usize) -> anyhow::Result<usize> {
    let limit = raise_file_limit();
    let open = std::fs::read_dir("/proc/self/fd").map_or(0, |entries| entries.count() as u64);
    connections_within(configured, limit, open)
}

/// Raises the soft open-file limit to the hard one (the usual default soft limit, 1024, is what 1000
/// idle connections exhausted) and returns the soft limit now in force.
pub fn raise_file_limit() -> u64 {
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit/setrlimit read and write only the struct passed by pointer.
    unsafe {
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) != 0 {
            return 1024;
        }
        if limit.rlim_cur < limit.rlim_max {
            let raised = libc::rlimit { rlim_cur: limit.rlim_max, rlim_max: limit.rlim_max };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                limit.rlim_cur = limit.rlim_max;
            }
        }
    }
    limit.rlim_cur
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn connections_are_sized_from_what_the_server_left_of_the_limit() {
        // A limit of 258 with 40 descriptors open: 109 connections (the old rule, (limit - 256) / 2, gave 1).
        assert_eq!(connections_within(1024, 258, 40).unwrap(), 109);
        assert_eq!(connections_within(1024, 1 << 20, 40).unwrap(), 1024, "at most what is configured");
        assert_eq!(connections_within(2, 64, 58).unwrap(), 2, "a configured limit under the minimum is kept");
        let refused = connections_within(1024, 64, 50).unwrap_err().to_string();
        assert!(refused.contains("open-file limit (64) leaves room for 7 connections"), "{refused}");
        assert!(refused.contains("raise it to at least 66"), "{refused}");
    }
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio_stream::StreamExt;

    #[tokio::test]
    async fn connections_beyond_the_limit_are_closed_and_silent_ones_time_out() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let address = listener.local_addr().unwrap();
        let limits = ConnectionLimits { max_connections: 2, idle_timeout: Duration::from_millis(300) };
        let mut accepted = incoming(listener, limits);
        let talking = TcpStream::connect(address).await.unwrap();
        let _silent_client = TcpStream::connect(address).await.unwrap();
        let mut first = accepted.next().await.unwrap().unwrap();
        let second = accepted.next().await.unwrap().unwrap();
        // A third is accepted and dropped at once: the client reads end-of-stream.
        let mut third = TcpStream::connect(address).await.unwrap();
        let mut byte = [0u8; 1];
        let read = tokio::time::timeout(Duration::from_secs(5), third.read(&mut byte)).await.unwrap();
        assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");
        // A peer that keeps talking stays; a silent one times out.
        let talker = tokio::spawn(async move {
            let mut client = talking;
            for _ in 0..8 {
                client.write_all(b"x").await.unwrap();
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            client
        });
        let mut received = 0;
        let started = Instant::now();
        while received < 8 {
            let mut buf = [0u8; 8];
            received += first.read(&mut buf).await.expect("a talking peer is not idle");
        }
        assert!(started.elapsed() > Duration::from_millis(600), "outlived the idle timeout while talking");
        drop(talker.await.unwrap());
        let mut silent = second;
        let error = tokio::time::timeout(Duration::from_secs(5), silent.read(&mut byte)).await.unwrap().unwrap_err();
        assert_eq!(error.kind(), io::ErrorKind::TimedOut);
        drop(silent);
        drop(first);
        // Places freed: a new connection is accepted.
        let _client = TcpStream::connect(address).await.unwrap();
        assert!(tokio::time::timeout(Duration::from_secs(5), accepted.next()).await.unwrap().unwrap().is_ok());
    }
}
