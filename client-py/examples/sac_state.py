"""SAC from states with RAD's state augmentations, trained through radserve.

The server steps gymnasium MuJoCo (or classic-control) environments, keeps the replay buffer and
applies random amplitude scaling (`ras_s`: one factor per sample, `ras_m`: one per dimension, both
U[0.6, 1.4]) or Gaussian noise (`noise(std=...)`) to obs and next_obs with the same draw, as RAD does
for proprioceptive inputs (Laskin et al. 2020, section 4 and appendix "state-based"). SAC itself
follows Haarnoja et al. 2018 with automatic temperature, with the defaults of CleanRL's
`sac_continuous_action.py`; environments with discrete actions (gym/CartPole-v1) get the discrete
SAC of Christodoulou 2019 (expectations over the policy's action probabilities), as CleanRL's
`sac_atari.py` does. The code is our own.

    python client-py/examples/sac_state.py --env gym/HalfCheetah-v5 --aug ras_s
    python client-py/examples/sac_state.py --env gym/InvertedPendulum-v5 --aug "ras_m" --total-steps 20000
    python client-py/examples/sac_state.py --env gym/CartPole-v1 --aug "noise(std=0.1)"
    python client-py/examples/sac_state.py --actor server                           # the server acts

Results go to runs/<env>__sac_state__<seed>__<time>/: metrics.csv, TensorBoard events, curve.png,
checkpoint.pt.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from gymnasium import spaces
import tyro
from tqdm import tqdm

import radserve
from radserve.torch import to_tensors
from radserve.training import episode_stats, evaluate, evaluate_on_servers, learn_while_servers_act
from runs import RunLog, plot_curves, run_name, select_device


@dataclass
class Args:
    env: str = "gym/HalfCheetah-v5"
    """a state-observation environment (`radserve envs --prefix gym/`); continuous or discrete actions"""
    aug: str = "ras_s"
    """state augmentation the server applies to obs and next_obs: ras_s, ras_m, ras_s(alpha=0.8,beta=1.2), noise(std=0.1), none"""
    total_steps: int = 200_000
    """environment steps to train for (summed over the envs)"""
    num_envs: int = 1
    """environments acting together; each vector step takes num_envs updates"""
    seed: int = 1
    """seed of the environments (env i gets seed + i), the sampler and torch"""
    learning_starts: int = 5_000
    """environment steps of uniform random actions before learning starts"""
    buffer_size: int = 1_000_000
    """transitions kept by the server's replay buffer"""
    batch_size: int = 256
    """transitions per minibatch"""
    hidden_dim: int = 256
    """units of the two hidden layers of actor and critics"""
    gamma: float = 0.99
    """discount"""
    tau: float = 0.005
    """EMA rate of the target critics"""
    policy_lr: float = 3e-4
    """learning rate of the actor (and the temperature)"""
    q_lr: float = 1e-3
    """learning rate of the critics"""
    policy_frequency: int = 2
    """updates between actor updates (each then takes that many actor steps, TD3-style delayed)"""
    target_network_frequency: int = 1
    """updates between target EMA steps"""
    alpha: float = 0.2
    """initial entropy temperature"""
    autotune: bool = True
    """tune the temperature towards the target entropy (-|A|; 0.89 log|A| for discrete actions)"""
    eval_every: int = 5_000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation, on a separate session with other seeds, deterministic policy"""
    prefetch: int = 2
    """minibatches the server prepares ahead of the learner"""
    delivery: str = "auto"
    """how minibatches and acting travel: "shared_memory" (learner on the server's host: through memory this process maps), "grpc" (bytes through the socket), "auto" (shared memory when it can be mapped)"""
    device: str = "auto"
    """torch device: auto (cuda when present), cpu, cuda ..."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default)"""
    log_every: int = 1_000
    """environment steps between loss logs"""
    runs_dir: str = "runs"
    """where the run directory is created"""
    wait_ready_s: float = 0.0
    """seconds to wait for every server to answer SERVING before starting (a learner started beside its servers, as a Kubernetes Job is); 0: only the connection is waited for, 10 s"""
    session_name: str = ""
    """name of the training session on its server(s) (`make_vec(name=...)`): a server that snapshots replay (`[replay] snapshot_dir`) gives a session of this name its replay back after a restart; empty: anonymous"""
    on_server_loss: str = "raise"
    """with several servers, what a lost server does to the run: "raise" stops it, "continue" acts and samples on the others until it is back (docs/deployment.md)"""
    checkpoint: bool = True
    """save the networks and optimizers to checkpoint.pt at every evaluation"""
    address: str = ""
    """an existing radserve server, or several separated by commas (one sharded session over them); empty starts one on a free localhost port"""
    workers: int = 0
    """worker processes of a started server (0: one per core)"""
    actor: str = "learner"
    """who acts: "learner" (this process runs the policy and steps the envs over gRPC) or "server" (the policy is exported to ONNX and sent; the servers step the envs with it and evaluate, this process only streams batches and sends new weights; docs/actors.md)"""
    policy_every: int = 50
    """with --actor server: updates between two policy versions sent to the servers"""


def mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs))


class ContinuousPolicy(nn.Module):
    """Tanh-squashed Gaussian, rescaled to the action box; log std squashed into [-5, 2]."""

    LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0

    def __init__(self, obs_dim: int, space: spaces.Box, hidden: int):
        super().__init__()
        self.net = mlp(obs_dim, hidden, 2 * space.shape[0])
        self.register_buffer("scale", torch.tensor((space.high - space.low) / 2.0, dtype=torch.float32))
        self.register_buffer("bias", torch.tensor((space.high + space.low) / 2.0, dtype=torch.float32))

    def gaussian(self, obs):
        """The Gaussian's mean and squashed log std before the tanh."""
        mean, log_std = self.net(obs).chunk(2, dim=-1)
        return mean, self.LOG_STD_MIN + 0.5 * (self.LOG_STD_MAX - self.LOG_STD_MIN) * (torch.tanh(log_std) + 1)

    def forward(self, obs):
        """(sampled action, its log-probability, deterministic action)."""
        mean, log_std = self.gaussian(obs)
        normal = torch.distributions.Normal(mean, log_std.exp())
        raw = normal.rsample()
        squashed = torch.tanh(raw)
        log_prob = normal.log_prob(raw) - torch.log(self.scale * (1 - squashed.pow(2)) + 1e-6)
        return squashed * self.scale + self.bias, log_prob.sum(-1, keepdim=True), torch.tanh(mean) * self.scale + self.bias


class ContinuousCritic(nn.Module):
    def __init__(self, obs_dim: int, action_dim: int, hidden: int):
        super().__init__()
        self.q1, self.q2 = mlp(obs_dim + action_dim, hidden, 1), mlp(obs_dim + action_dim, hidden, 1)

    def forward(self, obs, action):
        features = torch.cat([obs, action], dim=1)
        return self.q1(features), self.q2(features)


class ServerPolicy(nn.Module):
    """The actor as the servers run it: the Gaussian's mean and log std (head gaussian_tanh: the server
    draws tanh(mean + exp(log_std) * N(0, 1)) and scales it onto the action bounds, as
    ContinuousPolicy does) or the logits (head categorical)."""

    def __init__(self, policy: nn.Module):
        super().__init__()
        self.policy = policy

    def forward(self, obs: torch.Tensor):
        if isinstance(self.policy, ContinuousPolicy):
            return self.policy.gaussian(obs)
        return self.policy.net(obs)


class DiscretePolicy(nn.Module):
    def __init__(self, obs_dim: int, num_actions: int, hidden: int):
        super().__init__()
        self.net = mlp(obs_dim, hidden, num_actions)

    def forward(self, obs):
        """(sampled action, log-probabilities of every action, their probabilities, greedy action)."""
        logits = self.net(obs)
        distribution = torch.distributions.Categorical(logits=logits)
        return distribution.sample(), F.log_softmax(logits, dim=-1), distribution.probs, logits.argmax(-1)


class DiscreteCritic(nn.Module):
    """Q values of every action at once."""

    def __init__(self, obs_dim: int, num_actions: int, hidden: int):
        super().__init__()
        self.q1, self.q2 = mlp(obs_dim, hidden, num_actions), mlp(obs_dim, hidden, num_actions)

    def forward(self, obs):
        return self.q1(obs), self.q2(obs)


class Sac:
    def __init__(self, obs_dim: int, action_space: spaces.Space, args: Args, device: torch.device):
        self.args, self.device = args, device
        self.discrete = isinstance(action_space, spaces.Discrete)
        if self.discrete:
            self.actor = DiscretePolicy(obs_dim, int(action_space.n), args.hidden_dim).to(device)
            self.critic = DiscreteCritic(obs_dim, int(action_space.n), args.hidden_dim).to(device)
            self.target_entropy = 0.89 * math.log(int(action_space.n))
        else:
            self.actor = ContinuousPolicy(obs_dim, action_space, args.hidden_dim).to(device)
            self.critic = ContinuousCritic(obs_dim, action_space.shape[0], args.hidden_dim).to(device)
            self.target_entropy = -float(np.prod(action_space.shape))
        self.critic_target = copy.deepcopy(self.critic)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=args.policy_lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=args.q_lr)
        self.log_alpha = torch.tensor(math.log(args.alpha), device=device, requires_grad=True)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=args.policy_lr)
        self.updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp().detach()

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> np.ndarray:
        outputs = self.actor(torch.as_tensor(np.array(obs), dtype=torch.float32, device=self.device))
        return (outputs[-1] if deterministic else outputs[0]).cpu().numpy()

    def _critic_loss(self, batch):
        args = self.args
        reward, not_done = batch.reward.float(), (~batch.terminated).float()  # bootstrap through time limits
        with torch.no_grad():
            if self.discrete:
                _, next_log_probs, next_probs, _ = self.actor(batch.next_obs)
                next_q = torch.min(*self.critic_target(batch.next_obs)) - self.alpha * next_log_probs
                next_v = (next_probs * next_q).sum(-1)
            else:
                next_action, next_log_prob, _ = self.actor(batch.next_obs)
                next_v = (torch.min(*self.critic_target(batch.next_obs, next_action)) - self.alpha * next_log_prob).squeeze(-1)
            target = reward + not_done * args.gamma * next_v
        if self.discrete:
            action = batch.action.long().unsqueeze(-1)
            q1, q2 = (q.gather(1, action).squeeze(-1) for q in self.critic(batch.obs))
        else:
            q1, q2 = (q.squeeze(-1) for q in self.critic(batch.obs, batch.action))
        return F.mse_loss(q1, target) + F.mse_loss(q2, target), q1

    def _actor_losses(self, obs):
        if self.discrete:
            _, log_probs, probs, _ = self.actor(obs)
            with torch.no_grad():
                q = torch.min(*self.critic(obs))
            actor_loss = (probs * (self.alpha * log_probs - q)).sum(-1).mean()
            entropy = -(probs * log_probs).sum(-1).detach()
            alpha_loss = (self.log_alpha.exp() * (entropy - self.target_entropy)).mean()
        else:
            action, log_prob, _ = self.actor(obs)
            actor_loss = (self.alpha * log_prob - torch.min(*self.critic(obs, action))).mean()
            entropy = -log_prob.detach()
            alpha_loss = (-self.log_alpha.exp() * (log_prob.detach() + self.target_entropy)).mean()
        return actor_loss, alpha_loss, entropy.mean()

    def update(self, batch) -> dict:
        args = self.args
        critic_loss, q1 = self._critic_loss(batch)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()
        metrics = {"losses/qf_loss": critic_loss.item() / 2, "losses/qf1_values": q1.mean().item()}
        if self.updates % args.policy_frequency == 0:
            # Delayed: as many actor steps as updates skipped (CleanRL's TD3-style compensation).
            for _ in range(args.policy_frequency):
                actor_loss, alpha_loss, entropy = self._actor_losses(batch.obs)
                self.actor_optimizer.zero_grad(set_to_none=True)
                actor_loss.backward()
                self.actor_optimizer.step()
                if args.autotune:
                    self.alpha_optimizer.zero_grad(set_to_none=True)
                    alpha_loss.backward()
                    self.alpha_optimizer.step()
            metrics.update({"losses/actor_loss": actor_loss.item(), "losses/alpha_loss": alpha_loss.item(),
                            "losses/alpha": self.alpha.item(), "losses/entropy": entropy.item()})
        if self.updates % args.target_network_frequency == 0:
            with torch.no_grad():
                for param, target_param in zip(self.critic.parameters(), self.critic_target.parameters()):
                    target_param.lerp_(param, args.tau)
        self.updates += 1
        return metrics

    def state_dict(self) -> dict:
        return {name: getattr(self, name).state_dict() for name in
                ("actor", "critic", "critic_target", "actor_optimizer", "critic_optimizer", "alpha_optimizer")} | {
                    "log_alpha": self.log_alpha.detach().cpu(), "updates": self.updates}


def train(args: Args, address: str) -> RunLog:
    device = select_device(args.device)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    client = radserve.Client(address, on_server_loss=args.on_server_loss, wait_ready_s=args.wait_ready_s or None)
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           delivery=args.delivery, name=args.session_name,
                           replay_capacity=min(args.buffer_size, max(args.total_steps, args.batch_size)))
    eval_envs = client.make_vec(args.env, num_envs=min(args.eval_episodes, 10), seed=args.seed + 10_000,
                                autoreset_mode="SameStep", delivery=args.delivery)
    obs_space, action_space = envs.single_observation_space, envs.single_action_space
    if len(obs_space.shape) != 1:
        raise SystemExit(f"{args.env} observes {obs_space.shape}; sac_state.py takes flat state vectors "
                         "(dm_control tasks: pass pixels=False to the session, or use sac_pixels.py)")
    agent = Sac(obs_space.shape[0], action_space, args, device)
    log = RunLog(args.runs_dir, run_name(args.env, "sac_state", args.seed), args)
    vector_steps = max(1, args.total_steps // args.num_envs)
    kind = "discrete" if agent.discrete else "continuous"
    print(f"SAC on {args.env} ({kind} actions): aug {args.aug}, {args.total_steps} steps, batch {args.batch_size}, {device}")
    print(f"run directory: {log.dir}")

    def run_evaluation(steps: int) -> float:
        return record_evaluation(args, log, agent, steps,
                                 evaluate(eval_envs, lambda o: agent.act(o, deterministic=True), args.eval_episodes))

    if args.actor == "server":
        try:
            steps, last_eval = train_server_side(args, client, envs, eval_envs, agent, log, device)
        finally:
            envs.close()
            eval_envs.close()
            client.close()
            log.close()
        return finish(args, log, steps, last_eval)

    stream = envs.sample_batches(args.batch_size, augment=args.aug, seed=args.seed,
                                   prefetch=args.prefetch, min_size=args.learning_starts, delivery=args.delivery)
    batches = iter(stream)
    obs, _ = envs.reset()
    last_return, last_eval = float("nan"), run_evaluation(0)
    next_eval, next_log = args.eval_every, args.learning_starts
    start = time.perf_counter()
    try:
        bar = tqdm(range(vector_steps), unit="step", dynamic_ncols=True)
        for step in bar:
            steps = (step + 1) * args.num_envs
            if steps <= args.learning_starts:
                action = envs.action_space.sample()
            else:
                action = agent.act(obs, deterministic=False)
            obs, _, _, _, infos = envs.step(action)
            for episode_return, episode_length in episode_stats(infos):
                last_return = episode_return
                log.scalars(steps, **{"charts/episodic_return": episode_return, "charts/episodic_length": episode_length})
            if steps > args.learning_starts:
                for _ in range(args.num_envs):
                    metrics = agent.update(to_tensors(next(batches), device))
                if steps >= next_log:
                    next_log += args.log_every
                    log.scalars(steps, **metrics, **{"charts/SPS": steps / (time.perf_counter() - start)})
            if steps >= next_eval:
                next_eval += args.eval_every
                last_eval = run_evaluation(steps)
            bar.set_postfix(ret=f"{last_return:.0f}", eval=f"{last_eval:.0f}", sps=f"{steps / (time.perf_counter() - start):.0f}")
        if (vector_steps * args.num_envs) % args.eval_every:
            last_eval = run_evaluation(vector_steps * args.num_envs)
    finally:
        stream.close()
        envs.close()
        eval_envs.close()
        client.close()
        log.close()
    return finish(args, log, vector_steps * args.num_envs, last_eval)


def finish(args: Args, log: RunLog, steps: int, final: float) -> RunLog:
    curve = plot_curves({f"SAC ({args.aug})": log.dir}, log.dir / "curve.png", title=f"{args.env}, aug {args.aug}")
    print(f"final evaluation return {final:.1f} after {steps} steps; curve: {curve}")
    return log


def train_server_side(args: Args, client, envs, eval_envs, agent: Sac, log: RunLog, device) -> "tuple[int, float]":
    """--actor server: the servers act with the exported actor (uniform random actions for the first
    learning_starts steps) and record into the replay; this process streams batches, updates, and
    sends the actor every `policy_every` updates. The rate limiter on both sides keeps one update of
    `batch_size` transitions per transition acted, as the learner-side loop does. No Step call is
    made: evaluation acts on the servers too."""
    head = "categorical" if agent.discrete else "gaussian_tanh"
    example = np.zeros((1, *envs.single_observation_space.shape), dtype=np.float32)

    def policy() -> bytes:
        return radserve.actors.export_onnx(ServerPolicy(copy.deepcopy(agent.actor).cpu()), example)

    min_size = min(args.learning_starts, args.buffer_size)
    ratio, slack = float(args.batch_size), float(args.batch_size * max(args.num_envs, 4) * 4)
    envs.set_policy(policy(), head=head)
    envs.start_acting(random_steps=args.learning_starts, samples_per_insert=ratio, error_buffer=slack,
                      min_size=min_size, seed=args.seed)

    def run_evaluation(steps: int) -> float:
        returns = evaluate_on_servers(eval_envs, policy(), head, args.eval_episodes, seed=args.seed + 10_000)
        return record_evaluation(args, log, agent, steps, returns)

    stream = envs.sample_batches(args.batch_size, augment=args.aug, seed=args.seed,
                                   prefetch=args.prefetch, min_size=min_size, samples_per_insert=ratio,
                                   error_buffer=slack, delivery=args.delivery)
    with stream:
        return learn_while_servers_act(envs, stream, update=lambda batch: agent.update(to_tensors(batch, device)),
                                        policy=policy, head=head, policy_every=args.policy_every,
                                        total_env_steps=args.total_steps, eval_every=args.eval_every,
                                        evaluate_at=run_evaluation, log=log, log_every=args.log_every)


def record_evaluation(args: Args, log: RunLog, agent: Sac, steps: int, returns: "list[float]") -> float:
    """Logs an evaluation's returns (and saves the checkpoint); their mean."""
    checkpoint = agent.state_dict() | {"env_steps": steps, "args": vars(args)} if args.checkpoint else None
    return log.evaluation(steps, returns, checkpoint)


def main() -> None:
    args = tyro.cli(Args, description=__doc__)
    if args.actor not in ("learner", "server"):
        raise SystemExit(f"--actor must be learner or server, got {args.actor!r}")
    if args.address:
        train(args, args.address)
        return
    with radserve.LocalServer(workers=args.workers or None) as server:
        train(args, server.address)


if __name__ == "__main__":
    main()
