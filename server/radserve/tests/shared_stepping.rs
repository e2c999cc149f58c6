//! The shared-stepping channel's socket, over the fake simulators: a silent connection does
//! not hold up the rightful client, and a channel (its memory, socket and connection) is freed when
//! its session closes. Shared stepping against the real simulators (results, errors, the memory's
//! protection) is tested in tests/test_shared_stepping.py.

mod common;

use std::os::linux::net::SocketAddrExt;
use std::time::{Duration, Instant};

use common::{connect, start_fake_server};
use radserve_core::fake::FAKE_ENV;
use radserve_core::Limits;
use radserve_service::proto::{self, rad_serve_client::RadServeClient};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::UnixStream;
use tonic::transport::Channel;

async fn connect_socket(name: &str) -> UnixStream {
    let address = std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes()).unwrap();
    let stream = std::os::unix::net::UnixStream::connect_addr(&address).unwrap();
    stream.set_nonblocking(true).unwrap();
    UnixStream::from_std(stream).unwrap()
}

/// Presents the token and takes the memory's descriptor (one byte; read without its descriptor, which
/// the kernel then closes).
async fn present(stream: &mut UnixStream, token: &[u8]) {
    stream.write_all(token).await.unwrap();
    let mut handed = [0u8; 1];
    stream.read_exact(&mut handed).await.unwrap();
    assert_eq!(handed[0], 1);
}

/// Sends a reset ('R', no seed) and returns the answer's status code.
async fn reset(stream: &mut UnixStream) -> u32 {
    let mut request = [0u8; 16];
    request[0] = b'R';
    stream.write_all(&request).await.unwrap();
    let mut header = [0u8; 8];
    stream.read_exact(&mut header).await.unwrap();
    let mut body = vec![0u8; u32::from_le_bytes(header[4..].try_into().unwrap()) as usize];
    stream.read_exact(&mut body).await.unwrap();
    u32::from_le_bytes(header[..4].try_into().unwrap())
}

async fn session_with_channel(client: &mut RadServeClient<Channel>) -> (String, proto::SharedActingChannel) {
    let request = proto::CreateSessionRequest { env_id: FAKE_ENV.into(), num_envs: 2, ..Default::default() };
    let session_id = client.create_session(request).await.unwrap().into_inner().session_id;
    let channel = client.share_acting(proto::ShareActingRequest { session_id: session_id.clone() }).await.unwrap().into_inner();
    (session_id, channel)
}

fn open_fds() -> usize {
    std::fs::read_dir("/proc/self/fd").unwrap().count()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_connection_does_not_hold_up_the_client() {
    let (server, _simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let (_, channel) = session_with_channel(&mut client).await;
    assert!(!channel.socket.contains(&std::process::id().to_string()), "the name tells nothing: {}", channel.socket);
    let token_hex: String = channel.token.iter().map(|byte| format!("{byte:02x}")).collect();
    assert!(!channel.socket.contains(&token_hex[..8]), "the name tells nothing of the token");

    // Connected first, never says anything.
    let _squatters = [connect_socket(&channel.socket).await, connect_socket(&channel.socket).await];
    let started = Instant::now();
    let mut rightful = connect_socket(&channel.socket).await;
    present(&mut rightful, &channel.token).await;
    // Read one after the other, the squatters would have held the client for the whole connect
    // timeout (10 s); read concurrently, not at all.
    let waited = started.elapsed();
    assert!(waited < Duration::from_millis(100), "the client waited {waited:?} behind silent connections");
    assert_eq!(reset(&mut rightful).await, 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_a_session_frees_its_shared_stepping_channel() {
    let (server, simulators) = start_fake_server(Limits::default(), 1).await;
    let mut client = RadServeClient::new(connect(&server.address).await);
    let mut cycle = |client: &mut RadServeClient<Channel>| {
        let mut client = client.clone();
        async move {
            let (session_id, channel) = session_with_channel(&mut client).await;
            let mut stream = connect_socket(&channel.socket).await;
            present(&mut stream, &channel.token).await;
            assert_eq!(reset(&mut stream).await, 0);
            client.close_session(proto::CloseSessionRequest { session_id, discard_snapshot: false }).await.unwrap();
            // The server ends the channel: the client reads the end of the stream.
            let mut byte = [0u8; 1];
            let read = tokio::time::timeout(Duration::from_secs(5), stream.read(&mut byte)).await;
            assert_eq!(read.expect("the channel outlived its session").unwrap(), 0);
        }
    };
    cycle(&mut client).await;
    let baseline = open_fds();
    for _ in 0..200 {
        cycle(&mut client).await;
    }
    let deadline = Instant::now() + Duration::from_secs(5);
    while open_fds() > baseline && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(open_fds() <= baseline, "{} descriptors open after 200 channels, {baseline} before", open_fds());
    assert_eq!(simulators.groups_alive(), 0);
    let _ = &mut cycle;
}
