//! The worker process: one embedded CPython interpreter that owns a set of environment groups on its
//! main thread for its whole life, and answers the server's requests one at a time.
//!
//! Measured on a 2-core host, two threads stepping dm_control in one interpreter are slower than one,
//! while two processes are about twice as fast; hence processes, each holding the GIL across a whole
//! group step.

use std::collections::HashMap;
use std::ffi::CString;
use std::fs::File;
use std::io::{self, BufReader, BufWriter};
use std::mem::MaybeUninit;
use std::os::fd::FromRawFd;
use std::os::unix::ffi::OsStrExt;
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};

use pyo3::exceptions::PyValueError;
use pyo3::ffi;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict};
use serde::{Deserialize, Serialize};

use radserve_core::{DType, EnvNames, Family, InfoColumn, InfoKind, Infos, OptionValue, Options, Space};
use radserve_shm::MemFile;

use crate::protocol::{self, EnvSpec, GroupConfig, Request, Response, StepResult};

/// The worker's Python package (server/sim/python/radserve_worker/), embedded in the binary: its
/// modules in the order they import each other, the package first and the entry points last.
const ADAPTERS: [(&str, &str); 8] = [
    ("radserve_worker", include_str!("../python/radserve_worker/__init__.py")),
    ("radserve_worker.common", include_str!("../python/radserve_worker/common.py")),
    ("radserve_worker.group", include_str!("../python/radserve_worker/group.py")),
    ("radserve_worker.dmc", include_str!("../python/radserve_worker/dmc.py")),
    ("radserve_worker.gymnasium_tasks", include_str!("../python/radserve_worker/gymnasium_tasks.py")),
    ("radserve_worker.procgen_games", include_str!("../python/radserve_worker/procgen_games.py")),
    ("radserve_worker.envpool_engine", include_str!("../python/radserve_worker/envpool_engine.py")),
    ("radserve_worker.adapters", include_str!("../python/radserve_worker/adapters.py")),
];

/// Which OpenGL platform MuJoCo renders with. EGL is the default; OSMesa is pure software.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum GlBackend {
    #[default]
    Egl,
    Osmesa,
}

impl GlBackend {
    pub fn name(self) -> &'static str {
        match self {
            GlBackend::Egl => "egl",
            GlBackend::Osmesa => "osmesa",
        }
    }

    pub fn parse(text: &str) -> Option<GlBackend> {
        match text {
            "egl" => Some(GlBackend::Egl),
            "osmesa" => Some(GlBackend::Osmesa),
            _ => None,
        }
    }
}

/// Why a worker process could not start or had to stop (main.rs prints it; the server sees the
/// worker exit and replaces it).
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// A system call the worker's set-up or its protocol needs.
    #[error("{what}: {source}")]
    Io { what: &'static str, source: io::Error },
    #[error("no Python interpreter at {0}; run `make setup` or point sim.venv at a virtualenv")]
    NoInterpreter(PathBuf),
    /// CPython refused to start (`what` was being done), or the adapters failed to load.
    #[error("{what}: {detail}")]
    Python { what: &'static str, detail: String },
}

fn io_error(what: &'static str) -> impl FnOnce(io::Error) -> WorkerError {
    move |source| WorkerError::Io { what, source }
}

pub struct WorkerArgs {
    /// The virtualenv whose interpreter and packages the worker uses.
    pub venv: PathBuf,
    pub gl: GlBackend,
}

/// Runs a worker until the server closes its end of the protocol stream.
pub fn run_worker(args: &WorkerArgs) -> Result<(), WorkerError> {
    let (mut input, mut output) = take_protocol_streams().map_err(io_error("protocol streams"))?;
    // SAFETY: the server starts every worker with its descriptor socket at this fd (pool.rs), and
    // nothing else in this process owns it.
    let fds = unsafe { UnixStream::from_raw_fd(crate::pool::WORKER_FD_SOCKET) };
    // The frames of the sessions hosted here reach only this process and the server's.
    radserve_shm::make_undumpable().map_err(io_error("making the worker non-dumpable"))?;
    // MuJoCo may write MUJOCO_LOG.TXT into the working directory; keep it out of the user's.
    let workdir = std::env::temp_dir().join(format!("radserve-worker-{}", std::process::id()));
    if std::fs::create_dir_all(&workdir).is_ok() {
        let _ = std::env::set_current_dir(&workdir);
    }
    std::env::set_var("MUJOCO_GL", args.gl.name());
    std::env::set_var("PYOPENGL_PLATFORM", args.gl.name());
    std::env::set_var("TF_CPP_MIN_LOG_LEVEL", "3");
    init_python(&args.venv)?;
    // The interpreter is never finalized: simulators' native threads and GL contexts do not survive it.
    let result = Python::attach(|py| serve(py, &mut input, &mut output, &fds));
    let _ = std::fs::remove_dir_all(&workdir);
    result
}

/// Keeps the protocol on private descriptors and points fd 1 at stderr, so that anything a simulator
/// prints cannot corrupt the protocol stream.
fn take_protocol_streams() -> io::Result<(BufReader<File>, BufWriter<File>)> {
    // SAFETY: fds 0, 1 and 2 are open in a process the server spawned with pipes; `dup` returns fresh
    // descriptors that the `File`s below own exclusively.
    unsafe {
        let input = libc::dup(0);
        let output = libc::dup(1);
        if input < 0 || output < 0 || libc::dup2(2, 1) < 0 {
            return Err(io::Error::last_os_error());
        }
        let null = libc::open(c"/dev/null".as_ptr(), libc::O_RDONLY);
        if null >= 0 {
            libc::dup2(null, 0);
            libc::close(null);
        }
        Ok((BufReader::new(File::from_raw_fd(input)), BufWriter::new(File::from_raw_fd(output))))
    }
}

/// Starts CPython as if it were the virtualenv's own `bin/python`, so that `pyvenv.cfg` is honoured:
/// the venv's site-packages are on the path and the base installation's are not.
fn init_python(venv: &Path) -> Result<(), WorkerError> {
    let executable = venv.join("bin").join("python");
    if !executable.exists() {
        return Err(WorkerError::NoInterpreter(executable));
    }
    let executable = CString::new(executable.as_os_str().as_bytes())
        .map_err(|err| WorkerError::Python { what: "the interpreter's path", detail: err.to_string() })?;
    // SAFETY: PyConfig is initialised by PyConfig_InitPythonConfig before any field is touched, cleared
    // exactly once, and the interpreter is initialised once from this (only) thread.
    unsafe {
        let mut config = MaybeUninit::<ffi::PyConfig>::uninit();
        ffi::PyConfig_InitPythonConfig(config.as_mut_ptr());
        let config = config.as_mut_ptr();
        (*config).install_signal_handlers = 0;
        (*config).parse_argv = 0;
        let status = ffi::PyConfig_SetBytesString(config, &raw mut (*config).executable, executable.as_ptr());
        if ffi::PyStatus_Exception(status) != 0 {
            ffi::PyConfig_Clear(config);
            return Err(status_message("setting the interpreter path", &status));
        }
        let status = ffi::Py_InitializeFromConfig(config);
        ffi::PyConfig_Clear(config);
        if ffi::PyStatus_Exception(status) != 0 {
            return Err(status_message("starting Python", &status));
        }
        // Hand the GIL back; `Python::attach` takes it for the worker loop.
        ffi::PyEval_SaveThread();
    }
    Ok(())
}

fn status_message(what: &'static str, status: &ffi::PyStatus) -> WorkerError {
    let detail = if status.err_msg.is_null() {
        "unknown error".to_string()
    } else {
        // SAFETY: a non-null err_msg is a static C string set by CPython.
        unsafe { std::ffi::CStr::from_ptr(status.err_msg) }.to_string_lossy().into_owned()
    };
    WorkerError::Python { what, detail }
}

/// An info column as `radserve_worker.common.info_columns` writes it: path, kind, dtype, shape, envs,
/// data, texts.
type ColumnTuple<'py> = (Vec<String>, String, String, Vec<u32>, Vec<u32>, Bound<'py, PyBytes>, Vec<String>);

/// What a group's `step` returns: rewards, terminated, truncated, errors (env, message), and the
/// step's and the resets' infos as columns.
type GroupStepTuple<'py> = (Vec<f64>, Vec<bool>, Vec<bool>, Vec<(u32, String)>, Vec<ColumnTuple<'py>>, Vec<ColumnTuple<'py>>);

/// Info columns as the worker's Python wrote them; the server checks them against the group
/// (`Infos::check`) before it takes anything from them.
fn extract_infos(columns: Vec<ColumnTuple<'_>>) -> PyResult<Infos> {
    let columns = columns
        .into_iter()
        .map(|(path, kind, dtype, shape, envs, data, texts)| {
            let kind = match kind.as_str() {
                "python" => InfoKind::Python,
                "scalar" => InfoKind::Scalar,
                "array" => InfoKind::Array,
                "text" => InfoKind::Text,
                "json" => InfoKind::Json,
                other => return Err(PyValueError::new_err(format!("unknown info column kind {other:?}"))),
            };
            let dtype = match kind.numeric() {
                true => DType::from_name(&dtype).ok_or_else(|| PyValueError::new_err(format!("unsupported info dtype {dtype:?}")))?,
                false => DType::Uint8,
            };
            Ok(InfoColumn { path, kind, envs, dtype, shape, data: data.as_bytes().to_vec(), texts })
        })
        .collect::<PyResult<Vec<_>>>()?;
    Ok(Infos { columns })
}

struct HostedGroup {
    object: Py<PyAny>,
    /// The memoryview over `frames` handed to Python; released before `frames` is unmapped.
    view: Option<Py<PyAny>>,
    frames: Option<MemFile>,
}

/// Loads the embedded package module by module (each goes into `sys.modules` as it loads, so the
/// later ones import the earlier ones as from files) and returns its entry points, `adapters`.
fn load_adapters(py: Python<'_>) -> PyResult<Bound<'_, PyModule>> {
    let mut package: Option<Bound<'_, PyModule>> = None;
    let mut module = None;
    for (name, source) in ADAPTERS {
        let file = match name.split_once('.') {
            Some((_, leaf)) => format!("radserve_worker/{leaf}.py"),
            None => "radserve_worker/__init__.py".to_string(),
        };
        let cstring = |text: &str| CString::new(text).map_err(|err| PyValueError::new_err(err.to_string()));
        let loaded = PyModule::from_code(py, &cstring(source)?, &cstring(&file)?, &cstring(name)?)?;
        match &package {
            // A package: its modules are found as its attributes.
            None => {
                loaded.setattr("__path__", pyo3::types::PyList::empty(py))?;
                package = Some(loaded.clone());
            }
            Some(package) => package.setattr(name.rsplit('.').next().unwrap_or(name), &loaded)?,
        }
        if name == "radserve_worker.common" {
            // The native frame copy replaces the numpy fallback of the same name.
            loaded.add_function(pyo3::wrap_pyfunction!(crate::pixels::hwc_to_chw, &loaded)?)?;
        }
        module = Some(loaded);
    }
    module.ok_or_else(|| PyValueError::new_err("the worker's package has no modules"))
}

fn serve(
    py: Python<'_>,
    input: &mut BufReader<File>,
    output: &mut BufWriter<File>,
    fds: &UnixStream,
) -> Result<(), WorkerError> {
    let python = |what| move |err: PyErr| WorkerError::Python { what, detail: err.to_string() };
    let module = load_adapters(py).map_err(python("loading the environment adapters"))?;
    module.call_method0("configure").map_err(python("configuring the adapters"))?;
    let mut groups: HashMap<u64, HostedGroup> = HashMap::new();
    loop {
        let request: Request = match protocol::read_blocking(input) {
            Ok(Some(request)) => request,
            Ok(None) => return Ok(()),
            Err(err) => return Err(WorkerError::Io { what: "reading a request", source: err }),
        };
        let response = handle(py, &module, &mut groups, fds, request).unwrap_or_else(|err| Response::Failed(err.to_string()));
        protocol::write_blocking(output, &response).map_err(io_error("writing a response"))?;
    }
}

fn handle(
    py: Python<'_>,
    module: &Bound<'_, PyModule>,
    groups: &mut HashMap<u64, HostedGroup>,
    fds: &UnixStream,
    request: Request,
) -> PyResult<Response> {
    match request {
        Request::ListNames => {
            let names: HashMap<String, Vec<String>> = module.call_method0("list_names")?.extract()?;
            let mut env_names = EnvNames::default();
            for family in Family::ALL {
                let listed = names.get(family.prefix()).cloned().unwrap_or_default();
                env_names.by_family.insert(family, listed);
            }
            Ok(Response::Names(env_names))
        }
        Request::Specs { entries } => {
            let specs = entries
                .iter()
                .map(|(family, name, options)| {
                    let spec = module.call_method1("spec", (family.prefix(), name, options_dict(py, options)?))?;
                    extract_spec(&spec)
                })
                .map(|result| result.map_err(|err| err.to_string()))
                .collect();
            Ok(Response::Specs(specs))
        }
        Request::CreateGroup(GroupConfig { group, family, name, options, seeds }) => {
            if let Some(previous) = groups.remove(&group) {
                close_group(py, previous);
            }
            let object = module.getattr("make_group")?.call1((family.prefix(), name, options_dict(py, &options)?, seeds))?;
            let spec = extract_spec(&object.call_method0("spec")?)?;
            groups.insert(group, HostedGroup { object: object.unbind(), view: None, frames: None });
            Ok(Response::Created(spec))
        }
        Request::Attach { group, shm_len, .. } => {
            // The descriptor was sent just before the request: take it first, whatever follows.
            let received = radserve_shm::receive_fd(fds);
            let hosted = hosted_group(groups, group)?;
            let fd = match received {
                Ok((_, Some(fd))) => fd,
                Ok((_, None)) => return Err(PyValueError::new_err("the server sent no frame memory with Attach")),
                Err(err) => return Err(PyValueError::new_err(format!("receiving the frame memory: {err}"))),
            };
            let mut frames =
                MemFile::from_fd(fd).map_err(|err| PyValueError::new_err(format!("mapping the frame memory: {err}")))?;
            if frames.len() < shm_len {
                return Err(PyValueError::new_err(format!("shared memory holds {} bytes, expected {shm_len}", frames.len())));
            }
            // SAFETY: the mapping lives in `hosted.frames` for as long as the view exists; `close_group`
            // releases the view before dropping the mapping.
            let view = unsafe {
                let pointer = ffi::PyMemoryView_FromMemory(
                    frames.as_mut_ptr().cast(),
                    shm_len as ffi::Py_ssize_t,
                    ffi::PyBUF_WRITE,
                );
                Bound::from_owned_ptr_or_err(py, pointer)?
            };
            hosted.object.bind(py).call_method1("attach", (&view,))?;
            hosted.view = Some(view.unbind());
            hosted.frames = Some(frames);
            Ok(Response::Attached)
        }
        Request::Reset { group, seeds, mask } => {
            let infos = hosted_group(groups, group)?.object.bind(py).call_method1("reset", (seeds, mask))?;
            Ok(Response::Reset(extract_infos(infos.extract()?)?))
        }
        Request::Step { group, actions, skip } => {
            let hosted = hosted_group(groups, group)?;
            let outcome = hosted.object.bind(py).call_method1("step", (PyBytes::new(py, &actions), skip))?;
            let (rewards, terminated, truncated, errors, step_infos, reset_infos): GroupStepTuple = outcome.extract()?;
            let (step_infos, reset_infos) = (extract_infos(step_infos)?, extract_infos(reset_infos)?);
            Ok(Response::Stepped(StepResult { rewards, terminated, truncated, errors, step_infos, reset_infos }))
        }
        Request::AsyncReset { group, seeds } => {
            hosted_group(groups, group)?.object.bind(py).call_method1("async_reset", (seeds,))?;
            Ok(Response::Sent)
        }
        Request::Send { group, actions, sent } => {
            send_to_group(py, hosted_group(groups, group)?, &actions, &sent)?;
            Ok(Response::Sent)
        }
        Request::Recv { group } => recv_from_group(py, hosted_group(groups, group)?),
        Request::SendRecv { group, actions, sent } => {
            let hosted = hosted_group(groups, group)?;
            send_to_group(py, hosted, &actions, &sent)?;
            recv_from_group(py, hosted)
        }
        Request::CloseGroup { group } => {
            if let Some(hosted) = groups.remove(&group) {
                close_group(py, hosted);
            }
            Ok(Response::Closed)
        }
    }
}

fn hosted_group(groups: &mut HashMap<u64, HostedGroup>, group: u64) -> PyResult<&mut HostedGroup> {
    groups.get_mut(&group).ok_or_else(|| PyValueError::new_err(format!("no group {group} in this worker")))
}

/// Hands the envs `sent` marks their rows of `actions` (every env's row) through the group's `send`,
/// which takes the sent envs' ids and their actions in that order.
fn send_to_group(py: Python<'_>, hosted: &HostedGroup, actions: &[u8], sent: &[bool]) -> PyResult<()> {
    let row = actions.len().checked_div(sent.len()).filter(|row| row * sent.len() == actions.len());
    let row = row.ok_or_else(|| PyValueError::new_err(format!("{} action bytes for {} envs", actions.len(), sent.len())))?;
    let ids: Vec<u32> = (0..sent.len()).filter(|&env| sent[env]).map(|env| env as u32).collect();
    let rows: Vec<u8> = ids.iter().flat_map(|&env| &actions[env as usize * row..][..row]).copied().collect();
    hosted.object.bind(py).call_method1("send", (PyBytes::new(py, &rows), ids))?;
    Ok(())
}

/// The group's `recv`, laid out per env of the group (zero for the envs not ready).
fn recv_from_group(py: Python<'_>, hosted: &HostedGroup) -> PyResult<Response> {
    let n = hosted.object.bind(py).getattr("n")?.extract::<usize>()?;
    let outcome = hosted.object.bind(py).call_method0("recv")?;
    let list = |index: usize| outcome.get_item(index)?.call_method0("tolist");
    let ids: Vec<usize> = list(0)?.extract()?;
    let (rewards, terminated, truncated): (Vec<f64>, Vec<bool>, Vec<bool>) =
        (list(1)?.extract()?, list(2)?.extract()?, list(3)?.extract()?);
    let mut ready = vec![false; n];
    let mut result =
        StepResult { rewards: vec![0.0; n], terminated: vec![false; n], truncated: vec![false; n], ..StepResult::default() };
    for (j, &env) in ids.iter().enumerate() {
        if env >= n || j >= rewards.len().min(terminated.len()).min(truncated.len()) {
            return Err(PyValueError::new_err(format!("recv returned env {env} of a group of {n}")));
        }
        ready[env] = true;
        result.rewards[env] = rewards[j];
        result.terminated[env] = terminated[j];
        result.truncated[env] = truncated[j];
    }
    Ok(Response::Received { ready, result })
}

fn close_group(py: Python<'_>, hosted: HostedGroup) {
    let _ = hosted.object.bind(py).call_method0("close");
    drop(hosted.object);
    if let Some(view) = hosted.view {
        // A view that Python still exports (an array leaked somewhere) cannot be released; then the
        // mapping is leaked too rather than unmapped under Python's feet.
        if view.bind(py).call_method0("release").is_err() {
            std::mem::forget(hosted.frames);
        }
    }
}

fn options_dict<'py>(py: Python<'py>, options: &Options) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    for (name, value) in options {
        match value {
            OptionValue::Bool(value) => dict.set_item(name, value)?,
            OptionValue::Int(value) => dict.set_item(name, value)?,
            OptionValue::Float(value) => dict.set_item(name, value)?,
            OptionValue::Str(value) => dict.set_item(name, value)?,
        }
    }
    Ok(dict)
}

fn extract_spec(spec: &Bound<'_, PyAny>) -> PyResult<EnvSpec> {
    Ok(EnvSpec {
        observation: extract_space(&spec.get_item("observation")?)?,
        action: extract_space(&spec.get_item("action")?)?,
    })
}

fn extract_space(space: &Bound<'_, PyAny>) -> PyResult<Space> {
    let kind: String = space.get_item("kind")?.extract()?;
    match kind.as_str() {
        "box" => {
            let dtype_name: String = space.get_item("dtype")?.extract()?;
            let dtype = DType::from_name(&dtype_name)
                .ok_or_else(|| PyValueError::new_err(format!("unsupported dtype {dtype_name}")))?;
            Ok(Space::Box {
                dtype,
                shape: space.get_item("shape")?.extract()?,
                low: space.get_item("low")?.extract()?,
                high: space.get_item("high")?.extract()?,
            })
        }
        "discrete" => Ok(Space::Discrete { n: space.get_item("n")?.extract()? }),
        other => Err(PyValueError::new_err(format!("unknown space kind {other}"))),
    }
}
