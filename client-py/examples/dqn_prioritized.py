"""DQN with prioritized replay and n-step returns, the replay kept and sampled by radserve.

The server keeps the replay buffer, sums the n-step returns (`n_step`, `discount`) and samples in
proportion to priority^alpha (`sampler="prioritized"`, Schaul et al. 2016); each batch carries its
importance weights, and the learner sends |TD error| back as the new priorities
(`stream.update_priorities`) after every update, as Ape-X's and Rainbow's learners do. The agent is
double DQN (van Hasselt et al. 2016) with a dueling head (Wang et al. 2016): the parts of Rainbow
(Hessel et al. 2018) that the replay serves, without the distributional head and noisy nets. Beta
is annealed from `beta_start` to 1 over the run from the batches' `probability` and `table_size`
(`radserve.importance_weights`). Epsilon-greedy acting is the learner's (`--actor learner` only:
the servers' categorical head samples from a softmax, not epsilon-greedy). The code is our own;
CleanRL's `dqn.py` is the model for its shape.

    python client-py/examples/dqn_prioritized.py                                  # gym/CartPole-v1
    python client-py/examples/dqn_prioritized.py --env gym/Acrobot-v1 --total-steps 100000
    python client-py/examples/dqn_prioritized.py --priority-exponent 0           # uniform, for comparison

Results go to runs/<env>__dqn_prioritized__<seed>__<time>/: metrics.csv, TensorBoard events,
curve.png, checkpoint.pt.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
import tyro
from gymnasium import spaces
from tqdm import tqdm

import radserve
from radserve.torch import to_tensors
from radserve.training import episode_stats, evaluate
from runs import RunLog, run_name, select_device


@dataclass
class Args:
    env: str = "gym/CartPole-v1"
    """an environment with flat state observations and discrete actions (`radserve envs --prefix gym/`)"""
    total_steps: int = 50_000
    """environment steps to train for (summed over the envs)"""
    num_envs: int = 1
    """environments acting together; each vector step takes num_envs updates"""
    seed: int = 1
    """seed of the environments (env i gets seed + i), the sampler and torch"""
    learning_starts: int = 1_000
    """environment steps of uniform random actions before learning starts"""
    buffer_size: int = 100_000
    """transitions kept by the server's replay buffer"""
    batch_size: int = 64
    """transitions per minibatch"""
    hidden_dim: int = 128
    """units of the two hidden layers"""
    lr: float = 1e-3
    """Adam's learning rate"""
    gamma: float = 0.99
    """discount"""
    n_step: int = 3
    """rewards summed per transition by the server"""
    priority_exponent: float = 0.6
    """alpha: draws in proportion to priority^alpha (0: uniform)"""
    beta_start: float = 0.4
    """beta of the importance weights at the start, annealed linearly to 1 at the end"""
    priority_epsilon: float = 1e-6
    """added to |TD error| so that no transition's priority is 0"""
    target_every: int = 500
    """updates between copies of the online network into the target network"""
    epsilon_start: float = 1.0
    """exploration rate at the start of learning"""
    epsilon_end: float = 0.05
    """... after epsilon_fraction of the run"""
    epsilon_fraction: float = 0.2
    """fraction of total_steps over which epsilon decays linearly"""
    eval_every: int = 5_000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation, on a separate session with other seeds, greedy policy"""
    prefetch: int = 2
    """minibatches the server prepares ahead of the learner (their priorities are the ones at their draw)"""
    delivery: str = "auto"
    """how minibatches and steps travel: "shared_memory", "grpc", "auto" (shared memory when it can be mapped)"""
    device: str = "auto"
    """torch device: auto (cuda when present), cpu, cuda ..."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default)"""
    log_every: int = 1_000
    """environment steps between loss logs"""
    runs_dir: str = "runs"
    """where the run directory is created"""
    checkpoint: bool = True
    """save the network and optimizer to checkpoint.pt at every evaluation"""
    address: str = ""
    """an existing radserve server, or several separated by commas (one sharded session over them); empty starts one on a free localhost port"""
    workers: int = 0
    """worker processes of a started server (0: one per core)"""


class DuelingQ(nn.Module):
    """Q(s, a) = V(s) + A(s, a) - mean_a A(s, a) over a shared trunk."""

    def __init__(self, obs_dim: int, num_actions: int, hidden: int):
        super().__init__()
        self.trunk = nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())
        self.value, self.advantage = nn.Linear(hidden, 1), nn.Linear(hidden, num_actions)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        features = self.trunk(obs)
        advantage = self.advantage(features)
        return self.value(features) + advantage - advantage.mean(dim=-1, keepdim=True)


class Dqn:
    def __init__(self, obs_dim: int, num_actions: int, args: Args, device: torch.device):
        self.args, self.device, self.num_actions = args, device, num_actions
        self.q = DuelingQ(obs_dim, num_actions, args.hidden_dim).to(device)
        self.q_target = copy.deepcopy(self.q)
        self.optimizer = torch.optim.Adam(self.q.parameters(), lr=args.lr)
        self.updates = 0

    @torch.no_grad()
    def act(self, obs: np.ndarray, epsilon: float, rng: np.random.Generator) -> np.ndarray:
        greedy = self.q(torch.as_tensor(np.asarray(obs), dtype=torch.float32, device=self.device)).argmax(-1).cpu().numpy()
        explore = rng.random(len(greedy)) < epsilon
        return np.where(explore, rng.integers(self.num_actions, size=len(greedy)), greedy)

    def update(self, batch, beta: float) -> "tuple[dict, torch.Tensor]":
        """One step on a prioritized n-step batch; (metrics, |TD error| per transition)."""
        obs, next_obs = batch.obs.float(), batch.next_obs.float()
        with torch.no_grad():
            # Double DQN: the online network picks the next action, the target network values it.
            next_action = self.q(next_obs).argmax(-1, keepdim=True)
            next_q = self.q_target(next_obs).gather(1, next_action).squeeze(-1)
            # `discount` is gamma^k for the k rewards summed, 0 after a termination.
            target = batch.reward.float() + batch.discount.float() * next_q
        q = self.q(obs).gather(1, batch.action.long().unsqueeze(-1)).squeeze(-1)
        td_error = target - q
        weights = torch.as_tensor(radserve.importance_weights(batch.probability.cpu().numpy(), batch.table_size.cpu().numpy(),
                                                              beta), device=self.device)
        loss = (weights * F.smooth_l1_loss(q, target, reduction="none")).mean()
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.q.parameters(), 10.0)
        self.optimizer.step()
        self.updates += 1
        if self.updates % self.args.target_every == 0:
            self.q_target.load_state_dict(self.q.state_dict())
        metrics = {"losses/td_loss": loss.item(), "losses/q_values": q.mean().item(),
                   "losses/mean_weight": weights.mean().item(), "charts/beta": beta}
        return metrics, td_error.detach().abs()

    def state_dict(self) -> dict:
        return {"q": self.q.state_dict(), "q_target": self.q_target.state_dict(), "optimizer": self.optimizer.state_dict(),
                "updates": self.updates}


def linear(start: float, end: float, fraction: float) -> float:
    return start + (end - start) * min(1.0, max(0.0, fraction))


def train(args: Args, address: str) -> RunLog:
    device = select_device(args.device)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    client = radserve.Client(address)
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           delivery=args.delivery, replay_capacity=min(args.buffer_size, max(args.total_steps, args.batch_size)))
    eval_envs = client.make_vec(args.env, num_envs=min(args.eval_episodes, 10), seed=args.seed + 10_000,
                                autoreset_mode="SameStep", delivery=args.delivery)
    obs_space, action_space = envs.single_observation_space, envs.single_action_space
    if len(obs_space.shape) != 1 or not isinstance(action_space, spaces.Discrete):
        raise SystemExit(f"{args.env} observes {obs_space.shape} with {action_space}; dqn_prioritized.py takes flat "
                         "state vectors and discrete actions")
    agent = Dqn(obs_space.shape[0], int(action_space.n), args, device)
    log = RunLog(args.runs_dir, run_name(args.env, "dqn_prioritized", args.seed), args)
    print(f"DQN on {args.env}: {args.n_step}-step returns, priority exponent {args.priority_exponent}, "
          f"{args.total_steps} steps, batch {args.batch_size}, {device}")
    print(f"run directory: {log.dir}")

    def run_evaluation(steps: int) -> float:
        returns = evaluate(eval_envs, lambda o: agent.act(o, 0.0, rng), args.eval_episodes)
        checkpoint = agent.state_dict() | {"env_steps": steps, "args": vars(args)} if args.checkpoint else None
        return log.evaluation(steps, returns, checkpoint)

    # min_size counts transitions whose n-step windows are complete: up to n - 1 per env are not yet.
    stream = envs.sample_batches(args.batch_size, sampler="prioritized", priority_exponent=args.priority_exponent,
                                 n_step=args.n_step, discount=args.gamma, seed=args.seed, prefetch=args.prefetch,
                                 min_size=max(args.batch_size, args.learning_starts - args.num_envs * (args.n_step - 1)),
                                 delivery=args.delivery)
    batches = iter(stream)
    vector_steps = max(1, args.total_steps // args.num_envs)
    obs, _ = envs.reset()
    last_return, last_eval = float("nan"), run_evaluation(0)
    next_eval, next_log = args.eval_every, args.learning_starts
    start = time.perf_counter()
    try:
        bar = tqdm(range(vector_steps), unit="step", dynamic_ncols=True)
        for step in bar:
            steps = (step + 1) * args.num_envs
            learning = steps > args.learning_starts
            epsilon = linear(args.epsilon_start, args.epsilon_end,
                             (steps - args.learning_starts) / max(1.0, args.epsilon_fraction * args.total_steps))
            action = agent.act(obs, epsilon, rng) if learning else envs.action_space.sample()
            obs, _, _, _, infos = envs.step(action)
            for episode_return, episode_length in episode_stats(infos):
                last_return = episode_return
                log.scalars(steps, **{"charts/episodic_return": episode_return, "charts/episodic_length": episode_length})
            if learning:
                beta = linear(args.beta_start, 1.0, steps / args.total_steps)
                for _ in range(args.num_envs):
                    batch = next(batches)
                    metrics, td_errors = agent.update(to_tensors(batch, device), beta)
                    stream.update_priorities(batch, td_errors + args.priority_epsilon)
                if steps >= next_log:
                    next_log += args.log_every
                    log.scalars(steps, **metrics, **{"charts/epsilon": epsilon,
                                                     "charts/SPS": steps / (time.perf_counter() - start)})
            if steps >= next_eval:
                next_eval += args.eval_every
                last_eval = run_evaluation(steps)
            bar.set_postfix(ret=f"{last_return:.0f}", eval=f"{last_eval:.0f}", sps=f"{steps / (time.perf_counter() - start):.0f}")
        if (vector_steps * args.num_envs) % args.eval_every:
            run_evaluation(vector_steps * args.num_envs)
    finally:
        stream.close()
        envs.close()
        eval_envs.close()
        client.close()
        log.close()
    log.summarize(args.env, "DQN, prioritized", f"{args.env}, DQN with prioritized {args.n_step}-step replay",
                  args.eval_episodes, log.started)
    return log


def main() -> None:
    args = tyro.cli(Args, description=__doc__)
    if args.address:
        train(args, args.address)
        return
    with radserve.LocalServer(workers=args.workers or None) as server:
        train(args, server.address)


if __name__ == "__main__":
    main()
