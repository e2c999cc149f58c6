//! Conversions between proto messages and core types.

use std::collections::HashMap;

use radserve_sim::{CatalogEntry, DType, EpisodeEnd, OptionValue, Options, SessionInfo, Space, StepOutcome};
use tonic::Status;

use crate::proto;

pub fn dtype_to_proto(dtype: DType) -> proto::DType {
    match dtype {
        DType::Uint8 => proto::DType::DtypeUint8,
        DType::Int32 => proto::DType::DtypeInt32,
        DType::Int64 => proto::DType::DtypeInt64,
        DType::Float32 => proto::DType::DtypeFloat32,
        DType::Float64 => proto::DType::DtypeFloat64,
        DType::Bool => proto::DType::DtypeBool,
    }
}

pub fn dtype_from_proto(raw: i32) -> Result<DType, Status> {
    match proto::DType::try_from(raw) {
        Ok(proto::DType::DtypeUint8) => Ok(DType::Uint8),
        Ok(proto::DType::DtypeInt32) => Ok(DType::Int32),
        Ok(proto::DType::DtypeInt64) => Ok(DType::Int64),
        Ok(proto::DType::DtypeFloat32) => Ok(DType::Float32),
        Ok(proto::DType::DtypeFloat64) => Ok(DType::Float64),
        Ok(proto::DType::DtypeBool) => Ok(DType::Bool),
        Ok(proto::DType::DtypeUnspecified) | Err(_) => {
            Err(Status::invalid_argument(format!("tensor dtype {raw} is not one of the DType values")))
        }
    }
}

pub fn space_to_proto(space: &Space) -> proto::Space {
    let kind = match space {
        Space::Box { dtype, shape, low, high } => proto::space::Kind::Box(proto::BoxSpace {
            dtype: dtype_to_proto(*dtype) as i32,
            shape: shape.iter().map(|&d| d as i64).collect(),
            low: low.clone(),
            high: high.clone(),
        }),
        Space::Discrete { n } => proto::space::Kind::Discrete(proto::DiscreteSpace { n: *n }),
    };
    proto::Space { kind: Some(kind) }
}

pub fn option_to_proto(value: &OptionValue) -> proto::OptionValue {
    use proto::option_value::Value;
    let value = match value {
        OptionValue::Bool(v) => Value::BoolValue(*v),
        OptionValue::Int(v) => Value::IntValue(*v),
        OptionValue::Float(v) => Value::FloatValue(*v),
        OptionValue::Str(v) => Value::StringValue(v.clone()),
    };
    proto::OptionValue { value: Some(value) }
}

pub fn options_to_proto(options: &Options) -> HashMap<String, proto::OptionValue> {
    options.iter().map(|(name, value)| (name.clone(), option_to_proto(value))).collect()
}

pub fn options_from_proto(options: &HashMap<String, proto::OptionValue>) -> Result<Options, Status> {
    use proto::option_value::Value;
    options
        .iter()
        .map(|(name, value)| {
            let value = match &value.value {
                Some(Value::BoolValue(v)) => OptionValue::Bool(*v),
                Some(Value::IntValue(v)) => OptionValue::Int(*v),
                Some(Value::FloatValue(v)) => OptionValue::Float(*v),
                Some(Value::StringValue(v)) => OptionValue::Str(v.clone()),
                None => return Err(Status::invalid_argument(format!("option '{name}' has no value"))),
            };
            Ok((name.clone(), value))
        })
        .collect()
}

pub fn catalog_entry_to_proto(entry: &CatalogEntry) -> proto::EnvInfo {
    let (observation_space, action_space) = match &entry.spaces {
        Ok((observation, action)) => (Some(space_to_proto(observation)), Some(space_to_proto(action))),
        Err(_) => (None, None),
    };
    proto::EnvInfo {
        id: entry.id.full(),
        family: entry.id.family.prefix().to_string(),
        observation_space,
        action_space,
        default_options: options_to_proto(&entry.default_options),
    }
}

pub fn session_info_to_proto(info: &SessionInfo) -> proto::SessionInfo {
    proto::SessionInfo {
        session_id: info.session_id.clone(),
        env_id: info.env_id.clone(),
        num_envs: info.num_envs as u32,
        seed: info.seed,
        options: options_to_proto(&info.options),
        observation_space: Some(space_to_proto(&info.observation_space)),
        action_space: Some(space_to_proto(&info.action_space)),
        frame_stack: info.frame_stack as u32,
        autoreset_mode: "same-step".to_string(),
        total_env_steps: info.total_env_steps,
        episodes_completed: info.episodes_completed,
    }
}

pub fn tensor(dtype: DType, shape: Vec<usize>, data: Vec<u8>) -> proto::Tensor {
    proto::Tensor {
        dtype: dtype_to_proto(dtype) as i32,
        shape: shape.into_iter().map(|d| d as i64).collect(),
        data: data.into(),
    }
}

/// The batched observation tensor of a session: [rows, *observation shape].
pub fn observation_tensor(space: &Space, rows: usize, data: Vec<u8>) -> proto::Tensor {
    let mut shape = vec![rows];
    shape.extend_from_slice(space.shape());
    tensor(space.dtype(), shape, data)
}

/// Reads a request tensor's dtype and shape; the core checks them against the session's spec.
pub fn tensor_header(tensor: Option<&proto::Tensor>, what: &str) -> Result<(DType, Vec<usize>), Status> {
    let tensor = tensor.ok_or_else(|| Status::invalid_argument(format!("{what} tensor is missing")))?;
    let dtype = dtype_from_proto(tensor.dtype)?;
    let shape = tensor
        .shape
        .iter()
        .map(|&d| usize::try_from(d).map_err(|_| Status::invalid_argument(format!("{what} shape has a negative dimension {d}"))))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((dtype, shape))
}

pub fn step_to_proto(space: &Space, outcome: StepOutcome) -> proto::StepResponse {
    let num_envs = outcome.rewards.len();
    let rewards: Vec<u8> = outcome.rewards.iter().flat_map(|r| r.to_le_bytes()).collect();
    proto::StepResponse {
        obs: Some(observation_tensor(space, num_envs, outcome.obs)),
        reward: Some(tensor(DType::Float64, vec![num_envs], rewards)),
        terminated: outcome.terminated,
        truncated: outcome.truncated,
        final_obs: Some(observation_tensor(space, outcome.episodes.len(), outcome.final_obs)),
        episodes: outcome.episodes.iter().map(episode_to_proto).collect(),
    }
}

fn episode_to_proto(episode: &EpisodeEnd) -> proto::EpisodeEnd {
    proto::EpisodeEnd {
        env_index: episode.env_index as u32,
        episode_return: episode.episode_return,
        episode_length: episode.episode_length,
        terminated: episode.terminated,
        truncated: episode.truncated,
        error: episode.error.clone().unwrap_or_default(),
    }
}
