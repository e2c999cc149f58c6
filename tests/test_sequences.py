"""Sequences end to end through the real server and CartPole, against a numpy model of what the
client saw: each env's frames in order (reset observations, step observations and the final
observations of ended episodes), the step taken from each, and the window rules (within an episode
with padding and a period counted from its first frame; across episodes with flags). The Rust
twin: server/replay/tests/sequences.rs."""

from dataclasses import dataclass

import numpy as np
import pytest

import radserve

from test_replay import act


@dataclass
class Frame:
    stack: np.ndarray
    first: bool
    terminal: bool
    offset: int  # steps since its episode's first frame
    step: int  # the step taken from it, or (a last frame) the step that produced it
    taken: "dict | None"  # the step taken from it; None for an episode's last frame


def model_frames(seen, num_envs, steps):
    """Each env's frames as the client saw them, oldest first, up to its last step's outcome."""
    frames = []
    for env in range(num_envs):
        own, offset, first = [], 0, True
        for step in range(steps):
            transition = seen[(env, step)]
            own.append(Frame(transition["obs"], first, False, offset, step, transition))
            offset, first = offset + 1, False
            if transition["terminated"] or transition["truncated"]:
                own.append(Frame(transition["next_obs"], False, transition["terminated"], offset, step, None))
                offset, first = 0, True
        frames.append(own)
    return frames


def allowed(frames, start, length, burn_in, period, boundary):
    """The window rule, written from the docs: does a sequence start at frames[start]?"""
    if boundary == "across_episodes":
        # The last step's successor must be known: a step taken or its episode's end.
        return start % period == 0 and start + length <= len(frames)
    if frames[start].offset % period:
        return False
    for step in range(length):
        if start + step >= len(frames):
            return False
        if frames[start + step].taken is None:
            return step > burn_in
    return True


def locate(frames, batch, i):
    """The model frame a batch's sequence i starts at, by its env, step index and is_last."""
    env, step, last = int(batch.env_index[i, 0]), int(batch.step_index[i, 0]), bool(batch.is_last[i, 0])
    matches = [index for index, frame in enumerate(frames[env]) if frame.step == step and (frame.taken is None) == last]
    assert len(matches) == 1, (env, step, last)
    return env, matches[0]


def check_sequence(frames, batch, i, length, boundary):
    env, start = locate(frames, batch, i)
    ended = False
    for step in range(length):
        if ended:
            assert not batch.mask[i, step] and not batch.obs[i, step].any() and batch.reward[i, step] == 0
            assert not (batch.is_first[i, step] or batch.is_last[i, step] or batch.terminated[i, step])
            continue
        frame = frames[env][start + step]
        assert batch.mask[i, step]
        np.testing.assert_array_equal(batch.obs[i, step], frame.stack)
        assert (bool(batch.is_first[i, step]), bool(batch.is_terminal[i, step])) == (frame.first, frame.terminal)
        assert bool(batch.is_last[i, step]) == (frame.taken is None)
        assert batch.env_index[i, step] == env and batch.step_index[i, step] == frame.step
        if frame.taken is None:
            assert batch.action[i, step] == 0 and batch.reward[i, step] == 0 and batch.discount[i, step] == 0
            ended = boundary == "within_episode"
        else:
            taken = frame.taken
            assert batch.action[i, step] == taken["action"] and batch.reward[i, step] == taken["reward"]
            assert (bool(batch.terminated[i, step]), bool(batch.truncated[i, step])) == (taken["terminated"], taken["truncated"])
            assert batch.discount[i, step] == np.float32(0.0 if taken["terminated"] else 0.9)
    return env, start


@pytest.fixture(scope="module")
def cartpole(client):
    """Two CartPole envs, stacks of 2, 150 random steps: episodes of ~20 steps, many ends."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=8, replay_capacity=2000, frame_stack=2,
                           autoreset_mode="SameStep")
    seen = act(envs, 150, seed=8)
    yield envs, model_frames(seen, 2, 150)
    envs.close()


@pytest.mark.parametrize("delivery,boundary,length,burn_in,period", [
    ("grpc", "within_episode", 12, 3, 4),
    ("shared_memory", "within_episode", 6, 0, 1),
    ("grpc", "across_episodes", 30, 0, 1),
    ("shared_memory", "across_episodes", 8, 0, 5),
])
def test_sequences_are_the_windows_the_client_saw(cartpole, delivery, boundary, length, burn_in, period):
    envs, frames = cartpole
    sequence = radserve.Sequence(length, burn_in=burn_in, period=period, boundary=boundary)
    starts = set()
    padded = crossed = 0
    with envs.sample_batches(256, sequence=sequence, discount=0.9, seed=3, max_batches=20, delivery=delivery) as stream:
        for batch in stream:
            assert batch.obs.shape == (256, length, 8) and batch.obs.dtype == np.float32
            assert batch.next_obs is None, "a sequence's next observations are its steps"
            for name in ("action", "reward", "terminated", "is_first", "is_last", "is_terminal", "mask", "env_index",
                         "step_index", "discount"):
                assert getattr(batch, name).shape == (256, length), name
            assert batch.mask.dtype == bool and batch.is_first.dtype == bool
            for i in range(len(batch)):
                starts.add(check_sequence(frames, batch, i, length, boundary))
            padded += int((~batch.mask).any(axis=1).sum())
            crossed += int(batch.is_first[:, 1:].any(axis=1).sum())
    want = {(env, start) for env in range(2) for start in range(len(frames[env]))
            if allowed(frames[env], start, length, burn_in, period, boundary)}
    # The newest frames' successors are unknown to the model only where the server knows them
    # neither: every allowed start is drawn (5120 draws over a few hundred), nothing else.
    assert starts == want
    if boundary == "within_episode":
        assert padded > 0 and crossed == 0
    else:
        assert crossed > 0 and padded == 0


def test_a_sequence_stream_waits_for_a_window(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=1, seed=2, replay_capacity=500, autoreset_mode="SameStep")
    try:
        act(envs, 3, seed=2)
        sequence = radserve.Sequence(40, boundary="across_episodes")
        with envs.sample_batches(4, sequence=sequence, min_size=1, max_batches=1) as stream:
            # 3 frames recorded: no window of 40 yet; the stream waits rather than failing.
            act(envs, 60, seed=3)
            batch = next(stream)
        assert batch.obs.shape == (4, 40, 4) and batch.mask.all()
    finally:
        envs.close()


def test_bad_sequence_requests_are_refused(cartpole):
    envs, _ = cartpole
    refused = [
        (dict(sequence=radserve.Sequence(10, burn_in=10)), r"burn_in \(10\) must be below its length \(10\)"),
        (dict(sequence=0), "sequence length must be between 1 and 1024"),
        (dict(sequence=radserve.Sequence(10, period=2000)), "period must be between 1 and 1024"),
        (dict(sequence=1001), "a sequence of 1001 steps needs 1002 frames of one env"),
        (dict(sequence=10, include_next_obs=True), "next observation is its next step"),
        (dict(sequence=10, views={"next_obs": "none"}), "views of obs only"),
        (dict(sequence=10, n_step=3, discount=0.9), "n_step returns apply to single transitions"),
        (dict(sequence=10, sampler="prioritized"), "sequences are drawn uniformly"),
        (dict(sequence=10, source="rollout"), "sequences sample replay"),
    ]
    for settings, message in refused:
        with pytest.raises(radserve.InvalidArgumentError, match=message):
            envs.sample_batches(8, **settings)
    with pytest.raises(radserve.InvalidArgumentError, match="boundary one of"):
        envs.sample_batches(8, sequence=radserve.Sequence(10, boundary="sideways"))
    # The session still serves.
    with envs.sample_batches(8, sequence=10, max_batches=1) as stream:
        assert next(stream).obs.shape == (8, 10, 8)
