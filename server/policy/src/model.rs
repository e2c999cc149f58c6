//! What an ONNX model holds, read from its bytes before ONNX Runtime sees it: the operators, the
//! opsets, the graph's inputs and outputs, and whether it points outside itself (external data,
//! local functions, subgraphs). Every refusal happens here, at SetPolicy, with the reason named.
//!
//! Only the few fields of `onnx.proto` this needs are declared (field numbers as in onnx/onnx's
//! `onnx.proto3`); prost skips the rest, so the weights (`raw_data`) are never copied.

use std::collections::BTreeMap;

use prost::Message;

use crate::PolicyError;

#[derive(Clone, PartialEq, Message)]
struct ModelProto {
    #[prost(int64, tag = "1")]
    ir_version: i64,
    #[prost(message, optional, tag = "7")]
    graph: Option<GraphProto>,
    #[prost(message, repeated, tag = "8")]
    opset_import: Vec<OperatorSetId>,
    /// Training information (TrainingInfoProto): graphs and initializers beside the graph, refused.
    #[prost(bytes = "vec", repeated, tag = "20")]
    training_info: Vec<Vec<u8>>,
    /// Model-local functions (FunctionProto): a graph beside the graph, refused.
    #[prost(bytes = "vec", repeated, tag = "25")]
    functions: Vec<Vec<u8>>,
}

#[derive(Clone, PartialEq, Message)]
struct OperatorSetId {
    #[prost(string, tag = "1")]
    domain: String,
    #[prost(int64, tag = "2")]
    version: i64,
}

#[derive(Clone, PartialEq, Message)]
struct GraphProto {
    #[prost(message, repeated, tag = "1")]
    node: Vec<NodeProto>,
    #[prost(message, repeated, tag = "5")]
    initializer: Vec<TensorProto>,
    #[prost(message, repeated, tag = "11")]
    input: Vec<ValueInfo>,
    #[prost(message, repeated, tag = "12")]
    output: Vec<ValueInfo>,
    #[prost(bytes = "vec", repeated, tag = "15")]
    sparse_initializer: Vec<Vec<u8>>,
}

#[derive(Clone, PartialEq, Message)]
struct NodeProto {
    #[prost(string, tag = "3")]
    name: String,
    #[prost(string, tag = "4")]
    op_type: String,
    #[prost(message, repeated, tag = "5")]
    attribute: Vec<AttributeProto>,
    #[prost(string, tag = "7")]
    domain: String,
}

#[derive(Clone, PartialEq, Message)]
struct AttributeProto {
    #[prost(string, tag = "1")]
    name: String,
    #[prost(message, optional, tag = "5")]
    t: Option<TensorProto>,
    /// A subgraph (If, Loop, Scan): only its presence matters.
    #[prost(bytes = "vec", optional, tag = "6")]
    g: Option<Vec<u8>>,
    #[prost(message, repeated, tag = "10")]
    tensors: Vec<TensorProto>,
    #[prost(bytes = "vec", repeated, tag = "11")]
    graphs: Vec<Vec<u8>>,
    /// A sparse tensor (Constant's sparse_value): its values and indices are tensors too.
    #[prost(message, optional, tag = "22")]
    sparse_tensor: Option<SparseTensorProto>,
    #[prost(message, repeated, tag = "23")]
    sparse_tensors: Vec<SparseTensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct SparseTensorProto {
    #[prost(message, optional, tag = "1")]
    values: Option<TensorProto>,
    #[prost(message, optional, tag = "2")]
    indices: Option<TensorProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorProto {
    #[prost(string, tag = "8")]
    name: String,
    /// Key/value pairs naming a file: their presence is enough to refuse.
    #[prost(bytes = "vec", repeated, tag = "13")]
    external_data: Vec<Vec<u8>>,
    /// 1: EXTERNAL (the bytes are in a file beside the model).
    #[prost(int32, tag = "14")]
    data_location: i32,
}

#[derive(Clone, PartialEq, Message)]
struct ValueInfo {
    #[prost(string, tag = "1")]
    name: String,
    #[prost(message, optional, tag = "2")]
    r#type: Option<TypeProto>,
}

#[derive(Clone, PartialEq, Message)]
struct TypeProto {
    #[prost(message, optional, tag = "1")]
    tensor_type: Option<TensorType>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorType {
    #[prost(int32, tag = "1")]
    elem_type: i32,
    #[prost(message, optional, tag = "2")]
    shape: Option<TensorShape>,
}

#[derive(Clone, PartialEq, Message)]
struct TensorShape {
    #[prost(message, repeated, tag = "1")]
    dim: Vec<Dimension>,
}

#[derive(Clone, PartialEq, Message)]
struct Dimension {
    #[prost(int64, optional, tag = "1")]
    dim_value: Option<i64>,
    #[prost(string, optional, tag = "2")]
    dim_param: Option<String>,
}

/// ONNX's element types this needs to name (TensorProto.DataType).
pub const ELEM_FLOAT: i32 = 1;
pub const ELEM_UINT8: i32 = 2;

/// The name of an ONNX element type, for messages.
pub fn elem_name(elem: i32) -> String {
    match elem {
        1 => "float32".into(),
        2 => "uint8".into(),
        3 => "int8".into(),
        6 => "int32".into(),
        7 => "int64".into(),
        9 => "bool".into(),
        10 => "float16".into(),
        11 => "float64".into(),
        16 => "bfloat16".into(),
        other => format!("element type {other}"),
    }
}

/// The opsets of the default domain (`ai.onnx`) a model may import: what torch.onnx.export writes
/// (17 and 18 today) and what ONNX Runtime 1.31 runs.
pub const OPSETS: std::ops::RangeInclusive<i64> = 9..=23;

/// The operators a policy may use (domain `ai.onnx`): what torch.onnx.export writes for the actors
/// of RAD, DrQ(-v2), SAC, TD3 and PPO (convolutions, MLPs, normalizations, activations, the shape
/// arithmetic of `x.view(x.size(0), -1)`) and nothing that loops, draws random numbers, or sizes a
/// tensor from data (ConstantOfShape, Expand, Range, Tile: an input could make them allocate without
/// bound). The heads' sampling happens in the server, seeded, so models stay deterministic.
pub const SUPPORTED_OPS: &[&str] = &[
    "Abs", "Add", "AveragePool", "BatchNormalization", "Cast", "Ceil", "Clip", "Concat", "Constant", "Conv",
    "Div", "Dropout", "Elu", "Equal", "Erf", "Exp", "Flatten", "Floor", "Gather", "Gelu", "Gemm",
    "GlobalAveragePool", "GlobalMaxPool", "Greater", "HardSigmoid", "HardSwish", "Identity",
    "InstanceNormalization", "LayerNormalization", "LeakyRelu", "Less", "Log", "LogSoftmax", "MatMul", "Max",
    "MaxPool", "Mean", "Min", "Mish", "Mul", "Neg", "Not", "Pad", "Pow", "PRelu", "Reciprocal", "ReduceL2",
    "ReduceMax", "ReduceMean", "ReduceMin", "ReduceSum", "Relu", "Reshape", "Selu", "Shape", "Sigmoid", "Sign",
    "Slice", "Softmax", "Softplus", "Softsign", "Split", "Sqrt", "Squeeze", "Sub", "Sum", "Tanh", "Transpose",
    "Unsqueeze", "Where",
];

/// A dimension of a graph input or output: a number, or a name (a dynamic axis, e.g. the batch).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Dim {
    Fixed(i64),
    Named(String),
    Unknown,
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Dim::Fixed(value) => write!(f, "{value}"),
            Dim::Named(name) => write!(f, "{name}"),
            Dim::Unknown => write!(f, "?"),
        }
    }
}

/// A graph input or output.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Port {
    pub name: String,
    pub elem: i32,
    /// None: the model does not say (a rank-unknown tensor).
    pub dims: Option<Vec<Dim>>,
}

impl Port {
    pub fn describe(&self) -> String {
        let dims = match &self.dims {
            Some(dims) => format!("[{}]", dims.iter().map(Dim::to_string).collect::<Vec<_>>().join(", ")),
            None => "[unknown shape]".into(),
        };
        format!("'{}' {} {dims}", self.name, elem_name(self.elem))
    }
}

/// What a model is made of, as far as the server checks it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ModelSummary {
    pub opset: i64,
    /// Each operator and how often it appears.
    pub ops: BTreeMap<String, usize>,
    pub input: Port,
    pub outputs: Vec<Port>,
}

fn port(value: &ValueInfo) -> Port {
    let tensor = value.r#type.as_ref().and_then(|t| t.tensor_type.as_ref());
    Port {
        name: value.name.clone(),
        elem: tensor.map_or(0, |t| t.elem_type),
        dims: tensor.and_then(|t| t.shape.as_ref()).map(|shape| {
            shape
                .dim
                .iter()
                .map(|dim| match (&dim.dim_value, &dim.dim_param) {
                    (Some(value), _) => Dim::Fixed(*value),
                    (None, Some(name)) if !name.is_empty() => Dim::Named(name.clone()),
                    _ => Dim::Unknown,
                })
                .collect()
        }),
    }
}

fn external(tensor: &TensorProto) -> bool {
    tensor.data_location == 1 || !tensor.external_data.is_empty()
}

/// The most nodes and initializers a policy's graph may have. The actors this serves have tens to
/// hundreds of nodes; a graph of a million (27 MB) took ONNX Runtime minutes and gigabytes to load.
pub const MAX_NODES: usize = 10_000;
pub const MAX_INITIALIZERS: usize = 10_000;

/// How many times field `field` occurs at the top level of the message `bytes` (a wire-format scan
/// that allocates nothing), and the bytes of the last occurrence when it is length-delimited.
fn count_field(mut bytes: &[u8], field: u32) -> Result<(usize, Option<&[u8]>), String> {
    use prost::encoding::{decode_key, decode_varint, WireType};
    let (mut count, mut last) = (0, None);
    while !bytes.is_empty() {
        let (tag, wire_type) = decode_key(&mut bytes).map_err(|error| error.to_string())?;
        let skip = match wire_type {
            WireType::Varint => {
                decode_varint(&mut bytes).map_err(|error| error.to_string())?;
                0
            }
            WireType::SixtyFourBit => 8,
            WireType::ThirtyTwoBit => 4,
            WireType::LengthDelimited => usize::try_from(decode_varint(&mut bytes).map_err(|error| error.to_string())?).unwrap_or(usize::MAX),
            WireType::StartGroup | WireType::EndGroup => return Err("groups are not ONNX".into()),
        };
        if skip > bytes.len() {
            return Err("a field runs past the end".into());
        }
        if tag == field {
            count += 1;
            if wire_type == WireType::LengthDelimited {
                last = Some(&bytes[..skip]);
            }
        }
        bytes = &bytes[skip..];
    }
    Ok((count, last))
}

/// Refuses a graph with more nodes or initializers than a policy may have, before the model is
/// decoded (decoding a million nodes is itself hundreds of megabytes).
fn check_size(bytes: &[u8]) -> Result<(), PolicyError> {
    let not_onnx = |error: String| PolicyError::NotOnnx(format!("the bytes do not decode as an ONNX ModelProto ({error})"));
    let (_, graph) = count_field(bytes, 7).map_err(not_onnx)?;
    let Some(graph) = graph else { return Ok(()) };
    let (nodes, _) = count_field(graph, 1).map_err(not_onnx)?;
    let (initializers, _) = count_field(graph, 5).map_err(not_onnx)?;
    if nodes > MAX_NODES || initializers > MAX_INITIALIZERS {
        return Err(PolicyError::Unsupported(format!(
            "the graph has {nodes} nodes and {initializers} initializers; a policy has at most {MAX_NODES} of each"
        )));
    }
    Ok(())
}

/// Reads and checks a model's structure: an ONNX model of one graph, opset in `OPSETS`, only
/// `SUPPORTED_OPS`, no subgraph, no local function, no tensor stored outside the model (a path the
/// server would open), one input, at least one output.
pub fn inspect(bytes: &[u8]) -> Result<ModelSummary, PolicyError> {
    check_size(bytes)?;
    let model = ModelProto::decode(bytes)
        .map_err(|error| PolicyError::NotOnnx(format!("the bytes do not decode as an ONNX ModelProto ({error})")))?;
    let graph = model.graph.as_ref().ok_or_else(|| PolicyError::NotOnnx("the model has no graph (ModelProto.graph is empty)".into()))?;
    if model.ir_version <= 0 {
        return Err(PolicyError::NotOnnx("the model has no ir_version: not an ONNX model".into()));
    }
    let mut opset = None;
    for import in &model.opset_import {
        match import.domain.as_str() {
            "" | "ai.onnx" => opset = Some(import.version),
            other => {
                return Err(PolicyError::Unsupported(format!(
                    "the model imports operator domain '{other}'; only the default domain (ai.onnx) is supported"
                )))
            }
        }
    }
    let opset = opset.ok_or_else(|| PolicyError::NotOnnx("the model imports no opset of the default domain".into()))?;
    if !OPSETS.contains(&opset) {
        return Err(PolicyError::Unsupported(format!(
            "the model uses opset {opset}; supported: {} to {} (torch.onnx.export(..., opset_version=17))",
            OPSETS.start(),
            OPSETS.end()
        )));
    }
    if !model.training_info.is_empty() {
        return Err(PolicyError::Unsupported("the model carries training information (ModelProto.training_info); export it for inference".into()));
    }
    if !model.functions.is_empty() {
        return Err(PolicyError::Unsupported("the model defines local functions; export without them (inline them)".into()));
    }
    if !graph.sparse_initializer.is_empty() {
        return Err(PolicyError::Unsupported("the model has sparse initializers; export dense weights".into()));
    }
    if let Some(tensor) = graph.initializer.iter().find(|tensor| external(tensor)) {
        return Err(PolicyError::Unsupported(format!(
            "initializer '{}' is stored outside the model (external data); send one self-contained file \
             (onnx.save(model, path, save_as_external_data=False))",
            tensor.name
        )));
    }
    let mut ops = BTreeMap::new();
    for node in &graph.node {
        if !matches!(node.domain.as_str(), "" | "ai.onnx") {
            return Err(PolicyError::Unsupported(format!(
                "node '{}' is operator {} of domain '{}'; only the default domain (ai.onnx) is supported",
                node.name, node.op_type, node.domain
            )));
        }
        if !SUPPORTED_OPS.contains(&node.op_type.as_str()) {
            return Err(PolicyError::Unsupported(format!(
                "node '{}' uses operator {}, which server-side policies do not support; supported: {}",
                node.name,
                node.op_type,
                SUPPORTED_OPS.join(", ")
            )));
        }
        for attribute in &node.attribute {
            if attribute.g.is_some() || !attribute.graphs.is_empty() {
                return Err(PolicyError::Unsupported(format!(
                    "node '{}' ({}) carries a subgraph in attribute '{}'",
                    node.name, node.op_type, attribute.name
                )));
            }
            let sparse = attribute.sparse_tensor.iter().chain(&attribute.sparse_tensors).flat_map(|sparse| sparse.values.iter().chain(&sparse.indices));
            if attribute.t.iter().chain(&attribute.tensors).chain(sparse).any(external) {
                return Err(PolicyError::Unsupported(format!(
                    "node '{}' ({}) has a tensor stored outside the model (external data) in attribute '{}': a path the \
                     server would open; send one self-contained file",
                    node.name, node.op_type, attribute.name
                )));
            }
        }
        *ops.entry(node.op_type.clone()).or_insert(0) += 1;
    }
    let weights: std::collections::HashSet<&str> = graph.initializer.iter().map(|tensor| tensor.name.as_str()).collect();
    // Models of IR version 3 list their weights among the inputs too.
    let inputs: Vec<Port> = graph.input.iter().filter(|input| !weights.contains(input.name.as_str())).map(port).collect();
    let input = match inputs.as_slice() {
        [input] => input.clone(),
        [] => return Err(PolicyError::Unsupported("the model has no input; it must take the observations".into())),
        more => {
            return Err(PolicyError::Unsupported(format!(
                "the model has {} inputs ({}); a policy takes one, the observations",
                more.len(),
                more.iter().map(Port::describe).collect::<Vec<_>>().join(", ")
            )))
        }
    };
    if graph.output.is_empty() {
        return Err(PolicyError::Unsupported("the model has no output".into()));
    }
    Ok(ModelSummary { opset, ops, input, outputs: graph.output.iter().map(port).collect() })
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    const FIXTURE: &[u8] = include_bytes!("../tests/models/categorical_fake.onnx");

    #[test]
    fn a_fixture_reads_back() {
        let summary = inspect(FIXTURE).unwrap();
        assert_eq!(summary.opset, 17);
        assert_eq!(summary.input.name, "obs");
        assert_eq!(summary.input.dims, Some(vec![Dim::Named("batch".into()), Dim::Fixed(1), Dim::Fixed(2), Dim::Fixed(2)]));
        assert_eq!(summary.outputs.iter().map(|port| port.name.as_str()).collect::<Vec<_>>(), ["logits", "value"]);
        assert_eq!(summary.ops.get("Gemm"), Some(&3));
    }

    /// A graph of `nodes` Identity nodes, encoded by hand (field numbers of onnx.proto3).
    fn graph_of(nodes: usize) -> Vec<u8> {
        let node = [0x22, 8, b'I', b'd', b'e', b'n', b't', b'i', b't', b'y'];
        let mut graph = Vec::new();
        for _ in 0..nodes {
            graph.extend_from_slice(&[0x0a, node.len() as u8]);
            graph.extend_from_slice(&node);
        }
        let mut model = vec![0x08, 8, 0x3a];
        prost::encoding::encode_varint(graph.len() as u64, &mut model);
        model.extend_from_slice(&graph);
        model
    }

    #[test]
    fn a_graph_past_the_node_limit_is_refused_before_it_is_decoded() {
        let error = inspect(&graph_of(MAX_NODES + 1)).unwrap_err();
        assert!(error.to_string().contains(&format!("the graph has {} nodes", MAX_NODES + 1)), "{error}");
        // At the limit the size check passes (and the model fails later for what it lacks).
        assert!(!inspect(&graph_of(MAX_NODES)).unwrap_err().to_string().contains("nodes and"));
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

        /// The loader's entry never panics: arbitrary bytes, and a real model with bytes flipped or
        /// cut, are a model or a refusal.
        #[test]
        fn inspect_takes_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = inspect(&bytes);
        }

        #[test]
        fn inspect_takes_damaged_models(flips in proptest::collection::vec((0..FIXTURE.len(), any::<u8>()), 1..8), cut in 0..FIXTURE.len()) {
            let mut bytes = FIXTURE.to_vec();
            for (at, value) in flips {
                bytes[at] = value;
            }
            let _ = inspect(&bytes);
            let _ = inspect(&bytes[..cut]);
        }
    }
}
