"""The torch adapter on a real batch stream (runs where the torch extra is installed)."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import radserve  # noqa: E402
import radserve.torch as radserve_torch  # noqa: E402


@pytest.fixture(scope="module")
def cartpole():
    """Two CartPoles after 20 random steps, recorded in a replay of 100."""
    with radserve.LocalServer(workers=1) as server, radserve.Client(server.address) as client:
        envs = client.make_vec("gym/CartPole-v1", num_envs=2, seed=0, replay_capacity=100)
        envs.reset()
        for _ in range(20):
            envs.step(envs.action_space.sample())
        yield envs


def test_batches_become_tensors_sharing_memory_on_cpu(cartpole):
    with cartpole.sample_batches(8, max_batches=2) as stream:
        converted = list(radserve_torch.tensors(stream))
    assert [b.index for b in converted] == [0, 1]
    batch = converted[0]
    assert batch.obs.dtype == torch.float32 and batch.obs.shape == (8, 4)
    assert batch.terminated.dtype == torch.bool and batch.action.dtype == torch.int64
    assert batch.t is None and isinstance(batch.next_obs, torch.Tensor)
    plain = radserve.Batch(index=0, obs=np.arange(6, dtype=np.uint8).reshape(2, 3), action=np.zeros(2),
                           reward=np.zeros(2, np.float32), terminated=np.zeros(2, bool), truncated=np.zeros(2, bool),
                           env_index=np.zeros(2, np.int32), step_index=np.zeros(2, np.int64))
    tensors = radserve_torch.to_tensors(plain)
    plain.obs[0, 0] = 42
    assert tensors.obs[0, 0] == 42, "CPU tensors share the arrays' memory"


def test_a_tensor_batch_has_every_field_of_a_batch():
    from dataclasses import fields

    assert [f.name for f in fields(radserve_torch.TensorBatch)] == [f.name for f in fields(radserve.Batch)]


def test_views_and_the_discount_become_tensors_once(cartpole):
    views = {"obs": "noise(std=0.1)", "obs_aug": "noise(std=0.1)", "next_obs": "none"}
    with cartpole.sample_batches(8, max_batches=1, views=views, n_step=3, discount=0.99) as stream:
        (batch,) = list(radserve_torch.tensors(stream))
    assert list(batch.views) == ["obs", "obs_aug", "next_obs"]
    assert batch.obs is batch.views["obs"] and batch.next_obs is batch.views["next_obs"]
    assert batch.views["obs_aug"].dtype == torch.float32 and batch.discount.shape == (8,)
    assert not torch.equal(batch.views["obs"], batch.views["obs_aug"]), "two independent draws of noise"


def test_a_prioritized_tensor_batch_updates_its_priorities_from_tensors(cartpole):
    with cartpole.sample_batches(8, sampler="prioritized", max_batches=1) as stream:
        batch = radserve_torch.to_tensors(next(stream))
        assert batch.key.dtype == torch.int64 and batch.weight.dtype == torch.float32
        assert batch.probability.dtype == torch.float64 and batch.table_size.shape == (8,)
        td_errors = torch.linspace(-1.0, 1.0, 8)
        update = stream.update_priorities(batch, td_errors.abs() + 1e-6)
    assert (update.updated, update.missing) == (8, 0)
