//! dm_env_rpc's tensors and specs as radserve's spaces and bytes: settings, actions, observations.

use std::collections::HashMap;

use radserve_core::actions::{validate_actions, MAX_SEED};
use radserve_core::bounds::{check_count, check_len, MAX_OPTION_TEXT_BYTES};
use radserve_core::{DType, OptionValue, Space};

use super::{bad, dm, TensorPayload, ACTION_NAME, ACTION_UID, MAX_ENTRIES, OBSERVATION_NAME, OBSERVATION_UID, REWARD_NAME, REWARD_UID};
use crate::error::Result;
use dm::tensor_spec::value::Payload as BoundPayload;

/// A setting's single value.
pub(super) fn setting(name: &str, tensor: &dm::Tensor) -> Result<OptionValue> {
    let clipped = radserve_core::bounds::clip(name);
    // The one element of a scalar tensor (shape [] or all ones).
    let only = |count: usize| {
        let elements: i64 = tensor.shape.iter().map(|&d| i64::from(d)).product();
        if count != 1 || elements != 1 {
            return Err(bad(format!("setting '{clipped}' must be a single value (a scalar tensor); it holds {count}")));
        }
        Ok(0)
    };
    Ok(match &tensor.payload {
        Some(TensorPayload::Strings(array)) => {
            let text = &array.array[only(array.array.len())?];
            check_len(&format!("setting '{clipped}'"), text, MAX_OPTION_TEXT_BYTES)?;
            OptionValue::Str(text.clone())
        }
        Some(TensorPayload::Bools(array)) => OptionValue::Bool(array.array[only(array.array.len())?]),
        Some(TensorPayload::Int32s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Int64s(array)) => OptionValue::Int(array.array[only(array.array.len())?]),
        Some(TensorPayload::Uint32s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Uint64s(array)) => OptionValue::Int(
            i64::try_from(array.array[only(array.array.len())?]).map_err(|_| bad(format!("setting '{clipped}' is too large")))?,
        ),
        Some(TensorPayload::Uint8s(array)) => OptionValue::Int(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Int8s(array)) => OptionValue::Int(i64::from(array.array[only(array.array.len())?] as i8)),
        Some(TensorPayload::Floats(array)) => OptionValue::Float(array.array[only(array.array.len())?].into()),
        Some(TensorPayload::Doubles(array)) => OptionValue::Float(array.array[only(array.array.len())?]),
        Some(TensorPayload::Protos(_)) | None => {
            return Err(bad(format!("setting '{clipped}' must hold a number, a bool or a string")));
        }
    })
}

/// An integer setting in `[0, max]`.
pub(super) fn non_negative(name: &str, value: &OptionValue, max: u64) -> Result<u64> {
    match value {
        OptionValue::Int(value) if *value >= 0 && (*value as u64) <= max => Ok(*value as u64),
        other @ (OptionValue::Bool(_) | OptionValue::Int(_) | OptionValue::Float(_) | OptionValue::Str(_)) => {
            Err(bad(format!("setting {name} must be an integer in [0, {max}], got {other:?}")))
        }
    }
}

/// The optional `seed` setting of Reset and ResetWorld; any other setting is refused.
pub(super) fn seed_setting(settings: &HashMap<String, dm::Tensor>, what: &str) -> Result<Option<u64>> {
    check_count(&format!("{what} settings"), settings.len(), MAX_ENTRIES)?;
    let mut seed = None;
    for (name, tensor) in settings {
        if name != "seed" {
            return Err(bad(format!(
                "unknown {what} setting '{}': the only one is seed (an integer)",
                radserve_core::bounds::clip(name)
            )));
        }
        seed = Some(non_negative("seed", &setting(name, tensor)?, MAX_SEED)?);
    }
    Ok(seed)
}

/// The element type of a tensor's payload as radserve's, its values as little-endian bytes and its
/// element count; None for payloads no radserve space holds.
fn payload_bytes(payload: &TensorPayload) -> Option<(DType, Vec<u8>, usize)> {
    fn bytes<T: Copy, const N: usize>(values: &[T], to: fn(T) -> [u8; N]) -> Vec<u8> {
        values.iter().flat_map(|&value| to(value)).collect()
    }
    Some(match payload {
        TensorPayload::Floats(array) => (DType::Float32, bytes(&array.array, f32::to_le_bytes), array.array.len()),
        TensorPayload::Doubles(array) => (DType::Float64, bytes(&array.array, f64::to_le_bytes), array.array.len()),
        TensorPayload::Int32s(array) => (DType::Int32, bytes(&array.array, i32::to_le_bytes), array.array.len()),
        TensorPayload::Int64s(array) => (DType::Int64, bytes(&array.array, i64::to_le_bytes), array.array.len()),
        TensorPayload::Uint8s(array) => (DType::Uint8, array.array.clone(), array.array.len()),
        TensorPayload::Bools(array) => (DType::Bool, array.array.iter().map(|&b| u8::from(b)).collect(), array.array.len()),
        TensorPayload::Int8s(_)
        | TensorPayload::Uint32s(_)
        | TensorPayload::Uint64s(_)
        | TensorPayload::Strings(_)
        | TensorPayload::Protos(_) => return None,
    })
}

fn data_type_name(dtype: DType) -> &'static str {
    match dtype {
        DType::Float32 => "FLOAT",
        DType::Float64 => "DOUBLE",
        DType::Int32 => "INT32",
        DType::Int64 => "INT64",
        DType::Uint8 => "UINT8",
        DType::Bool => "BOOL",
    }
}

/// The shape a tensor of `count` elements has: its own with a variable (negative) dimension
/// inferred, the way dm_env_rpc's `tensor_utils.unpack_tensor` reads it (at most one variable
/// dimension; a single element broadcasts to the whole shape; no shape and several elements: 1-D).
fn resolved_shape(shape: &[i32], count: usize) -> std::result::Result<Vec<usize>, String> {
    if shape.is_empty() {
        return Ok(if count == 1 { Vec::new() } else { vec![count] });
    }
    if shape.len() > 32 {
        return Err(format!("a shape of {} dimensions", shape.len()));
    }
    let variable: Vec<usize> = (0..shape.len()).filter(|&axis| shape[axis] < 0).collect();
    if variable.len() > 1 {
        return Err(format!("shape {shape:?} has {} variable dimensions; at most one may be negative", variable.len()));
    }
    let known: usize = shape.iter().filter(|&&dim| dim >= 0).map(|&dim| dim as usize).product();
    let mut resolved: Vec<usize> = shape.iter().map(|&dim| dim.max(0) as usize).collect();
    match variable.first() {
        Some(&axis) => {
            if known == 0 || !count.is_multiple_of(known) {
                return Err(format!("{count} elements do not fill shape {shape:?}"));
            }
            resolved[axis] = count / known;
        }
        None if count == known || count == 1 => {}
        None => return Err(format!("shape {shape:?} holds {known} elements but the payload has {count}")),
    }
    Ok(resolved)
}

/// The action of a Step request as one env's action bytes, checked against the world's action
/// space (its dtype exactly, its shape, its bounds: the core checks them again).
pub(super) fn action_bytes(actions: &HashMap<u64, dm::Tensor>, space: &Space) -> Result<Vec<u8>> {
    let expected = || format!("{} {ACTION_NAME} (uid {ACTION_UID}) {}", data_type_name(space.dtype()), space.describe());
    if let Some(uid) = actions.keys().find(|&&uid| uid != ACTION_UID) {
        return Err(bad(format!("no action has uid {uid}: this world's one action is {}", expected())));
    }
    let tensor = actions.get(&ACTION_UID).ok_or_else(|| bad(format!("the step has no action; it needs {}", expected())))?;
    let payload = tensor.payload.as_ref().ok_or_else(|| bad(format!("the action tensor is empty; it must be {}", expected())))?;
    let Some((dtype, data, count)) = payload_bytes(payload).filter(|(dtype, _, _)| *dtype == space.dtype()) else {
        return Err(bad(format!("the action's payload type does not match its spec: it must be {}", expected())));
    };
    let shape = resolved_shape(&tensor.shape, count).map_err(|problem| bad(format!("action: {problem}; it must be {}", expected())))?;
    if shape != space.shape() {
        return Err(bad(format!("an action of shape {shape:?}; it must be {}", expected())));
    }
    let elements = space.num_elements().max(1);
    let data = if count == 1 && elements > 1 { data.repeat(elements) } else { data };
    validate_actions(space, 1, dtype, &{
        let mut batch = vec![1];
        batch.extend_from_slice(space.shape());
        batch
    }, &data)?;
    Ok(data)
}

/// An observation row as a Tensor of its space's type and shape.
pub(super) fn tensor(space: &Space, data: Vec<u8>) -> dm::Tensor {
    fn values<T, const N: usize>(data: &[u8], from: fn([u8; N]) -> T) -> Vec<T> {
        data.chunks_exact(N).map(|chunk| from(chunk.try_into().expect("N bytes"))).collect()
    }
    let payload = match space.dtype() {
        DType::Uint8 => TensorPayload::Uint8s(dm::tensor::Uint8Array { array: data }),
        DType::Bool => TensorPayload::Bools(dm::tensor::BoolArray { array: data.iter().map(|&b| b != 0).collect() }),
        DType::Float32 => TensorPayload::Floats(dm::tensor::FloatArray { array: values(&data, f32::from_le_bytes) }),
        DType::Float64 => TensorPayload::Doubles(dm::tensor::DoubleArray { array: values(&data, f64::from_le_bytes) }),
        DType::Int32 => TensorPayload::Int32s(dm::tensor::Int32Array { array: values(&data, i32::from_le_bytes) }),
        DType::Int64 => TensorPayload::Int64s(dm::tensor::Int64Array { array: values(&data, i64::from_le_bytes) }),
    };
    dm::Tensor { payload: Some(payload), shape: space.shape().iter().map(|&dim| dim as i32).collect() }
}

fn data_type(dtype: DType) -> dm::DataType {
    match dtype {
        DType::Uint8 => dm::DataType::Uint8,
        DType::Bool => dm::DataType::Bool,
        DType::Float32 => dm::DataType::Float,
        DType::Float64 => dm::DataType::Double,
        DType::Int32 => dm::DataType::Int32,
        DType::Int64 => dm::DataType::Int64,
    }
}

/// A bound in the spec's own element type: one value for every element, or one per element.
fn bound(dtype: DType, values: &[f64]) -> Option<dm::tensor_spec::Value> {
    if values.is_empty() || values.iter().all(|value| value.is_infinite()) {
        return None;
    }
    let payload = match dtype {
        DType::Float32 => BoundPayload::Floats(dm::tensor::FloatArray { array: values.iter().map(|&v| v as f32).collect() }),
        DType::Float64 => BoundPayload::Doubles(dm::tensor::DoubleArray { array: values.to_vec() }),
        DType::Int32 => BoundPayload::Int32s(dm::tensor::Int32Array { array: values.iter().map(|&v| v as i32).collect() }),
        DType::Int64 => BoundPayload::Int64s(dm::tensor::Int64Array { array: values.iter().map(|&v| v as i64).collect() }),
        DType::Uint8 => BoundPayload::Uint8s(dm::tensor::Uint8Array { array: values.iter().map(|&v| v as u8).collect() }),
        // Not a number to dm_env_rpc: no bounds.
        DType::Bool => return None,
    };
    Some(dm::tensor_spec::Value { payload: Some(payload) })
}

fn tensor_spec(name: &str, space: &Space) -> dm::TensorSpec {
    let (min, max) = match space {
        Space::Box { dtype, low, high, .. } => (bound(*dtype, low), bound(*dtype, high)),
        Space::Discrete { n } => (bound(DType::Int64, &[0.0]), bound(DType::Int64, &[(*n - 1) as f64])),
    };
    dm::TensorSpec {
        name: name.to_string(),
        shape: space.shape().iter().map(|&dim| dim as i32).collect(),
        dtype: data_type(space.dtype()) as i32,
        min,
        max,
    }
}

/// Every world's specs: its action, its observation and its reward.
pub(super) fn specs(action: &Space, observation: &Space) -> dm::ActionObservationSpecs {
    let reward = dm::TensorSpec { name: REWARD_NAME.into(), shape: vec![], dtype: dm::DataType::Double as i32, min: None, max: None };
    dm::ActionObservationSpecs {
        actions: HashMap::from([(ACTION_UID, tensor_spec(ACTION_NAME, action))]),
        observations: HashMap::from([(OBSERVATION_UID, tensor_spec(OBSERVATION_NAME, observation)), (REWARD_UID, reward)]),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_resolve_as_dm_env_rpc_reads_them() {
        assert_eq!(resolved_shape(&[], 1).unwrap(), Vec::<usize>::new());
        assert_eq!(resolved_shape(&[], 3).unwrap(), vec![3]);
        assert_eq!(resolved_shape(&[2, 3], 6).unwrap(), vec![2, 3]);
        assert_eq!(resolved_shape(&[-1, 3], 6).unwrap(), vec![2, 3]);
        assert_eq!(resolved_shape(&[2, 3], 1).unwrap(), vec![2, 3], "one element broadcasts");
        assert!(resolved_shape(&[-1, -1], 6).is_err());
        assert!(resolved_shape(&[-1, 4], 6).is_err());
        assert!(resolved_shape(&[2, 3], 5).is_err());
        assert!(resolved_shape(&[0, -1], 0).is_err());
    }

    fn action(payload: TensorPayload, shape: Vec<i32>) -> HashMap<u64, dm::Tensor> {
        HashMap::from([(ACTION_UID, dm::Tensor { payload: Some(payload), shape })])
    }

    #[test]
    fn actions_must_match_the_spec_exactly() {
        let space = Space::Box { dtype: DType::Float32, shape: vec![2], low: vec![-1.0], high: vec![1.0] };
        let floats = |values: Vec<f32>| TensorPayload::Floats(dm::tensor::FloatArray { array: values });
        let ok = action_bytes(&action(floats(vec![0.5, -0.5]), vec![2]), &space).unwrap();
        assert_eq!(ok, [0.5f32.to_le_bytes(), (-0.5f32).to_le_bytes()].concat());
        assert_eq!(action_bytes(&action(floats(vec![0.25]), vec![2]), &space).unwrap().len(), 8, "broadcast");
        let doubles = TensorPayload::Doubles(dm::tensor::DoubleArray { array: vec![0.0, 0.0] });
        assert!(action_bytes(&action(doubles, vec![2]), &space).unwrap_err().to_string().contains("FLOAT action"));
        assert!(action_bytes(&action(floats(vec![2.0, 0.0]), vec![2]), &space).unwrap_err().to_string().contains("outside"));
        assert!(action_bytes(&action(floats(vec![0.0, 0.0]), vec![2, 1]), &space).is_err());
        let mut two = action(floats(vec![0.0, 0.0]), vec![2]);
        two.insert(7, dm::Tensor::default());
        assert!(action_bytes(&two, &space).unwrap_err().to_string().contains("uid 7"));
        assert!(action_bytes(&HashMap::new(), &space).unwrap_err().to_string().contains("no action"));
        let discrete = Space::Discrete { n: 2 };
        let ints = |value| TensorPayload::Int64s(dm::tensor::Int64Array { array: vec![value] });
        assert_eq!(action_bytes(&action(ints(1), vec![]), &discrete).unwrap(), 1i64.to_le_bytes());
        assert!(action_bytes(&action(ints(2), vec![]), &discrete).is_err());
        assert!(action_bytes(&action(ints(i64::MIN), vec![]), &discrete).is_err());
    }

    #[test]
    fn specs_carry_bounds_in_the_spec_type() {
        let state = Space::Box { dtype: DType::Float64, shape: vec![3], low: vec![f64::NEG_INFINITY], high: vec![f64::INFINITY] };
        let specs = specs(&Space::Discrete { n: 4 }, &state);
        let action = &specs.actions[&ACTION_UID];
        assert_eq!((action.dtype, action.shape.as_slice()), (dm::DataType::Int64 as i32, &[][..]));
        assert_eq!(action.max.as_ref().unwrap().payload, Some(BoundPayload::Int64s(dm::tensor::Int64Array { array: vec![3] })));
        let observation = &specs.observations[&OBSERVATION_UID];
        assert!(observation.min.is_none() && observation.max.is_none(), "infinite bounds are left out");
        assert_eq!(specs.observations[&REWARD_UID].dtype, dm::DataType::Double as i32);
    }
}
