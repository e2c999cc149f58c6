//! The manager's side of the server-side actor (SetPolicy, StartActing, StopActing): the session
//! found for its caller, the policy checked against the session's spaces and charged to its owner,
//! the request checked, the session handed to the actor. The actor itself is [`crate::actor`].

use std::sync::atomic::Ordering;

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use radserve_policy::{Head, Policy, PolicyError, PolicySpec, RuntimeLauncher};
use tracing::info;

use super::SessionManager;
use crate::actor::{action_spec, observation_spec, ActingConfig, ActingRequest, ActingStatus, Actor, ActorPolicy, HeldPolicy, LoadedPolicy};
use crate::error::CoreError;
use crate::principal::{log_id, Principal};

impl SessionManager {
    /// Server-side policies: how they are loaded.
    pub fn with_acting(mut self, config: ActingConfig) -> SessionManager {
        self.acting = config;
        self
    }

    pub fn acting_config(&self) -> &ActingConfig {
        &self.acting
    }

    /// How policy runtimes start. ONNX Runtime's library is located once, at the first SetPolicy
    /// (the workers' Python asked where its wheel is, on a blocking thread, never on an async
    /// worker); the outcome, found or not, is kept until the server restarts.
    async fn launcher(&self) -> Result<RuntimeLauncher, CoreError> {
        let located = self
            .onnxruntime
            .get_or_init(|| async {
                let (library, python) = (self.acting.library.clone(), self.acting.python.clone());
                let found = tokio::task::spawn_blocking(move || match (library, python) {
                    (Some(library), _) => Ok(library),
                    (None, Some(python)) => radserve_policy::library_of_python(&python),
                    (None, None) => Err(PolicyError::Unavailable("no [acting] onnxruntime_library and no workers' Python to find it in".into())),
                })
                .await;
                match found {
                    Ok(Ok(library)) => Ok(library),
                    Ok(Err(PolicyError::Unavailable(message))) => Err(message),
                    Ok(Err(error)) => Err(error.to_string()),
                    Err(error) => Err(format!("finding ONNX Runtime: {error}")),
                }
            })
            .await;
        let library = located.clone().map_err(|message| CoreError::from(PolicyError::Unavailable(message)))?;
        let program = match &self.acting.program {
            Some(program) => program.clone(),
            None => std::env::current_exe().map_err(|error| CoreError::Host(format!("locating the radserve executable: {error}")))?,
        };
        Ok(RuntimeLauncher {
            program,
            args: vec!["policy-runtime".into()],
            library,
            memory_bytes: self.acting.policy_memory_bytes,
            load_timeout: self.acting.load_timeout,
            call_timeout: self.acting.call_timeout,
        })
    }

    /// Loads a policy for the session (checked, built and run once on zeros) and makes it the
    /// session's newest: a running actor takes it before its next step.
    pub async fn set_policy(
        &self,
        caller: &Principal,
        session_id: &str,
        model: Vec<u8>,
        head: Head,
        version: u32,
    ) -> Result<LoadedPolicy, CoreError> {
        if model.len() > self.acting.max_model_bytes {
            return Err(CoreError::TooLarge(format!(
                "the model is {} bytes; this server takes models of at most {} bytes (acting.max_model_bytes)",
                model.len(),
                self.acting.max_model_bytes
            )));
        }
        let (slot, info) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch(&registry, caller, session_id)?;
            (entry.actor.clone(), entry.info.clone())
        };
        let _loading = slot.loading.lock().await;
        if let Some(last) = slot.status().policy_version {
            if version <= last {
                return Err(CoreError::Acting(format!("policy version {version} is not newer than the session's version {last}; versions must grow")));
            }
        }
        let observations = observation_spec(&info.observation_space, info.num_envs)?;
        let actions = action_spec(&info.action_space)?;
        let launcher = self.launcher().await?;
        // Charged before the runtime starts: its memory limit and the model's bytes, which the
        // server holds while the policy is loaded.
        let charge = self.reserve_memory(caller, launcher.memory_bytes + model.len() as u64, "a policy (acting.policy_memory_bytes and the model)")?;
        let spec = PolicySpec { head, threads: self.acting.threads.max(1) };
        let head_name = spec.head.name();
        let policy = Policy::load(&launcher, &model, spec, observations, actions).await?;
        let loaded = LoadedPolicy {
            opset: policy.summary.opset,
            ops: policy.summary.ops.clone(),
            input: policy.summary.input.clone(),
            outputs: policy.summary.outputs.clone(),
            has_value: policy.has_value(),
        };
        info!(session = log_id(session_id), version, peak_mib = policy.peak_bytes() >> 20, "policy loaded in its runtime");
        slot.install(HeldPolicy { policy: ActorPolicy::Runtime(Box::new(policy)), version, _charge: charge }, head_name);
        self.metrics.acting.policies.fetch_add(1, Ordering::Relaxed);
        info!(session = log_id(session_id), version, head = head_name, "policy set");
        Ok(loaded)
    }

    /// Starts the session's actor with its newest policy.
    pub async fn start_acting(&self, caller: &Principal, session_id: &str, request: ActingRequest) -> Result<ActingStatus, CoreError> {
        let limiter = request.check()?;
        let (slot, session, replay, closed) = {
            let registry = self.sessions.lock().expect("registry lock");
            let entry = self.touch(&registry, caller, session_id)?;
            (entry.actor.clone(), entry.session.clone(), entry.replay.clone(), entry.lease.closed.subscribe())
        };
        if let Some(limiter) = &limiter {
            let Some(replay) = &replay else {
                return Err(CoreError::Acting("samples_per_insert limits acting against the sampling of a buffer; this session keeps none".into()));
            };
            let capacity = replay.read().expect("replay lock").layout().capacity as u64;
            if limiter.min_size > capacity {
                return Err(CoreError::OutOfBounds(format!("min_size {} can never be reached: the replay capacity is {capacity}", limiter.min_size)));
            }
        }
        slot.start(|| {
            // The session's lock is free unless a client's call is in progress: refuse then, and
            // refuse a session whose mode the actor cannot step.
            let Ok(mut locked) = session.try_lock() else {
                return Err(CoreError::Acting("a call is stepping this session; StartActing once it returned".into()));
            };
            if let Some(batch) = locked.async_batch() {
                return Err(CoreError::Acting(format!(
                    "the actor steps every env at once; this session returns {batch} envs at a time (batch_size): create it without batch_size"
                )));
            }
            locked.hand_to_actor();
            let seed = request.seed.unwrap_or(locked.config.seed);
            drop(locked);
            Ok(Actor {
                session: session.clone(),
                slot: slot.clone(),
                replay,
                limiter,
                request,
                rng: ChaCha8Rng::seed_from_u64(seed),
                metrics: self.metrics.clone(),
                session_id: session_id.to_string(),
                closed,
            })
        })?;
        info!(session = log_id(session_id), "acting started");
        Ok(slot.status())
    }

    /// Stops the session's actor after its current step; clients may step the session again.
    pub async fn stop_acting(&self, caller: &Principal, session_id: &str) -> Result<ActingStatus, CoreError> {
        let slot = {
            let registry = self.sessions.lock().expect("registry lock");
            self.touch(&registry, caller, session_id)?.actor.clone()
        };
        slot.stop().await;
        Ok(slot.status())
    }
}

#[cfg(test)]
impl SessionManager {
    /// The session's actor slot, for core's tests of the actor.
    pub(crate) fn actor_slot(&self, caller: &Principal, session_id: &str) -> std::sync::Arc<crate::actor::ActorSlot> {
        let registry = self.sessions.lock().expect("registry lock");
        self.touch(&registry, caller, session_id).expect("a live session").actor.clone()
    }

    /// A test's policy, charged 1 MiB as SetPolicy charges a runtime's.
    pub(crate) fn scripted_policy(&self, caller: &Principal, scripted: crate::actor::tests::Scripted, version: u32) -> HeldPolicy {
        let charge = self.reserve_memory(caller, 1 << 20, "a test's policy").expect("room for a test's policy");
        HeldPolicy { policy: ActorPolicy::Scripted(scripted), version, _charge: charge }
    }
}
