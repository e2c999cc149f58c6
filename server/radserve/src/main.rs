use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use radserve::config::Config;
use radserve::ServerSettings;
use radserve_core::Space;
use radserve_sim::{GlBackend, WorkerArgs};
use tokio::net::TcpListener;
use tracing::info;

/// radserve: reinforcement-learning simulators served over gRPC.
#[derive(Parser)]
#[command(name = "radserve", version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve the simulators over gRPC.
    Serve {
        /// Address to listen on (overrides server.address); port 0 picks a free port.
        #[arg(long)]
        address: Option<String>,
        /// Worker processes (overrides sim.workers; default: one per core).
        #[arg(long)]
        workers: Option<usize>,
        /// A TOML configuration file.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Serve a non-loopback address without authentication (server.insecure): anyone who can
        /// reach the port can use every session.
        #[arg(long)]
        insecure: bool,
    },
    /// Print a new bearer token, and the tokens-file entry (its SHA-256 digest) that admits it.
    Token {
        /// The principal the token belongs to.
        #[arg(long)]
        name: String,
        /// user (creates and uses its own sessions), monitor (lists and describes every session),
        /// or admin (everything, on every session).
        #[arg(long, default_value = "user")]
        role: String,
    },
    /// Ask a server's gRPC health service (grpc.health.v1) and exit 0 only if it answers SERVING:
    /// the container HEALTHCHECK, for images with no grpc_health_probe or curl.
    Healthcheck {
        /// The server (default: the configuration's server.address, with 0.0.0.0 read as 127.0.0.1).
        #[arg(long)]
        address: Option<String>,
        #[arg(long)]
        config: Option<PathBuf>,
        /// The service to ask about; "" (the default) is the whole server, "radserve.v1.RadServe"
        /// or "dm_env_rpc.v1.Environment" one of its services.
        #[arg(long, default_value = "")]
        service: String,
        /// Seconds allowed for connecting and for the answer.
        #[arg(long, default_value_t = 3.0)]
        timeout_s: f64,
        /// A server with TLS: the CA certificate (PEM) that signed its certificate.
        #[arg(long)]
        ca: Option<PathBuf>,
        /// With --ca: the name the server's certificate must carry.
        #[arg(long, default_value = "localhost")]
        server_name: String,
        /// With --ca, for a server that admits only clients with a certificate its client CA signed
        /// (tls.client_ca_file, mutual TLS): this client's certificate (PEM).
        #[arg(long, requires_all = ["key", "ca"])]
        cert: Option<PathBuf>,
        /// The private key (PEM) of --cert.
        #[arg(long, requires = "cert")]
        key: Option<PathBuf>,
    },
    /// Print the configuration: the one `serve` would run with (defaults, then --config, then
    /// RADSERVE__SECTION__KEY variables), every default, or the reference table of the docs.
    Config {
        #[arg(long)]
        config: Option<PathBuf>,
        /// Every key at its default, as a commented TOML file (a starting point for --config).
        #[arg(long, conflicts_with_all = ["config", "markdown"])]
        defaults: bool,
        /// The reference tables of docs/configuration.md (key, default, variable, meaning).
        #[arg(long, conflicts_with = "config")]
        markdown: bool,
    },
    /// List every environment id with its observation and action spaces.
    Envs {
        /// Only ids starting with this prefix, e.g. `dmc/`.
        #[arg(long, default_value = "")]
        prefix: String,
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Time every augmentation at the paper's batch size against a plain copy of the output bytes.
    AugmentBench {
        /// Samples per batch.
        #[arg(long, default_value_t = 512)]
        batch: usize,
        /// Batches timed per case (the median is reported).
        #[arg(long, default_value_t = 20)]
        repeats: usize,
        /// Threads (0: one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Only pipelines containing this text.
        #[arg(long, default_value = "")]
        filter: String,
        /// One JSON object per line instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Write a PNG grid of a rendered frame under every augmentation (rows) and several draws (columns).
    AugmentPreview {
        /// A pixel environment to render the frame with.
        #[arg(long, default_value = "dmc/cheetah-run")]
        env: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Draws per augmentation.
        #[arg(long, default_value_t = 6)]
        columns: usize,
        #[arg(long, default_value = "augment-preview.png")]
        out: PathBuf,
        #[arg(long)]
        config: Option<PathBuf>,
    },
    /// Internal: run as a simulator worker process (started by the server).
    #[command(hide = true)]
    Worker {
        #[arg(long)]
        venv: PathBuf,
        #[arg(long, default_value = "egl")]
        gl: String,
    },
    /// Internal: run as a policy runtime process (started by the server for each policy; see
    /// radserve_policy::runtime).
    #[command(hide = true)]
    PolicyRuntime {
        #[arg(long)]
        library: PathBuf,
        #[arg(long)]
        memory_bytes: u64,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Command::PolicyRuntime { library, memory_bytes } = &cli.command {
        // No tokio and no tracing: one thread reads requests and runs the model.
        return radserve_policy::runtime::main(library, *memory_bytes, radserve_policy::runtime::Containment::FULL);
    }
    if let Command::Worker { venv, gl } = &cli.command {
        // No tokio and no tracing in workers: one thread owns the interpreter and the simulators.
        let Some(gl) = GlBackend::parse(gl) else {
            eprintln!("radserve worker: --gl must be egl or osmesa, got {gl}");
            return ExitCode::FAILURE;
        };
        return match radserve_sim::run_worker(&WorkerArgs { venv: venv.clone(), gl }) {
            Ok(()) => ExitCode::SUCCESS,
            Err(error) => {
                eprintln!("radserve worker: {error}");
                ExitCode::FAILURE
            }
        };
    }
    if let Err(error) = exit_with_parent() {
        eprintln!("radserve: {error}");
        return ExitCode::FAILURE;
    }
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().expect("tokio runtime");
    let result = runtime.block_on(run(cli.command));
    // Dropping the runtime would wait for every blocking task, and one may be stuck on a file (a
    // stalled disk under snapshot_dir): the drain deadline has passed by now, so it is not waited on.
    runtime.shutdown_timeout(std::time::Duration::from_secs(1));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("radserve: {error:#}");
            ExitCode::FAILURE
        }
    }
}

/// A launcher that wants the server gone with it (the Python client's `LocalServer`) sets
/// `RADSERVE_PARENT_PID` to its own pid: the kernel then sends SIGTERM when that process dies
/// (PR_SET_PDEATHSIG), and a server whose launcher died before this call exits at once. Done here
/// rather than by the launcher between fork and exec, which in a multithreaded launcher (grpcio's
/// threads) can deadlock the child before it ever runs.
fn exit_with_parent() -> Result<(), String> {
    let Some(value) = std::env::var_os("RADSERVE_PARENT_PID") else { return Ok(()) };
    let expected: libc::pid_t =
        value.to_str().and_then(|text| text.parse().ok()).ok_or("RADSERVE_PARENT_PID must be a process id")?;
    // SAFETY: prctl with PR_SET_PDEATHSIG reads two integers; getppid has no arguments.
    unsafe {
        if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
            return Err(format!("setting the parent-death signal: {}", std::io::Error::last_os_error()));
        }
        if libc::getppid() != expected {
            return Err(format!("the process that started radserve ({expected}) has already exited"));
        }
    }
    Ok(())
}

fn settings(config: &Config) -> anyhow::Result<ServerSettings> {
    Ok(ServerSettings {
        worker_program: std::env::current_exe().context("locating the radserve executable")?,
        venv: config.resolve_venv()?,
        gl: config.sim.gl,
        workers: config.worker_count(),
        limits: config.limits.clone(),
        replay: config.replay.clone(),
        worker_call_timeout: std::time::Duration::from_secs_f64(config.sim.worker_call_timeout_s),
        worker_create_timeout: std::time::Duration::from_secs_f64(config.sim.worker_create_timeout_s),
        acting: config.acting.to_core(),
    })
}

/// The address a client on this host reaches a server bound to `bound` at: an unspecified address
/// (0.0.0.0, [::]) is read as the loopback of its family.
fn local_address(bound: &str) -> String {
    match bound.parse::<std::net::SocketAddr>() {
        Ok(address) if address.ip().is_unspecified() => {
            let loopback: std::net::IpAddr =
                if address.is_ipv4() { std::net::Ipv4Addr::LOCALHOST.into() } else { std::net::Ipv6Addr::LOCALHOST.into() };
            std::net::SocketAddr::new(loopback, address.port()).to_string()
        }
        _ => bound.to_string(),
    }
}

/// `radserve healthcheck`: the serving status the server reports for `service` (SERVING,
/// NOT_SERVING, ...), or an error if it could not be asked.
/// How `radserve healthcheck` reaches a server with TLS: the CA that signed its certificate, the name
/// that certificate carries, and for mutual TLS this client's certificate and key.
struct HealthTls {
    ca: PathBuf,
    server_name: String,
    identity: Option<(PathBuf, PathBuf)>,
}

async fn health(address: &str, service: String, timeout: std::time::Duration, tls: Option<HealthTls>) -> anyhow::Result<String> {
    use tonic_health::pb::{health_check_response::ServingStatus, health_client::HealthClient, HealthCheckRequest};
    let scheme = if tls.is_some() { "https" } else { "http" };
    let mut endpoint = tonic::transport::Endpoint::from_shared(format!("{scheme}://{address}"))
        .with_context(|| format!("{address} is not a host:port address"))?
        .connect_timeout(timeout)
        .timeout(timeout);
    if let Some(HealthTls { ca, server_name, identity }) = tls {
        let read = |path: &PathBuf, flag: &str| std::fs::read(path).with_context(|| format!("reading --{flag} {}", path.display()));
        let mut config = tonic::transport::ClientTlsConfig::new()
            .ca_certificate(tonic::transport::Certificate::from_pem(read(&ca, "ca")?))
            .domain_name(server_name);
        if let Some((cert, key)) = identity {
            config = config.identity(tonic::transport::Identity::from_pem(read(&cert, "cert")?, read(&key, "key")?));
        }
        endpoint = endpoint.tls_config(config)?;
    }
    let channel = endpoint.connect().await.with_context(|| format!("connecting to {address}"))?;
    let reply = HealthClient::new(channel)
        .check(HealthCheckRequest { service })
        .await
        .with_context(|| format!("asking {address} for its health"))?;
    let status = reply.into_inner().status;
    Ok(ServingStatus::try_from(status).map_or_else(|_| format!("UNKNOWN({status})"), |status| status.as_str_name().to_string()))
}

async fn run(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Config { config, defaults, markdown } => {
            use radserve::config_reference;
            let text = if defaults {
                config_reference::defaults_toml()
            } else if markdown {
                config_reference::markdown()
            } else {
                let title = match &config {
                    Some(file) => format!("radserve's configuration from the defaults, {}, and the environment", file.display()),
                    None => "radserve's configuration from the defaults and the environment".to_string(),
                };
                config_reference::toml_of(&Config::load(config.as_deref())?, &title)
            };
            print!("{text}");
            Ok(())
        }
        Command::Healthcheck { address, config, service, timeout_s, ca, server_name, cert, key } => {
            let address = match address {
                Some(address) => address,
                None => local_address(&Config::load(config.as_deref())?.server.address),
            };
            let timeout = std::time::Duration::try_from_secs_f64(timeout_s).context("--timeout-s must be a positive number of seconds")?;
            let identity = cert.zip(key);
            let tls = ca.map(|ca| HealthTls { ca, server_name, identity });
            let status = health(&address, service, timeout, tls).await?;
            println!("{status}");
            anyhow::ensure!(status == "SERVING", "{address} reports {status}");
            Ok(())
        }
        Command::Serve { address, workers, config, insecure } => {
            let mut config = Config::load(config.as_deref())?;
            if let Some(address) = address {
                config.server.address = address;
            }
            if let Some(workers) = workers {
                config.sim.workers = workers;
            }
            config.server.insecure |= insecure;
            config.validate()?;
            let security = config.security()?;
            // The memory files this server holds (frames, batches, acting arrays) reach only the
            // processes it hands them to: /proc/<pid>/fd is closed to everyone else.
            radserve_shm::make_undumpable().context("making the server non-dumpable")?;
            if config.server.insecure && !security.loopback && !security.auth.is_on() {
                tracing::warn!(address = %config.server.address, "serving WITHOUT authentication on a non-loopback address (--insecure): anyone who can reach it can use every session");
            }
            let settings = settings(&config)?;
            let listener = TcpListener::bind(&config.server.address)
                .await
                .with_context(|| format!("binding {}", config.server.address))?;
            let bound = listener.local_addr()?;
            info!(address = %bound, workers = settings.workers, venv = %settings.venv.display(), gl = settings.gl.name(), "radserve starting");
            // The one line on stdout: launchers (the Python client's, the tests') read the port here.
            println!("radserve listening on {bound}");
            // The Prometheus endpoint, on its own port (off unless metrics.address is set).
            let metrics = match config.metrics.address.as_str() {
                "" => None,
                address => {
                    let listener = TcpListener::bind(address).await.with_context(|| format!("binding metrics.address {address}"))?;
                    info!(address = %listener.local_addr()?, "metrics at http://<address>/metrics");
                    Some(listener)
                }
            };
            let (manager, workers) = radserve::session_manager(settings);
            let pool = workers.clone();
            if let Some(listener) = metrics {
                let sources = radserve::metrics::Sources { manager: manager.clone(), workers: Some(pool.clone()) };
                tokio::spawn(radserve::metrics::serve(listener, sources));
            }
            let (first_signal, signalled) = tokio::sync::oneshot::channel::<()>();
            tokio::spawn(async move {
                shutdown_signal().await;
                let _ = first_signal.send(());
                // A second signal while draining: exit now, taking the workers along.
                shutdown_signal().await;
                tracing::warn!("second signal: exiting without draining");
                workers.kill_all();
                std::process::exit(130);
            });
            let options = radserve::ServeOptions { security, ..config.serve_options() };
            let served = radserve::serve(listener, manager, options, async {
                let _ = signalled.await;
            })
            .await;
            // Exit with no worker left: each is ended and reaped before the process goes (one stuck in
            // a call is not waited for: killed).
            if tokio::time::timeout(std::time::Duration::from_secs(2), pool.stop()).await.is_err() {
                pool.kill_all();
            }
            served
        }
        Command::Envs { prefix, config } => {
            let mut config = Config::load(config.as_deref())?;
            config.sim.workers = 1;
            let (manager, _workers) = radserve::session_manager(settings(&config)?);
            let catalog = manager.catalog().await?;
            println!("{:<36} {:<40} action", "id", "observation");
            for entry in catalog.iter().filter(|entry| entry.id.full().starts_with(&prefix)) {
                match &entry.spaces {
                    Ok((observation, action)) => {
                        println!("{:<36} {:<40} {}", entry.id.full(), observation.describe(), describe_action(action))
                    }
                    Err(error) => println!("{:<36} unavailable: {error}", entry.id.full()),
                }
            }
            Ok(())
        }
        Command::Token { name, role } => {
            let role = match role.as_str() {
                "user" => "user",
                "monitor" => "monitor",
                "admin" => "admin",
                other => anyhow::bail!("--role is user, monitor or admin, got {other:?}"),
            };
            let (token, digest) = radserve_service::auth::new_token().context("drawing random bytes for the token")?;
            // The token on stdout alone (for `TOKEN=$(radserve token ...)`), the entry on stderr.
            println!("{token}");
            eprintln!("# Give the token to {name}; add this entry to the server's auth.tokens_file:");
            eprintln!("[[principal]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken_sha256 = [\"{digest}\"]");
            Ok(())
        }
        Command::AugmentBench { batch, repeats, threads, filter, json } => {
            radserve::augment_cli::bench(batch, repeats, threads, &filter, json)
        }
        Command::AugmentPreview { env, seed, columns, out, config } => {
            let mut config = Config::load(config.as_deref())?;
            config.sim.workers = 1;
            let (manager, _workers) = radserve::session_manager(settings(&config)?);
            let result = radserve::augment_cli::preview(&manager, &env, seed, columns.max(1), &out).await;
            manager.shutdown().await;
            result
        }
        Command::Worker { .. } | Command::PolicyRuntime { .. } => unreachable!("handled before the runtime starts"),
    }
}

fn describe_action(space: &Space) -> String {
    match space {
        Space::Discrete { n } => format!("discrete({n})"),
        Space::Box { .. } => space.describe(),
    }
}

async fn shutdown_signal() {
    let interrupt = tokio::signal::ctrl_c();
    let mut terminate =
        tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()).expect("SIGTERM handler");
    tokio::select! {
        _ = interrupt => {}
        _ = terminate.recv() => {}
    }
}
