//! The gRPC face of radserve. Handlers here only validate and convert messages, call the core
//! (`radserve_core`), and map its errors to statuses; no logic lives in the transport.

pub mod shared_stepping;
pub mod auth;
pub mod codec;
pub mod convert;
mod deadline;
pub mod dm_env_rpc;
pub mod error;
pub mod handoff;
pub mod handlers;
pub mod sample_streams;
pub mod streams;

pub mod proto {
    tonic::include_proto!("radserve.v1");

    /// The encoded descriptors of the proto files, for the reflection service.
    pub const FILE_DESCRIPTOR_SET: &[u8] = tonic::include_file_descriptor_set!("radserve_descriptor");
}

/// Other protocols served on the same port, at their packages' paths (their generated code refers
/// to each other by those paths).
pub mod pb {
    pub mod dm_env_rpc {
        pub mod v1 {
            tonic::include_proto!("dm_env_rpc.v1");
        }
    }
    pub mod google {
        pub mod rpc {
            tonic::include_proto!("google.rpc");
        }
    }
}

pub use dm_env_rpc::EnvironmentService;
pub use pb::dm_env_rpc::v1::environment_server::EnvironmentServer;
pub use handlers::RadServeService;
pub use streams::StreamStopper;
pub use proto::rad_serve_server::RadServeServer;

/// The server's release (the workspace's one version, Cargo.toml): ServerInfo, `--version` and
/// `radserve_build_info` all report it.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The gRPC API package the server implements.
pub const API: &str = "radserve.v1";

/// Largest message the server sends or accepts. A session's batched observations (64 dm_control
/// pixel stacks are ~6 MB) must fit.
pub const MAX_MESSAGE_BYTES: usize = 256 << 20;
