//! Element types and spaces, mirroring gymnasium's `Box` and `Discrete`.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DType {
    Uint8,
    Int32,
    Int64,
    Float32,
    Float64,
    Bool,
}

impl DType {
    pub fn size_of(self) -> usize {
        match self {
            DType::Uint8 | DType::Bool => 1,
            DType::Int32 | DType::Float32 => 4,
            DType::Int64 | DType::Float64 => 8,
        }
    }

    /// The numpy name, used by the Python side and in error messages.
    pub fn name(self) -> &'static str {
        match self {
            DType::Uint8 => "uint8",
            DType::Int32 => "int32",
            DType::Int64 => "int64",
            DType::Float32 => "float32",
            DType::Float64 => "float64",
            DType::Bool => "bool",
        }
    }

    pub fn from_name(name: &str) -> Option<DType> {
        [DType::Uint8, DType::Int32, DType::Int64, DType::Float32, DType::Float64, DType::Bool]
            .into_iter()
            .find(|dtype| dtype.name() == name)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Space {
    /// `low` and `high` hold one bound per element, or a single bound for every element.
    Box { dtype: DType, shape: Vec<usize>, low: Vec<f64>, high: Vec<f64> },
    Discrete { n: i64 },
}

impl Space {
    pub fn dtype(&self) -> DType {
        match self {
            Space::Box { dtype, .. } => *dtype,
            Space::Discrete { .. } => DType::Int64,
        }
    }

    /// Shape of one element of the space (a discrete action is a scalar).
    pub fn shape(&self) -> &[usize] {
        match self {
            Space::Box { shape, .. } => shape,
            Space::Discrete { .. } => &[],
        }
    }

    pub fn num_elements(&self) -> usize {
        self.shape().iter().product()
    }

    pub fn num_bytes(&self) -> usize {
        self.num_elements() * self.dtype().size_of()
    }

    /// The space of `k` of these observations concatenated on the first axis (oldest first).
    /// Bounds are per element, so they repeat `k` times unless they are a single scalar.
    pub fn stacked(&self, k: usize) -> Space {
        match self {
            Space::Box { dtype, shape, low, high } => {
                let mut stacked_shape = shape.clone();
                if stacked_shape.is_empty() {
                    stacked_shape.push(k);
                } else {
                    stacked_shape[0] *= k;
                }
                let repeat = |bounds: &Vec<f64>| {
                    if bounds.len() <= 1 {
                        bounds.clone()
                    } else {
                        bounds.iter().copied().cycle().take(bounds.len() * k).collect()
                    }
                };
                Space::Box { dtype: *dtype, shape: stacked_shape, low: repeat(low), high: repeat(high) }
            }
            Space::Discrete { .. } => self.clone(),
        }
    }

    /// A short human form for error messages, e.g. `float32[6] in [-1, 1]` or `int64 in [0, 15)`.
    pub fn describe(&self) -> String {
        match self {
            Space::Box { dtype, shape, low, high } => {
                let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
                let bound = |b: &Vec<f64>, pick: fn(f64, f64) -> f64, start: f64| {
                    b.iter().copied().fold(start, pick)
                };
                format!(
                    "{}[{}] in [{}, {}]",
                    dtype.name(),
                    dims.join(", "),
                    bound(low, f64::min, f64::INFINITY),
                    bound(high, f64::max, f64::NEG_INFINITY)
                )
            }
            Space::Discrete { n } => format!("int64 in [0, {n})"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stacking_multiplies_the_first_axis_and_repeats_per_element_bounds() {
        let image = Space::Box { dtype: DType::Uint8, shape: vec![3, 8, 8], low: vec![0.0], high: vec![255.0] };
        assert_eq!(image.stacked(3).shape(), &[9, 8, 8]);
        let state = Space::Box { dtype: DType::Float32, shape: vec![2], low: vec![-1.0, -2.0], high: vec![1.0, 2.0] };
        match state.stacked(2) {
            Space::Box { shape, low, .. } => {
                assert_eq!(shape, vec![4]);
                assert_eq!(low, vec![-1.0, -2.0, -1.0, -2.0]);
            }
            Space::Discrete { .. } => unreachable!(),
        }
    }

    #[test]
    fn describe_names_dtype_shape_and_range() {
        let action = Space::Box { dtype: DType::Float32, shape: vec![6], low: vec![-1.0; 6], high: vec![1.0; 6] };
        assert_eq!(action.describe(), "float32[6] in [-1, 1]");
        assert_eq!(Space::Discrete { n: 15 }.describe(), "int64 in [0, 15)");
    }
}
