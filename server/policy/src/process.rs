//! The server's side of a policy runtime process ([`crate::runtime`] is the other): started per
//! policy, spoken to over its stdin and stdout, every answer awaited with a deadline and bounded in
//! size (the process runs untrusted input and is trusted no more than its model), killed when
//! dropped.

use std::os::fd::AsRawFd;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::process::{Child, ChildStdin, ChildStdout, Command};

use crate::runtime::{Output, Reply, Request};
use crate::{ObservationType, PolicyError};

/// How to start a policy runtime and what it may use.
#[derive(Clone, Debug)]
pub struct RuntimeLauncher {
    /// The executable and the arguments that make it a policy runtime (`radserve policy-runtime`);
    /// `--library` and `--memory-bytes` follow.
    pub program: PathBuf,
    pub args: Vec<String>,
    /// libonnxruntime.
    pub library: PathBuf,
    /// The runtime's data memory (RLIMIT_DATA): ONNX Runtime itself, the model, its weights and
    /// every intermediate tensor. What a session is charged for its policy.
    pub memory_bytes: u64,
    /// Building the model (and the first run) must finish within this.
    pub load_timeout: Duration,
    /// Each inference must answer within this.
    pub call_timeout: Duration,
}

/// A running policy runtime with its model loaded.
pub(crate) struct RuntimeProcess {
    child: Child,
    stdin: ChildStdin,
    stdout: ChildStdout,
    call_timeout: Duration,
    memory_bytes: u64,
    /// The largest answer taken (the outputs a model of this session can have, with room).
    max_reply_bytes: usize,
    /// The runtime's peak resident memory at its last answer.
    pub(crate) peak_bytes: u64,
    /// Killed (or gone) after a call that failed: it answers nothing any more.
    dead: bool,
}

/// Whether a runtime's failure reads as an allocation that its memory limit refused.
fn out_of_memory(message: &str, peak_bytes: u64, limit: u64) -> bool {
    let lower = message.to_ascii_lowercase();
    lower.contains("bad_alloc") || lower.contains("allocat") || lower.contains("out of memory") || peak_bytes >= limit / 10 * 9
}

impl RuntimeProcess {
    /// Starts a runtime and loads `model` in it.
    pub(crate) async fn start(launcher: &RuntimeLauncher, model: &[u8], threads: usize, max_reply_bytes: usize) -> Result<RuntimeProcess, PolicyError> {
        let mut command = Command::new(&launcher.program);
        command
            .args(&launcher.args)
            .arg("--library")
            .arg(&launcher.library)
            .arg("--memory-bytes")
            .arg(launcher.memory_bytes.to_string())
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .kill_on_drop(true);
        // SAFETY: between fork and exec only prctl, which is async-signal-safe: the runtime dies
        // with the server, whatever ends the server.
        unsafe {
            command.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = command
            .spawn()
            .map_err(|error| PolicyError::Unavailable(format!("starting the policy runtime {}: {error}", launcher.program.display())))?;
        let stdin = child.stdin.take().expect("stdin is piped");
        let stdout = child.stdout.take().expect("stdout is piped");
        // A step's observations (a few hundred kilobytes of pixels) in one write, not sixteen of the
        // default 64 KiB pipe; best effort (a lower pipe-max-size keeps the default).
        for fd in [stdin.as_raw_fd(), stdout.as_raw_fd()] {
            // SAFETY: fcntl on a descriptor this process owns, with an integer argument.
            unsafe { libc::fcntl(fd, libc::F_SETPIPE_SZ, 1 << 20) };
        }
        let mut process = RuntimeProcess {
            child,
            stdin,
            stdout,
            call_timeout: launcher.call_timeout,
            memory_bytes: launcher.memory_bytes,
            max_reply_bytes,
            peak_bytes: 0,
            dead: false,
        };
        let request = Request::Load { threads: threads as u32 };
        match process.call(&request, model, launcher.load_timeout, "loading the model").await? {
            Reply::Loaded { peak_bytes, .. } => {
                process.peak_bytes = peak_bytes;
                Ok(process)
            }
            Reply::Failed { message, peak_bytes } => Err(process.failed(&message, peak_bytes, "loading the model")),
            Reply::Outputs(_) => Err(PolicyError::Runtime("the policy runtime answered a load with outputs".into())),
        }
    }

    /// Runs the model on one batch: `data` is the observations' raw bytes of `dtype`.
    pub(crate) async fn run(&mut self, shape: Vec<i64>, dtype: ObservationType, uint8_input: bool, data: &[u8]) -> Result<Vec<Output>, PolicyError> {
        match self.call(&Request::Run { shape, dtype, uint8_input }, data, self.call_timeout, "running the model").await? {
            Reply::Outputs(outputs) => Ok(outputs),
            Reply::Failed { message, peak_bytes } => Err(self.failed(&message, peak_bytes, "running the model")),
            Reply::Loaded { .. } => Err(PolicyError::Runtime("the policy runtime answered a run with a load".into())),
        }
    }

    fn failed(&mut self, message: &str, peak_bytes: u64, doing: &str) -> PolicyError {
        self.peak_bytes = self.peak_bytes.max(peak_bytes);
        if out_of_memory(message, peak_bytes, self.memory_bytes) {
            // A runtime that reached its limit is stopped, its memory given back: it would reach it
            // again on the next frame.
            self.dead = true;
            let _ = self.child.start_kill();
            PolicyError::Exhausted(format!(
                "{doing} needs more than the {} bytes a policy may use (acting.policy_memory_bytes; the runtime reached {} \
                 bytes resident): {message}",
                self.memory_bytes, peak_bytes
            ))
        } else {
            PolicyError::Runtime(message.to_string())
        }
    }

    async fn call(&mut self, request: &Request, payload: &[u8], limit: Duration, doing: &str) -> Result<Reply, PolicyError> {
        match tokio::time::timeout(limit, self.exchange(request, payload)).await {
            Ok(Ok(reply)) => Ok(reply),
            Ok(Err(error)) => {
                // The process ended or said something unreadable: how it ended tells why.
                self.dead = true;
                let _ = self.child.start_kill();
                let status = tokio::time::timeout(Duration::from_secs(5), self.child.wait()).await;
                let ended = match status {
                    // Exit code 1: it could not contain itself or start ONNX Runtime (it says why
                    // on the server's standard error) before it read anything of the model.
                    Ok(Ok(status)) if status.code() == Some(1) => {
                        return Err(PolicyError::Unavailable(format!(
                            "the policy runtime could not start ({status}; the server's log says why)"
                        )))
                    }
                    Ok(Ok(status)) => status.to_string(),
                    _ => "no exit status".into(),
                };
                let aborted = ended.contains("signal: 6") || ended.contains("SIGABRT");
                let reason = format!("the policy runtime stopped while {doing} ({ended}; {error})");
                if aborted || out_of_memory("", self.peak_bytes, self.memory_bytes) {
                    Err(PolicyError::Exhausted(format!(
                        "{reason}: most likely an allocation past the {} bytes a policy may use (acting.policy_memory_bytes)",
                        self.memory_bytes
                    )))
                } else {
                    Err(PolicyError::Runtime(reason))
                }
            }
            Err(_) => {
                self.dead = true;
                let _ = self.child.start_kill();
                let key = if doing == "loading the model" { "acting.policy_load_timeout_s" } else { "acting.policy_call_timeout_s" };
                Err(PolicyError::Exhausted(format!("{doing} took longer than {} s ({key}); the policy runtime was stopped", limit.as_secs_f64())))
            }
        }
    }

    /// Sends `request` and its payload (the model's or the observations' bytes, raw, in a frame of
    /// their own: neither copied into the request nor encoded a byte at a time as a postcard Vec<u8>
    /// would be) and reads the answer.
    async fn exchange(&mut self, request: &Request, payload: &[u8]) -> std::io::Result<Reply> {
        let body = postcard::to_allocvec(request).map_err(|error| std::io::Error::new(std::io::ErrorKind::InvalidData, error.to_string()))?;
        let length = u32::try_from(payload.len()).map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidData, "a payload over 4 GiB"))?;
        self.stdin.write_all(&(body.len() as u32).to_le_bytes()).await?;
        self.stdin.write_all(&body).await?;
        self.stdin.write_all(&length.to_le_bytes()).await?;
        self.stdin.write_all(payload).await?;
        self.stdin.flush().await?;
        let mut header = [0u8; 4];
        self.stdout.read_exact(&mut header).await?;
        let length = u32::from_le_bytes(header) as usize;
        if length > self.max_reply_bytes {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("an answer of {length} bytes, more than the outputs of this session's policy can take ({})", self.max_reply_bytes),
            ));
        }
        let mut body = vec![0u8; length];
        self.stdout.read_exact(&mut body).await?;
        postcard::from_bytes(&body).map_err(|error| std::io::Error::new(std::io::ErrorKind::InvalidData, error.to_string()))
    }

    /// Whether the runtime still answers (it is killed after a call that failed or timed out).
    pub(crate) fn alive(&self) -> bool {
        !self.dead
    }
}
