"""Prioritized replay end to end through the real server and CartPole: batches carry each
transition's key, draw probability, table size and importance weight; priorities a learner sets
with `update_priorities` decide what the next streams draw, over both deliveries; bad input is
refused and changes nothing. The Rust twins: server/replay/src/priority.rs (the sum tree and the
buffer's priorities) and server/replay/tests/buffer.rs
(`a_prioritized_stream_draws_by_priority_with_keys_probabilities_and_weights`)."""

import numpy as np
import pytest

import radserve
from radserve.proto import radserve_pb2 as pb

from test_replay import act, samples


def cartpole(client, seed):
    """Two CartPole envs with stacks of 2 in a replay of 400 (200 transitions per env), 100 steps in."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=seed, replay_capacity=400, frame_stack=2,
                           autoreset_mode="SameStep")
    return envs, act(envs, 100, seed=seed)


@pytest.mark.parametrize("delivery", ["grpc", "shared_memory"])
def test_draws_follow_the_priorities_the_learner_sets(client, delivery):
    envs, seen = cartpole(client, seed=3)
    try:
        prioritized = dict(sampler="prioritized", priority_exponent=1.0, delivery=delivery)
        with envs.sample_batches(64, importance_sampling_exponent=1.0, seed=1, max_batches=1, **prioritized) as stream:
            first = next(stream)
            keys = np.array(first.key)
            size = int(first.table_size[0])
            assert (first.key.dtype, first.probability.dtype, first.weight.dtype) == (np.int64, np.float64, np.float32)
            # Before any update every transition is at priority 1: uniform, weights 1.
            np.testing.assert_allclose(first.probability, 1.0 / size, rtol=1e-12)
            np.testing.assert_array_equal(first.weight, 1.0)
            for i, key in samples(first):
                np.testing.assert_array_equal(first.obs[i], seen[key]["obs"])
            chosen = keys[0]
            update = stream.update_priorities(first, np.where(keys == chosen, 50.0, 0.0))
        assert update == radserve.PriorityUpdate(updated=64, missing=0)
        # alpha 1: the chosen transition is drawn with probability 50 / (50 + those never updated).
        others = size - len(set(keys.tolist()))
        want = 50.0 / (50.0 + others)
        hits = draws = 0
        with envs.sample_batches(128, importance_sampling_exponent=0.5, seed=2, max_batches=10, **prioritized) as stream:
            for batch in stream:
                drawn = np.asarray(batch.key)
                assert not np.isin(drawn[drawn != chosen], keys).any(), "a transition at priority 0 was drawn"
                expected = np.where(drawn == chosen, want, 1.0 / (50.0 + others))
                np.testing.assert_allclose(batch.probability, expected, rtol=1e-9)
                np.testing.assert_allclose(batch.weight, radserve.importance_weights(batch.probability, batch.table_size, 0.5),
                                           rtol=1e-6)
                hits += int((drawn == chosen).sum())
                draws += len(drawn)
        sd = np.sqrt(want * (1 - want) / draws)
        assert abs(hits / draws - want) < 5 * sd, (hits, draws, want)
        # 300 more steps overwrite every transition of the first batch (200 per env are kept).
        act(envs, 300, seed=4)
        assert envs_update(envs, first) == radserve.PriorityUpdate(updated=0, missing=64)
    finally:
        envs.close()


def envs_update(envs, batch):
    """update_priorities through a fresh prioritized stream of the same session."""
    with envs.sample_batches(1, sampler="prioritized", max_batches=1) as stream:
        return stream.update_priorities(batch, np.ones(len(batch)))


def test_bad_prioritized_requests_and_updates_are_refused_and_change_nothing(client):
    envs, _ = cartpole(client, seed=5)
    try:
        raw = client.transports[0]
        update = pb.UpdatePrioritiesRequest(session_id=envs.session_id, keys=[1], priorities=[1.0])
        with pytest.raises(radserve.FailedPreconditionError, match="no prioritized stream sampled this replay"):
            raw.call("UpdatePriorities", update)
        with pytest.raises(radserve.InvalidArgumentError, match="sampler must be one of"):
            envs.sample_batches(8, sampler="greedy")
        with pytest.raises(radserve.InvalidArgumentError, match=r"priority_exponent must be in \[0, 1\]"):
            envs.sample_batches(8, sampler="prioritized", priority_exponent=1.5)
        with pytest.raises(radserve.InvalidArgumentError, match="applies to sampler SAMPLER_PRIORITIZED"):
            envs.sample_batches(8, importance_sampling_exponent=0.5)
        with envs.sample_batches(8, max_batches=1) as uniform:
            with pytest.raises(radserve.InvalidArgumentError, match="carries no `key`"):
                uniform.update_priorities(next(uniform), np.ones(8))
        with envs.sample_batches(8, sampler="prioritized", priority_exponent=1.0, seed=3) as stream:
            batch = next(stream)
            with pytest.raises(radserve.InvalidArgumentError, match="one priority per transition"):
                stream.update_priorities(batch, np.ones(7))
            for bad in (np.nan, -1.0, np.inf):
                values = np.ones(8)
                values[3] = bad
                with pytest.raises(radserve.InvalidArgumentError, match=r"priorities\[3\] is"):
                    stream.update_priorities(batch, values)
            foreign = pb.UpdatePrioritiesRequest(session_id=envs.session_id, keys=[int(batch.key[0]), 7 << 40],
                                                 priorities=[5.0, 5.0])
            with pytest.raises(radserve.InvalidArgumentError, match=r"keys\[1\]"):
                raw.call("UpdatePriorities", foreign)
        # Nothing changed: every transition is still at priority 1.
        with envs.sample_batches(64, sampler="prioritized", priority_exponent=1.0, seed=4, max_batches=1) as stream:
            after = next(stream)
        np.testing.assert_allclose(after.probability, 1.0 / after.table_size, rtol=1e-12)
    finally:
        envs.close()
