//! The envs' own info dicts (gymnasium's `info`), as typed columns: one column per key and value
//! type, holding the values of the envs that reported the key, in env order, and those envs' indices
//! (the `_key` mask of gymnasium's vector infos, as indices). A nested dict's keys are paths from the
//! top. Workers build the columns of their group (`radserve_worker/common.py`, `info_columns`); a
//! session concatenates its groups' columns; the service sends them as `InfoColumn` messages, in gRPC
//! answers and in shared-memory records alike. The server never looks inside the values; it checks
//! that each column is consistent with itself before carrying it ([`Infos::check`]).

use serde::{Deserialize, Serialize};

use crate::space::DType;

/// How a column's values were typed in the env's info dict, so that a client rebuilds them as the
/// env returned them (gymnasium batches an info key by its first value's Python type).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum InfoKind {
    /// Python `bool`, `int` (within int64) or `float` scalars: numbers of dtype bool, int64, float64.
    Python,
    /// numpy scalars (`np.float32(1.0)`): numbers of their dtype.
    Scalar,
    /// numpy arrays, all of one shape and dtype: numbers [envs, *shape].
    Array,
    /// `str` values: texts.
    Text,
    /// Anything else (lists, None, empty dicts, numbers of other dtypes): each value as JSON text
    /// (numpy values tagged with their dtype, as the worker's `_tagged` writes them).
    Json,
}

impl InfoKind {
    /// Whether the values are numbers (else texts).
    pub fn numeric(self) -> bool {
        matches!(self, InfoKind::Python | InfoKind::Scalar | InfoKind::Array)
    }
}

/// One info key's values (of one type) over the envs that reported it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InfoColumn {
    /// The key; a key of a nested dict is its path from the top (`["episode", "r"]`).
    pub path: Vec<String>,
    pub kind: InfoKind,
    /// Ascending env indices (within the group, or the session once merged).
    pub envs: Vec<u32>,
    /// Numeric kinds: the element type and the shape of one env's value ([] for scalars). Text and
    /// JSON columns have no shape, and their dtype means nothing.
    pub dtype: DType,
    pub shape: Vec<u32>,
    /// Numeric kinds: [envs.len(), *shape] elements of `dtype`, little-endian, C order.
    pub data: Vec<u8>,
    /// Text and JSON kinds: one text per env of `envs`.
    pub texts: Vec<String>,
}

impl InfoColumn {
    /// Bytes of one env's value (numeric kinds); None when it overflows.
    fn row_bytes(&self) -> Option<usize> {
        self.shape.iter().try_fold(self.dtype.size_of(), |bytes, &d| bytes.checked_mul(d as usize))
    }

    /// Whether `other` holds values of this column's key and type, so that its rows can follow these.
    fn same_values(&self, other: &InfoColumn) -> bool {
        self.path == other.path && self.kind == other.kind && (!self.kind.numeric() || (self.dtype == other.dtype && self.shape == other.shape))
    }

    /// Whether the column is consistent: a path, ascending envs below `num_envs`, one value per env
    /// (`data` sized for the rows, or one text each), and scalars without a shape.
    fn check(&self, num_envs: usize) -> Result<(), String> {
        let key = self.path.join(".");
        if self.path.is_empty() {
            return Err("an info column has no key".to_string());
        }
        if self.envs.is_empty() {
            return Err(format!("info column {key:?} has no envs"));
        }
        if self.envs.windows(2).any(|pair| pair[0] >= pair[1]) || self.envs.iter().any(|&env| env as usize >= num_envs) {
            return Err(format!("info column {key:?} has envs {:?}: expected ascending indices below {num_envs}", self.envs));
        }
        let rows = self.envs.len();
        if self.kind.numeric() {
            if self.kind != InfoKind::Array && !self.shape.is_empty() {
                return Err(format!("info column {key:?} of scalars has shape {:?}", self.shape));
            }
            if self.kind == InfoKind::Python && !matches!(self.dtype, DType::Bool | DType::Int64 | DType::Float64) {
                return Err(format!("info column {key:?} of Python numbers has dtype {}", self.dtype.name()));
            }
            let expected = self.row_bytes().and_then(|bytes| bytes.checked_mul(rows));
            if expected != Some(self.data.len()) || !self.texts.is_empty() {
                return Err(format!(
                    "info column {key:?} holds {} bytes and {} texts for {rows} values of {} {:?}",
                    self.data.len(),
                    self.texts.len(),
                    self.dtype.name(),
                    self.shape
                ));
            }
        } else if self.texts.len() != rows || !self.data.is_empty() || !self.shape.is_empty() {
            return Err(format!("info column {key:?} holds {} texts and {} bytes for {rows} values", self.texts.len(), self.data.len()));
        }
        Ok(())
    }
}

/// The info dicts of some envs (a group's or a session's), as columns in the order their keys were
/// first reported.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Infos {
    pub columns: Vec<InfoColumn>,
}

impl Infos {
    pub fn is_empty(&self) -> bool {
        self.columns.is_empty()
    }

    /// Whether every column is consistent for a group of `num_envs` envs (a worker's answer is
    /// checked before anything is taken from it).
    pub fn check(&self, num_envs: usize) -> Result<(), String> {
        self.columns.iter().try_for_each(|column| column.check(num_envs))
    }

    /// Appends the rows of `group`'s columns whose env (within the group) `keep` accepts, their envs
    /// moved by `offset` (the group's first env in the session). Called for a session's groups in
    /// env order, so each column's envs stay ascending: rows join the column of the same key and type
    /// when it ends before them, else start a new one. `group` must have passed [`Infos::check`].
    pub fn append(&mut self, group: &Infos, offset: usize, keep: impl Fn(usize) -> bool) {
        for column in &group.columns {
            let kept: Vec<usize> = (0..column.envs.len()).filter(|&row| keep(column.envs[row] as usize)).collect();
            if kept.is_empty() {
                continue;
            }
            let first = offset as u32 + column.envs[kept[0]];
            let index = match self.columns.iter().position(|mine| mine.same_values(column) && mine.envs.last().is_some_and(|&last| last < first)) {
                Some(index) => index,
                None => {
                    self.columns.push(column.clone_empty());
                    self.columns.len() - 1
                }
            };
            let target = &mut self.columns[index];
            let row_bytes = column.row_bytes().unwrap_or(0);
            for &row in &kept {
                target.envs.push(offset as u32 + column.envs[row]);
                if column.kind.numeric() {
                    target.data.extend_from_slice(&column.data[row * row_bytes..(row + 1) * row_bytes]);
                } else {
                    target.texts.push(column.texts[row].clone());
                }
            }
        }
    }

    /// Bytes the columns' values hold (texts included).
    pub fn value_bytes(&self) -> usize {
        self.columns.iter().map(|column| column.data.len() + column.texts.iter().map(String::len).sum::<usize>()).sum()
    }
}

impl InfoColumn {
    /// A column of the same key and type without values.
    fn clone_empty(&self) -> InfoColumn {
        InfoColumn {
            path: self.path.clone(),
            kind: self.kind,
            envs: Vec::new(),
            dtype: self.dtype,
            shape: self.shape.clone(),
            data: Vec::new(),
            texts: Vec::new(),
        }
    }

    /// A column of Python numbers (int64 values), as a test's fake env reports one.
    #[cfg(any(test, feature = "testing"))]
    pub fn python_ints(path: &[&str], envs: Vec<u32>, values: &[i64]) -> InfoColumn {
        InfoColumn {
            path: path.iter().map(|part| part.to_string()).collect(),
            kind: InfoKind::Python,
            envs,
            dtype: DType::Int64,
            shape: Vec::new(),
            data: values.iter().flat_map(|value| value.to_le_bytes()).collect(),
            texts: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn floats(path: &str, envs: Vec<u32>, values: &[f64]) -> InfoColumn {
        InfoColumn {
            path: vec![path.to_string()],
            kind: InfoKind::Python,
            envs,
            dtype: DType::Float64,
            shape: Vec::new(),
            data: values.iter().flat_map(|value| value.to_le_bytes()).collect(),
            texts: Vec::new(),
        }
    }

    fn texts(path: &str, envs: Vec<u32>, values: &[&str]) -> InfoColumn {
        InfoColumn {
            path: vec![path.to_string()],
            kind: InfoKind::Text,
            envs,
            dtype: DType::Uint8,
            shape: Vec::new(),
            data: Vec::new(),
            texts: values.iter().map(|value| value.to_string()).collect(),
        }
    }

    #[test]
    fn groups_join_their_columns_in_env_order_and_keep_only_the_rows_asked_for() {
        let first = Infos { columns: vec![floats("x", vec![0, 1], &[1.0, 2.0]), texts("s", vec![1], &["b"])] };
        let second = Infos { columns: vec![floats("x", vec![0, 1], &[3.0, 4.0]), texts("s", vec![0, 1], &["c", "d"])] };
        let mut session = Infos::default();
        session.append(&first, 0, |_| true);
        session.append(&second, 2, |local| local != 1);
        assert_eq!(session.columns.len(), 2);
        assert_eq!(session.columns[0], floats("x", vec![0, 1, 2], &[1.0, 2.0, 3.0]));
        assert_eq!(session.columns[1], texts("s", vec![1, 2], &["b", "c"]));
        assert!(session.check(4).is_ok());
    }

    #[test]
    fn a_key_of_another_type_is_its_own_column() {
        let mut ints = InfoColumn::python_ints(&["x"], vec![0], &[7]);
        let mut session = Infos::default();
        session.append(&Infos { columns: vec![floats("x", vec![0], &[1.0])] }, 0, |_| true);
        session.append(&Infos { columns: vec![ints.clone()] }, 1, |_| true);
        ints.envs = vec![1];
        assert_eq!(session.columns, vec![floats("x", vec![0], &[1.0]), ints]);
    }

    #[test]
    fn inconsistent_columns_are_refused_with_their_key() {
        let cases = [
            (floats("x", vec![1, 0], &[1.0, 2.0]), "ascending"),
            (floats("x", vec![0, 4], &[1.0, 2.0]), "below 4"),
            (floats("x", vec![0, 1], &[1.0]), "8 bytes"),
            (floats("x", vec![], &[]), "no envs"),
            (texts("s", vec![0], &["a", "b"]), "2 texts"),
            (InfoColumn { shape: vec![2], ..floats("x", vec![0], &[1.0]) }, "shape"),
            (InfoColumn { dtype: DType::Uint8, data: vec![1], ..floats("x", vec![0], &[]) }, "dtype uint8"),
            (InfoColumn { path: Vec::new(), ..floats("x", vec![0], &[1.0]) }, "no key"),
            (InfoColumn { kind: InfoKind::Array, shape: vec![u32::MAX, u32::MAX, u32::MAX], ..floats("x", vec![0], &[1.0]) }, "bytes"),
        ];
        for (column, expected) in cases {
            let error = Infos { columns: vec![column] }.check(4).unwrap_err();
            assert!(error.contains(expected), "{error:?} should say {expected:?}");
        }
    }
}
