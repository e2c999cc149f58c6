"""dm_env_rpc v1 against the real server: DeepMind's own compliance suites (`dm_env_rpc.v1.compliance`)
subclassed here, dm_env's `EnvironmentTestMixin` through the unmodified `dm_env_adaptor`, and the
semantics radserve gives the protocol (docs/dm_env_rpc.md) checked against gymnasium itself."""

import grpc
from google.protobuf import any_pb2
import gymnasium as gym
import numpy as np
import pytest
from absl.testing import absltest
from dm_env import StepType, test_utils
from dm_env_rpc.v1 import compliance, dm_env_adaptor, dm_env_rpc_pb2, error, tensor_utils
from dm_env_rpc.v1.connection import Connection

import radserve

_SERVER: dict = {}


@pytest.fixture(autouse=True, scope="module")
def _address(server):
    """unittest classes take no fixtures: the compliance suites read the server's address here."""
    _SERVER["address"] = server.address
    yield


def pack(settings: dict) -> dict:
    return {name: tensor_utils.pack_tensor(value) for name, value in settings.items()}


class _Connected:
    """A fresh channel and dm_env_rpc connection per test, closed after it."""

    def setUp(self):
        self._channel = grpc.insecure_channel(_SERVER["address"])
        self._connection = Connection(self._channel)
        super().setUp()

    def tearDown(self):
        try:
            super().tearDown()
            self.before_close()
        finally:
            self._connection.close()
            self._channel.close()

    def before_close(self):
        pass

    @property
    def connection(self):
        return self._connection


class _WithWorld(_Connected):
    """A world created before each test and destroyed after it (left first)."""

    world_settings = {"env_id": "gym/CartPole-v1", "seed": 3}

    def setUp(self):
        super().setUp()
        self._world = self._connection.send(dm_env_rpc_pb2.CreateWorldRequest(settings=pack(self.world_settings))).world_name

    def before_close(self):
        self._connection.send(dm_env_rpc_pb2.LeaveWorldRequest())
        self._connection.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=self._world))

    @property
    def world_name(self):
        return self._world


class CreateDestroyWorld(_Connected, compliance.CreateDestroyWorld):
    required_world_settings = pack({"env_id": "gym/CartPole-v1"})
    # Each is added to the required settings: a negative seed, no envs, an unknown option, an
    # option out of its range, a seed that is no integer.
    invalid_world_settings = pack({"seed": -1, "num_envs": 0, "frame_stak": 2, "frame_stack": 99})
    has_multiple_world_support = True


class JoinLeaveWorld(_WithWorld, compliance.JoinLeaveWorld):
    invalid_join_settings = pack({"env_index": 1, "bogus": 0})


class Reset(_WithWorld, compliance.Reset):
    def join_world(self):
        return self._connection.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=self._world)).specs


class ResetWorld(_WithWorld, compliance.ResetWorld):
    pass


class _Step(_WithWorld):
    def setUp(self):
        super().setUp()
        self._specs = self._connection.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=self._world)).specs

    @property
    def specs(self):
        return self._specs


class StepDiscrete(_Step, compliance.Step):
    """CartPole: an int64 scalar action in [0, 1], float32 state observations."""

    required_actions = {1: tensor_utils.pack_tensor(np.int64(0))}


class StepContinuous(_Step, compliance.Step):
    """Pendulum: a float32 [1] action in [-2, 2]."""

    world_settings = {"env_id": "gym/Pendulum-v1", "seed": 5}
    required_actions = {1: tensor_utils.pack_tensor(np.zeros(1, np.float32))}


class StepPixels(_Step, compliance.Step):
    """dm_control pixels: uint8 [9, 64, 64] stacked frames, a float32 [1] action in [-1, 1]."""

    world_settings = {"env_id": "dmc/cartpole-balance", "seed": 1, "frame_stack": 3, "height": 64, "width": 64}
    required_actions = {1: tensor_utils.pack_tensor(np.zeros(1, np.float32))}


class _AdaptorTest(test_utils.EnvironmentTestMixin, absltest.TestCase):
    """dm_env's contract through the unmodified adaptor: `create_and_join_world` as written in its docs."""

    __test__ = False  # the subclasses below name the envs
    world_settings: dict = {}
    sequence_length = 20

    def make_object_under_test(self):
        self._channel = grpc.insecure_channel(_SERVER["address"])
        self._connection = Connection(self._channel)
        env, self._world = dm_env_adaptor.create_and_join_world(
            self._connection, create_world_settings=self.world_settings, join_world_settings={})
        return env

    def make_action_sequence(self):
        # Long enough for episodes to end (the mixin then checks LAST -> FIRST).
        for _ in range(self.sequence_length):
            yield self.make_action()

    def tearDown(self):
        try:
            super().tearDown()
        finally:
            self._connection.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=self._world))
            self._connection.close()
            self._channel.close()


class AdaptorCartPole(_AdaptorTest):
    __test__ = True
    # The constant action (0) tips the pole within ~10 steps: terminations.
    world_settings = {"env_id": "gym/CartPole-v1", "seed": 3}
    sequence_length = 40


class AdaptorPendulum(_AdaptorTest):
    __test__ = True
    # 200-step time limit: truncations.
    world_settings = {"env_id": "gym/Pendulum-v1", "seed": 3}
    sequence_length = 210


class AdaptorDmcPixels(_AdaptorTest):
    __test__ = True
    world_settings = {"env_id": "dmc/cartpole-balance", "seed": 2, "height": 48, "width": 48, "action_repeat": 8}
    sequence_length = 130


class AdaptorProcgen(_AdaptorTest):
    __test__ = True
    world_settings = {"env_id": "procgen/coinrun", "seed": 4}


@pytest.fixture
def connection(server):
    with grpc.insecure_channel(server.address) as channel:
        connected = Connection(channel)
        yield connected
        connected.close()


def test_the_adaptor_plays_gymnasiums_episodes(connection):
    """The issue's line as written; episodes equal gymnasium's CartPole-v1 reset with the same seed
    and stepped with the same actions: observations, rewards, termination (discount 0) and the
    next episode's first observation (the seed's random stream continued)."""
    env, world = dm_env_adaptor.create_and_join_world(
        connection, create_world_settings={"env_id": "gym/CartPole-v1", "seed": 3}, join_world_settings={})
    reference = gym.make("CartPole-v1")
    rng = np.random.default_rng(0)
    try:
        spec = env.action_spec()["action"]
        assert spec.dtype == np.int64 and (spec.minimum, spec.maximum) == (0, 1)
        timestep = env.reset()
        expected, _ = reference.reset(seed=3)
        assert timestep.step_type == StepType.FIRST
        np.testing.assert_array_equal(timestep.observation["observation"], expected)
        episodes = 0
        for _ in range(300):
            action = int(rng.integers(2))
            timestep = env.step({"action": np.int64(action)})
            if timestep.first():
                expected, _ = reference.reset()
                np.testing.assert_array_equal(timestep.observation["observation"], expected)
                continue
            expected, reward, terminated, truncated, _ = reference.step(action)
            np.testing.assert_array_equal(timestep.observation["observation"], expected)
            assert timestep.reward == reward
            assert timestep.last() == (terminated or truncated)
            if terminated:
                assert timestep.discount == 0.0
                episodes += 1
        assert episodes >= 3
    finally:
        env.close()
        connection.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=world))


def test_truncation_is_interrupted_with_discount_one(connection):
    env, world = dm_env_adaptor.create_and_join_world(
        connection, create_world_settings={"env_id": "gym/Pendulum-v1", "seed": 0}, join_world_settings={})
    try:
        assert env.reset().first()
        timesteps = [env.step({"action": np.zeros(1, np.float32)}) for _ in range(200)]
        assert [t.step_type for t in timesteps[:-1]] == [StepType.MID] * 199
        assert timesteps[-1].last() and timesteps[-1].discount == 1.0
        assert env.step({"action": np.zeros(1, np.float32)}).first()
    finally:
        env.close()
        connection.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=world))


def test_a_world_is_a_session_and_its_envs_are_joined_one_stream_each(server):
    channels = [grpc.insecure_channel(server.address) for _ in range(3)]
    first, second, third = (Connection(channel) for channel in channels)
    try:
        world = first.send(dm_env_rpc_pb2.CreateWorldRequest(
            settings=pack({"env_id": "gym/CartPole-v1", "seed": 10, "num_envs": 2}))).world_name
        with radserve.Client(server.address) as client:
            info = client.describe_session(world)
            assert (info.env_id, info.num_envs) == ("gym/CartPole-v1", 2)
        first.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=world))
        second.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=world, settings=pack({"env_index": 1})))
        with pytest.raises(error.DmEnvRpcError, match="joined by another stream") as taken:
            third.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=world, settings=pack({"env_index": 1})))
        assert taken.value.code == grpc.StatusCode.FAILED_PRECONDITION.value[0]

        # Each stream's env is seeded seed + env_index, as in a session; stepping one leaves the other.
        def observe(connection, action=None):
            actions = {} if action is None else {1: tensor_utils.pack_tensor(np.int64(action))}
            response = connection.send(dm_env_rpc_pb2.StepRequest(actions=actions, requested_observations=[1, 2]))
            return tensor_utils.unpack_tensor(response.observations[1])

        for index, connection in enumerate((first, second)):
            np.testing.assert_array_equal(observe(connection), gym.make("CartPole-v1").reset(seed=10 + index)[0])
        reference = gym.make("CartPole-v1")
        reference.reset(seed=11)
        for _ in range(3):
            observe(first, 1)
        np.testing.assert_array_equal(observe(second, 0), reference.step(0)[0])

        # A bad action is answered in-band; the stream goes on.
        with pytest.raises(error.DmEnvRpcError, match="outside") as bad:
            observe(first, 5)
        assert bad.value.code == grpc.StatusCode.INVALID_ARGUMENT.value[0]
        observe(first, 0)

        with pytest.raises(error.DmEnvRpcError, match="joined streams"):
            third.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=world))
        first.send(dm_env_rpc_pb2.LeaveWorldRequest())
        second.send(dm_env_rpc_pb2.LeaveWorldRequest())
        third.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=world))
        with radserve.Client(server.address) as client, pytest.raises(radserve.NotFoundError):
            client.describe_session(world)
    finally:
        for connection in (first, second, third):
            connection.close()
        for channel in channels:
            channel.close()


def test_reset_settings_seed_the_episode_and_reset_world_starts_new_ones(connection):
    world = connection.send(dm_env_rpc_pb2.CreateWorldRequest(settings=pack({"env_id": "gym/CartPole-v1"}))).world_name
    try:
        connection.send(dm_env_rpc_pb2.JoinWorldRequest(world_name=world))

        def first_observation():
            response = connection.send(dm_env_rpc_pb2.StepRequest(requested_observations=[1]))
            assert response.state == dm_env_rpc_pb2.EnvironmentStateType.RUNNING
            return tensor_utils.unpack_tensor(response.observations[1])

        first_observation()
        connection.send(dm_env_rpc_pb2.ResetRequest(settings=pack({"seed": 42})))
        np.testing.assert_array_equal(first_observation(), gym.make("CartPole-v1").reset(seed=42)[0])
        with pytest.raises(error.DmEnvRpcError, match="unknown Reset setting"):
            connection.send(dm_env_rpc_pb2.ResetRequest(settings=pack({"sed": 1})))
        # ResetWorld (seeded) restarts every env; a joined stream's next step is the new first one.
        connection.send(dm_env_rpc_pb2.StepRequest(actions={1: tensor_utils.pack_tensor(np.int64(0))}))
        connection.send(dm_env_rpc_pb2.ResetWorldRequest(world_name=world, settings=pack({"seed": 7})))
        np.testing.assert_array_equal(first_observation(), gym.make("CartPole-v1").reset(seed=7)[0])
        with pytest.raises(error.DmEnvRpcError, match="no dm_env_rpc extension"):
            connection.send(any_pb2.Any(type_url="type.googleapis.com/example.Unknown"))
    finally:
        connection.send(dm_env_rpc_pb2.LeaveWorldRequest())
        connection.send(dm_env_rpc_pb2.DestroyWorldRequest(world_name=world))
