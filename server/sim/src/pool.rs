//! Worker processes as seen from the server: each is driven by one supervising task
//! (`supervise_worker`) that owns its pipes, handles requests in order, and replaces the process
//! when it dies.

use std::collections::{BTreeMap, HashSet};
use std::io;
use std::os::fd::{AsFd, AsRawFd};
use std::path::PathBuf;
use std::process::Stdio;
use std::sync::atomic::{AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::process::{Child, ChildStdin, ChildStdout, Command};
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{info, warn};

use crate::protocol::{self, PassedFd, Request, Response};
use crate::worker::GlBackend;

/// How to start a worker: the same binary in its `worker` mode.
#[derive(Clone, Debug)]
pub struct WorkerLauncher {
    pub program: PathBuf,
    pub venv: PathBuf,
    pub gl: GlBackend,
    /// How long a worker may take to answer a reset, step or close before it is killed and replaced.
    pub call_timeout: Duration,
    /// The same for building environments (CreateGroup, rebuilding groups in a new process, the
    /// catalog), which loads simulators and can take seconds per env.
    pub create_timeout: Duration,
}

impl WorkerLauncher {
    /// Defaults: 60 s per call (a step of 64 default-look dm_control envs renders for ~10 s on two
    /// cores), 300 s to build.
    pub fn new(program: PathBuf, venv: PathBuf, gl: GlBackend) -> WorkerLauncher {
        WorkerLauncher { program, venv, gl, call_timeout: Duration::from_secs(60), create_timeout: Duration::from_secs(300) }
    }

    fn timeout_for(&self, request: &Request) -> Duration {
        if is_call(request) {
            self.call_timeout
        } else {
            self.create_timeout
        }
    }
}

/// Whether `request` is a reset, step or close (bounded by `call_timeout`, and stamped while it runs),
/// not a build (bounded by `create_timeout`).
fn is_call(request: &Request) -> bool {
    match request {
        Request::CreateGroup(_) | Request::ListNames | Request::Specs { .. } | Request::Attach { .. } => false,
        Request::Reset { .. }
        | Request::AsyncReset { .. }
        | Request::Step { .. }
        | Request::Send { .. }
        | Request::Recv { .. }
        | Request::SendRecv { .. }
        | Request::CloseGroup { .. } => true,
    }
}

/// The niceness of the catalog worker: the catalog is built in the background at start-up (about 14 s
/// of one core: every task is loaded once for its spaces), and on a small host it must not take CPU
/// from the workers that serve sessions. At niceness 19 it gets what they leave.
const BACKGROUND_NICENESS: libc::c_int = 19;

impl WorkerLauncher {
    pub(crate) async fn spawn(&self) -> io::Result<WorkerProcess> {
        // Descriptors (the groups' frame memory) go to the worker over a socket pair, its end at fd 3.
        let (fds, worker_end) = std::os::unix::net::UnixStream::pair()?;
        let worker_fd = worker_end.as_raw_fd();
        let mut command = Command::new(&self.program);
        command
            .arg("worker")
            .arg("--venv")
            .arg(&self.venv)
            .arg("--gl")
            .arg(self.gl.name())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true);
        // SAFETY: between fork and exec only async-signal-safe calls (dup2, fcntl) on descriptors
        // this process owns; dup2 clears close-on-exec on fd 3, fcntl does when it is already fd 3.
        unsafe {
            command.pre_exec(move || {
                let result = if worker_fd == WORKER_FD_SOCKET {
                    libc::fcntl(worker_fd, libc::F_SETFD, 0)
                } else {
                    libc::dup2(worker_fd, WORKER_FD_SOCKET)
                };
                if result < 0 {
                    return Err(io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = command.spawn()?;
        drop(worker_end);
        let stdin = child.stdin.take().expect("stdin is piped");
        let stdout = child.stdout.take().expect("stdout is piped");
        Ok(WorkerProcess { child, stdin, stdout, fds, registration: None })
    }
}

/// The worker's end of its descriptor socket.
pub const WORKER_FD_SOCKET: libc::c_int = 3;

pub struct WorkerProcess {
    child: Child,
    stdin: ChildStdin,
    stdout: ChildStdout,
    /// The server's end of the descriptor socket.
    fds: std::os::unix::net::UnixStream,
    /// A transient worker's entry among the pool's, removed when the process is dropped (killed).
    registration: Option<Registration>,
}

/// Pids of the transient workers alive now, for `WorkerPool::kill_all`.
type TransientPids = Arc<std::sync::Mutex<HashSet<u32>>>;

struct Registration {
    pids: TransientPids,
    pid: u32,
}

impl Drop for Registration {
    fn drop(&mut self) {
        self.pids.lock().expect("transient pid lock").remove(&self.pid);
    }
}

impl WorkerProcess {
    /// Sends one request and waits at most `limit` for its response. An error means the worker is
    /// gone or stuck (`TimedOut`); either way it must not be used again.
    pub async fn call_within(&mut self, request: &Request, limit: Duration) -> io::Result<Response> {
        match tokio::time::timeout(limit, self.call(request)).await {
            Ok(result) => result,
            Err(_) => Err(io::Error::new(io::ErrorKind::TimedOut, format!("no answer within {} s", limit.as_secs_f64()))),
        }
    }

    /// Sends one request and waits for its response. An I/O error means the worker is gone.
    pub async fn call(&mut self, request: &Request) -> io::Result<Response> {
        if let Request::Attach { memory: PassedFd(Some(fd)), .. } = request {
            // Before the request, so the worker finds it when it reads the request. One byte into a
            // socket the worker drains once per Attach: it does not block.
            radserve_shm::send_fd(&self.fds, fd.as_fd(), 0)?;
        }
        self.stdin.write_all(&protocol::encode(request)?).await?;
        self.stdin.flush().await?;
        let mut header = [0u8; 4];
        self.stdout.read_exact(&mut header).await?;
        let mut body = vec![0u8; protocol::check_length(header)?];
        self.stdout.read_exact(&mut body).await?;
        protocol::decode(&body)
    }

    pub fn pid(&self) -> Option<u32> {
        self.child.id()
    }

    /// Kills the process if it still runs and says how it ended.
    async fn reap(mut self) -> String {
        let _ = self.child.start_kill();
        match self.child.wait().await {
            Ok(status) => status.to_string(),
            Err(err) => format!("unknown status ({err})"),
        }
    }
}

/// Why a request got no response from a worker.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum WorkerFault {
    /// The worker died while handling the request. It has been replaced, and the groups it hosted were
    /// built again (unreset) in the new process.
    Crashed(String),
    /// No worker process could be started.
    Unavailable(String),
}

/// A worker's answer and the generation of the process that gave it (the worker's restarts so far).
pub type Reply = Result<(Response, u64), WorkerFault>;

struct Job {
    request: Request,
    /// Run only in this generation of the worker: a group built in an earlier process was rebuilt
    /// unreset in this one, and its session must learn that before stepping it.
    generation: Option<u64>,
    reply: oneshot::Sender<Reply>,
}

/// A handle on one worker's supervising task; cheap to clone.
#[derive(Clone)]
pub struct WorkerHandle {
    index: usize,
    jobs: mpsc::Sender<Job>,
    state: Arc<WorkerState>,
}

#[derive(Default)]
struct WorkerState {
    hosted_envs: AtomicUsize,
    pid: AtomicU32,
    restarts: AtomicU64,
    /// When the reset, step or close the process is answering now was sent (None: no such call):
    /// the stamp `WorkerPool::overdue_workers` reads to tell a stuck worker before its deadline.
    call_started: std::sync::Mutex<Option<std::time::Instant>>,
}

impl WorkerHandle {
    pub fn index(&self) -> usize {
        self.index
    }

    /// Queues a request; the returned receiver resolves when the worker has answered. Queue requests to
    /// several workers before awaiting any of them to run them in parallel.
    pub async fn submit(&self, request: Request) -> oneshot::Receiver<Reply> {
        self.submit_job(request, None).await
    }

    /// Like `submit`, but the worker refuses the request (`WorkerFault::Crashed`) unless its process
    /// is still of `generation`.
    pub async fn submit_in(&self, request: Request, generation: u64) -> oneshot::Receiver<Reply> {
        self.submit_job(request, Some(generation)).await
    }

    async fn submit_job(&self, request: Request, generation: Option<u64>) -> oneshot::Receiver<Reply> {
        let (reply, receiver) = oneshot::channel();
        if let Err(mpsc::error::SendError(job)) = self.jobs.send(Job { request, generation, reply }).await {
            let _ = job.reply.send(Err(WorkerFault::Unavailable("the worker pool has stopped".into())));
        }
        receiver
    }

    pub async fn call(&self, request: Request) -> Result<Response, WorkerFault> {
        await_reply(self.submit(request).await).await
    }

    /// A call whose reply carries the generation that answered.
    pub async fn call_generation(&self, request: Request) -> Reply {
        await_generation(self.submit(request).await).await
    }

    pub fn hosted_envs(&self) -> usize {
        self.state.hosted_envs.load(Ordering::Relaxed)
    }

    pub fn add_hosted_envs(&self, count: usize) {
        self.state.hosted_envs.fetch_add(count, Ordering::Relaxed);
    }

    pub fn remove_hosted_envs(&self, count: usize) {
        self.state.hosted_envs.fetch_sub(count, Ordering::Relaxed);
    }

    /// The current process id (0 before the first start).
    pub fn pid(&self) -> u32 {
        self.state.pid.load(Ordering::Relaxed)
    }

    pub fn restarts(&self) -> u64 {
        self.state.restarts.load(Ordering::Relaxed)
    }
}

pub async fn await_reply(receiver: oneshot::Receiver<Reply>) -> Result<Response, WorkerFault> {
    await_generation(receiver).await.map(|(response, _)| response)
}

pub async fn await_generation(receiver: oneshot::Receiver<Reply>) -> Reply {
    receiver.await.unwrap_or_else(|_| Err(WorkerFault::Unavailable("the worker pool has stopped".into())))
}

pub struct WorkerPool {
    workers: Vec<WorkerHandle>,
    launcher: WorkerLauncher,
    transient: TransientPids,
    /// Tells the supervisors to end their workers' processes and return (`stop`).
    stopping: watch::Sender<bool>,
    supervisors: std::sync::Mutex<Vec<tokio::task::JoinHandle<()>>>,
}

impl WorkerPool {
    /// Starts `count` workers (at least one) in the background; requests wait for their start.
    pub fn start(launcher: WorkerLauncher, count: usize) -> WorkerPool {
        let stopping = watch::Sender::new(false);
        let mut supervisors = Vec::new();
        let workers = (0..count.max(1))
            .map(|index| {
                let (jobs, receiver) = mpsc::channel(256);
                let state = Arc::new(WorkerState::default());
                supervisors.push(tokio::spawn(supervise_worker(index, launcher.clone(), receiver, state.clone(), stopping.subscribe())));
                WorkerHandle { index, jobs, state }
            })
            .collect();
        WorkerPool { workers, launcher, transient: TransientPids::default(), stopping, supervisors: std::sync::Mutex::new(supervisors) }
    }

    /// The workers whose current reset, step or close has run longer than `after` (stuck, or very
    /// slow), by index.
    pub fn overdue_workers(&self, after: Duration) -> Vec<usize> {
        self.workers
            .iter()
            .filter(|worker| {
                let started = *worker.state.call_started.lock().expect("call stamp lock");
                started.is_some_and(|started| started.elapsed() > after)
            })
            .map(|worker| worker.index)
            .collect()
    }

    /// Ends every worker process and waits until each has exited (and is reaped), so that the
    /// server exits with no worker left. Requests still queued are answered UNAVAILABLE.
    pub async fn stop(&self) {
        self.stopping.send_replace(true);
        // A transient worker (the catalog's, a few seconds after start-up) is killed where it
        // stands: nothing it computes is needed any more.
        let transient = self.transient_pids();
        transient.iter().copied().for_each(kill);
        let supervisors = std::mem::take(&mut *self.supervisors.lock().expect("supervisor list lock"));
        for supervisor in supervisors {
            let _ = supervisor.await;
        }
        let deadline = std::time::Instant::now() + Duration::from_secs(1);
        while transient.iter().any(|&pid| alive(pid)) && std::time::Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }

    pub fn len(&self) -> usize {
        self.workers.len()
    }

    pub fn is_empty(&self) -> bool {
        self.workers.is_empty()
    }

    pub fn workers(&self) -> &[WorkerHandle] {
        &self.workers
    }

    /// How long building environments may take in a worker.
    pub fn create_timeout(&self) -> Duration {
        self.launcher.create_timeout
    }

    /// Kills every worker process now (SIGKILL), for an exit that cannot wait for them.
    pub fn kill_all(&self) {
        for pid in self.workers.iter().map(WorkerHandle::pid).chain(self.transient_pids()) {
            kill(pid);
        }
    }

    fn transient_pids(&self) -> Vec<u32> {
        self.transient.lock().expect("transient pid lock").iter().copied().collect()
    }

    /// The `count` workers hosting the fewest environments, least loaded first.
    pub fn least_loaded(&self, count: usize) -> Vec<WorkerHandle> {
        let mut workers = self.workers.clone();
        workers.sort_by_key(|worker| (worker.hosted_envs(), worker.index));
        workers.truncate(count.clamp(1, self.workers.len()));
        workers
    }

    /// A worker outside the pool for a one-off background job (the catalog), at the lowest CPU priority;
    /// dropped (killed) when done.
    pub async fn spawn_transient(&self) -> io::Result<WorkerProcess> {
        let mut worker = self.launcher.spawn().await?;
        if let Some(pid) = worker.pid() {
            self.transient.lock().expect("transient pid lock").insert(pid);
            worker.registration = Some(Registration { pids: self.transient.clone(), pid });
            // SAFETY: setpriority only reads its integer arguments. The worker was just spawned and is
            // owned (kill_on_drop) by `worker`, so the pid names it. Python threads it starts later
            // inherit the niceness.
            let failed = unsafe { libc::setpriority(libc::PRIO_PROCESS, pid, BACKGROUND_NICENESS) } != 0;
            if failed {
                warn!(pid, error = %io::Error::last_os_error(), "could not lower the catalog worker's priority");
            }
        }
        Ok(worker)
    }
}

/// SIGKILL to a worker of this pool (0: none started).
fn kill(pid: u32) {
    if pid > 0 {
        // SAFETY: kill only reads its integer arguments; the pid is this pool's child (a process
        // that already exited and was reaped makes it fail with ESRCH).
        unsafe { libc::kill(pid as libc::pid_t, libc::SIGKILL) };
    }
}

/// Whether process `pid` still runs (an exited one is gone or a zombie until reaped).
fn alive(pid: u32) -> bool {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { return false };
    let state = stat.rsplit_once(')').and_then(|(_, rest)| rest.split_whitespace().next());
    !matches!(state, None | Some("Z" | "X"))
}

async fn supervise_worker(
    index: usize,
    launcher: WorkerLauncher,
    mut jobs: mpsc::Receiver<Job>,
    state: Arc<WorkerState>,
    mut stopping: watch::Receiver<bool>,
) {
    // The requests that built each hosted group, sent again to a replacement process.
    let mut rebuilds: BTreeMap<u64, Vec<Request>> = BTreeMap::new();
    let mut process = start(index, &launcher, &state, &rebuilds).await.ok();
    // Why the current process replaced the previous one, for sessions that learn of it later.
    let mut last_restart = String::new();
    loop {
        let job = tokio::select! {
            job = jobs.recv() => match job {
                Some(job) => job,
                None => break,
            },
            _ = stopping.wait_for(|stop| *stop) => break,
        };
        let generation = state.restarts.load(Ordering::Acquire);
        if job.generation.is_some_and(|expected| expected != generation) {
            let fault = format!(
                "simulator worker {index} was restarted since this session last used it ({last_restart}); its \
                 environments were rebuilt"
            );
            let _ = job.reply.send(Err(WorkerFault::Crashed(fault)));
            continue;
        }
        if process.is_none() {
            match start(index, &launcher, &state, &rebuilds).await {
                Ok(started) => process = Some(started),
                Err(err) => {
                    let _ = job.reply.send(Err(WorkerFault::Unavailable(format!("cannot start worker {index}: {err}"))));
                    continue;
                }
            }
        }
        let worker = process.as_mut().expect("started above");
        // Creates may take minutes by design: only the calls bounded by worker_call_timeout_s are stamped.
        let stamped = is_call(&job.request);
        if stamped {
            *state.call_started.lock().expect("call stamp lock") = Some(std::time::Instant::now());
        }
        let answer = worker.call_within(&job.request, launcher.timeout_for(&job.request)).await;
        if stamped {
            *state.call_started.lock().expect("call stamp lock") = None;
        }
        match answer {
            Ok(response) => {
                remember(&mut rebuilds, &job.request, &response);
                let _ = job.reply.send(Ok((response, generation)));
            }
            Err(err) => {
                let stuck = err.kind() == io::ErrorKind::TimedOut;
                let status = process.take().expect("present").reap().await;
                if stuck {
                    warn!(worker = index, error = %err, "worker did not answer in time, killed it; replacing it");
                } else {
                    warn!(worker = index, error = %err, status = %status, "worker died, replacing it");
                }
                if let Request::CloseGroup { group } = &job.request {
                    rebuilds.remove(group);
                }
                let fault = if stuck {
                    format!("simulator worker {index} did not answer within {} s ({err}); it was killed and restarted",
                        launcher.timeout_for(&job.request).as_secs_f64())
                } else {
                    format!("simulator worker {index} died ({status}); it was restarted")
                };
                last_restart.clone_from(&fault);
                // The generation changes before the new process exists: requests of the old one are refused.
                state.restarts.fetch_add(1, Ordering::AcqRel);
                process = start(index, &launcher, &state, &rebuilds).await.ok();
                let _ = job.reply.send(Err(WorkerFault::Crashed(fault)));
            }
        }
    }
    if let Some(process) = process {
        let status = process.reap().await;
        info!(worker = index, %status, "worker stopped");
    }
}

async fn start(
    index: usize,
    launcher: &WorkerLauncher,
    state: &WorkerState,
    rebuilds: &BTreeMap<u64, Vec<Request>>,
) -> io::Result<WorkerProcess> {
    let mut process = launcher.spawn().await.inspect_err(|err| warn!(worker = index, error = %err, "cannot start worker"))?;
    state.pid.store(process.pid().unwrap_or(0), Ordering::Relaxed);
    info!(worker = index, pid = process.pid().unwrap_or(0), groups = rebuilds.len(), "worker started");
    for (group, requests) in rebuilds {
        for request in requests {
            match process.call_within(request, launcher.create_timeout).await {
                Ok(Response::Failed(message)) => warn!(worker = index, group, %message, "could not rebuild group"),
                Ok(_) => {}
                Err(err) => {
                    let _ = process.reap().await;
                    return Err(err);
                }
            }
        }
    }
    Ok(process)
}

fn remember(rebuilds: &mut BTreeMap<u64, Vec<Request>>, request: &Request, response: &Response) {
    match (request, response) {
        (Request::CreateGroup(config), Response::Created(_)) => {
            rebuilds.insert(config.group, vec![request.clone()]);
        }
        (Request::Attach { group, .. }, Response::Attached) => {
            if let Some(requests) = rebuilds.get_mut(group) {
                requests.truncate(1);
                requests.push(request.clone());
            }
        }
        (Request::CloseGroup { group }, _) => {
            rebuilds.remove(group);
        }
        _ => {}
    }
}
