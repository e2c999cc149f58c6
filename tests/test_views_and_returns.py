"""Named views and n-step returns, end to end through the real server and simulators: every sampled
n-step transition against a plain numpy reference computed from what the stepping client saw, and
the views DrQ, CURL and SVEA ask for over both deliveries. The Rust twin, against a model of the
episodes: server/replay/tests/buffer.rs (`n_step_windows_match_a_model_of_the_episodes`,
`named_views_carry_their_own_draws_and_the_n_step_next_obs`)."""

import numpy as np
import pytest

import radserve
from radserve.proto import radserve_pb2 as pb

from test_replay import act, copies, samples


def n_step_reference(seen, key, n, discount):
    """The n-step window of transition `key` (env, step) from the client's own record: up to n
    rewards of its episode summed, the bootstrap's factor (0 after a termination), the flags, and
    the observation after the last summed step; None while fewer than n steps were taken."""
    env, step = key
    total, factor = np.float64(0.0), 1.0
    for k in range(n):
        transition = seen.get((env, step + k))
        if transition is None:
            return None
        total += factor * np.float64(transition["reward"])
        factor *= discount
        if transition["terminated"]:
            return total, 0.0, True, False, transition["next_obs"]
        if transition["truncated"] or k == n - 1:
            return total, factor, False, transition["truncated"], transition["next_obs"]


@pytest.fixture(scope="module")
def short_episodes(client):
    """CartPole with stacks of 2, three envs, episodes cut at 16 steps (truncation) when random
    actions do not end them first (termination), in a replay of 90 that wraps many times."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=3, seed=11, replay_capacity=90, frame_stack=2,
                           max_episode_steps=16, autoreset_mode="SameStep")
    seen = act(envs, 200, seed=11)
    yield envs, seen
    envs.close()


@pytest.mark.parametrize("n", [1, 3, 5])
def test_n_step_returns_match_a_numpy_reference(short_episodes, n):
    envs, seen = short_episodes
    assert any(t["terminated"] for t in seen.values()) and any(t["truncated"] for t in seen.values())
    with envs.sample_batches(64, n_step=n, discount=0.9, seed=n, max_batches=8, min_size=30) as stream:
        batches = list(stream)
    ends = {"terminated": 0, "truncated": 0}
    newest = max(step for _, step in seen)
    for batch in batches:
        assert batch.discount.dtype == np.float32 and list(batch.views) == ["obs", "next_obs"]
        for i, key in samples(batch):
            reference = n_step_reference(seen, key, n, 0.9)
            assert reference is not None, f"{key} was sampled before its {n} steps were taken"
            reward, discount, terminated, truncated, next_obs = reference
            assert batch.reward[i] == pytest.approx(reward, abs=1e-5), key
            assert batch.discount[i] == pytest.approx(discount, abs=1e-6), key
            assert (batch.terminated[i], batch.truncated[i]) == (terminated, truncated), key
            np.testing.assert_array_equal(batch.obs[i], seen[key]["obs"])
            np.testing.assert_array_equal(batch.next_obs[i], next_obs, err_msg=str(key))
            assert key[1] >= newest - 30, "only what the ring of each env holds (a share of 90)"
            ends["terminated"] += terminated
            ends["truncated"] += truncated
    if n > 1:
        assert ends["terminated"] and ends["truncated"], f"windows end both ways: {ends}"


def test_one_step_with_a_discount_is_todays_batch_with_its_bootstrap_factor(short_episodes):
    envs, seen = short_episodes
    with envs.sample_batches(32, seed=4, max_batches=2) as stream:
        plain = [copies(batch) for batch in stream]
    with envs.sample_batches(32, seed=4, max_batches=2, discount=0.99) as stream:
        discounted = [copies(batch) for batch in stream]
    for want, have in zip(plain, discounted):
        assert want["discount"] is None
        for name in ("obs", "next_obs", "reward", "terminated", "action", "step_index"):
            np.testing.assert_array_equal(have[name], want[name], err_msg=name)
        np.testing.assert_allclose(have["discount"], np.where(want["terminated"], 0.0, 0.99).astype(np.float32))


DRQ = {"obs": "shift(4)", "obs_aug": "shift(4)", "next_obs": "shift(4)", "next_obs_aug": "shift(4)"}


@pytest.fixture(scope="module")
def walker(client):
    """Two walkers rendered at DrQ's 84x84, stacks of 3."""
    envs = client.make_vec("dmc/walker-walk", num_envs=2, seed=6, replay_capacity=400, render_profile="fast",
                           height=84, width=84, autoreset_mode="SameStep")
    seen = act(envs, 30, seed=6)
    yield envs, seen
    envs.close()


@pytest.mark.parametrize("delivery", ["grpc", "shared_memory"])
def test_drq_views_are_independent_shifts_of_the_stored_stacks(walker, delivery):
    envs, seen = walker
    views = {**DRQ, "clean": "none", "next_clean": radserve.View(of="next_obs")}
    with envs.sample_batches(24, views=views, n_step=3, discount=0.99, seed=2, max_batches=3,
                             delivery=delivery) as stream:
        batches = [copies(batch) for batch in stream]
    differ = 0
    for batch in batches:
        assert list(batch["views"]) == ["obs", "obs_aug", "next_obs", "next_obs_aug", "clean", "next_clean"]
        for name, view in batch["views"].items():
            assert view.shape == (24, 9, 84, 84) and view.dtype == np.uint8, name
        np.testing.assert_array_equal(batch["obs"], batch["views"]["obs"])
        for i in range(24):
            key = (int(batch["env_index"][i]), int(batch["step_index"][i]))
            np.testing.assert_array_equal(batch["views"]["clean"][i], seen[key]["obs"])
            reference = n_step_reference(seen, key, 3, 0.99)
            np.testing.assert_array_equal(batch["views"]["next_clean"][i], reference[4])
            for name, source in [("obs", "clean"), ("obs_aug", "clean"), ("next_obs", "next_clean"),
                                 ("next_obs_aug", "next_clean")]:
                assert shift_of(batch["views"][source][i], batch["views"][name][i]) is not None, (name, key)
            differ += not np.array_equal(batch["views"]["obs"][i], batch["views"]["obs_aug"][i])
    assert differ > 50, "obs and obs_aug are shifted independently"


def shift_of(clean, shifted, pad=4):
    """The (dy, dx) in [-pad, pad]^2 that makes `shifted` the replicate-padded shift of `clean`."""
    padded = np.pad(clean, ((0, 0), (pad, pad), (pad, pad)), mode="edge")
    height, width = clean.shape[1:]
    for top in range(2 * pad + 1):
        for left in range(2 * pad + 1):
            if np.array_equal(padded[:, top:top + height, left:left + width], shifted):
                return top - pad, left - pad
    return None


def test_views_sharing_draws_and_the_two_deliveries_agree(walker):
    """CURL's anchor and positive (independent crops), SVEA's pair (a shift, and the same shift then
    a flip: one `draws` label): the same batches over gRPC and shared memory, byte for byte."""
    envs, _ = walker
    views = {"anchor": "crop(72)", "positive": "crop(72)",
             "svea_clean": radserve.View("shift(4)", draws="svea"),
             "svea_strong": radserve.View("shift(4)|flip(p=1)", draws="svea")}
    request = dict(views=views, seed=5, max_batches=2)
    with envs.sample_batches(16, **request) as stream:
        expected = [copies(batch) for batch in stream]
    with envs.sample_batches(16, delivery="shared_memory", **request) as stream:
        got = [copies(batch) for batch in stream]
    assert len(got) == len(expected) == 2
    for want, have in zip(expected, got):
        assert want["obs"] is None and want["next_obs"] is None and list(have["views"]) == list(views)
        for name in views:
            np.testing.assert_array_equal(have["views"][name], want["views"][name], err_msg=name)
        anchor, positive = want["views"]["anchor"], want["views"]["positive"]
        assert anchor.shape == (16, 9, 72, 72)
        assert sum(not np.array_equal(a, p) for a, p in zip(anchor, positive)) > 8
        # The strong view is the clean one flipped: the same shift.
        np.testing.assert_array_equal(want["views"]["svea_strong"], want["views"]["svea_clean"][..., ::-1])


def test_a_rollout_serves_two_views(client):
    envs = client.make_vec("procgen/bigfish", num_envs=2, seed=4, rollout_steps=8, autoreset_mode="SameStep")
    try:
        act(envs, 8)
        views = {"obs": "crop(56)", "obs_aug": "crop(56)|grayscale(p=1)"}
        with envs.sample_batches(8, source="rollout", views=views, per_env_augmentation=True) as stream:
            batches = list(stream)
        assert sum(len(batch) for batch in batches) == 16
        for batch in batches:
            assert batch.views["obs_aug"].shape == (8, 3, 56, 56) and batch.next_obs is None and batch.t is not None
            gray = batch.views["obs_aug"]
            assert (gray[:, 0] == gray[:, 1]).all() and (gray[:, 1] == gray[:, 2]).all()
    finally:
        envs.close()


def test_bad_views_and_returns_are_refused_naming_the_field(client, walker, short_episodes):
    envs = walker[0]
    cart = short_episodes[0]
    cases = [
        (envs, dict(views={f"v{i}": "none" for i in range(9)}), "views: at most 8 per request, got 9"),
        (envs, dict(views={"Obs": "none"}), "view names are lowercase names"),
        (envs, dict(views={"reward": "none"}), 'view name "reward" is a field every batch has'),
        (envs, dict(views={"a": "crop(120)"}), 'view "a": '),
        (envs, dict(views={"a": "shiftt(4)"}), 'view "a": '),
        (cart, dict(views={"a": "crop(84)"}), "applies to images, not state vectors"),
        (envs, dict(n_step=0, discount=0.9), "n_step must be between 1 and 64, got 0"),
        (envs, dict(n_step=65, discount=0.9), "n_step must be between 1 and 64, got 65"),
        (envs, dict(n_step=3), "n_step 3 needs the discount"),
        (envs, dict(n_step=3, discount=float("nan")), r"discount must be in \[0, 1\], got NaN"),
        (envs, dict(discount=-0.1), r"discount must be in \[0, 1\], got -0.1"),
        (envs, dict(views={"a": "none"}, include_next_obs=True), "include_next_obs applies to obs and next_obs"),
        (envs, dict(views={"a": "none"}, sharing="shared"), "sharing applies to obs and next_obs"),
        # 8 views of 256 translated stacks: 8 x 256 x 9 x 300 x 300 bytes is over a batch's 1 GiB.
        (envs, dict(views={f"v{i}": "translate(300)" for i in range(8)}), "views v0, v1"),
    ]
    for target, settings, message in cases:
        with pytest.raises(radserve.InvalidArgumentError, match=message):
            target.sample_batches(256 if "translate(300)" in str(settings) else 8, **settings)
    with pytest.raises(radserve.InvalidArgumentError, match="must be a pipeline's text or a radserve.View"):
        envs.sample_batches(8, views={"a": radserve.View(of="action")})
    # Through the raw API: a pipeline beside views, an `of` the transition does not have.
    raw = [
        (pb.SampleBatchesRequest(session_id=envs.session_id, batch_size=8, pipeline_text="crop(84)",
                                 views=[pb.SampleView(name="a")]),
         "augmentation applies to obs and next_obs when no views are named"),
        (pb.SampleBatchesRequest(session_id=envs.session_id, batch_size=8, views=[pb.SampleView(name="a", of=7)]),
         "`of` must be VIEW_OF_OBS or VIEW_OF_NEXT_OBS"),
    ]
    for request, message in raw:
        with pytest.raises(radserve.InvalidArgumentError, match=message):
            envs._open_batches(request, "grpc")
