//! The policy runtime's own process (`radserve policy-runtime`): ONNX Runtime running one model a
//! learner sent, where nothing the model makes ONNX Runtime do can reach the server.
//!
//! A model is untrusted input to a large C++ library: external data names a file ONNX Runtime opens
//! relative to the working directory, and a few hundred bytes of model can make it allocate
//! gigabytes. So the server never loads a model itself. It starts this process per policy, which,
//! before it reads the model:
//! 1. moves its working directory into an empty directory it then removes, so a relative name
//!    resolves to nothing (ONNX Runtime refuses absolute paths and `..` itself);
//! 2. loads ONNX Runtime's library (the last file it opens);
//! 3. limits its own data memory (RLIMIT_DATA: the heap and every private writable mapping) to
//!    what the session was charged, so an allocation past it fails in this process, never the
//!    server's;
//! 4. installs a seccomp filter that fails every call that opens, creates, removes, renames, stats
//!    or executes a file by name, opens a socket, or reaches another process (EACCES): even a check
//!    the server missed, or a bug in ONNX Runtime, cannot read a file.
//!
//! Then it answers requests on stdin/stdout ([`Request`], [`Reply`]: a little-endian u32 length and
//! a postcard body, then a frame of raw bytes: the model for a load, the observations for a run),
//! one at a time. The server kills it when the policy is replaced or its session
//! closes, when a load or a call passes its deadline, and the kernel kills it with the server
//! (PR_SET_PDEATHSIG).

use std::io::{self, Read, Write};
use std::path::Path;

use ort::session::builder::GraphOptimizationLevel;
use ort::session::Session;
use ort::value::Tensor;
use serde::{Deserialize, Serialize};

/// What the server asks of the runtime.
#[derive(Debug, Serialize, Deserialize)]
pub(crate) enum Request {
    /// Build the model (first request, once); its bytes are the request's payload.
    Load { threads: u32 },
    /// Run it on one batch, whose observations are the payload (raw little-endian bytes of `dtype`,
    /// converted here: uint8 as it is for a uint8 input, else to float32).
    Run { shape: Vec<i64>, dtype: crate::ObservationType, uint8_input: bool },
}

/// One output tensor of a run.
#[derive(Debug, Serialize, Deserialize)]
pub(crate) struct Output {
    pub shape: Vec<i64>,
    pub values: Vec<f32>,
}

/// What the runtime answers; `peak_bytes` is its peak resident memory so far.
#[derive(Debug, Serialize, Deserialize)]
pub(crate) enum Reply {
    Loaded { outputs: u32, peak_bytes: u64 },
    Outputs(Vec<Output>),
    Failed { message: String, peak_bytes: u64 },
}

/// The largest request the runtime reads (a model is at most acting.max_model_bytes, checked by
/// the server before it starts this process).
const MAX_REQUEST_BYTES: usize = 1 << 30;

pub(crate) fn write_message(out: &mut impl Write, message: &impl Serialize) -> io::Result<()> {
    let body = postcard::to_allocvec(message).map_err(|error| io::Error::new(io::ErrorKind::InvalidData, error.to_string()))?;
    let length = u32::try_from(body.len()).map_err(|_| io::Error::new(io::ErrorKind::InvalidData, "a message over 4 GiB"))?;
    out.write_all(&length.to_le_bytes())?;
    out.write_all(&body)?;
    out.flush()
}

/// One frame (a little-endian u32 length, then the bytes) into `body`; false at the end of input.
fn read_frame(input: &mut impl Read, body: &mut Vec<u8>) -> io::Result<bool> {
    let mut header = [0u8; 4];
    match input.read_exact(&mut header) {
        Ok(()) => {}
        Err(error) if error.kind() == io::ErrorKind::UnexpectedEof => return Ok(false),
        Err(error) => return Err(error),
    }
    let length = u32::from_le_bytes(header) as usize;
    if length > MAX_REQUEST_BYTES {
        return Err(io::Error::new(io::ErrorKind::InvalidData, format!("a request of {length} bytes")));
    }
    body.resize(length, 0);
    input.read_exact(body)?;
    Ok(true)
}

fn read_request(input: &mut impl Read, body: &mut Vec<u8>) -> io::Result<Option<Request>> {
    if !read_frame(input, body)? {
        return Ok(None);
    }
    postcard::from_bytes(body).map(Some).map_err(|error| io::Error::new(io::ErrorKind::InvalidData, error.to_string()))
}

/// This process's peak resident memory (getrusage's ru_maxrss).
fn peak_bytes() -> u64 {
    // SAFETY: getrusage writes only the struct passed by pointer, which is zeroed and large enough.
    let usage = unsafe {
        let mut usage: libc::rusage = std::mem::zeroed();
        libc::getrusage(libc::RUSAGE_SELF, &mut usage);
        usage
    };
    (usage.ru_maxrss.max(0) as u64) * 1024
}

/// Step 1: the working directory becomes an empty directory that no longer exists.
fn leave_the_filesystem() -> Result<(), String> {
    let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0, |since| since.as_nanos());
    let empty = std::env::temp_dir().join(format!("radserve-policy-{}-{stamp}", std::process::id()));
    std::fs::create_dir(&empty).map_err(|error| format!("creating {}: {error}", empty.display()))?;
    std::env::set_current_dir(&empty).map_err(|error| format!("entering {}: {error}", empty.display()))?;
    std::fs::remove_dir(&empty).map_err(|error| format!("removing {}: {error}", empty.display()))
}

/// Step 3: RLIMIT_DATA, soft and hard (the hard limit cannot be raised again).
fn limit_memory(bytes: u64) -> Result<(), String> {
    let limit = libc::rlimit { rlim_cur: bytes as libc::rlim_t, rlim_max: bytes as libc::rlim_t };
    // SAFETY: setrlimit reads only the struct passed by pointer.
    if unsafe { libc::setrlimit(libc::RLIMIT_DATA, &limit) } != 0 {
        return Err(format!("setting RLIMIT_DATA to {bytes}: {}", io::Error::last_os_error()));
    }
    Ok(())
}

/// Step 4: the seccomp filter (seccompiler, the rust-vmm project's, as Firecracker uses it). A
/// matched call fails with EACCES rather than killing the process, so ONNX Runtime reports it.
fn forbid_files() -> Result<(), String> {
    use seccompiler::{SeccompAction, SeccompCmpArgLen, SeccompCmpOp, SeccompCondition, SeccompFilter, SeccompRule};
    let always: Vec<i64> = vec![
        libc::SYS_open,
        libc::SYS_openat,
        libc::SYS_openat2,
        libc::SYS_creat,
        libc::SYS_open_by_handle_at,
        libc::SYS_name_to_handle_at,
        libc::SYS_execve,
        libc::SYS_execveat,
        libc::SYS_stat,
        libc::SYS_lstat,
        libc::SYS_access,
        libc::SYS_faccessat,
        libc::SYS_faccessat2,
        libc::SYS_readlink,
        libc::SYS_readlinkat,
        libc::SYS_statfs,
        libc::SYS_truncate,
        libc::SYS_mknod,
        libc::SYS_mknodat,
        libc::SYS_mkdir,
        libc::SYS_mkdirat,
        libc::SYS_rmdir,
        libc::SYS_link,
        libc::SYS_linkat,
        libc::SYS_symlink,
        libc::SYS_symlinkat,
        libc::SYS_unlink,
        libc::SYS_unlinkat,
        libc::SYS_rename,
        libc::SYS_renameat,
        libc::SYS_renameat2,
        libc::SYS_chmod,
        libc::SYS_fchmodat,
        libc::SYS_chown,
        libc::SYS_lchown,
        libc::SYS_fchownat,
        libc::SYS_chdir,
        libc::SYS_chroot,
        libc::SYS_mount,
        libc::SYS_socket,
        libc::SYS_socketpair,
        libc::SYS_ptrace,
        libc::SYS_process_vm_readv,
        libc::SYS_process_vm_writev,
        libc::SYS_kill,
    ];
    let mut rules: std::collections::BTreeMap<i64, Vec<SeccompRule>> = always.into_iter().map(|call| (call, Vec::new())).collect();
    let error = |error: seccompiler::BackendError| error.to_string();
    // fstat is newfstatat(fd, "", AT_EMPTY_PATH) in glibc: only calls that name a path are refused.
    let by_path = |flags_arg: u8| -> Result<Vec<SeccompRule>, String> {
        let condition = SeccompCondition::new(flags_arg, SeccompCmpArgLen::Dword, SeccompCmpOp::MaskedEq(libc::AT_EMPTY_PATH as u64), 0).map_err(error)?;
        Ok(vec![SeccompRule::new(vec![condition]).map_err(error)?])
    };
    rules.insert(libc::SYS_newfstatat, by_path(3)?);
    rules.insert(libc::SYS_statx, by_path(2)?);
    // Signals only to this process (abort() raises SIGABRT with tgkill on itself).
    let pid = u64::from(std::process::id());
    let other = SeccompCondition::new(0, SeccompCmpArgLen::Dword, SeccompCmpOp::Ne, pid).map_err(error)?;
    rules.insert(libc::SYS_tgkill, vec![SeccompRule::new(vec![other]).map_err(error)?]);
    let arch = std::env::consts::ARCH.try_into().map_err(|error: seccompiler::BackendError| error.to_string())?;
    let filter = SeccompFilter::new(rules, SeccompAction::Allow, SeccompAction::Errno(libc::EACCES as u32), arch).map_err(error)?;
    let program: seccompiler::BpfProgram = filter.try_into().map_err(error)?;
    seccompiler::apply_filter_all_threads(&program).map_err(|error| format!("installing the seccomp filter: {error}"))
}

fn build(environment: &ort::environment::Environment, model: &[u8], threads: u32) -> Result<Session, String> {
    let text = |error: ort::Error| error.to_string();
    let builder = |error: ort::Error<ort::session::builder::SessionBuilder>| error.to_string();
    Session::builder(environment)
        .map_err(text)?
        .with_intra_threads(threads.max(1) as usize)
        .map_err(builder)?
        .with_inter_threads(1)
        .map_err(builder)?
        .with_intra_op_spinning(false)
        .map_err(builder)?
        .with_optimization_level(GraphOptimizationLevel::Level3)
        .map_err(builder)?
        .commit_from_memory(model)
        .map_err(text)
}

fn run(session: &mut Session, shape: Vec<i64>, dtype: crate::ObservationType, uint8_input: bool, data: &[u8]) -> Result<Vec<Output>, String> {
    let text = |error: ort::Error| error.to_string();
    let outputs = if uint8_input {
        session.run(ort::inputs![Tensor::from_array((shape, data.to_vec())).map_err(text)?]).map_err(text)?
    } else {
        session.run(ort::inputs![Tensor::from_array((shape, dtype.to_f32(data))).map_err(text)?]).map_err(text)?
    };
    let mut answers = Vec::with_capacity(outputs.len());
    for index in 0..outputs.len() {
        let (shape, values) = outputs[index].try_extract_tensor::<f32>().map_err(text)?;
        answers.push(Output { shape: shape.to_vec(), values: values.to_vec() });
    }
    Ok(answers)
}

/// The steps of containment `serve` takes: all of them in the server (`radserve policy-runtime`);
/// the tests leave one out at a time to show that each alone keeps a file unread.
#[derive(Clone, Copy, Debug)]
pub struct Containment {
    pub leave_the_filesystem: bool,
    pub forbid_files: bool,
}

impl Containment {
    pub const FULL: Containment = Containment { leave_the_filesystem: true, forbid_files: true };
}

/// The runtime's main: contained as the module says, then one model loaded and run on request until
/// stdin closes. Errors before the first request end the process (the server reports the message it
/// wrote to stderr); errors of a request are answered.
pub fn serve(library: &Path, memory_bytes: u64, containment: Containment) -> Result<(), String> {
    if containment.leave_the_filesystem {
        leave_the_filesystem()?;
    }
    let environment = ort::init_from(library)
        .map_err(|error| format!("loading {}: {error}", library.display()))?
        .with_name("radserve-policy")
        .build()
        .map_err(|error| format!("starting ONNX Runtime: {error}"))?;
    limit_memory(memory_bytes)?;
    if containment.forbid_files {
        forbid_files()?;
    }
    let (mut input, mut output) = (io::stdin().lock(), io::stdout().lock());
    let mut session: Option<Session> = None;
    let (mut body, mut payload) = (Vec::new(), Vec::new());
    while let Some(request) = read_request(&mut input, &mut body).map_err(|error| format!("reading a request: {error}"))? {
        if !read_frame(&mut input, &mut payload).map_err(|error| format!("reading a request's payload: {error}"))? {
            return Err("the input ended before a request's payload".into());
        }
        let reply = match (request, &mut session) {
            // The model's bytes are released once it is built.
            (Request::Load { threads }, None) => match build(&environment, &std::mem::take(&mut payload), threads) {
                Ok(built) => {
                    let outputs = built.outputs().len() as u32;
                    session = Some(built);
                    Reply::Loaded { outputs, peak_bytes: peak_bytes() }
                }
                Err(message) => Reply::Failed { message, peak_bytes: peak_bytes() },
            },
            (Request::Load { .. }, Some(_)) => Reply::Failed { message: "a model is already loaded".into(), peak_bytes: peak_bytes() },
            (Request::Run { .. }, None) => Reply::Failed { message: "no model is loaded".into(), peak_bytes: peak_bytes() },
            (Request::Run { shape, dtype, uint8_input }, Some(session)) => match run(session, shape, dtype, uint8_input, &payload) {
                Ok(outputs) => Reply::Outputs(outputs),
                Err(message) => Reply::Failed { message, peak_bytes: peak_bytes() },
            },
        };
        write_message(&mut output, &reply).map_err(|error| format!("answering: {error}"))?;
    }
    Ok(())
}

/// `serve` from a command line `--library PATH --memory-bytes N`, for this crate's test binary,
/// which also takes `--chdir DIR` (start there) and, to show what each step of containment does
/// alone, `--keep-working-directory` and `--allow-files`. The server's own subcommand has none of
/// these: it always contains fully.
pub fn main_from_args(args: impl Iterator<Item = String>) -> std::process::ExitCode {
    let args: Vec<String> = args.collect();
    let value = |name: &str| args.iter().position(|arg| arg == name).and_then(|at| args.get(at + 1)).cloned();
    let (Some(library), Some(memory)) = (value("--library"), value("--memory-bytes").and_then(|text| text.parse().ok())) else {
        eprintln!("usage: radserve-policy-runtime [--chdir DIR] [--keep-working-directory] [--allow-files] --library PATH --memory-bytes N");
        return std::process::ExitCode::from(2);
    };
    if let Some(dir) = value("--chdir") {
        if let Err(error) = std::env::set_current_dir(&dir) {
            eprintln!("radserve policy runtime: entering {dir}: {error}");
            return std::process::ExitCode::FAILURE;
        }
    }
    let containment = Containment {
        leave_the_filesystem: !args.iter().any(|arg| arg == "--keep-working-directory"),
        forbid_files: !args.iter().any(|arg| arg == "--allow-files"),
    };
    main(Path::new(&library), memory, containment)
}

/// `serve` as a process's main (the server's `radserve policy-runtime` and the test binary): its
/// error on standard error and exit code 1, which the server reads as a runtime that could not start.
pub fn main(library: &Path, memory_bytes: u64, containment: Containment) -> std::process::ExitCode {
    match serve(library, memory_bytes, containment) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("radserve policy runtime: {message}");
            std::process::ExitCode::FAILURE
        }
    }
}
