"""Replay buffers and augmented minibatch streams, end to end: act with random actions through the
real server, then check every sampled transition against what the acting client saw."""

import itertools
import os
import queue
import re
import time

import grpc
import numpy as np
import pytest

import radserve
from radserve.batches import map_region, sample_request
from radserve.proto import radserve_pb2 as pb


def act(envs, steps, seed=0):
    """Step `envs` with random actions; returns {(env, step index): the transition the client saw}."""
    envs.action_space.seed(seed)
    obs, _ = envs.reset(seed=seed)
    seen = {}
    for step in range(steps):
        actions = envs.action_space.sample()
        next_obs, rewards, terminated, truncated, infos = envs.step(actions)
        for env in range(envs.num_envs):
            ended = terminated[env] or truncated[env]
            true_next = infos["final_obs"][env] if ended else next_obs[env]
            seen[(env, step)] = dict(
                obs=np.array(obs[env]), action=np.array(actions[env]), reward=np.float32(rewards[env]),
                terminated=bool(terminated[env]), truncated=bool(truncated[env]), next_obs=np.array(true_next),
            )
        obs = next_obs
    return seen


def samples(batch):
    for i in range(len(batch)):
        yield i, (int(batch.env_index[i]), int(batch.step_index[i]))


@pytest.fixture(scope="module")
def cartpole(client):
    """CartPole with stacks of 3: short random episodes, so stacks cross many episode starts."""
    envs = client.make_vec("gym/CartPole-v1", num_envs=3, seed=5, replay_capacity=5000, frame_stack=3,
                           autoreset_mode="SameStep")
    seen = act(envs, 150, seed=5)
    yield envs, seen
    envs.close()


@pytest.fixture(scope="module")
def cheetah(client):
    envs = client.make_vec("dmc/cheetah-run", num_envs=2, seed=3, replay_capacity=1000, render_profile="fast",
                           autoreset_mode="SameStep")
    seen = act(envs, 40, seed=3)
    yield envs, seen
    envs.close()


def test_sampled_transitions_are_the_ones_the_client_saw(client, cartpole):
    envs, seen = cartpole
    episodes = sum(t["terminated"] or t["truncated"] for t in seen.values())
    assert episodes >= 10, "random CartPole episodes end often"
    with envs.sample_batches(256, max_batches=4, seed=1) as stream:
        batches = list(stream)
    assert [b.index for b in batches] == [0, 1, 2, 3]
    checked = set()
    for batch in batches:
        assert batch.obs.shape == (256, 12) and batch.obs.dtype == np.float32
        for i, key in samples(batch):
            want = seen[key]
            # Stacks never leak a frame of another episode: they equal the client's own stacks,
            # which the server padded with the episode's first frame at every reset.
            np.testing.assert_array_equal(batch.obs[i], want["obs"])
            np.testing.assert_array_equal(batch.next_obs[i], want["next_obs"])
            assert batch.action[i] == want["action"] and batch.reward[i] == want["reward"]
            assert batch.terminated[i] == want["terminated"] and batch.truncated[i] == want["truncated"]
            # next_obs continues obs: the newest frames of obs are the oldest of next_obs.
            np.testing.assert_array_equal(batch.next_obs[i][:8], batch.obs[i][4:])
            checked.add(key)
    assert len(checked) > 300, "samples spread over the buffer"
    assert any(seen[key]["terminated"] for key in checked)


def test_replay_statistics(client, cartpole):
    envs, seen = cartpole
    replay = client.describe_session(envs.session_id).replay
    assert replay.capacity == 5000 and replay.inserts == len(seen) == replay.size
    assert replay.frames_per_transition <= 1.1
    assert replay.samples >= 4 * 256 and replay.batches >= 4
    with envs.sample_batches(64, max_batches=3) as stream:
        assert len(list(stream)) == 3
    rate = client.describe_session(envs.session_id).replay.batches_per_second
    assert rate > 0, "3 batches just now: a rate over the last 5 seconds"


def test_pixel_transitions_and_crop(client, cheetah):
    envs, seen = cheetah
    with envs.sample_batches(32, max_batches=1) as stream:
        (plain,) = list(stream)
    assert plain.obs.shape == (32, 9, 100, 100) and plain.action.shape == (32, 6)
    for i, key in samples(plain):
        np.testing.assert_array_equal(plain.obs[i], seen[key]["obs"])
        np.testing.assert_array_equal(plain.next_obs[i], seen[key]["next_obs"])
        np.testing.assert_array_equal(plain.action[i], seen[key]["action"].astype(np.float32))

    with envs.sample_batches(32, augment="crop(84)", max_batches=2, seed=4) as stream:
        batches = list(stream)
    offsets = set()
    for batch in batches:
        assert batch.obs.shape == (32, 9, 84, 84)
        for i, key in samples(batch):
            for name in ("obs", "next_obs"):
                full, cropped = seen[key][name], getattr(batch, name)[i]
                found = [(y, x) for y in range(17) for x in range(17)
                         if np.array_equal(full[:, y:y + 84, x:x + 84], cropped)]
                assert found, f"{name} of {key} is a window of the real observation"
                offsets.add(found[0])
    assert len(offsets) > 10, "crop offsets differ across samples"


def translate_offset(full, translated):
    """Where the 100x100 observation sits in the 108x108 canvas, checking the zeros around it."""
    for y in range(9):
        for x in range(9):
            if np.array_equal(translated[:, y:y + 100, x:x + 100], full):
                rest = translated.copy()
                rest[:, y:y + 100, x:x + 100] = 0
                assert not rest.any(), "zeros around the observation"
                return y, x
    raise AssertionError("the observation is not inside the canvas")


def test_translate_and_draw_sharing(client, cheetah):
    envs, seen = cheetah
    for sharing, same in [("reference", True), ("independent", False)]:
        with envs.sample_batches(16, augment="translate(108)", sharing=sharing, max_batches=1) as s:
            (batch,) = list(s)
        assert batch.obs.shape == (16, 9, 108, 108)
        pairs = [(translate_offset(seen[key]["obs"], batch.obs[i]), translate_offset(seen[key]["next_obs"], batch.next_obs[i]))
                 for i, key in samples(batch)]
        if same:
            assert all(a == b for a, b in pairs), "RAD shares translate draws between obs and next_obs"
        else:
            assert any(a != b for a, b in pairs)
    with envs.sample_batches(16, augment="crop(84)", sharing="shared", max_batches=1) as s:
        (batch,) = list(s)
    for i, key in samples(batch):
        # A shared crop cuts obs and next_obs at one offset: their common frames agree.
        np.testing.assert_array_equal(batch.next_obs[i][:6], batch.obs[i][3:])


def test_state_amplitude_scaling_is_shared_by_obs_and_next_obs(client, cartpole):
    envs, seen = cartpole
    with envs.sample_batches(64, augment="ras_s(0.5, 1.5)", max_batches=1) as stream:
        (batch,) = list(stream)
    for i, key in samples(batch):
        obs, next_obs = seen[key]["obs"], seen[key]["next_obs"]
        nonzero = np.abs(obs) > 1e-3
        factor = (batch.obs[i][nonzero] / obs[nonzero])[0]
        assert 0.5 <= factor <= 1.5
        np.testing.assert_allclose(batch.obs[i], obs * factor, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(batch.next_obs[i], next_obs * factor, rtol=1e-5, atol=1e-6)


def test_bad_requests_are_refused_before_the_stream(client, cartpole, cheetah):
    cart, _ = cartpole
    pixels, _ = cheetah
    cases = [
        (dict(session_id=cart.session_id, batch_size=0), radserve.InvalidArgumentError, "batch_size must be between 1"),
        (dict(session_id=cart.session_id, batch_size=6000), radserve.InvalidArgumentError, "replay capacity (5000)"),
        (dict(session_id=cart.session_id, batch_size=8, augment="crop(84)"), radserve.InvalidArgumentError,
         "applies to images, not state vectors"),
        (dict(session_id=pixels.session_id, batch_size=8, augment="crop(120)"), radserve.InvalidArgumentError,
         "needs frames of at least 120x120"),
        (dict(session_id=pixels.session_id, batch_size=8, augment="grayscale(p=2)"), radserve.InvalidArgumentError,
         "p must be a probability"),
        (dict(session_id=pixels.session_id, batch_size=8, prefetch=100), radserve.InvalidArgumentError, "prefetch"),
        (dict(session_id="s0-nope", batch_size=8), radserve.NotFoundError, "s0-nope"),
    ]
    for kwargs, error, message in cases:
        with pytest.raises(error, match=message.replace("(", r"\(").replace(")", r"\)")):
            client.sample_batches(**kwargs)


def test_the_clients_sample_batches_by_id_is_a_deprecated_alias(client, cartpole):
    """`client.sample_batches(session_id, ...)` (0.1's call) warns and gives the env's stream."""
    envs = cartpole[0]
    with envs.sample_batches(16, max_batches=2, seed=3) as stream:
        expected = [batch.action.copy() for batch in stream]
    with pytest.warns(DeprecationWarning, match="envs.sample_batches"):
        stream = client.sample_batches(envs.session_id, 16, max_batches=2, seed=3)
    with stream:
        got = [batch.action.copy() for batch in stream]
    assert len(got) == len(expected) == 2 and all(np.array_equal(a, b) for a, b in zip(got, expected))


def test_sessions_without_replay_and_over_budget(client):
    envs = client.make_vec("gym/CartPole-v1", num_envs=1)
    try:
        with pytest.raises(radserve.FailedPreconditionError, match="keeps no replay buffer"):
            envs.sample_batches(8)
    finally:
        envs.close()
    with pytest.raises(radserve.InvalidArgumentError, match="replay budget"):  # above the whole budget
        client.make_vec("dmc/cheetah-run", num_envs=1, replay_capacity=10**7)


def wait_for_streams(client, session_id, count, timeout=1.0):
    deadline = time.monotonic() + timeout
    while client.describe_session(session_id).replay.active_streams != count:
        assert time.monotonic() < deadline, f"expected {count} active sample streams within {timeout} s"
        time.sleep(0.02)


def test_a_client_that_leaves_releases_its_producer(client, cartpole):
    envs, _ = cartpole
    stream = envs.sample_batches(16, prefetch=2)
    next(stream)
    wait_for_streams(client, envs.session_id, 1)
    stream.close()
    wait_for_streams(client, envs.session_id, 0)
    # Also while the producer waits for data that never comes (min_size above what acting inserted).
    waiting = envs.sample_batches(16, min_size=4000)
    wait_for_streams(client, envs.session_id, 1)
    waiting.close()
    wait_for_streams(client, envs.session_id, 0)


def test_rollout_minibatches_cover_every_step_and_env_once_per_epoch(client):
    steps, num_envs = 32, 4
    envs = client.make_vec("procgen/bigfish", num_envs=num_envs, seed=2, rollout_steps=steps, autoreset_mode="SameStep")
    try:
        with pytest.raises(radserve.FailedPreconditionError, match="needs 32 steps"):
            envs.sample_batches(16, source="rollout")
        seen = act(envs, steps + 5)  # the rollout is the last 32 of the 37 steps
        assert client.describe_session(envs.session_id).replay.rollout_steps == steps
        with pytest.raises(radserve.FailedPreconditionError, match="not a replay buffer"):
            envs.sample_batches(16)
        stream = envs.sample_batches(16, source="rollout", epochs=2, augment="crop(56)",
                                       per_env_augmentation=True)
        visits, offsets = [], {}
        for batch in stream:
            assert batch.next_obs is None and batch.obs.shape == (16, 3, 56, 56)
            for i, key in samples(batch):
                assert batch.step_index[i] == 5 + batch.t[i]
                full = seen[key]["obs"]
                found = [(y, x) for y in range(9) for x in range(9) if np.array_equal(full[:, y:y + 56, x:x + 56], batch.obs[i])]
                assert found, "a window of the observation the client saw"
                offsets.setdefault(int(batch.env_index[i]), set()).update(found[:1])
                visits.append((int(batch.t[i]), int(batch.env_index[i])))
        every = sorted((t, e) for t in range(steps) for e in range(num_envs))
        assert len(visits) == 2 * steps * num_envs
        assert sorted(visits[: steps * num_envs]) == every and sorted(visits[steps * num_envs:]) == every
        assert visits[: steps * num_envs] != visits[steps * num_envs:], "a fresh order each epoch"
        # Held per env for the whole rollout: one crop offset per env (ProcGen frames are rarely
        # ambiguous; the first match is the offset).
        assert all(len(found) == 1 for found in offsets.values()), offsets
    finally:
        envs.close()


def test_stepping_through_the_evaluation_view_while_replay_keeps_raw_frames(client):
    raw = client.make_vec("dmc/walker-walk", num_envs=2, seed=8, render_profile="fast")
    viewed = client.make_vec("dmc/walker-walk", num_envs=2, seed=8, render_profile="fast",
                             observation_view="center_crop(84)", replay_capacity=100)
    try:
        assert viewed.single_observation_space.shape == (9, 84, 84)
        raw_obs, _ = raw.reset()
        view_obs, _ = viewed.reset()
        np.testing.assert_array_equal(view_obs, raw_obs[:, :, 8:92, 8:92])
        actions = raw.action_space.sample()
        raw_obs, *_ = raw.step(actions)
        view_obs, *_ = viewed.step(actions)
        np.testing.assert_array_equal(view_obs, raw_obs[:, :, 8:92, 8:92])
        with viewed.sample_batches(2, max_batches=1, min_size=1) as stream:
            (batch,) = list(stream)
        assert batch.obs.shape == (2, 9, 100, 100), "replay keeps the rendered frames"
    finally:
        raw.close()
        viewed.close()
    translated = client.make_vec("dmc/walker-walk", num_envs=1, observation_view="center_translate(108)", render_profile="fast")
    try:
        obs, _ = translated.reset()
        assert obs.shape == (1, 9, 108, 108) and not obs[:, :, :4].any() and obs[:, :, 4:104, 4:104].any()
    finally:
        translated.close()
    for view, message in [("crop(84)", "crop(84) is random"), ("center_crop(120)", "at least 120x120")]:
        with pytest.raises(radserve.InvalidArgumentError, match=re.escape(message)):
            client.make_vec("dmc/walker-walk", num_envs=1, observation_view=view)
    with pytest.raises(radserve.InvalidArgumentError, match="views apply to image observations"):
        client.make_vec("gym/Hopper-v5", num_envs=1, observation_view="center_crop(84)")


def test_outputs_too_large_and_too_many_streams_are_refused(client, cheetah):
    envs, _ = cheetah
    with pytest.raises(radserve.InvalidArgumentError, match="the most allowed is 67108864"):
        envs.sample_batches(8, augment="translate(100000)")
    with pytest.raises(radserve.InvalidArgumentError, match="the most allowed is 1073741824"):
        envs.sample_batches(100, augment="translate(2000)")
    with pytest.raises(radserve.InvalidArgumentError, match="the most allowed"):
        client.make_vec("dmc/cheetah-run", num_envs=1, observation_view="center_translate(100000)")
    # 66 batches of 512 translated obs + next_obs (107.5 MB each) would be 7 GB held by one stream.
    for delivery in ("grpc", "shared_memory"):
        with pytest.raises(radserve.InvalidArgumentError, match=r"would hold 7094697984 bytes .*prefetch 64 \+ 2.*limits.stream_memory_bytes"):
            envs.sample_batches(512, augment="translate(108)", prefetch=64, delivery=delivery)
    streams = [envs.sample_batches(4, min_size=1000) for _ in range(4)]  # never reached: waits
    try:
        wait_for_streams(client, envs.session_id, 4)
        with pytest.raises(radserve.ResourceExhaustedError, match="already has 4 sample streams open"):
            envs.sample_batches(4)
    finally:
        for stream in streams:
            stream.close()
    wait_for_streams(client, envs.session_id, 0)


def copies(batch):
    """Every array of a batch, copied (shared-memory arrays are only valid until the next batch)."""
    arrays = {name: None if value is None else np.array(value) for name, value in vars(batch).items()
              if name not in ("index", "views")}
    return {**arrays, "views": {name: np.array(value) for name, value in batch.views.items()}}


def test_a_shared_stream_that_ran_out_ends_once_its_batches_are_released(cheetah):
    """max_batches=1 over shared memory: the producer is done at once, and the stream still waits for
    the client to release its batch, so a learner that maps the memory after the batch was sent finds
    the hand-off socket open (before, the stream ended and closed it: connection refused)."""
    envs = cheetah[0]
    method = envs._transport.channel.stream_stream(
        "/radserve.v1.RadServe/SampleBatchesShared", request_serializer=pb.SharedSampleRequest.SerializeToString,
        response_deserializer=pb.SharedSampleResponse.FromString)
    requests = queue.SimpleQueue()
    requests.put(pb.SharedSampleRequest(start=sample_request(envs.session_id, 8, max_batches=1)))
    call = method(iter(requests.get, None), timeout=30)
    try:
        first, only = next(call), next(call)
        time.sleep(0.5)  # a slow learner: the batch was made long ago
        memory = map_region(first.region)
        assert len(memory) == first.region.size
        requests.put(pb.SharedSampleRequest(release=only.batch.batch_index))
        assert list(call) == [], "the stream ends once the batch is released"
    finally:
        requests.put(None)
        call.cancel()


@pytest.mark.parametrize("source", ["replay", "rollout"])
def test_shared_memory_batches_equal_the_grpc_ones(client, cheetah, source):
    """Same request, same seed: the batches read in place from shared memory are the batches the
    byte stream delivers, field by field (obs and next_obs from the slots, the rest inline)."""
    if source == "replay":
        envs, sampled = None, cheetah[0]
        request = dict(augment="crop(84)|flip(p=0.5)", max_batches=5, seed=9, prefetch=1)
    else:
        envs = client.make_vec("procgen/bigfish", num_envs=3, seed=4, rollout_steps=8, autoreset_mode="SameStep")
        act(envs, 8)
        sampled = envs
        # 24 transitions in batches of 10: the last batch of each epoch is short.
        request = dict(augment="crop(56)", source="rollout", epochs=2, seed=9, include_next_obs=True)
    try:
        with sampled.sample_batches(10, **request) as stream:
            expected = [copies(batch) for batch in stream]
        stream = sampled.sample_batches(10, delivery="shared_memory", **request)
        assert isinstance(stream, radserve.SharedBatchStream)
        got = []
        for batch in stream:
            assert batch.obs.base is not None, "obs is a view of the shared memory, not a copy"
            got.append(copies(batch))
        # Run out without close(): the stream ends its request iterator itself (no thread left
        # waiting on it).
        assert stream.closed
    finally:
        if envs is not None:
            envs.close()
    assert len(got) == len(expected) == (5 if source == "replay" else 6)
    for want, have in zip(expected, got):
        assert want.keys() == have.keys() and list(want["views"]) == list(have["views"])
        for name in want:
            if want[name] is None:
                assert have[name] is None, name
                continue
            for field, array in (want[name].items() if name == "views" else [(name, want[name])]):
                other = have[name][field] if name == "views" else have[name]
                assert other.dtype == array.dtype and other.shape == array.shape, field
                np.testing.assert_array_equal(other, array, err_msg=field)


def test_shared_memory_slots_are_reused_only_after_release(client, cheetah):
    """A batch's observations stay intact while the client holds it, even with the producer running
    ahead; slots cycle once released, and a client that leaves frees the producer and the memory."""
    envs, _ = cheetah
    stream = envs.sample_batches(8, augment="crop(84)", prefetch=2, seed=1,
                                   delivery="shared_memory")
    assert stream.slots == 4
    first = next(stream)
    kept = first.obs.copy()
    time.sleep(0.3)  # the producer fills every other slot meanwhile
    np.testing.assert_array_equal(first.obs, kept, err_msg="the held batch was overwritten")
    offsets = set()
    for _ in range(12):
        batch = next(stream)
        offsets.add(batch.obs.__array_interface__["data"][0])
    assert 1 < len(offsets) <= 4, "batches cycle through the slots of the ring, and only those"
    wait_for_streams(client, envs.session_id, 1)
    stream.close()
    wait_for_streams(client, envs.session_id, 0)


def test_shared_memory_refusals_and_fallback(client, cheetah, monkeypatch):
    envs, _ = cheetah
    with pytest.raises(radserve.InvalidArgumentError, match="a batch of 1001 .* the most allowed|between 1 and the replay capacity"):
        envs.sample_batches(1001, delivery="shared_memory")
    with pytest.raises(ValueError, match="delivery must be one of"):
        envs.sample_batches(8, delivery="pigeon")

    # The first request must say what to sample.
    method = client.transports[0].channel.stream_stream("/radserve.v1.RadServe/SampleBatchesShared",
                                           request_serializer=pb.SharedSampleRequest.SerializeToString,
                                           response_deserializer=pb.SharedSampleResponse.FromString)
    with pytest.raises(grpc.RpcError) as refused:
        next(method(iter([pb.SharedSampleRequest(release=0)])))
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "must hold `start`" in refused.value.details()

    # Releasing a batch the client does not hold ends the stream with what it holds.
    requests = queue.SimpleQueue()
    requests.put(pb.SharedSampleRequest(start=pb.SampleBatchesRequest(session_id=envs.session_id, batch_size=8)))
    call = method(iter(requests.get, None))
    region, first = next(call), next(call)
    assert region.HasField("region") and first.batch.batch_index == 0
    requests.put(pb.SharedSampleRequest(release=77))
    with pytest.raises(grpc.RpcError) as refused:
        for _ in range(50):
            next(call)
    assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert re.search(r"release of batch 77, which the client does not hold \(it holds \[0", refused.value.details())
    requests.put(None)

    # A learner that cannot map the memory (another host, another user) gets a clear error, and
    # "auto" falls back to the byte stream.
    def unreachable(region):
        raise radserve.SharedMemoryError(f"cannot receive the server's batch memory over {region.socket!r}")

    monkeypatch.setattr(radserve.batches, "map_region", unreachable)
    with pytest.raises(radserve.SharedMemoryError, match="cannot receive"):
        envs.sample_batches(8, delivery="shared_memory")
    with envs.sample_batches(8, delivery="auto", max_batches=1) as stream:
        assert isinstance(stream, radserve.BatchStream)
        assert next(stream).obs.shape == (8, 9, 100, 100)
    wait_for_streams(client, envs.session_id, 0)


_HANDOVERS = itertools.count()


def _hand_over(fd: int) -> str:
    """A socket that hands `fd` to the first client that sends 16 bytes, as the server does."""
    import socket
    import threading

    name = f"radserve-test-{os.getpid()}-{next(_HANDOVERS)}"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind("\0" + name)
    listener.listen(1)

    def serve():
        connection, _ = listener.accept()
        connection.recv(16, socket.MSG_WAITALL)
        socket.send_fds(connection, [b"\x01"], [fd])
        connection.close()
        listener.close()

    threading.Thread(target=serve, daemon=True).start()
    return name


def test_shared_memory_token_is_checked():
    """Memory that is not the stream's (a descriptor of something else) is refused, not read."""
    import mmap

    fd = os.memfd_create("not-radserve")
    os.ftruncate(fd, 8192)
    try:
        region = pb.SharedMemoryRegion(socket=_hand_over(fd), size=8192, token=b"\x01" * 16, slots=1, slot_bytes=4096)
        with pytest.raises(radserve.SharedMemoryError, match="not the batch memory the server described"):
            radserve.batches.map_region(region)
        with mmap.mmap(fd, 8192) as memory:
            memory[:32] = b"radserve-batches" + b"\x01" * 16
        region.socket = _hand_over(fd)
        assert radserve.batches.map_region(region)[:16] == b"radserve-batches"
    finally:
        os.close(fd)
