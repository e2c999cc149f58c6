"""The server's ProcGen frames for seed s are procgen's own: env i plays what a one-game
`ProcgenGym3Env(num=1, rand_seed=s+i)` plays for the same actions, through episode ends, although the
worker steps its games as one procgen vector (radserve_worker.procgen_games.ProcgenGroup)."""

import contextlib
import io

import numpy as np

with contextlib.redirect_stderr(io.StringIO()):  # procgen imports gym, which prints a banner
    from procgen import ProcgenGym3Env


def direct_frame(env):
    return env.observe()[1]["rgb"][0].transpose(2, 0, 1)


def test_frames_rewards_and_episode_ends_equal_one_game_envs_seeded_s_plus_i(client):
    game, seed, num_envs, steps = "starpilot", 7, 4, 400
    envs = client.make_vec(f"procgen/{game}", num_envs=num_envs, seed=seed, autoreset_mode="SameStep")
    direct = [ProcgenGym3Env(num=1, env_name=game, rand_seed=seed + i, distribution_mode="easy")
              for i in range(num_envs)]
    rng = np.random.default_rng(0)
    try:
        obs, _ = envs.reset()
        for i, env in enumerate(direct):
            np.testing.assert_array_equal(obs[i], direct_frame(env))
        episode_ends = 0
        for _ in range(steps):
            actions = rng.integers(0, 15, size=num_envs)
            previous = obs
            obs, rewards, terminated, truncated, infos = envs.step(actions)
            for i, env in enumerate(direct):
                env.act(actions[i:i + 1].astype(np.int32))
                reward, _, first = env.observe()
                np.testing.assert_array_equal(obs[i], direct_frame(env))
                assert rewards[i] == reward[0] and terminated[i] == first[0] and not truncated[i]
                if terminated[i]:
                    np.testing.assert_array_equal(infos["final_obs"][i], previous[i])
            episode_ends += int(terminated.sum())
        assert episode_ends >= 2, "the comparison should cross episode ends"

        # Reseeding at reset starts every game over from its new seed.
        obs, _ = envs.reset(seed=40)
        for i in range(num_envs):
            np.testing.assert_array_equal(
                obs[i], direct_frame(ProcgenGym3Env(num=1, env_name=game, rand_seed=40 + i, distribution_mode="easy")))
    finally:
        envs.close()


def test_unseeded_resets_go_on_to_new_levels_the_same_way_for_the_same_seed(client):
    # gym3 games have no reset: an unseeded reset must not replay the levels of the last seeding.
    def first_frames(resets):
        envs = client.make_vec("procgen/starpilot", num_envs=2, seed=3)
        try:
            frames = [envs.reset()[0].copy()]
            for _ in range(resets):
                envs.step(np.zeros(2, dtype=np.int64))
                frames.append(envs.reset()[0].copy())
            return frames
        finally:
            envs.close()

    frames = first_frames(3)
    for earlier in range(len(frames)):
        for later in range(earlier + 1, len(frames)):
            assert not np.array_equal(frames[earlier], frames[later]), f"reset {later} replayed reset {earlier}'s levels"
    for mine, again in zip(frames, first_frames(3)):
        np.testing.assert_array_equal(mine, again)
