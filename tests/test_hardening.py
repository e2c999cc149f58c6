"""Hostile requests through grpcio, the client most learners use: malformed messages and oversized
fields get the status that names the client's mistake, in a message a client can read. The same
requests through the generated Rust stubs, with a check that the server serves everyone else after
each: server/radserve/tests/hardening.rs."""

import subprocess
import sys
import time
from pathlib import Path

import grpc
import pytest

import radserve
from radserve.proto import radserve_pb2 as pb


def _raw_call(server, method):
    channel = grpc.insecure_channel(server.address)
    call = channel.unary_unary(f"/radserve.v1.RadServe/{method}", request_serializer=None, response_deserializer=None)
    return channel, call


@pytest.mark.parametrize("payload", [b"\xff\xff\xff", b"\x0a\xff\x01", b"\x12\x05abc"], ids=["bad-tag", "truncated", "short-field"])
def test_malformed_protobuf_is_the_clients_fault(server, client, payload):
    channel, call = _raw_call(server, "CreateSession")
    with channel:
        with pytest.raises(grpc.RpcError) as raised:
            call(payload, timeout=10)
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "not a valid CreateSessionRequest protobuf" in raised.value.details()
    assert client.list_envs("gym/CartPole")  # still serving


def test_huge_ids_come_back_as_the_real_error(client):
    # A 100 KB id used to be echoed whole: grpcio refused the trailer ("metadata size exceeds hard
    # limit", RESOURCE_EXHAUSTED) and the caller never saw why the call failed.
    with pytest.raises(radserve.NotFoundError, match=r"unknown session 'sss.*\(100000 bytes in all\)"):
        client.describe_session("s" * 100_000)
    with pytest.raises(radserve.InvalidArgumentError, match="env_id is 100000 bytes long; the most accepted is 256"):
        client.make_vec("e" * 100_000)
    with pytest.raises(radserve.InvalidArgumentError, match="a pipeline has at most 8 stages"):
        envs = client.make_vec("gym/CartPole-v1", replay_capacity=100)
        try:
            envs.reset()
            envs.sample_batches(batch_size=1, augment="|".join(["noise"] * 100))
        finally:
            envs.close()


def test_malformed_stream_messages_end_the_stream_cleanly(server, client):
    channel = grpc.insecure_channel(server.address)
    with channel:
        act = channel.stream_stream("/radserve.v1.RadServe/Act", request_serializer=None, response_deserializer=None)
        replies = act(iter([b"\xff\xff\xff"]), timeout=10)
        with pytest.raises(grpc.RpcError) as raised:
            list(replies)
    assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT, raised.value
    assert "not a valid ActRequest protobuf" in raised.value.details()
    envs = client.make_vec("gym/CartPole-v1")  # still serving
    envs.close()


def test_typed_requests_with_wrong_enum_values_are_refused(server, client):
    envs = client.make_vec("gym/CartPole-v1", replay_capacity=100)
    try:
        envs.reset()
        request = pb.SampleBatchesRequest(session_id=envs.session_id, batch_size=1, sharing=77)
        with grpc.insecure_channel(server.address) as channel:
            sample = channel.unary_stream(
                "/radserve.v1.RadServe/SampleBatches",
                request_serializer=pb.SampleBatchesRequest.SerializeToString,
                response_deserializer=pb.BatchChunk.FromString,
            )
            with pytest.raises(grpc.RpcError) as raised:
                next(iter(sample(request, timeout=10)))
        assert raised.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "unknown DrawSharing value 77" in raised.value.details()
    finally:
        envs.close()


def test_sessions_of_a_process_that_exits_are_closed(server, client):
    script = (
        "import sys, radserve\n"
        "client = radserve.Client(sys.argv[1])\n"
        "kept = [client.make_vec('gym/CartPole-v1', num_envs=2) for _ in range(2)]\n"
        "closed = client.make_vec('gym/Pendulum-v1'); closed.close()\n"
        "print(' '.join(envs.session_id for envs in kept), flush=True)\n"
        "listed = {s.session_id for s in client.list_sessions()}\n"
        "assert all(envs.session_id in listed for envs in kept), listed\n"
    )
    done = subprocess.run([sys.executable, "-c", script, server.address], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    ids = done.stdout.split()
    assert len(ids) == 2
    open_ids = {summary.session_id for summary in client.list_sessions()}
    assert not open_ids & set(ids), "the exiting process closed the sessions it left open"


def test_list_sessions_reports_what_each_session_holds(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=3, replay_capacity=1000)
    try:
        envs.reset()
        summary = next(s for s in client.list_sessions() if s.session_id == envs.session_id)
        assert (summary.env_id, summary.num_envs, summary.open_streams) == ("gym/CartPole-v1", 3, 0)
        # The replay buffer, the envs at their family's cost, their frame buffers.
        assert summary.memory_bytes > client.describe_session(envs.session_id).replay.memory_bytes
        assert 0 <= summary.idle_seconds < 5 and summary.age_seconds >= summary.idle_seconds
        assert summary.idle_timeout_seconds == 300
    finally:
        envs.close()


def _under_file_limit(tmp_path, files: int) -> str:
    """A launcher that runs the server binary with `files` as its hard and soft open-file limit."""
    script = tmp_path / f"radserve-nofile-{files}"
    script.write_text(f'#!/bin/sh\nexec prlimit --nofile={files}:{files} -- {radserve.server.find_binary()} "$@"\n')
    script.chmod(0o755)
    return str(script)


def test_a_low_open_file_limit_serves_many_connections_or_refuses_to_start(tmp_path):
    # At 258 open files the old sizing, (limit - 256) / 2, served one connection at a time: the
    # second client's connection was closed as it arrived.
    with radserve.LocalServer(workers=1, binary=_under_file_limit(tmp_path, 258)) as server:
        # A subchannel pool per channel: grpcio otherwise shares one connection between channels.
        channels = [grpc.insecure_channel(server.address, options=[("grpc.use_local_subchannel_pool", 1)])
                    for _ in range(8)]
        try:
            stubs = [radserve.proto.radserve_pb2_grpc.RadServeStub(channel) for channel in channels]
            for stub in stubs:
                stub.ServerInfo(pb.ServerInfoRequest(), timeout=30)
            for stub in stubs:  # every connection still open and served
                assert stub.ServerInfo(pb.ServerInfoRequest(), timeout=30).version == radserve.__version__
        finally:
            for channel in channels:
                channel.close()
    # Too few to serve at all: refused at start, saying what to raise.
    refused = subprocess.run([_under_file_limit(tmp_path, 24), "serve", "--address", "127.0.0.1:0", "--workers", "1"],
                             capture_output=True, text=True, timeout=120)
    assert refused.returncode != 0, refused.stderr
    assert "the open-file limit (24) leaves room for" in refused.stderr and "raise it to at least" in refused.stderr, refused.stderr


def _augment_threads(pid: int) -> "dict[str, tuple[int, int]]":
    """The server's augmentation threads: name -> (scheduling policy, nice), from /proc/<pid>/task."""
    threads = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        stat = (task / "stat").read_text()
        name = stat[stat.index("(") + 1:stat.rindex(")")]
        if name.startswith("radserve-augmen"):  # the kernel keeps 15 characters of a thread's name
            fields = stat[stat.rindex(")") + 2:].split()
            threads[task.name] = (int(fields[38]), int(fields[16]))  # policy (field 41), nice (field 19)
    return threads


@pytest.mark.parametrize("settings,expected", [({}, (0, 0)), ({"RADSERVE__AUGMENT__NICE": "19"}, (0, 19)),
                                               ({"RADSERVE__AUGMENT__IDLE": "true"}, (5, 0))],
                         ids=["default", "nice", "idle"])
def test_augmentation_threads_run_at_the_configured_priority(settings, expected):
    # Acting ahead of augmentation: augment.nice lowers the threads' niceness, augment.idle puts them
    # in SCHED_IDLE (policy 5); the rayon pool starts its threads when the server starts.
    with radserve.LocalServer(workers=1, env={"RADSERVE__AUGMENT__THREADS": "2", **settings}) as server:
        # The pool is built as the server starts serving, after its address is out; each thread shows in
        # /proc before its start handler has lowered its priority, so wait for the settled state.
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            threads = _augment_threads(server.process.pid)
            if len(threads) == 2 and set(threads.values()) == {expected}:
                break
            time.sleep(0.05)
    assert len(threads) == 2, threads
    assert set(threads.values()) == {expected}, threads
