//! Worlds (dm_env_rpc's name for a session) and the streams' seats in them: CreateWorld, JoinWorld,
//! ResetWorld, DestroyWorld.

use std::collections::{BTreeSet, HashMap};
use std::sync::{Arc, Mutex};

use radserve_core::actions::MAX_SEED;
use radserve_core::bounds::{check_count, check_len, MAX_ID_BYTES, MAX_OPTION_NAME_BYTES};
use radserve_core::{OptionValue, Options, ResetSpec, SessionExtras};

use super::tensors::{non_negative, seed_setting, setting, specs};
use super::{bad, dm, Connection, Joined, Next, MAX_ENTRIES};
use crate::error::{Result, ServiceError};

/// Which envs of which worlds a stream has joined, and how often each world was reset as a whole.
#[derive(Default)]
pub(super) struct Worlds {
    pub(super) joined: HashMap<String, World>,
}

#[derive(Default)]
pub(super) struct World {
    seats: BTreeSet<usize>,
    /// ResetWorld calls while someone was joined: a joined stream that sees a new count starts a
    /// new episode at its next step.
    pub(super) resets: u64,
}

pub(super) type SharedWorlds = Arc<Mutex<Worlds>>;

/// A stream's place in a world; leaving (or the stream ending) frees it.
pub(super) struct Seat {
    worlds: SharedWorlds,
    world: String,
    env: usize,
}

impl Drop for Seat {
    fn drop(&mut self) {
        let mut worlds = self.worlds.lock().expect("worlds lock");
        if let Some(world) = worlds.joined.get_mut(&self.world) {
            world.seats.remove(&self.env);
            if world.seats.is_empty() {
                worlds.joined.remove(&self.world);
            }
        }
    }
}

impl Connection {
    pub(super) async fn create_world(&mut self, request: dm::CreateWorldRequest) -> Result<dm::CreateWorldResponse> {
        check_count("CreateWorld settings", request.settings.len(), MAX_ENTRIES)?;
        let mut env_id = None;
        let (mut seed, mut num_envs) = (0u64, 1usize);
        let mut options = Options::new();
        for (name, tensor) in &request.settings {
            check_len("a setting name", name, MAX_OPTION_NAME_BYTES)?;
            let value = setting(name, tensor)?;
            match name.as_str() {
                "env_id" => match value {
                    OptionValue::Str(id) => env_id = Some(id),
                    other @ (OptionValue::Bool(_) | OptionValue::Int(_) | OptionValue::Float(_)) => {
                        return Err(bad(format!("setting env_id must be a string (e.g. \"gym/CartPole-v1\"), got {other:?}")))
                    }
                },
                "seed" => seed = non_negative("seed", &value, MAX_SEED)?,
                "num_envs" => num_envs = non_negative("num_envs", &value, u32::MAX as u64)? as usize,
                _ => {
                    options.insert(name.clone(), value);
                }
            }
        }
        let env_id = env_id.ok_or_else(|| {
            bad(format!(
                "CreateWorld needs the setting env_id (a string, e.g. \"gym/CartPole-v1\"); got settings {:?}",
                request.settings.keys().collect::<Vec<_>>()
            ))
        })?;
        check_len("env_id", &env_id, MAX_ID_BYTES)?;
        let info = self
            .service
            .manager
            .create_session(&self.caller, &env_id, num_envs, seed, &options, &SessionExtras::default())
            .await?;
        Ok(dm::CreateWorldResponse { world_name: info.session_id })
    }

    pub(super) async fn join_world(&mut self, request: dm::JoinWorldRequest) -> Result<dm::JoinWorldResponse> {
        if let Some(joined) = &self.joined {
            return Err(ServiceError::FailedPrecondition(format!(
                "this stream already joined world {} (env {}); send LeaveWorldRequest before joining again",
                joined.world, joined.env
            )));
        }
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        check_count("JoinWorld settings", request.settings.len(), MAX_ENTRIES)?;
        let mut env = 0usize;
        for (name, tensor) in &request.settings {
            match name.as_str() {
                "env_index" => env = non_negative("env_index", &setting(name, tensor)?, u32::MAX as u64)? as usize,
                _ => {
                    return Err(bad(format!(
                        "unknown JoinWorld setting '{}': the only one is env_index (which env of the world this stream acts in)",
                        radserve_core::bounds::clip(name)
                    )))
                }
            }
        }
        let manager = &self.service.manager;
        let info = manager.describe(&self.caller, &request.world_name).await?;
        if env >= info.num_envs {
            return Err(bad(format!("env_index {env} is out of range: world {} has {} envs", info.session_id, info.num_envs)));
        }
        let lease = manager.hold(&self.caller, &info.session_id)?;
        let resets_seen = {
            let mut worlds = self.service.worlds.lock().expect("worlds lock");
            let world = worlds.joined.entry(info.session_id.clone()).or_default();
            if !world.seats.insert(env) {
                return Err(ServiceError::FailedPrecondition(format!(
                    "env {env} of world {} is joined by another stream; join another env_index or leave it there first",
                    info.session_id
                )));
            }
            world.resets
        };
        let seat = Seat { worlds: self.service.worlds.clone(), world: info.session_id.clone(), env };
        let specs = specs(&info.action_space, &info.observation_space);
        self.joined = Some(Joined {
            world: info.session_id,
            env,
            action: info.action_space,
            observation: info.observation_space,
            specs: specs.clone(),
            next: Next::Join,
            resets_seen,
            _seat: seat,
            _lease: lease,
        });
        Ok(dm::JoinWorldResponse { specs: Some(specs) })
    }

    pub(super) async fn reset_world(&mut self, request: dm::ResetWorldRequest) -> Result<dm::ResetWorldResponse> {
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        let seed = seed_setting(&request.settings, "ResetWorld")?;
        let session = self.service.manager.get(&self.caller, &request.world_name)?;
        session.lock().await.reset_with(&ResetSpec { seed, ..ResetSpec::default() }).await?;
        let mut worlds = self.service.worlds.lock().expect("worlds lock");
        if let Some(world) = worlds.joined.get_mut(&request.world_name) {
            world.resets += 1;
        }
        Ok(dm::ResetWorldResponse {})
    }

    pub(super) async fn destroy_world(&mut self, request: dm::DestroyWorldRequest) -> Result<dm::DestroyWorldResponse> {
        check_len("world_name", &request.world_name, MAX_ID_BYTES)?;
        let manager = &self.service.manager;
        // Unknown (or another principal's) worlds answer NOT_FOUND before anything else.
        manager.get(&self.caller, &request.world_name)?;
        if let Some(world) = self.service.worlds.lock().expect("worlds lock").joined.get(&request.world_name) {
            return Err(ServiceError::FailedPrecondition(format!(
                "world {} has joined streams (envs {:?}); they must leave it before it is destroyed",
                request.world_name, world.seats
            )));
        }
        manager.close_session(&self.caller, &request.world_name).await?;
        Ok(dm::DestroyWorldResponse {})
    }
}
