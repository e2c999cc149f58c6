//! One configuration tree: defaults, then a TOML file, then `RADSERVE__SECTION__KEY` environment
//! variables (e.g. `RADSERVE__SIM__GL=osmesa`), validated at start-up.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;


use anyhow::{bail, Context};
use figment::providers::{Env, Format, Serialized, Toml};
use figment::Figment;
use radserve_core::Limits;
use radserve_sim::GlBackend;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    pub server: ServerConfig,
    pub sim: SimConfig,
    pub augment: AugmentConfig,
    pub limits: Limits,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AugmentConfig {
    /// Threads that sample and augment minibatches; 0 means one per core.
    pub threads: usize,
    /// Niceness of those threads (0..=19): above 0, acting (the gRPC handlers, the simulator
    /// workers) gets the cores first when both want them, and augmentation takes what is left.
    pub nice: i32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ServerConfig {
    pub address: String,
    /// Seconds from SIGTERM (or SIGINT) to exit, at most: streams end, calls finish, sessions close.
    /// A second signal exits at once.
    pub drain_timeout_s: f64,
    /// Seconds the server keeps answering after the signal (health NOT_SERVING, new sessions
    /// refused) before it closes its listener, so that probes and load balancers see it leave.
    pub shutdown_notice_s: f64,
    /// Connections open at once; more are closed as they arrive (lowered at start-up if the
    /// open-file limit cannot hold them).
    pub max_connections: usize,
    /// Seconds a connection may stay silent (no bytes from the peer) before it is closed. Live
    /// clients answer the keepalive pings, so only dead or non-gRPC peers reach it.
    pub idle_connection_timeout_s: f64,
    /// Seconds between the server's HTTP/2 pings on each connection, and how long an answer may take.
    pub keepalive_interval_s: f64,
    pub keepalive_timeout_s: f64,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            address: "127.0.0.1:50051".into(),
            drain_timeout_s: 20.0,
            shutdown_notice_s: 1.0,
            max_connections: 1024,
            idle_connection_timeout_s: 120.0,
            keepalive_interval_s: 30.0,
            keepalive_timeout_s: 20.0,
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimConfig {
    /// Worker processes; 0 means one per core.
    pub workers: usize,
    /// OpenGL platform for MuJoCo rendering: "egl" (default) or "osmesa".
    pub gl: GlBackend,
    /// The virtualenv whose Python the workers embed. Unset: $VIRTUAL_ENV, then a `.venv` found
    /// walking up from the executable (the layout `make setup` creates).
    pub venv: Option<PathBuf>,
    /// Seconds a worker may take to answer a reset, step or close before it is killed and replaced
    /// and the episodes it hosted end as truncated. Generous: a step of 64 default-look dm_control
    /// pixel envs renders for ~10 s on two cores.
    pub worker_call_timeout_s: f64,
    /// The same for building environments (creating a session's envs, the catalog at start-up).
    pub worker_create_timeout_s: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig { workers: 0, gl: GlBackend::default(), venv: None, worker_call_timeout_s: 60.0, worker_create_timeout_s: 300.0 }
    }
}

impl Config {
    pub fn load(file: Option<&Path>) -> anyhow::Result<Config> {
        let mut figment = Figment::from(Serialized::defaults(Config::default()));
        if let Some(file) = file {
            if !file.exists() {
                bail!("config file {} does not exist", file.display());
            }
            figment = figment.merge(Toml::file(file));
        }
        let config: Config = figment
            .merge(Env::prefixed("RADSERVE__").split("__"))
            .extract()
            .context("invalid configuration")?;
        config.validate()?;
        Ok(config)
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        self.server
            .address
            .parse::<SocketAddr>()
            .with_context(|| format!("server.address '{}' is not a host:port socket address", self.server.address))?;
        let server = &self.server;
        let seconds = |value: f64| value.is_finite() && (0.0..=86_400.0).contains(&value);
        let positive = |value: f64| seconds(value) && value > 0.0;
        if !positive(server.idle_connection_timeout_s) || !positive(server.keepalive_interval_s) || !positive(server.keepalive_timeout_s) {
            bail!(
                "server.idle_connection_timeout_s, keepalive_interval_s and keepalive_timeout_s are seconds in (0, 86400], got {}, {} and {}",
                server.idle_connection_timeout_s,
                server.keepalive_interval_s,
                server.keepalive_timeout_s
            );
        }
        if server.keepalive_interval_s >= server.idle_connection_timeout_s {
            bail!(
                "server.keepalive_interval_s ({}) must be below server.idle_connection_timeout_s ({}): the pings are what keeps a live but quiet client from being idle",
                server.keepalive_interval_s,
                server.idle_connection_timeout_s
            );
        }
        if server.max_connections == 0 {
            bail!("server.max_connections must be at least 1");
        }
        if !seconds(server.drain_timeout_s) || !seconds(server.shutdown_notice_s) {
            bail!(
                "server.drain_timeout_s and server.shutdown_notice_s are seconds in [0, 86400], got {} and {}",
                server.drain_timeout_s,
                server.shutdown_notice_s
            );
        }
        let positive = |value: f64| value.is_finite() && value > 0.0 && value <= 86_400.0;
        if !positive(self.sim.worker_call_timeout_s) || !positive(self.sim.worker_create_timeout_s) {
            bail!(
                "sim.worker_call_timeout_s and sim.worker_create_timeout_s are seconds in (0, 86400], got {} and {}",
                self.sim.worker_call_timeout_s,
                self.sim.worker_create_timeout_s
            );
        }
        let limits = &self.limits;
        if !(0..=19).contains(&self.augment.nice) {
            bail!("augment.nice must be between 0 and 19 (a lower priority than the server's), got {}", self.augment.nice);
        }
        if limits.max_sessions == 0
            || limits.max_envs_per_session == 0
            || limits.max_total_envs == 0
            || limits.max_streams_per_session == 0
            || limits.stream_memory_bytes == 0
        {
            bail!("limits must all be at least 1, got {limits:?}");
        }
        Ok(())
    }

    pub fn serve_options(&self) -> crate::ServeOptions {
        crate::ServeOptions {
            augment_threads: self.augment.threads,
            augment_nice: self.augment.nice,
            drain_timeout: Duration::from_secs_f64(self.server.drain_timeout_s),
            shutdown_notice: Duration::from_secs_f64(self.server.shutdown_notice_s),
            max_connections: self.server.max_connections,
            idle_connection_timeout: Duration::from_secs_f64(self.server.idle_connection_timeout_s),
            keepalive_interval: Duration::from_secs_f64(self.server.keepalive_interval_s),
            keepalive_timeout: Duration::from_secs_f64(self.server.keepalive_timeout_s),
        }
    }

    pub fn worker_count(&self) -> usize {
        if self.sim.workers > 0 {
            self.sim.workers
        } else {
            std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
        }
    }

    pub fn resolve_venv(&self) -> anyhow::Result<PathBuf> {
        if let Some(venv) = &self.sim.venv {
            return Ok(venv.clone());
        }
        if let Some(active) = std::env::var_os("VIRTUAL_ENV") {
            return Ok(PathBuf::from(active));
        }
        let exe = std::env::current_exe().context("locating the radserve executable")?;
        for dir in exe.ancestors().skip(1) {
            let candidate = dir.join(".venv");
            if candidate.join("bin/python").exists() {
                return Ok(candidate);
            }
        }
        bail!("no Python virtualenv found: run `make setup`, or set sim.venv (RADSERVE__SIM__VENV)")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid() {
        Config::default().validate().unwrap();
    }

    #[test]
    fn a_bad_address_is_rejected_at_start_up() {
        let mut config = Config::default();
        config.server.address = "localhost".into();
        assert!(config.validate().unwrap_err().to_string().contains("server.address"));
    }

    #[test]
    #[allow(clippy::result_large_err)] // figment::Jail's closure signature, not ours
    fn files_and_environment_override_defaults() {
        figment::Jail::expect_with(|jail| {
            jail.create_file("radserve.toml", "[sim]\nworkers = 3\n[limits]\nmax_sessions = 5\n")?;
            jail.set_env("RADSERVE__SIM__GL", "osmesa");
            let config = Config::load(Some(Path::new("radserve.toml"))).expect("loads");
            assert_eq!(config.sim.workers, 3);
            assert_eq!(config.sim.gl, GlBackend::Osmesa);
            assert_eq!(config.limits.max_sessions, 5);
            assert_eq!(config.limits.max_total_envs, Limits::default().max_total_envs);
            Ok(())
        });
    }
}
