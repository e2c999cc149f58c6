"""A gymnasium training script as a gymnasium user writes one, to show that radserve runs it with only
its env line changed (tests/test_learners.py::test_a_gymnasium_script_runs_with_only_its_env_line_changed).

The shape is CleanRL's `ppo_continuous_action.py` (Huang et al. 2022, "The 37 implementation details
of PPO"): one vector env under gymnasium's vector wrappers (FlattenObservation,
RecordEpisodeStatistics, ClipAction, NormalizeObservation, observation clipping, NormalizeReward,
reward clipping), a Gaussian policy with a state-independent log-std, GAE, clipped surrogate and value
losses over shuffled minibatches, episodic returns logged from `infos["episode"]`. The code is our own.

    python tests/scripts/ppo_continuous_action.py --env-id Hopper-v5 --out run.json               # gymnasium
    python tests/scripts/ppo_continuous_action.py --env-id Hopper-v5 --out run.json --radserve ADDR  # radserve

The two differ in the one line that makes `envs`; everything after it is gymnasium's API. The run's
episodic returns and lengths (as RecordEpisodeStatistics reported them), and radserve's own episode
figures where the env gives them, are written to `--out` as JSON.
"""

import argparse
import json
import random

import gymnasium as gym
import numpy as np
import torch
import torch.nn as nn
from torch.distributions.normal import Normal


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env-id", default="Hopper-v5")
    parser.add_argument("--radserve", default="", help="a radserve server's address: make the envs there")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--total-timesteps", type=int, default=4096)
    parser.add_argument("--num-envs", type=int, default=1)
    parser.add_argument("--num-steps", type=int, default=1024)
    parser.add_argument("--learning-rate", type=float, default=3e-4)
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--gae-lambda", type=float, default=0.95)
    parser.add_argument("--num-minibatches", type=int, default=32)
    parser.add_argument("--update-epochs", type=int, default=4)
    parser.add_argument("--clip-coef", type=float, default=0.2)
    parser.add_argument("--ent-coef", type=float, default=0.0)
    parser.add_argument("--vf-coef", type=float, default=0.5)
    parser.add_argument("--max-grad-norm", type=float, default=0.5)
    parser.add_argument("--out", required=True)
    return parser.parse_args()


def dense(inputs: int, outputs: int, gain: float = float(np.sqrt(2))) -> nn.Linear:
    """A linear layer with orthogonal weights of the given gain and zero bias (PPO's usual initialisation)."""
    layer = nn.Linear(inputs, outputs)
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class Agent(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.critic = nn.Sequential(dense(obs_dim, 64), nn.Tanh(), dense(64, 64), nn.Tanh(), dense(64, 1, 1.0))
        self.actor_mean = nn.Sequential(dense(obs_dim, 64), nn.Tanh(), dense(64, 64), nn.Tanh(),
                                        dense(64, action_dim, 0.01))
        self.actor_logstd = nn.Parameter(torch.zeros(1, action_dim))

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(obs).squeeze(-1)

    def act(self, obs: torch.Tensor, action: "torch.Tensor | None" = None):
        mean = self.actor_mean(obs)
        dist = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action).sum(-1), dist.entropy().sum(-1), self.value(obs)


def wrap(envs: gym.vector.VectorEnv, gamma: float) -> gym.vector.VectorEnv:
    envs = gym.wrappers.vector.FlattenObservation(envs)
    envs = gym.wrappers.vector.RecordEpisodeStatistics(envs)
    envs = gym.wrappers.vector.ClipAction(envs)
    envs = gym.wrappers.vector.NormalizeObservation(envs)
    envs = gym.wrappers.vector.TransformObservation(envs, lambda obs: np.clip(obs, -10, 10))
    envs = gym.wrappers.vector.NormalizeReward(envs, gamma=gamma)
    return gym.wrappers.vector.TransformReward(envs, lambda reward: np.clip(reward, -10, 10))


def main() -> None:
    args = parse()
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches

    if args.radserve:
        import radserve
        envs = radserve.Client(args.radserve).make_vec(f"gym/{args.env_id}", num_envs=args.num_envs, seed=args.seed)
    else:
        envs = gym.make_vec(args.env_id, num_envs=args.num_envs, vectorization_mode="sync")
    envs = wrap(envs, args.gamma)
    assert isinstance(envs.single_action_space, gym.spaces.Box), "continuous actions only"

    obs_dim = int(np.prod(envs.single_observation_space.shape))
    action_dim = int(np.prod(envs.single_action_space.shape))
    agent = Agent(obs_dim, action_dim)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    obs_buf = torch.zeros((args.num_steps, args.num_envs, obs_dim))
    actions_buf = torch.zeros((args.num_steps, args.num_envs, action_dim))
    logprobs_buf = torch.zeros((args.num_steps, args.num_envs))
    rewards_buf = torch.zeros((args.num_steps, args.num_envs))
    dones_buf = torch.zeros((args.num_steps, args.num_envs))
    values_buf = torch.zeros((args.num_steps, args.num_envs))

    episodes = {"return": [], "length": [], "step": [], "radserve_return": []}
    global_step = 0
    next_obs, _ = envs.reset(seed=args.seed)
    next_obs = torch.as_tensor(next_obs, dtype=torch.float32)
    next_done = torch.zeros(args.num_envs)
    losses = []
    for iteration in range(args.total_timesteps // batch_size):
        # Learning-rate annealing, as the script this follows does.
        optimizer.param_groups[0]["lr"] = args.learning_rate * (1.0 - iteration / (args.total_timesteps // batch_size))
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs_buf[step], dones_buf[step] = next_obs, next_done
            with torch.no_grad():
                action, logprob, _, value = agent.act(next_obs)
            actions_buf[step], logprobs_buf[step], values_buf[step] = action, logprob, value
            next_obs, reward, terminations, truncations, infos = envs.step(action.numpy())
            next_obs = torch.as_tensor(next_obs, dtype=torch.float32)
            next_done = torch.as_tensor(np.logical_or(terminations, truncations), dtype=torch.float32)
            rewards_buf[step] = torch.as_tensor(reward, dtype=torch.float32)
            if "episode" in infos:
                for i in np.flatnonzero(infos["_episode"]):
                    episodes["return"].append(float(infos["episode"]["r"][i]))
                    episodes["length"].append(int(infos["episode"]["l"][i]))
                    episodes["step"].append(global_step)
                    if "radserve_episode" in infos:  # radserve's own figure for the same episode
                        episodes["radserve_return"].append(float(infos["radserve_episode"]["r"][i]))

        # Generalised advantage estimation over the rollout.
        with torch.no_grad():
            next_value = agent.value(next_obs)
            advantages = torch.zeros_like(rewards_buf)
            last = torch.zeros(args.num_envs)
            for t in reversed(range(args.num_steps)):
                not_done = 1.0 - (next_done if t == args.num_steps - 1 else dones_buf[t + 1])
                following = next_value if t == args.num_steps - 1 else values_buf[t + 1]
                delta = rewards_buf[t] + args.gamma * following * not_done - values_buf[t]
                last = delta + args.gamma * args.gae_lambda * not_done * last
                advantages[t] = last
            returns = advantages + values_buf

        b_obs, b_actions = obs_buf.reshape(batch_size, obs_dim), actions_buf.reshape(batch_size, action_dim)
        b_logprobs, b_advantages = logprobs_buf.reshape(-1), advantages.reshape(-1)
        b_returns, b_values = returns.reshape(-1), values_buf.reshape(-1)
        for _ in range(args.update_epochs):
            order = np.random.permutation(batch_size)
            for start in range(0, batch_size, minibatch_size):
                index = order[start:start + minibatch_size]
                _, logprob, entropy, value = agent.act(b_obs[index], b_actions[index])
                ratio = (logprob - b_logprobs[index]).exp()
                adv = b_advantages[index]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                policy_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                clipped = b_values[index] + (value - b_values[index]).clamp(-args.clip_coef, args.clip_coef)
                value_loss = 0.5 * torch.max((value - b_returns[index]) ** 2, (clipped - b_returns[index]) ** 2).mean()
                loss = policy_loss - args.ent_coef * entropy.mean() + args.vf_coef * value_loss
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
            losses.append(loss.item())
    envs.close()
    with open(args.out, "w") as out:
        json.dump({"global_step": global_step, "episodes": episodes, "losses": losses,
                   "autoreset_mode": str(envs.metadata["autoreset_mode"].value)}, out)
    print(f"{global_step} steps, {len(episodes['return'])} episodes, "
          f"mean return {np.mean(episodes['return']) if episodes['return'] else float('nan'):.1f}")


if __name__ == "__main__":
    main()
