//! Messages between the server and its worker processes: a little-endian u32 length, then a postcard
//! body. Observations do not travel here; workers write them into the group's frame memory.

use std::io::{self, Read, Write};
use std::os::fd::OwnedFd;
use std::sync::Arc;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

pub use radserve_core::simulators::{EnvSpec, StepResult};
pub use radserve_core::Infos;
use radserve_core::{EnvNames, Family, Options};

/// A descriptor the server sends beside a request (not serialized: it travels as SCM_RIGHTS). Kept
/// with the request so that a restarted worker gets it again when its groups are rebuilt.
#[derive(Clone, Debug, Default)]
pub struct PassedFd(pub Option<Arc<OwnedFd>>);

impl PassedFd {
    pub fn new(fd: OwnedFd) -> PassedFd {
        PassedFd(Some(Arc::new(fd)))
    }
}

impl PartialEq for PassedFd {
    /// The same descriptor, or both none (a decoded request never has one).
    fn eq(&self, other: &PassedFd) -> bool {
        match (&self.0, &other.0) {
            (Some(mine), Some(theirs)) => Arc::ptr_eq(mine, theirs),
            (None, None) => true,
            (Some(_), None) | (None, Some(_)) => false,
        }
    }
}

/// Largest message either side accepts (actions of a large session are well below this).
pub const MAX_MESSAGE_BYTES: usize = 64 << 20;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GroupConfig {
    pub group: u64,
    pub family: Family,
    pub name: String,
    /// Resolved options, minus the ones the server consumes itself.
    pub options: Options,
    /// One seed per environment of the group.
    pub seeds: Vec<u64>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Request {
    ListNames,
    /// Specs of each (family, name, options), for the catalog.
    Specs { entries: Vec<(Family, String, Options)> },
    /// Builds the group's environments; the reply carries their spec, which sizes the shared memory.
    CreateGroup(GroupConfig),
    /// Maps the shared memory the group writes its frames into: its descriptor goes over the
    /// worker's descriptor socket (fd 3) just before this request, sent from `memory`.
    Attach {
        group: u64,
        shm_len: usize,
        #[serde(skip)]
        memory: PassedFd,
    },
    /// Resets the group's envs, or those `mask` marks; `seeds` (one per env of the group) re-seed
    /// the envs reset.
    Reset { group: u64, seeds: Option<Vec<u64>>, mask: Option<Vec<bool>> },
    /// Actions of every environment of the group, raw little-endian bytes of the action dtype.
    /// Envs that `skip` marks are not stepped (their actions are ignored).
    Step { group: u64, actions: Vec<u8>, skip: Option<Vec<bool>> },
    /// EnvPool's asynchronous mode (a group built with `batch_size` below its envs): resets every env,
    /// re-seeding env j with `seeds[j]` when given; their first frames come back through `Recv`.
    AsyncReset { group: u64, seeds: Option<Vec<u64>> },
    /// Starts the next step of the envs `sent` marks with their rows of `actions` (every env's row,
    /// raw little-endian bytes of the action dtype) and answers without waiting for it.
    Send { group: u64, actions: Vec<u8>, sent: Vec<bool> },
    /// Waits for the group's next batch of envs whose step or reset is complete.
    Recv { group: u64 },
    /// A `Send` then a `Recv`, in one round trip (EnvPool's `step(action, env_id)`); answered as `Recv`.
    SendRecv { group: u64, actions: Vec<u8>, sent: Vec<bool> },
    CloseGroup { group: u64 },
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Response {
    Names(EnvNames),
    Specs(Vec<Result<EnvSpec, String>>),
    Created(EnvSpec),
    Attached,
    /// The reset infos of the envs reset (envs within the group).
    Reset(Infos),
    Stepped(StepResult),
    /// An `AsyncReset` or `Send` was handed to the envs.
    Sent,
    /// The envs a `Recv` (or `SendRecv`) returns (`ready`, one entry per env of the group) and their results, one
    /// entry per env of the group (zero for the others).
    Received { ready: Vec<bool>, result: StepResult },
    Closed,
    /// The request failed inside the worker; the worker itself is fine.
    Failed(String),
}

pub fn encode<T: Serialize>(message: &T) -> io::Result<Vec<u8>> {
    let body = postcard::to_stdvec(message).map_err(|err| io::Error::new(io::ErrorKind::InvalidData, err))?;
    let mut framed = Vec::with_capacity(body.len() + 4);
    framed.extend_from_slice(&(body.len() as u32).to_le_bytes());
    framed.extend_from_slice(&body);
    Ok(framed)
}

pub fn decode<T: DeserializeOwned>(body: &[u8]) -> io::Result<T> {
    postcard::from_bytes(body).map_err(|err| io::Error::new(io::ErrorKind::InvalidData, err))
}

pub fn check_length(header: [u8; 4]) -> io::Result<usize> {
    let length = u32::from_le_bytes(header) as usize;
    if length > MAX_MESSAGE_BYTES {
        return Err(io::Error::new(io::ErrorKind::InvalidData, format!("message of {length} bytes is too large")));
    }
    Ok(length)
}

/// Blocking read of one message (the worker side). `Ok(None)` on a clean end of stream.
pub fn read_blocking<T: DeserializeOwned>(reader: &mut impl Read) -> io::Result<Option<T>> {
    let mut header = [0u8; 4];
    match reader.read_exact(&mut header) {
        Ok(()) => {}
        Err(err) if err.kind() == io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(err) => return Err(err),
    }
    let mut body = vec![0u8; check_length(header)?];
    reader.read_exact(&mut body)?;
    decode(&body).map(Some)
}

pub fn write_blocking<T: Serialize>(writer: &mut impl Write, message: &T) -> io::Result<()> {
    writer.write_all(&encode(message)?)?;
    writer.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn messages_round_trip_through_the_framing() {
        let step = Request::Step { group: 7, actions: vec![1, 2, 3, 4], skip: Some(vec![true, false]) };
        let mut wire = Vec::new();
        write_blocking(&mut wire, &step).unwrap();
        write_blocking(&mut wire, &Request::ListNames).unwrap();
        let mut reader = wire.as_slice();
        assert_eq!(read_blocking::<Request>(&mut reader).unwrap(), Some(step));
        assert_eq!(read_blocking::<Request>(&mut reader).unwrap(), Some(Request::ListNames));
        assert_eq!(read_blocking::<Request>(&mut reader).unwrap(), None);
    }

    #[test]
    fn oversized_lengths_are_refused() {
        let header = ((MAX_MESSAGE_BYTES + 1) as u32).to_le_bytes();
        assert!(check_length(header).is_err());
    }
}
