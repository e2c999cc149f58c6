//! Checks of what a client sends a session: actions against the action space, masks, seeds.

use crate::error::CoreError;
use crate::space::{DType, Space};

/// Largest seed + num_envs: dm_control and ProcGen seeds are 32-bit signed integers.
pub const MAX_SEED: u64 = i32::MAX as u64;

/// A mask has one entry per env.
pub(crate) fn check_mask(mask: &[bool], num_envs: usize, what: &str) -> Result<(), CoreError> {
    if mask.len() != num_envs {
        return Err(CoreError::InvalidMask(format!("{what} has {} entries; the session has {num_envs} envs", mask.len())));
    }
    Ok(())
}

/// Every env's row of actions, their shape, and the mask of envs sent (`Session::scatter_actions`).
pub type ScatteredActions = (Vec<u8>, Vec<usize>, Vec<bool>);

pub fn check_seed(seed: u64, num_envs: usize) -> Result<(), CoreError> {
    if seed.saturating_add(num_envs as u64) > MAX_SEED {
        return Err(CoreError::InvalidSeed { seed, num_envs, max: MAX_SEED });
    }
    Ok(())
}

/// Checks a batch of actions against the action space: dtype, shape, finiteness and bounds.
pub fn validate_actions(
    space: &Space,
    num_envs: usize,
    dtype: DType,
    shape: &[usize],
    data: &[u8],
) -> Result<(), CoreError> {
    let mut expected_shape = vec![num_envs];
    expected_shape.extend_from_slice(space.shape());
    let expected = || {
        format!(
            "actions must be {} of shape {:?} ({num_envs} envs, each {})",
            space.dtype().name(),
            expected_shape,
            space.describe()
        )
    };
    if dtype != space.dtype() || shape != expected_shape.as_slice() {
        return Err(CoreError::InvalidActions(format!("{}; got {} of shape {:?}", expected(), dtype.name(), shape)));
    }
    let count: usize = expected_shape.iter().product();
    if data.len() != count * dtype.size_of() {
        return Err(CoreError::InvalidActions(format!(
            "{}; the tensor's shape says {count} elements but it holds {} bytes",
            expected(),
            data.len()
        )));
    }
    let per_env = space.num_elements().max(1);
    match space {
        Space::Box { low, high, .. } => {
            for (index, chunk) in data.chunks_exact(dtype.size_of()).enumerate() {
                let value = read_number(dtype, chunk);
                let element = index % per_env;
                let bound = |bounds: &Vec<f64>, fallback: f64| {
                    bounds.get(if bounds.len() == 1 { 0 } else { element }).copied().unwrap_or(fallback)
                };
                let (lo, hi) = (bound(low, f64::NEG_INFINITY), bound(high, f64::INFINITY));
                if value.is_nan() || value < lo || value > hi {
                    return Err(CoreError::InvalidActions(format!(
                        "action {value} of env {}, element {element} is outside [{lo}, {hi}]; {}",
                        index / per_env,
                        expected()
                    )));
                }
            }
        }
        Space::Discrete { n } => {
            for (env, chunk) in data.chunks_exact(8).enumerate() {
                let value = i64::from_le_bytes(chunk.try_into().expect("8 bytes"));
                if value < 0 || value >= *n {
                    return Err(CoreError::InvalidActions(format!(
                        "action {value} of env {env} is outside [0, {n}); {}",
                        expected()
                    )));
                }
            }
        }
    }
    Ok(())
}

fn read_number(dtype: DType, bytes: &[u8]) -> f64 {
    match dtype {
        DType::Float32 => f32::from_le_bytes(bytes.try_into().expect("4 bytes")) as f64,
        DType::Float64 => f64::from_le_bytes(bytes.try_into().expect("8 bytes")),
        DType::Int32 => i32::from_le_bytes(bytes.try_into().expect("4 bytes")) as f64,
        DType::Int64 => i64::from_le_bytes(bytes.try_into().expect("8 bytes")) as f64,
        DType::Uint8 | DType::Bool => bytes[0] as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytes_f32(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    fn unit_box(dims: usize) -> Space {
        Space::Box { dtype: DType::Float32, shape: vec![dims], low: vec![-1.0], high: vec![1.0] }
    }

    #[test]
    fn good_actions_pass() {
        let data = bytes_f32(&[0.5, -0.5, 1.0, -1.0]);
        validate_actions(&unit_box(2), 2, DType::Float32, &[2, 2], &data).unwrap();
    }

    #[test]
    fn wrong_shape_dtype_bounds_and_nan_are_rejected_with_the_spec() {
        let space = unit_box(2);
        let data = bytes_f32(&[0.5, -0.5, 1.0, -1.0]);
        let shape_error = validate_actions(&space, 2, DType::Float32, &[4], &data).unwrap_err().to_string();
        assert!(shape_error.contains("float32 of shape [2, 2]"), "{shape_error}");
        let dtype_error = validate_actions(&space, 2, DType::Float64, &[2, 2], &data).unwrap_err().to_string();
        assert!(dtype_error.contains("got float64"), "{dtype_error}");
        let too_big = bytes_f32(&[0.5, 1.5, 0.0, 0.0]);
        let bound_error = validate_actions(&space, 2, DType::Float32, &[2, 2], &too_big).unwrap_err().to_string();
        assert!(bound_error.contains("env 0, element 1 is outside [-1, 1]"), "{bound_error}");
        let nan = bytes_f32(&[0.0, 0.0, f32::NAN, 0.0]);
        let nan_error = validate_actions(&space, 2, DType::Float32, &[2, 2], &nan).unwrap_err().to_string();
        assert!(nan_error.contains("NaN of env 1"), "{nan_error}");
        let short = validate_actions(&space, 2, DType::Float32, &[2, 2], &data[..12]).unwrap_err().to_string();
        assert!(short.contains("holds 12 bytes"), "{short}");
    }

    #[test]
    fn discrete_actions_must_be_in_range() {
        let space = Space::Discrete { n: 15 };
        let ok: Vec<u8> = [0i64, 14].iter().flat_map(|v| v.to_le_bytes()).collect();
        validate_actions(&space, 2, DType::Int64, &[2], &ok).unwrap();
        let bad: Vec<u8> = [3i64, 15].iter().flat_map(|v| v.to_le_bytes()).collect();
        let error = validate_actions(&space, 2, DType::Int64, &[2], &bad).unwrap_err().to_string();
        assert!(error.contains("action 15 of env 1 is outside [0, 15)"), "{error}");
    }

    #[test]
    fn seeds_must_fit_in_32_bits() {
        assert!(check_seed(0, 16).is_ok());
        assert!(check_seed(MAX_SEED, 1).is_err());
    }
}
