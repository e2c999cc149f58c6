"""Property-based fuzzing through grpcio (the client learners use) with hypothesis: random but
well-typed requests to every RPC of a real server with small limits. Every answer is OK or a status
from the documented set, the server keeps serving, and what a refused or closed request reserved is
returned. `make fuzz` raises the number of examples (RADSERVE_FUZZ_EXAMPLES). The same properties
through the generated Rust stubs, with raw bytes as any method's message:
server/radserve/tests/fuzz.rs."""

import os
import time

import grpc
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import radserve
from radserve.proto import radserve_pb2 as pb
from radserve.proto import radserve_pb2_grpc as pb_grpc

EXAMPLES = int(os.environ.get("RADSERVE_FUZZ_EXAMPLES", "100"))

DOCUMENTED = {
    grpc.StatusCode.OK, grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND,
    grpc.StatusCode.FAILED_PRECONDITION, grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.DEADLINE_EXCEEDED,
    grpc.StatusCode.CANCELLED,
}

LIMITS = {
    "RADSERVE__LIMITS__MAX_SESSIONS": "8", "RADSERVE__LIMITS__MAX_ENVS_PER_SESSION": "8",
    "RADSERVE__LIMITS__MAX_TOTAL_ENVS": "24", "RADSERVE__LIMITS__MEMORY_BYTES": str(1 << 30),
    "RADSERVE__LIMITS__REPLAY_MEMORY_BYTES": str(256 << 20), "RADSERVE__LIMITS__MAX_STREAMS_PER_SESSION": "2",
    "RADSERVE__LIMITS__STREAM_MEMORY_BYTES": str(64 << 20),
}


@pytest.fixture(scope="module")
def fuzzed():
    """A server of its own (small limits), a raw stub, and two live sessions the examples can target."""
    with radserve.LocalServer(workers=2, env=LIMITS) as server:
        channel = grpc.insecure_channel(server.address)
        stub = pb_grpc.RadServeStub(channel)
        base = []
        for capacity in (300, 0):
            replay = pb.ReplayOptions(capacity=capacity) if capacity else None
            info = stub.CreateSession(pb.CreateSessionRequest(env_id="gym/CartPole-v1", num_envs=2, replay=replay))
            stub.Reset(pb.ResetRequest(session_id=info.session_id, seed=0))
            for step in range(30):
                actions = pb.Tensor(dtype=pb.DTYPE_INT64, shape=[2], data=(step % 2).to_bytes(8, "little") * 2)
                stub.Step(pb.StepRequest(session_id=info.session_id, actions=actions))
            base.append(info.session_id)
        yield server, stub, base
        channel.close()


u32 = st.one_of(st.integers(0, 8), st.integers(0, 2**32 - 1), st.sampled_from([2**32 - 1, 2**16, 64 << 10, 128 << 20]))
u64 = st.one_of(st.integers(0, 8), st.integers(0, 2**64 - 1), st.sampled_from([2**64 - 1, 2**40, 409927646082434480]))
f64 = st.one_of(st.floats(-2, 100), st.sampled_from([0.0, float("nan"), float("inf"), -float("inf"), 1e308]))
text = lambda *plausible: st.one_of(st.sampled_from(plausible), st.text(max_size=24), st.just("x" * 300))  # noqa: E731

env_ids = text("gym/CartPole-v1", "gym/Pendulum-v1", "gym/Acrobot-v1", "procgen/bigfish", "gym/CartPole-v9", "", "gym/")
option_values = st.one_of(
    st.builds(pb.OptionValue, bool_value=st.booleans()),
    st.builds(pb.OptionValue, int_value=st.integers(-2**63, 2**63 - 1)),
    st.builds(pb.OptionValue, int_value=st.integers(-2, 20)),
    st.builds(pb.OptionValue, float_value=f64),
    st.builds(pb.OptionValue, string_value=text("easy", "fast", "hard")),
    st.just(pb.OptionValue()),
)
options = st.dictionaries(text("frame_stack", "action_repeat", "max_episode_steps", "num_levels", "distribution_mode",
                               "pixels", "height"), option_values, max_size=3)
pipelines = st.lists(text("crop(84)", "translate(12)", "noise(std=0.1)", "ras_s", "ras_m", "conv", "crpo", "none", "",
                          "shift(4)", "intensity"),
                     max_size=10).map("|".join)


@st.composite
def tensors(draw):
    dtype = draw(st.one_of(st.integers(0, 6), st.integers(-2**31, 2**31 - 1)))
    shape = draw(st.lists(st.one_of(st.integers(0, 3), st.integers(-2**63, 2**63 - 1)), max_size=3))
    elements = 1
    for dim in shape:
        elements *= max(dim, 0)
    size = {1: 1, 2: 4, 3: 8, 4: 4, 5: 8, 6: 1}.get(dtype, 1)
    if elements * size <= 256 and draw(st.booleans()):
        data = draw(st.binary(min_size=elements * size, max_size=elements * size))
    else:
        data = draw(st.binary(max_size=40))
    return pb.Tensor(dtype=dtype, shape=shape, data=data)


views = st.lists(st.builds(
    pb.SampleView, name=text("obs", "obs_aug", "next_obs", "anchor", "reward", "Obs", ""),
    of=st.one_of(st.integers(0, 2), st.integers(-2**31, 2**31 - 1)), pipeline_text=pipelines, draws=text("", "a")),
    max_size=10)


def sample_requests(session_id):
    return st.builds(
        pb.SampleBatchesRequest, session_id=st.just(session_id), batch_size=u32, pipeline_text=pipelines,
        sharing=st.integers(0, 3), prefetch=u32, seed=u64, min_size=st.one_of(st.none(), u64),
        samples_per_insert=st.one_of(st.none(), f64), error_buffer=f64, max_batches=st.one_of(st.none(), st.integers(0, 4)),
        chunk_bytes=u32, source=st.integers(0, 2), epochs=u32, include_next_obs=st.one_of(st.none(), st.booleans()),
        views=st.one_of(st.just([]), views), n_step=st.one_of(st.none(), st.integers(0, 70), u32),
        discount=st.one_of(st.none(), f64), sampler=st.one_of(st.integers(0, 1), st.integers(-2**31, 2**31 - 1)),
        priority_exponent=st.one_of(st.none(), f64), importance_sampling_exponent=st.one_of(st.none(), f64),
        sequence=st.one_of(st.none(), st.builds(
            pb.SequenceRequest, length=st.one_of(st.integers(0, 12), u32), burn_in=st.one_of(st.integers(0, 4), u32),
            period=st.one_of(st.integers(0, 4), u32), boundary=st.one_of(st.integers(0, 1), st.integers(-2**31, 2**31 - 1)))),
    )


@st.composite
def calls(draw, base):
    """One RPC and its request; session ids are mostly live ones."""
    session_id = draw(st.one_of(st.sampled_from(base), st.sampled_from(base), text("", "s-0", "../x")))
    kind = draw(st.sampled_from(["ListEnvs", "CreateSession", "DescribeSession", "ListSessions", "Reset", "Step", "Act",
                                 "SampleBatches", "SampleBatchesShared", "UpdatePriorities"]))
    if kind == "ListEnvs":
        return kind, pb.ListEnvsRequest(prefix=draw(text("", "gym/", "dmc/", "zzz")))
    if kind == "CreateSession":
        replay = draw(st.one_of(st.none(), st.builds(pb.ReplayOptions, capacity=u64, rollout_steps=u32)))
        return kind, pb.CreateSessionRequest(env_id=draw(env_ids), num_envs=draw(st.one_of(st.integers(0, 4), u32)),
                                             seed=draw(u64), options=draw(options), replay=replay,
                                             observation_view=draw(st.one_of(st.just(""), pipelines)))
    if kind in ("DescribeSession", "ListSessions"):
        return kind, (pb.DescribeSessionRequest(session_id=session_id) if kind == "DescribeSession" else pb.ListSessionsRequest())
    if kind == "UpdatePriorities":
        return kind, pb.UpdatePrioritiesRequest(session_id=session_id, keys=draw(st.lists(u64, max_size=4)),
                                                priorities=draw(st.lists(f64, max_size=4)))
    if kind == "Reset":
        return kind, pb.ResetRequest(session_id=session_id, seed=draw(st.one_of(st.none(), u64)))
    if kind == "Step":
        return kind, pb.StepRequest(session_id=session_id, actions=draw(tensors()))
    if kind == "Act":
        messages = draw(st.lists(st.one_of(
            st.builds(lambda seed: pb.ActRequest(reset=pb.ResetRequest(session_id=session_id, seed=seed)), st.one_of(st.none(), u64)),
            st.builds(lambda actions: pb.ActRequest(step=pb.StepRequest(session_id=session_id, actions=actions)), tensors()),
            st.just(pb.ActRequest()),
        ), max_size=3))
        return kind, messages
    request = draw(sample_requests(session_id))
    if kind == "SampleBatchesShared":
        releases = draw(st.lists(u64, max_size=2))
        return kind, [pb.SharedSampleRequest(start=request)] + [pb.SharedSampleRequest(release=slot) for slot in releases]
    return kind, request


def _answer(stub, kind, request):
    """Sends one call and returns its status code (streams: read a little, then leave)."""
    try:
        if kind in ("Act", "SampleBatchesShared"):
            replies = getattr(stub, kind)(iter(request), timeout=20 if kind == "Act" else 1.0)
            for _ in replies:
                pass
        elif kind == "SampleBatches":
            replies = stub.SampleBatches(request, timeout=1.0)
            for index, _ in enumerate(replies):
                if index >= 4:
                    replies.cancel()
                    break
        else:
            reply = getattr(stub, kind)(request, timeout=30)
            if kind == "CreateSession":
                stub.CloseSession(pb.CloseSessionRequest(session_id=reply.session_id))
        return grpc.StatusCode.OK, ""
    except grpc.RpcError as error:
        code = error.code()
        # A stream the client left (cancel, or its own deadline while the server waited for data).
        if kind in ("SampleBatches", "SampleBatchesShared") and code in (grpc.StatusCode.CANCELLED, grpc.StatusCode.DEADLINE_EXCEEDED):
            return grpc.StatusCode.OK, ""
        return code, error.details() or ""


def test_random_requests_get_documented_answers_and_the_server_keeps_serving(fuzzed):
    server, stub, base = fuzzed
    seen = {}

    @settings(max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(calls(base), min_size=1, max_size=5))
    def property(sequence):
        for kind, request in sequence:
            code, details = _answer(stub, kind, request)
            seen[code] = seen.get(code, 0) + 1
            assert code in DOCUMENTED, f"{kind}: undocumented {code}: {details[:300]}"
            assert len(details) <= 4096
        # Still serving, and every base session still there.
        listed = stub.ListSessions(pb.ListSessionsRequest(), timeout=10)
        assert set(base) <= {s.session_id for s in listed.sessions}

    property()
    # Streams the examples left end shortly; then only the base sessions hold anything.
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        listed = stub.ListSessions(pb.ListSessionsRequest(), timeout=10).sessions
        if all(s.open_streams == 0 for s in listed):
            break
        time.sleep(0.2)
    assert {s.session_id for s in listed} == set(base)
    assert all(s.open_streams == 0 for s in listed), listed
    assert server.process.poll() is None
    print(f"fuzz: {EXAMPLES} examples, answers {dict((c.name, n) for c, n in seen.items())}")
