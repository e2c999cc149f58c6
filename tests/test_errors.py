"""Bad input is answered with a typed error that says what was expected; the server keeps serving."""

import os
import signal
import time

import grpc
import numpy as np
import pytest

import radserve
from _procs import wait_serving, worker_pids


def test_unknown_env_names_close_matches(client):
    with pytest.raises(radserve.NotFoundError, match="did you mean dmc/cheetah-run"):
        client.make_vec("dmc/cheetah-runn")
    with pytest.raises(radserve.NotFoundError, match="unknown environment id 'atari/pong'"):
        client.make_vec("atari/pong")


def test_bad_options_say_what_is_accepted(client):
    with pytest.raises(radserve.InvalidArgumentError, match="accepted options: .*frame_stack"):
        client.make_vec("gym/CartPole-v1", colour=True)
    with pytest.raises(radserve.InvalidArgumentError, match=r"frame_stack.*\[1, 16\]"):
        client.make_vec("gym/CartPole-v1", frame_stack=0)
    with pytest.raises(radserve.InvalidArgumentError, match="one of easy, hard"):
        client.make_vec("procgen/bigfish", distribution_mode="medium")
    with pytest.raises(radserve.InvalidArgumentError, match="must be a bool"):
        client.make_vec("dmc/cheetah-run", pixels="yes")


def test_sizes_and_seeds_are_checked(client):
    with pytest.raises(radserve.InvalidArgumentError, match="num_envs must be at least 1"):
        client.make_vec("gym/CartPole-v1", num_envs=0)
    # Larger than any session may be: no retry helps, so not RESOURCE_EXHAUSTED.
    with pytest.raises(radserve.InvalidArgumentError, match="per session"):
        client.make_vec("gym/CartPole-v1", num_envs=100_000)
    with pytest.raises(radserve.InvalidArgumentError, match="32-bit seeds"):
        client.make_vec("gym/CartPole-v1", seed=2**40)


def test_unknown_sessions_and_step_before_reset(client):
    with pytest.raises(radserve.NotFoundError, match="unknown session 'nope'"):
        client.describe_session("nope")
    envs = client.make_vec("gym/CartPole-v1", num_envs=2)
    try:
        with pytest.raises(radserve.FailedPreconditionError, match="Reset"):
            envs.step(np.zeros(2, dtype=np.int64))
        with pytest.raises(radserve.InvalidArgumentError, match="int64 of shape \\[2\\]"):
            envs.reset()
            envs.step(np.zeros((2, 3), dtype=np.float32))
    finally:
        envs.close()
    with pytest.raises(radserve.NotFoundError):
        client.close_session(envs.session_id)


def test_act_stream_gives_the_same_results_as_unary_calls(client):
    unary = client.make_vec("gym/Pendulum-v1", num_envs=3, seed=4)
    streamed = client.make_vec("gym/Pendulum-v1", num_envs=3, seed=4, stream=True)
    try:
        np.testing.assert_array_equal(unary.reset()[0], streamed.reset()[0])
        actions = np.random.default_rng(0).uniform(-2, 2, size=(20, 3, 1)).astype(np.float32)
        for action in actions:
            np.testing.assert_array_equal(unary.step(action)[0], streamed.step(action)[0])
        with pytest.raises(radserve.InvalidArgumentError):
            streamed.step(np.zeros((3, 2), dtype=np.float32))
    finally:
        unary.close()
        streamed.close()


@pytest.mark.parametrize("stream", [False, True], ids=["unary", "stream"])
def test_step_async_then_wait_gives_what_step_gives(client, stream):
    """Two sessions pipelined (one's step in flight while the other is read) give, step for step,
    what plain step() gives; a bad action surfaces at step_wait (and, unary, the session keeps going;
    an error status ends an Act stream, as gRPC streams end)."""
    plain = client.make_vec("gym/Pendulum-v1", num_envs=3, seed=8)
    pipelined = [client.make_vec("gym/Pendulum-v1", num_envs=3, seed=8, stream=stream) for _ in range(2)]
    try:
        first = plain.reset()[0]
        for envs in pipelined:
            np.testing.assert_array_equal(envs.reset()[0], first)
        actions = np.random.default_rng(1).uniform(-2, 2, size=(15, 3, 1)).astype(np.float32)
        pipelined[0].step_async(actions[0])
        for t, action in enumerate(actions):
            expected = plain.step(action)
            pipelined[1].step_async(action)  # in flight while session 0's reply is read
            got = [pipelined[0].step_wait(), pipelined[1].step_wait()]
            if t + 1 < len(actions):
                pipelined[0].step_async(actions[t + 1])
            for result in got:
                for want, have in zip(expected[:4], result[:4]):
                    np.testing.assert_array_equal(want, have)
        with pytest.raises(RuntimeError, match="step_wait"):
            pipelined[0].step_wait()
        pipelined[0].step_async(np.zeros((3, 2), dtype=np.float32))
        with pytest.raises(RuntimeError, match="awaits"):
            pipelined[0].step(actions[0])
        with pytest.raises(radserve.InvalidArgumentError, match="shape"):
            pipelined[0].step_wait()
        if not stream:
            assert pipelined[0].step(actions[0])[0].shape == (3, 3)
    finally:
        plain.close()
        for envs in pipelined:
            envs.close()


def test_health_reports_serving(server):
    """SERVING once the catalog is built (tens of seconds after the start)."""
    with grpc.insecure_channel(server.address) as channel:
        wait_serving(channel, "radserve.v1.RadServe")


def test_a_dead_worker_ends_its_episodes_and_is_replaced(server, client, catalog):
    # `catalog` first: the transient worker that builds it must be gone before workers are counted.
    victim_session = client.make_vec("gym/HalfCheetah-v5", num_envs=2, seed=0, autoreset_mode="SameStep")
    bystander = client.make_vec("gym/CartPole-v1", num_envs=1, seed=0)
    try:
        victim_session.reset()
        bystander.reset()
        before = worker_pids(server.process.pid)
        assert len(before) == 2
        os.kill(before[0], signal.SIGKILL)
        time.sleep(0.2)
        actions = np.zeros((2, 6), dtype=np.float32)
        _, _, _, truncated, infos = victim_session.step(actions)
        # One env lived in the killed worker: its episode ended, reported with the reason.
        assert truncated.sum() == 1
        i = int(np.flatnonzero(truncated)[0])
        assert "died" in infos["radserve_error"][i]
        assert infos["final_obs"][i].shape == (17,)
        after = worker_pids(server.process.pid)
        assert len(after) == 2 and before[0] not in after
        # Everything keeps working afterwards, for this session and the others.
        for _ in range(3):
            victim_session.step(actions)
            bystander.step(np.zeros(1, dtype=np.int64))
    finally:
        victim_session.close()
        bystander.close()
