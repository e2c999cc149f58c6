"""The client's own pieces, without a server: conversions, error mapping, generated stubs."""

import filecmp
import subprocess
from pathlib import Path

import grpc
import numpy as np
import pytest
from gymnasium import spaces

import radserve
from radserve import proto
from radserve.proto import radserve_pb2 as pb
from radserve.errors import from_rpc_error

CLIENT = Path(__file__).resolve().parents[1]


def test_tensors_round_trip_without_changing_values():
    for array in [np.arange(12, dtype=np.uint8).reshape(3, 4), np.linspace(-1, 1, 6, dtype=np.float32),
                  np.array([[1, -2]], dtype=np.int64), np.array([0.5, np.inf])]:
        back = proto.to_numpy(proto.to_tensor(array))
        assert back.dtype == array.dtype and back.shape == array.shape
        np.testing.assert_array_equal(back, array)


def test_spaces_become_gymnasium_spaces():
    image = pb.Space(box=pb.BoxSpace(dtype=pb.DTYPE_UINT8, shape=[9, 4, 4], low=[0], high=[255]))
    assert proto.to_space(image) == spaces.Box(0, 255, (9, 4, 4), np.uint8)
    action = pb.Space(box=pb.BoxSpace(dtype=pb.DTYPE_FLOAT32, shape=[2], low=[-1, -2], high=[1, 2]))
    assert proto.to_space(action) == spaces.Box(np.array([-1, -2], np.float32), np.array([1, 2], np.float32))
    assert proto.to_space(pb.Space(discrete=pb.DiscreteSpace(n=15))) == spaces.Discrete(15)


def test_option_values_keep_their_python_type():
    for value in [True, 3, 0.5, "easy"]:
        back = proto.from_option_value(proto.option_value(value))
        assert back == value and type(back) is type(value)
    with pytest.raises(TypeError):
        proto.option_value([1])


class _FakeRpcError(grpc.RpcError):
    def __init__(self, code, details):
        self._code, self._details = code, details

    def code(self):
        return self._code

    def details(self):
        return self._details


def test_status_codes_map_to_typed_errors():
    error = from_rpc_error(_FakeRpcError(grpc.StatusCode.NOT_FOUND, "unknown environment id"))
    assert isinstance(error, radserve.NotFoundError) and isinstance(error, radserve.RadServeError)
    assert str(error) == "unknown environment id" and error.code == grpc.StatusCode.NOT_FOUND
    assert type(from_rpc_error(_FakeRpcError(grpc.StatusCode.DATA_LOSS, "x"))) is radserve.RadServeError
    for code, cls in [(grpc.StatusCode.DEADLINE_EXCEEDED, radserve.DeadlineExceededError),
                      (grpc.StatusCode.CANCELLED, radserve.CancelledError),
                      (grpc.StatusCode.UNIMPLEMENTED, radserve.UnimplementedError)]:
        error = from_rpc_error(_FakeRpcError(code, "why"))
        assert type(error) is cls and error.code == code and str(error) == "why"


def test_generated_stubs_are_up_to_date(tmp_path):
    subprocess.run([str(CLIENT / "scripts" / "gen_proto.sh"), str(tmp_path)], check=True)
    generated = CLIENT / "radserve" / "_proto"
    for name in ["radserve_pb2.py", "radserve_pb2.pyi", "radserve_pb2_grpc.py"]:
        assert filecmp.cmp(tmp_path / name, generated / name, shallow=False), f"{name} is stale: run make proto"


def test_a_started_server_does_not_outlive_a_killed_learner():
    import os
    import signal
    import sys
    import time

    learner = subprocess.Popen(
        [sys.executable, "-c", "import radserve, time\n"
         "server = radserve.LocalServer(workers=1)\nserver.start()\nprint(server.process.pid, flush=True)\ntime.sleep(120)"],
        stdout=subprocess.PIPE, text=True)
    server_pid = int(learner.stdout.readline())
    learner.send_signal(signal.SIGKILL)  # no cleanup runs in the learner
    learner.wait()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{server_pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except FileNotFoundError:
            return
        if state == "Z":  # exited; its new parent has not reaped it yet
            return
        time.sleep(0.1)
    os.kill(server_pid, signal.SIGKILL)
    raise AssertionError("the server kept running after the learner that started it was killed")
