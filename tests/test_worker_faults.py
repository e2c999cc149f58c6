"""Workers that hang or are replaced: a deadline on every worker call ends the stuck worker's episodes
as truncated instead of hanging the sessions that touch it; Describe never waits for a step; a
session whose worker was replaced while it was idle sees its episodes end; a client deadline that
passed while the call waited for its session keeps the step from being sent at all; health reports
the services NOT_SERVING while a worker is stuck, before its deadline."""

import threading
import time

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

import radserve
from _procs import stopped, worker_pids
from radserve.proto import radserve_pb2 as pb

CALL_TIMEOUT_S = 2.0
STUCK_AFTER_S = 0.5


@pytest.fixture(scope="module")
def strict_server():
    env = {"RADSERVE__SIM__WORKER_CALL_TIMEOUT_S": str(CALL_TIMEOUT_S),
           "RADSERVE__SIM__WORKER_STUCK_AFTER_S": str(STUCK_AFTER_S)}
    with radserve.LocalServer(workers=2, env=env) as server:
        with radserve.Client(server.address) as client:
            client.list_envs()  # the catalog (a transient worker) is built before workers are counted
        yield server


def _pool_workers(server):
    deadline = time.monotonic() + 30
    while len(workers := worker_pids(server.process.pid)) != 2:
        assert time.monotonic() < deadline, workers
        time.sleep(0.1)
    return workers


def _threaded(function):
    result = {}

    def run():
        try:
            result["value"] = function()
        except BaseException as error:  # noqa: BLE001 - handed to the test thread
            result["error"] = error

    thread = threading.Thread(target=run)
    thread.start()
    return thread, result


def _health(server, service):
    with grpc.insecure_channel(server.address) as channel:
        return health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=service), timeout=5).status


def _wait_for_health(server, service, status, until):
    while time.monotonic() < until:
        if _health(server, service) == status:
            return True
        time.sleep(0.05)
    return False


def test_a_stuck_worker_is_killed_its_episodes_end_and_idle_sessions_learn_of_it(strict_server):
    # SERVING first (the catalog built), so that NOT_SERVING below is the stuck worker's doing.
    assert _wait_for_health(strict_server, "radserve.v1.RadServe", health_pb2.HealthCheckResponse.SERVING,
                            time.monotonic() + 300)
    client = radserve.Client(strict_server.address)
    victim = client.make_vec("gym/HalfCheetah-v5", num_envs=2, seed=0)  # one env per worker
    idle = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0)
    try:
        victim.reset(seed=0)
        idle.reset(seed=0)
        for _ in range(3):
            idle.step(np.zeros(2, dtype=np.int64))
        stuck = _pool_workers(strict_server)[0]
        with stopped(stuck):
            started = time.monotonic()
            thread, result = _threaded(lambda: victim.step(np.zeros((2, 6), dtype=np.float32)))
            time.sleep(0.3)
            # Describe reads what the session has without waiting for the step that holds it.
            before = time.monotonic()
            assert client.describe_session(victim.session_id).total_env_steps == 0
            assert time.monotonic() - before < 1.0
            # Stuck past sim.worker_stuck_after_s, before its deadline: the services that would wait
            # for it say NOT_SERVING; the process itself ("") still serves.
            assert _wait_for_health(strict_server, "radserve.v1.RadServe", health_pb2.HealthCheckResponse.NOT_SERVING,
                                    started + CALL_TIMEOUT_S - 0.1), "health stayed SERVING while a worker was stuck"
            assert _health(strict_server, "dm_env_rpc.v1.Environment") == health_pb2.HealthCheckResponse.NOT_SERVING
            assert _health(strict_server, "") == health_pb2.HealthCheckResponse.SERVING
            thread.join(timeout=CALL_TIMEOUT_S + 20)
            assert not thread.is_alive(), "the step still hangs past the worker deadline"
            elapsed = time.monotonic() - started
        assert "error" not in result, result.get("error")
        _, _, terminated, truncated, infos = result["value"]
        assert elapsed < CALL_TIMEOUT_S + 15
        assert truncated.sum() == 1 and not terminated.any()
        env = int(np.flatnonzero(truncated)[0])
        assert f"did not answer within {CALL_TIMEOUT_S:g} s" in infos["radserve_error"][env], infos["radserve_error"]
        assert stuck not in _pool_workers(strict_server), "the stuck worker was replaced"
        assert _wait_for_health(strict_server, "radserve.v1.RadServe", health_pb2.HealthCheckResponse.SERVING,
                                time.monotonic() + 5), "health did not come back once the worker was replaced"
        # The idle session had an env on the replaced worker: its next step ends that episode
        # (truncated, with the reason) instead of stepping a fresh, unreset env.
        _, _, terminated, truncated, infos = idle.step(np.zeros(2, dtype=np.int64))
        assert truncated[env] and not terminated[env]
        assert "was restarted since this session last used it" in infos["radserve_error"][env]
        assert infos["radserve_episode"]["l"][env] == 4
        assert not truncated[1 - env] and not terminated[1 - env]
        # Both sessions keep acting afterwards.
        for _ in range(3):
            victim.step(np.zeros((2, 6), dtype=np.float32))
            idle.step(np.zeros(2, dtype=np.int64))
    finally:
        victim.close()
        idle.close()
        client.close()


def test_a_step_whose_deadline_passed_while_waiting_is_never_sent(strict_server):
    client = radserve.Client(strict_server.address)
    # SameStep: the env whose worker was killed is stepped again at once (NextStep would skip it).
    envs = client.make_vec("gym/HalfCheetah-v5", num_envs=2, seed=0, autoreset_mode="SameStep")
    try:
        envs.reset(seed=0)
        stuck = _pool_workers(strict_server)[0]
        with stopped(stuck):
            # The first step holds the session until the worker deadline kills the stuck worker.
            thread, result = _threaded(lambda: envs.step(np.zeros((2, 6), dtype=np.float32)))
            time.sleep(0.3)
            actions = pb.Tensor(dtype=pb.DTYPE_FLOAT32, shape=[2, 6], data=np.zeros((2, 6), dtype=np.float32).tobytes())
            request = pb.StepRequest(session_id=envs.session_id, actions=actions)
            # The client's own deadline, or tonic's answer to it ("Timeout expired", CANCELLED), each
            # its own error class.
            with pytest.raises((radserve.DeadlineExceededError, radserve.CancelledError)) as raised:
                client.transports[0].call("Step", request, timeout=0.5)
            assert raised.value.code in (grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.CANCELLED)
            thread.join(timeout=CALL_TIMEOUT_S + 20)
        assert "error" not in result, result.get("error")
        time.sleep(CALL_TIMEOUT_S)  # the late step would have run by now
        # One step taken (the one that waited out the stuck worker); the expired one never ran.
        assert client.describe_session(envs.session_id).total_env_steps == 2
        envs.step(np.zeros((2, 6), dtype=np.float32))
        assert client.describe_session(envs.session_id).total_env_steps == 4
    finally:
        envs.close()
        client.close()


@pytest.mark.parametrize("delivery", ["shared_memory", "grpc"])
def test_an_async_session_whose_worker_died_answers_an_error_then_steps_after_async_reset(strict_server, delivery):
    # EnvPool's asynchronous mode: the envs in flight die with their worker. The call waiting on them
    # gets an error (no hang, no other session touched) and the session asks for async_reset, which
    # starts it over in the worker that replaced the dead one.
    import os
    import signal

    client = radserve.Client(strict_server.address)
    envs = client.make_vec("gym/CartPole-v1", num_envs=4, seed=0, engine="envpool", batch_size=2, delivery=delivery)
    other = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0)
    try:
        other.reset(seed=0)
        envs.async_reset(seed=3)
        ids = envs.recv()[4]["env_id"]
        for worker in _pool_workers(strict_server):
            os.kill(worker, signal.SIGKILL)
        started = time.monotonic()
        with pytest.raises(radserve.RadServeError) as failed:
            for _ in range(5):
                ids = envs.step(np.zeros(len(ids), dtype=np.int64), ids)[4]["env_id"]
        assert time.monotonic() - started < CALL_TIMEOUT_S + 15
        with pytest.raises(radserve.FailedPreconditionError, match="AsyncReset before Send/Recv"):
            envs.recv()
        envs.async_reset(seed=3)
        ids = envs.recv()[4]["env_id"]
        assert len(ids) == 2, failed.value
        for _ in range(10):
            ids = envs.step(np.zeros(len(ids), dtype=np.int64), ids)[4]["env_id"]
        assert envs.describe()[0].total_env_steps >= 18
        other.step(np.zeros(2, dtype=np.int64))
    finally:
        envs.close()
        other.close()
        client.close()
