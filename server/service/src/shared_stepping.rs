//! Shared stepping: a session reset and stepped through shared memory, with a Unix socket as the
//! doorbell.
//!
//! Through a Python gRPC client a step's request and reply cost the client ~0.8 ms of CPU and the
//! server ~0.3 ms (README, "where a gym step's time goes"), as much as the simulation itself on a
//! 2-core host. Here the client writes its actions into memory both processes map, sends 16 bytes on
//! a Unix socket, and reads the results in place after an 8-byte answer. The protocol is written
//! down in the proto (`SharedActingChannel`). This is a transport beside the gRPC handlers: it calls
//! the same `Session::reset`/`Session::step` and answers with the same statuses (`ServiceError`).
//!
//! The memory is a memfd whose descriptor the client receives on the channel's socket once it
//! presented the token (`crate::handoff`: peer credentials, token, SCM_RIGHTS); the socket is in the
//! abstract namespace, so nothing is left on disk. The channel ends when the connection does, when
//! its session is closed, or when no client connected in time.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};

use radserve_shm::{Header, MemFile};
use radserve_core::principal::log_id;
use radserve_core::session::Session;
use radserve_core::{Infos, LeaseHold, Principal, SessionManager, StepOutcome};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tonic::{Code, Status};
use tracing::debug;

use crate::error::{Result, ServiceError};
use crate::handoff::{HandoffSocket, PeerPolicy};
use crate::{convert, proto};

/// Bytes 0..16 of the region; the token follows.
pub const SHARED_STEPPING_MAGIC: &[u8; 16] = b"radserve-acting\0";
/// The magic and token, padded to a cache line.
const HEADER_BYTES: usize = 64;
const ARRAY_ALIGN: usize = 64;
/// Byte 2 of a request: the mask array holds a skip (step) or reset (reset) mask.
const MASK_FLAG: u8 = 1;
/// Byte 2 of a request: the seeds array holds one seed per env (reset).
const SEEDS_FLAG: u8 = 2;
/// How long a client has to connect and present the token after ShareActing answered.
pub use crate::handoff::CONNECT_TIMEOUT;
/// A request on the socket: kind, has-seed flag, array flags, 5 zero bytes, seed.
const REQUEST_BYTES: usize = 16;

/// Byte offsets of the arrays in the region, for a session of `num_envs` envs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SteppingLayout {
    pub num_envs: usize,
    pub action_bytes: usize,
    pub obs_bytes: usize,
    pub actions: usize,
    pub obs: usize,
    pub final_obs: usize,
    pub reward: usize,
    pub terminated: usize,
    pub truncated: usize,
    pub episode_return: usize,
    pub episode_length: usize,
    /// u8 [num_envs]: a step's skip mask or a reset's reset mask, read when the request says so.
    pub mask: usize,
    /// u64 [num_envs]: a reset's per-env seeds, read when the request says so.
    pub env_seeds: usize,
    pub len: usize,
}

impl SteppingLayout {
    /// `action_bytes` and `obs_bytes` are one env's action and (stacked, viewed) observation.
    pub fn new(num_envs: usize, action_bytes: usize, obs_bytes: usize) -> SteppingLayout {
        let mut end = HEADER_BYTES;
        let mut place = |bytes: usize| {
            let offset = end;
            end = (end + bytes).next_multiple_of(ARRAY_ALIGN);
            offset
        };
        let actions = place(num_envs * action_bytes);
        let obs = place(num_envs * obs_bytes);
        let final_obs = place(num_envs * obs_bytes);
        let reward = place(num_envs * 8);
        let terminated = place(num_envs);
        let truncated = place(num_envs);
        let episode_return = place(num_envs * 8);
        let episode_length = place(num_envs * 8);
        let mask = place(num_envs);
        let env_seeds = place(num_envs * 8);
        SteppingLayout {
            num_envs,
            action_bytes,
            obs_bytes,
            actions,
            obs,
            final_obs,
            reward,
            terminated,
            truncated,
            episode_return,
            episode_length,
            mask,
            env_seeds,
            len: end,
        }
    }
}

/// Sessions that have a channel open: one per session at a time, so that channels are bounded by the
/// server's session limit.
#[derive(Clone, Default)]
pub struct OpenChannels(Arc<Mutex<HashSet<String>>>);

struct ChannelClaim {
    open: OpenChannels,
    session_id: String,
}

impl Drop for ChannelClaim {
    fn drop(&mut self) {
        self.open.0.lock().expect("channel set lock").remove(&self.session_id);
    }
}

/// A channel waiting for its client; `serve` runs it to its end.
pub struct SteppingChannel {
    manager: Arc<SessionManager>,
    /// Who opened it: every request on it acts as that principal.
    caller: Principal,
    layout: SteppingLayout,
    memory: MemFile,
    token: [u8; 16],
    /// Until the client took the memory (closed then).
    socket: Option<HandoffSocket>,
    peers: PeerPolicy,
    _claim: ChannelClaim,
    /// An open channel keeps its session's lease alive, and ends when the session is closed.
    lease: LeaseHold,
    _memory: radserve_core::budget::Reservation,
}

/// Creates the region and the socket for `session_id`; the description goes to the client, the
/// channel to a task that serves it.
pub async fn open(
    manager: Arc<SessionManager>,
    caller: Principal,
    session_id: &str,
    open: &OpenChannels,
    peers: PeerPolicy,
) -> Result<(proto::SharedActingChannel, SteppingChannel)> {
    let layout = {
        let session = manager.get(&caller, session_id)?;
        let session = session.lock().await;
        SteppingLayout::new(session.num_envs(), session.frame_spec.action.num_bytes(), session.observation_space.num_bytes())
    };
    let claim = {
        let mut sessions = open.0.lock().expect("channel set lock");
        if !sessions.insert(session_id.to_string()) {
            return Err(ServiceError::AlreadyOpen(format!(
                "session {session_id} already has a shared-stepping channel; close that one (or its \
                 process) first"
            )));
        }
        ChannelClaim { open: open.clone(), session_id: session_id.to_string() }
    };
    let memory_reservation = manager
        .reserve_memory(&caller, layout.len as u64, &format!("a shared-stepping channel of {} bytes", layout.len))?;
    let (memory, Header { token, .. }) = MemFile::create_with_header(c"radserve-acting", layout.len, SHARED_STEPPING_MAGIC)
        .map_err(|error| radserve_core::error::resource_error("creating the shared-stepping memory", &error))?;
    let socket = HandoffSocket::bind().map_err(|error| ServiceError::Internal(format!("binding the shared-stepping socket: {error}")))?;
    let description = proto::SharedActingChannel {
        size: memory.len() as u64,
        token: token.to_vec(),
        socket: socket.name().to_string(),
        actions_offset: layout.actions as u64,
        obs_offset: layout.obs as u64,
        final_obs_offset: layout.final_obs as u64,
        reward_offset: layout.reward as u64,
        terminated_offset: layout.terminated as u64,
        truncated_offset: layout.truncated as u64,
        episode_return_offset: layout.episode_return as u64,
        episode_length_offset: layout.episode_length as u64,
        mask_offset: layout.mask as u64,
        env_seeds_offset: layout.env_seeds as u64,
    };
    let lease = manager.hold(&caller, session_id)?;
    let channel =
        SteppingChannel { manager, caller, layout, memory, token, socket: Some(socket), peers, _claim: claim, lease, _memory: memory_reservation };
    Ok((description, channel))
}

impl SteppingChannel {
    /// Waits for the client (the first connection of an allowed user that presents the token
    /// within `CONNECT_TIMEOUT`), hands it the memory, then answers its requests until it
    /// disconnects or the session is closed; then its memory, socket and connection are freed.
    pub async fn serve(mut self, session_id: String) {
        let closed = self.lease.session_closed();
        tokio::pin!(closed);
        let socket = self.socket.take().expect("a shared-stepping channel is served once");
        let accepted = tokio::select! {
            stream = socket.hand_over(self.token, self.memory.fd(), &self.peers) => stream,
            () = &mut closed => None,
        };
        let Some(mut stream) = accepted else {
            debug!(session = log_id(&session_id), "no client took the shared-stepping channel");
            return;
        };
        let mut request = [0u8; REQUEST_BYTES];
        loop {
            tokio::select! {
                read = stream.read_exact(&mut request) => if read.is_err() { break },
                () = &mut closed => break,
            }
            let (code, body) = match self.handle(&session_id, &request).await {
                Ok(errors) => (Code::Ok, errors),
                Err(error) => {
                    let status = Status::from(error);
                    (status.code(), status.message().as_bytes().to_vec())
                }
            };
            let mut answer = Vec::with_capacity(8 + body.len());
            answer.extend_from_slice(&(code as u32).to_le_bytes());
            answer.extend_from_slice(&(body.len() as u32).to_le_bytes());
            answer.extend_from_slice(&body);
            if stream.write_all(&answer).await.is_err() {
                break;
            }
        }
        debug!(session = log_id(&session_id), "shared-stepping channel closed");
    }

    /// One request: Ok holds the answer's records (simulator errors of ended episodes, the envs' infos).
    async fn handle(&mut self, session_id: &str, request: &[u8; REQUEST_BYTES]) -> Result<Vec<u8>> {
        let layout = self.layout;
        let memory = self.memory.as_mut_slice();
        let request = Request::read(request, memory, &layout)?;
        let session = self.manager.get(&self.caller, session_id)?;
        let mut session = session.lock().await;
        let mut exchange = Exchange { session: &mut session, memory, layout };
        match request.kind {
            b'R' => exchange.reset(request).await,
            b'S' => exchange.step(request).await,
            b'A' => exchange.async_reset(request).await,
            b'E' | b'V' => exchange.send_recv(request).await,
            other => Err(ServiceError::BadRequest(format!(
                "a request starts with 'S' (step), 'R' (reset), 'A' (async reset), 'E' (send) or 'V' (recv), got byte \
                 {other:#04x}"
            ))),
        }
    }
}

/// A request: its 16 bytes say what it asks (byte 0), whether a seed follows (byte 1, the seed in
/// bytes 8..16) and whether the mask and per-env seed arrays of the memory go with it (byte 2's
/// flags); the mask is copied out of the shared memory before use (the client may write it at any
/// time).
struct Request {
    kind: u8,
    seed: Option<u64>,
    mask: Option<Vec<bool>>,
    with_seeds: bool,
}

impl Request {
    fn read(request: &[u8; REQUEST_BYTES], memory: &[u8], layout: &SteppingLayout) -> Result<Request> {
        let seed = match request[1] {
            0 => None,
            1 => Some(u64::from_le_bytes(request[8..16].try_into().expect("8 bytes"))),
            other => {
                return Err(ServiceError::BadRequest(format!("byte 1 of a request is 0 or 1 (a seed follows), got {other}")))
            }
        };
        let (with_mask, with_seeds) = match request[2] {
            flags @ 0..=3 => (flags & MASK_FLAG != 0, flags & SEEDS_FLAG != 0),
            other => {
                return Err(ServiceError::BadRequest(format!(
                    "byte 2 of a request holds flags 1 (mask) and 2 (per-env seeds), got {other}"
                )))
            }
        };
        let mask = with_mask.then(|| memory[layout.mask..][..layout.num_envs].iter().map(|&byte| byte != 0).collect());
        Ok(Request { kind: request[0], seed, mask, with_seeds })
    }
}

/// A request being answered: the session it acts on and the channel's memory.
struct Exchange<'a> {
    session: &'a mut Session,
    memory: &'a mut [u8],
    layout: SteppingLayout,
}

impl Exchange<'_> {
    /// 'R': resets the envs of the mask (all without one), seeded by the seed or the per-env seeds.
    async fn reset(&mut self, request: Request) -> Result<Vec<u8>> {
        let layout = self.layout;
        let env_seeds = request.with_seeds.then(|| {
            self.memory[layout.env_seeds..][..8 * layout.num_envs]
                .chunks_exact(8)
                .map(|bytes| u64::from_le_bytes(bytes.try_into().expect("8 bytes")))
                .collect()
        });
        let spec = radserve_core::ResetSpec { seed: request.seed, env_seeds, mask: request.mask };
        let obs = self.session.reset_with(&spec).await?;
        check_len("observations", obs.len(), layout.num_envs * layout.obs_bytes)?;
        self.memory[layout.obs..][..obs.len()].copy_from_slice(&obs);
        let mut records = Vec::new();
        push_infos(&mut records, RECORD_RESET_INFOS, self.session.reset_infos().clone());
        Ok(records)
    }

    /// 'S': steps every env but those of the mask (gymnasium NEXT_STEP's reset step) with the actions.
    async fn step(&mut self, request: Request) -> Result<Vec<u8>> {
        if request.with_seeds {
            return Err(ServiceError::BadRequest("per-env seeds go with a reset, not a step".into()));
        }
        let (dtype, shape) = self.action_shape();
        let actions = self.actions();
        let outcome = self.session.step_except(dtype, &shape, &actions, request.mask.as_deref()).await?;
        write_outcome(self.memory, &self.layout, outcome, None)
    }

    /// 'A': EnvPool's asynchronous reset of every env.
    async fn async_reset(&mut self, request: Request) -> Result<Vec<u8>> {
        if request.mask.is_some() || request.with_seeds {
            return Err(ServiceError::BadRequest(
                "an async reset ('A') resets every env: it takes a seed (byte 1), no mask or per-env seeds".into(),
            ));
        }
        self.session.async_reset(request.seed).await?;
        Ok(Vec::new())
    }

    /// 'E' (send) and 'V' (recv, after a send of the mask's envs when a mask is given): the masked
    /// envs' rows of the actions array; a recv's ready envs are written back into the mask array.
    async fn send_recv(&mut self, request: Request) -> Result<Vec<u8>> {
        if request.seed.is_some() || request.with_seeds {
            return Err(ServiceError::BadRequest("a send or recv takes no seed".into()));
        }
        let (dtype, shape) = self.action_shape();
        let (ready, outcome) = match (request.kind, &request.mask) {
            (b'E', Some(sent)) => {
                let actions = self.actions();
                self.session.send(dtype, &shape, &actions, sent).await?;
                return Ok(Vec::new());
            }
            (b'E', None) => {
                return Err(ServiceError::BadRequest("a send ('E') names its envs in the mask array (byte 2, flag 1)".into()))
            }
            (_, Some(sent)) => {
                let actions = self.actions();
                self.session.send_recv(dtype, &shape, &actions, sent).await?
            }
            (_, None) => self.session.recv().await?,
        };
        let records = write_outcome(self.memory, &self.layout, outcome, Some(&ready))?;
        for (env, ready) in ready.iter().enumerate() {
            self.memory[self.layout.mask + env] = *ready as u8;
        }
        Ok(records)
    }

    /// Every env's row of the actions array, copied out of the shared memory.
    fn actions(&self) -> Vec<u8> {
        self.memory[self.layout.actions..][..self.layout.num_envs * self.layout.action_bytes].to_vec()
    }

    /// The dtype and shape of every env's actions, `[num_envs, *action shape]`.
    fn action_shape(&self) -> (radserve_core::DType, Vec<usize>) {
        let action = &self.session.frame_spec.action;
        let mut shape = vec![self.layout.num_envs];
        shape.extend_from_slice(action.shape());
        (action.dtype(), shape)
    }
}

/// Writes a step's (or recv's) outcome into the region at the envs' rows (only `rows`' envs when
/// given: a recv's ready envs) and returns the answer's records.
fn write_outcome(memory: &mut [u8], layout: &SteppingLayout, mut outcome: StepOutcome, rows: Option<&[bool]>) -> Result<Vec<u8>> {
    check_len("observations", outcome.obs.len(), layout.num_envs * layout.obs_bytes)?;
    let obs_bytes = layout.obs_bytes;
    for env in (0..layout.num_envs).filter(|&env| rows.is_none_or(|rows| rows[env])) {
        memory[layout.obs + env * obs_bytes..][..obs_bytes].copy_from_slice(&outcome.obs[env * obs_bytes..][..obs_bytes]);
        memory[layout.reward + 8 * env..][..8].copy_from_slice(&outcome.rewards[env].to_le_bytes());
        memory[layout.terminated + env] = outcome.terminated[env] as u8;
        memory[layout.truncated + env] = outcome.truncated[env] as u8;
    }
    let mut records = Vec::new();
    for (row, episode) in outcome.episodes.iter().enumerate() {
        let env = episode.env_index;
        let final_obs = &outcome.final_obs[row * obs_bytes..][..obs_bytes];
        memory[layout.final_obs + env * obs_bytes..][..obs_bytes].copy_from_slice(final_obs);
        memory[layout.episode_return + 8 * env..][..8].copy_from_slice(&episode.episode_return.to_le_bytes());
        memory[layout.episode_length + 8 * env..][..8].copy_from_slice(&episode.episode_length.to_le_bytes());
        if let Some(message) = &episode.error {
            push_record(&mut records, env, RECORD_ERROR, message.as_bytes());
        }
    }
    push_infos(&mut records, RECORD_STEP_INFOS, std::mem::take(&mut outcome.step_infos));
    push_infos(&mut records, RECORD_RESET_INFOS, std::mem::take(&mut outcome.reset_infos));
    Ok(records)
}

/// Kinds of the records of an OK answer: an env's simulator error, the step's infos, the resets'.
const RECORD_ERROR: u8 = 0;
const RECORD_STEP_INFOS: u8 = 1;
const RECORD_RESET_INFOS: u8 = 2;

/// Appends one record of an answer: u32 env index, u8 kind, u32 length, the bytes.
fn push_record(records: &mut Vec<u8>, env: usize, kind: u8, bytes: &[u8]) {
    records.extend_from_slice(&(env as u32).to_le_bytes());
    records.push(kind);
    records.extend_from_slice(&(bytes.len() as u32).to_le_bytes());
    records.extend_from_slice(bytes);
}

/// Appends `infos` as one record of `kind` (an encoded `InfoColumns`, as gRPC's answers carry them),
/// none when there are no infos.
fn push_infos(records: &mut Vec<u8>, kind: u8, infos: Infos) {
    if !infos.is_empty() {
        let columns = proto::InfoColumns { columns: convert::infos_to_proto(infos) };
        push_record(records, 0, kind, &prost::Message::encode_to_vec(&columns));
    }
}

fn check_len(what: &str, got: usize, expected: usize) -> Result<()> {
    if got != expected {
        return Err(ServiceError::Internal(format!("the session produced {got} bytes of {what}, the channel holds {expected}")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_are_aligned_and_do_not_overlap() {
        let layout = SteppingLayout::new(3, 6 * 4, 9 * 84 * 84 + 1);
        let arrays = [
            (layout.actions, 3 * 24),
            (layout.obs, 3 * layout.obs_bytes),
            (layout.final_obs, 3 * layout.obs_bytes),
            (layout.reward, 24),
            (layout.terminated, 3),
            (layout.truncated, 3),
            (layout.episode_return, 24),
            (layout.episode_length, 24),
            (layout.mask, 3),
            (layout.env_seeds, 24),
        ];
        let mut end = HEADER_BYTES;
        for (offset, bytes) in arrays {
            assert_eq!(offset % ARRAY_ALIGN, 0);
            assert!(offset >= end, "array at {offset} overlaps the one ending at {end}");
            end = offset + bytes;
        }
        assert!(layout.len >= end);
    }
}
