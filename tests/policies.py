"""ONNX policies for the tests and benches, built with onnx.helper (no torch needed): the RAD actor
(4 convs x 32, fc 50, LayerNorm, tanh, MLP 1024 x 2, mean and log_std; Laskin et al. 2020, appendix),
small models for the fake simulators, and broken ones (NaN outputs, an unsupported operator,
external data, a wrong input shape) for the refusal tests.

`python tests/policies.py` rewrites the small models the Rust tests read
(server/policy/tests/models/); the weights are seeded, so the files come out the same each time.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

OPSET = 17
RUST_MODELS = Path(__file__).resolve().parents[1] / "server" / "policy" / "tests" / "models"


class Graph:
    """A graph under construction: seeded weights, nodes, and a name for every tensor."""

    def __init__(self, seed: int = 0):
        self.rng = np.random.default_rng(seed)
        self.nodes: list = []
        self.weights: list = []
        self.count = 0

    def name(self, prefix: str) -> str:
        self.count += 1
        return f"{prefix}{self.count}"

    def weight(self, shape, scale: float) -> str:
        name = self.name("w")
        self.weights.append(numpy_helper.from_array((self.rng.standard_normal(shape) * scale).astype(np.float32), name))
        return name

    def constant(self, value) -> str:
        name = self.name("k")
        self.weights.append(numpy_helper.from_array(np.asarray(value, dtype=np.float32), name))
        return name

    def op(self, op_type: str, inputs: list, output: "str | None" = None, **attributes) -> str:
        output = output or self.name(op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [output], name=output, **attributes))
        return output

    def linear(self, x: str, fan_in: int, fan_out: int, output: "str | None" = None, scale: "float | None" = None) -> str:
        scale = np.sqrt(1.0 / fan_in) if scale is None else scale
        return self.op("Gemm", [x, self.weight((fan_out, fan_in), scale), self.weight((fan_out,), 0.01)], output, transB=1)

    def model(self, inputs: list, outputs: list) -> bytes:
        graph = helper.make_graph(self.nodes, "policy", inputs, outputs, self.weights)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="radserve-tests")
        model.ir_version = 8
        onnx.checker.check_model(model)
        return model.SerializeToString()


def obs_input(shape, uint8: bool = False, batch="batch"):
    return helper.make_tensor_value_info("obs", TensorProto.UINT8 if uint8 else TensorProto.FLOAT, [batch, *shape])


def output(name: str, dims: list):
    return helper.make_tensor_value_info(name, TensorProto.FLOAT, dims)


def rad_actor(frames: int = 9, size: int = 84, action_dim: int = 1, hidden: int = 1024, feature: int = 50,
              seed: int = 0) -> bytes:
    """RAD's SAC actor (the encoder of Laskin et al. 2020 / SAC-AE: 3x3 convs of 32, the first of stride
    2, then fc, LayerNorm, tanh; the actor's MLP) with gaussian_tanh outputs, on uint8 observations
    divided by 255 in the model."""
    g = Graph(seed)
    x = g.op("Cast", ["obs"], to=TensorProto.FLOAT)
    x = g.op("Div", [x, g.constant(255.0)])
    channels, side = frames, size
    for stride in (2, 1, 1, 1):
        x = g.op("Conv", [x, g.weight((32, channels, 3, 3), np.sqrt(2.0 / (channels * 9))), g.weight((32,), 0.01)],
                 kernel_shape=[3, 3], strides=[stride, stride])
        x = g.op("Relu", [x])
        channels, side = 32, (side - 3) // stride + 1
    x = g.op("Flatten", [x], axis=1)
    x = g.linear(x, 32 * side * side, feature)
    x = g.op("LayerNormalization", [x, g.constant(np.ones(feature)), g.constant(np.zeros(feature))], axis=-1)
    x = g.op("Tanh", [x])
    width = feature
    for _ in range(2):
        x = g.op("Relu", [g.linear(x, width, hidden)])
        width = hidden
    g.linear(x, width, action_dim, "mean")
    g.linear(x, width, action_dim, "log_std")
    return g.model([obs_input((frames, size, size), uint8=True)],
                   [output("mean", ["batch", action_dim]), output("log_std", ["batch", action_dim])])


def mlp_gaussian(obs_dim: int, action_dim: int, hidden: int = 64, seed: int = 0) -> bytes:
    """A state-based SAC actor: MLP, mean and log_std."""
    g = Graph(seed)
    x = g.op("Relu", [g.linear("obs", obs_dim, hidden)])
    g.linear(x, hidden, action_dim, "mean")
    g.linear(x, hidden, action_dim, "log_std")
    return g.model([obs_input((obs_dim,))], [output("mean", ["batch", action_dim]), output("log_std", ["batch", action_dim])])


def conv_categorical(shape, n: int, value: bool = True, uint8: bool = False, seed: int = 0) -> bytes:
    """A categorical policy for image observations [C, H, W] (or any shape: flattened), with a
    value output."""
    g = Graph(seed)
    x = g.op("Cast", ["obs"], to=TensorProto.FLOAT) if uint8 else "obs"
    x = g.op("Flatten", [g.op("Div", [x, g.constant(255.0)])], axis=1)
    features = int(np.prod(shape))
    x = g.op("Tanh", [g.linear(x, features, 16)])
    g.linear(x, 16, n, "logits", scale=1.0)
    outputs = [output("logits", ["batch", n])]
    if value:
        g.linear(x, 16, 1, "value")
        outputs.append(output("value", ["batch", 1]))
    return g.model([obs_input(shape, uint8=uint8)], outputs)


def linear_categorical(weights) -> bytes:
    """Categorical logits = obs @ weights ([obs_dim, n]): a policy whose choices are far from ties,
    so that two runtimes (or thread counts) that round differently still take the same actions."""
    weights = np.asarray(weights, dtype=np.float32)
    g = Graph(0)
    g.op("MatMul", ["obs", g.constant(weights)], "logits")
    return g.model([obs_input((weights.shape[0],))], [output("logits", ["batch", weights.shape[1]])])


def pick_first_byte(shape, n: int) -> bytes:
    """Categorical logits that make action = (first byte of the observation) mod n certain: a test
    can tell from the recorded actions which observations the policy saw."""
    g = Graph(0)
    flat = g.op("Flatten", ["obs"], axis=1)
    first = g.op("Slice", [flat, g.constant_int([0]), g.constant_int([1]), g.constant_int([1])])
    # logits[i] = -1000 * |first mod n - i|
    remainder = g.op("Sub", [first, g.op("Mul", [g.op("Floor", [g.op("Div", [first, g.constant(float(n))])]), g.constant(float(n))])])
    distance = g.op("Abs", [g.op("Sub", [remainder, g.constant(np.arange(n, dtype=np.float32))])])
    g.op("Mul", [distance, g.constant(-1000.0)], "logits")
    return g.model([obs_input(shape)], [output("logits", ["batch", n])])


def nan_policy(shape, n: int) -> bytes:
    """Logits that turn NaN once the observation has any non-zero byte (log of a negative number):
    finite on the zero observations of the load check, NaN on the first real frame."""
    g = Graph(0)
    flat = g.op("Flatten", ["obs"], axis=1)
    total = g.op("MatMul", [flat, g.constant(np.ones((int(np.prod(shape)), 1)))])
    bad = g.op("Log", [g.op("Sub", [g.constant(0.5), total])])
    g.op("Add", [g.op("Mul", [bad, g.constant(np.zeros(n))]), g.constant(np.zeros(n))], "logits")
    return g.model([obs_input(shape)], [output("logits", ["batch", n])])


def with_op(shape, n: int, op_type: str = "RandomNormalLike") -> bytes:
    """A categorical policy whose logits pass through `op_type` (one the server refuses)."""
    g = Graph(0)
    flat = g.op("Flatten", ["obs"], axis=1)
    x = g.linear(flat, int(np.prod(shape)), n)
    g.op("Add", [x, g.op(op_type, [x])], "logits")
    graph = helper.make_graph(g.nodes, "policy", [obs_input(shape)], [output("logits", ["batch", n])], g.weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    return model.SerializeToString()


def external_data(shape, n: int) -> bytes:
    """A categorical policy whose weight says it lives in a file beside the model (/etc/passwd)."""
    model = onnx.load_from_string(conv_categorical(shape, n, value=False))
    weight = model.graph.initializer[0]
    weight.ClearField("raw_data")
    weight.data_location = TensorProto.EXTERNAL
    entry = weight.external_data.add()
    entry.key, entry.value = "location", "/etc/passwd"
    return model.SerializeToString()


def sparse_exfiltration(shape, n: int, location: str = "creds.txt", count: int = 4) -> bytes:
    """The hostile probe of issue 53: a categorical policy whose value output adds a Constant whose
    sparse_value keeps its values in external data (`location`, relative to the runtime's working
    directory): `count` float32 values read from that file, summed into every env's value."""
    g = Graph(0)
    x = g.op("Flatten", [g.op("Div", ["obs", g.constant(255.0)])], axis=1)
    x = g.op("Tanh", [g.linear(x, int(np.prod(shape)), 16)])
    g.linear(x, 16, n, "logits", scale=1.0)
    values = TensorProto(name="leak_values", data_type=TensorProto.FLOAT, dims=[count])
    values.data_location = TensorProto.EXTERNAL
    for key, value in (("location", location), ("offset", "0"), ("length", str(4 * count))):
        entry = values.external_data.add()
        entry.key, entry.value = key, value
    indices = numpy_helper.from_array(np.arange(count, dtype=np.int64), "leak_indices")
    sparse = helper.make_sparse_tensor(values, indices, [count])
    g.nodes.append(helper.make_node("Constant", [], ["leak"], name="leak", sparse_value=sparse))
    leaked = g.op("ReduceSum", ["leak", g.constant_int([0])], keepdims=1)
    g.op("Add", [g.linear(x, 16, 1), leaked], "value")
    graph = helper.make_graph(g.nodes, "policy", [obs_input(shape)], [output("logits", ["batch", n]), output("value", ["batch", 1])], g.weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    return model.SerializeToString()


def memory_bomb(shape, n: int, kind: str, pad_scale: float = float(1 << 24)) -> bytes:
    """A categorical policy of a few hundred bytes within the allowed operators whose value output
    needs gigabytes (issue 53's probes): "concat", 30 chained doublings of one float (4 GiB at
    constant folding); "broadcast", [2^16, 1] + [1, 2^16] (16 GiB at constant folding); "pad", the
    observations padded by their largest byte x 2^24 columns (nothing on the zero observations of
    the load check, ~16 GiB per env on the first real frame)."""
    g = Graph(0)
    flat = g.op("Flatten", [g.op("Div", ["obs", g.constant(255.0)])], axis=1)
    g.op("Tanh", [g.linear(flat, int(np.prod(shape)), n)], "logits")
    if kind == "concat":
        x = g.constant([1.0])
        for _ in range(30):
            x = g.op("Concat", [x, x], axis=0)
        big = g.op("ReduceSum", [x, g.constant_int([0])], keepdims=1)
    elif kind == "broadcast":
        column = g.constant([[1.0]])
        for _ in range(16):
            column = g.op("Concat", [column, column], axis=0)
        row = g.op("Transpose", [column], perm=[1, 0])
        big = g.op("ReduceSum", [g.op("Add", [column, row])], keepdims=0)
        big = g.op("Reshape", [big, g.constant_int([1])])
    elif kind == "pad":
        largest = g.op("ReduceMax", ["obs"], keepdims=0)
        columns = g.op("Cast", [g.op("Mul", [largest, g.constant(pad_scale)])], to=TensorProto.INT64)
        pads = g.op("Concat", [g.constant_int([0] * (2 * (len(shape) + 1) - 1)), g.op("Reshape", [columns, g.constant_int([1])])], axis=0)
        padded = g.op("Pad", ["obs", pads], mode="constant")
        big = g.op("Reshape", [g.op("ReduceSum", [padded], keepdims=0), g.constant_int([1])])
    else:
        raise ValueError(kind)
    g.op("Add", [g.op("Mul", [g.linear(flat, int(np.prod(shape)), 1), g.constant(1.0)]), g.op("Mul", [big, g.constant(0.0)])], "value")
    graph = helper.make_graph(g.nodes, "policy", [obs_input(shape)], [output("logits", ["batch", n]), output("value", ["batch", 1])], g.weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    return model.SerializeToString()


def many_nodes(shape, n: int, count: int) -> bytes:
    """A categorical policy whose logits pass through `count` Identity nodes (a graph too large to
    load: a million took ONNX Runtime minutes)."""
    g = Graph(0)
    x = g.linear(g.op("Flatten", ["obs"], axis=1), int(np.prod(shape)), n)
    for _ in range(count - 1):
        x = g.op("Identity", [x])
    g.op("Identity", [x], "logits")
    graph = helper.make_graph(g.nodes, "policy", [obs_input(shape)], [output("logits", ["batch", n])], g.weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    return model.SerializeToString()


def random_policy(seed: int, obs_dim: int, n: int, max_width: int = 1 << 30) -> bytes:
    """A categorical policy drawn from a grammar of the allowed operators with random sizes, for the
    property test of the policy runtime's limits: the observations [batch, obs_dim] pass through
    2 to 8 random layers on a [batch, width] tensor (elementwise ops, MatMul, Concat doubling, Pad,
    a broadcast through a third axis, Softmax, Transpose round trips), then ReduceSum and a bias make
    the logits. Widths are drawn log-uniformly up to `max_width`, so some models are small, some
    need gigabytes at their first run; weights stay small (MatMul only while width x out <= 2^22)."""
    rng = np.random.default_rng(seed)
    g = Graph(seed)
    x, width = "obs", obs_dim
    for _ in range(int(rng.integers(2, 9))):
        choice = rng.choice(["unary", "binary", "matmul", "concat", "pad", "broadcast", "softmax", "transpose"])
        if choice == "unary":
            x = g.op(str(rng.choice(["Relu", "Tanh", "Sigmoid", "Abs", "Neg", "Softsign"])), [x])
        elif choice == "binary":
            x = g.op(str(rng.choice(["Add", "Mul", "Sub", "Max", "Min"])), [x, g.constant(rng.standard_normal((1, 1)))])
        elif choice == "matmul":
            out = int(2 ** rng.uniform(0, 12))
            if width * out <= 1 << 22:
                x, width = g.op("MatMul", [x, g.weight((width, out), 0.1)]), out
        elif choice == "concat":
            for _ in range(int(rng.integers(1, 6))):
                x, width = g.op("Concat", [x, x], axis=1), width * 2
        elif choice == "pad":
            extra = int(2 ** rng.uniform(0, np.log2(max_width)))
            x, width = g.op("Pad", [x, g.constant_int([0, 0, 0, extra])], mode="constant"), width + extra
        elif choice == "broadcast":
            depth = int(2 ** rng.uniform(0, 16))
            wide = g.op("Add", [g.op("Unsqueeze", [x, g.constant_int([1])]), g.constant(np.zeros((depth, 1)))])
            x = g.op("ReduceSum", [wide, g.constant_int([1])], keepdims=0)
        elif choice == "softmax":
            x = g.op("Softmax", [x], axis=1)
        else:
            x = g.op("Transpose", [g.op("Transpose", [x], perm=[1, 0])], perm=[1, 0])
    total = g.op("ReduceSum", [x, g.constant_int([1])], keepdims=1)
    g.op("Add", [g.op("Mul", [total, g.constant(1e-3)]), g.constant(rng.standard_normal((1, n)))], "logits")
    graph = helper.make_graph(g.nodes, "policy", [obs_input((obs_dim,))], [output("logits", ["batch", n])], g.weights)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 8
    return model.SerializeToString()


def _constant_int(self: Graph, value) -> str:
    name = self.name("i")
    self.weights.append(numpy_helper.from_array(np.asarray(value, dtype=np.int64), name))
    return name


Graph.constant_int = _constant_int


def write_rust_models() -> None:
    """The fixtures of server/policy's tests and the server's: the fake simulators' observations are
    uint8 [1, 2, 2], their actions Discrete(3)."""
    RUST_MODELS.mkdir(parents=True, exist_ok=True)
    fake = (1, 2, 2)
    models = {
        "categorical_fake.onnx": conv_categorical(fake, 3),
        "categorical_fake_u8.onnx": conv_categorical(fake, 3, value=False, uint8=True),
        "pick_first_byte.onnx": pick_first_byte(fake, 3),
        "nan_fake.onnx": nan_policy(fake, 3),
        "random_op_fake.onnx": with_op(fake, 3),
        "external_fake.onnx": external_data(fake, 3),
        "sparse_external_fake.onnx": sparse_exfiltration(fake, 3),
        "concat_bomb_fake.onnx": memory_bomb(fake, 3, "concat"),
        "broadcast_bomb_fake.onnx": memory_bomb(fake, 3, "broadcast"),
        "pad_bomb_fake.onnx": memory_bomb(fake, 3, "pad"),
        "gaussian_3x2.onnx": mlp_gaussian(3, 2, hidden=8),
        # gym/CartPole-v1 (float32 [4], Discrete(2)) and gym/Pendulum-v1 (float32 [3], Box(1)):
        # the fuzzer's base sessions.
        "categorical_cartpole.onnx": conv_categorical((4,), 2),
        "gaussian_pendulum.onnx": mlp_gaussian(3, 1, hidden=8),
    }
    for name, data in models.items():
        (RUST_MODELS / name).write_bytes(data)
        print(f"{RUST_MODELS / name}: {len(data)} bytes")


if __name__ == "__main__":
    write_rust_models() if len(sys.argv) == 1 else sys.exit(f"usage: {sys.argv[0]}")
