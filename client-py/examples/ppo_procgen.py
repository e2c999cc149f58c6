"""PPO with data augmentation on ProcGen, trained through radserve.

RAD's ProcGen setup (Laskin et al. 2020, appendix "Implementation details and additional results for
ProcGen"): PPO (Schulman et al. 2017) with the IMPALA CNN (Espeholt et al. 2018) and the
hyperparameters of ProcGen's own baseline (Cobbe et al. 2019): 64 envs, 256 steps per rollout,
8 minibatches, 3 epochs, clip 0.2, gamma 0.99, lambda 0.95, lr 5e-4, rewards normalized by a running
estimate of the discounted return's spread. RAD's table prints an entropy bonus of 0.1; ProcGen's
baseline, which the paper says it follows, uses 0.01, and so do we (`--ent-coef 0.1` for the table's).
The PPO loss follows CleanRL's `ppo_procgen.py` (clipped value loss, advantages normalized per
minibatch); the code is our own.

The server keeps the rollout (every env's last `num_steps` observations): the learner keeps only
actions, log-probabilities, values and rewards, computes advantages, then streams the rollout back
in shuffled minibatches, `update_epochs` passes, each observation augmented on the server, with the
augmentation drawn once per env for the whole rollout (`--per-env-augmentation`) or per sample.
Batches carry (t, env_index), which pair them with the learner's advantages. Acting and evaluation
see the augmentation's evaluation view (crop(56): the centre 56x56). Training uses `num_levels`
levels; evaluation runs zero-shot on the full level distribution (num_levels=0) in another session.

    python client-py/examples/ppo_procgen.py --env procgen/bigfish --num-levels 200
    python client-py/examples/ppo_procgen.py --env procgen/starpilot --aug "cutout_color"

Results go to runs/<env>__ppo_procgen__<seed>__<time>/: metrics.csv, TensorBoard events, curve.png,
checkpoint.pt.
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
from tqdm import tqdm

import radserve
from radserve.torch import to_tensors
from radserve.training import ActorProgress, episode_stats, evaluate, evaluate_on_servers, evaluation_view
from runs import RunLog, plot_curves, run_name, select_device


@dataclass
class Args:
    env: str = "procgen/bigfish"
    """a ProcGen game (`radserve envs --prefix procgen/`)"""
    aug: str = "crop(56)"
    """augmentation pipeline the server applies to every observation of a minibatch (docs/augmentations.md): crop(56), cutout_color, color_jitter, conv, flip, rotate, grayscale, none, ..."""
    per_env_augmentation: bool = True
    """draw the augmentation once per env for the whole rollout (False: once per sample)"""
    delivery: str = "auto"
    """how minibatches and acting travel: "shared_memory" (learner on the server's host: through memory this process maps), "grpc" (bytes through the socket), "auto" (shared memory when it can be mapped)"""
    num_levels: int = 200
    """training levels (the paper trains on 100 or 200)"""
    start_level: int = 0
    """first training level"""
    distribution_mode: str = "easy"
    """ProcGen difficulty"""
    total_timesteps: int = 20_000_000
    """environment steps to train for (summed over the envs)"""
    num_envs: int = 64
    """environments acting together"""
    num_steps: int = 256
    """steps per env and rollout"""
    num_minibatches: int = 8
    """minibatches per epoch over the rollout"""
    update_epochs: int = 3
    """passes over each rollout"""
    learning_rate: float = 5e-4
    """Adam learning rate"""
    anneal_lr: bool = False
    """anneal the learning rate linearly to 0"""
    gamma: float = 0.99
    """discount"""
    gae_lambda: float = 0.95
    """lambda of generalized advantage estimation"""
    clip_coef: float = 0.2
    """PPO clip range (policy and value)"""
    clip_vloss: bool = True
    """clip the value loss as ProcGen's baseline does"""
    ent_coef: float = 0.01
    """entropy bonus (ProcGen's baseline; RAD's table prints 0.1)"""
    vf_coef: float = 0.5
    """value loss weight"""
    max_grad_norm: float = 0.5
    """gradient clipping norm"""
    norm_adv: bool = True
    """normalize advantages per minibatch"""
    norm_reward: bool = True
    """divide rewards by a running std of the discounted return (baselines' VecNormalize), clipped to +-10"""
    seed: int = 1
    """seed of the environments (env i gets seed + i), the sampler and torch"""
    eval_every: int = 500_000
    """environment steps between evaluations"""
    eval_episodes: int = 16
    """episodes per evaluation on the full level distribution"""
    amp: bool = False
    """run the IMPALA CNN's convs in bfloat16 autocast (faster on CPUs with AMX/AVX512-BF16 and on recent GPUs)"""
    device: str = "auto"
    """torch device: auto (cuda when present), cpu, cuda ..."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default)"""
    runs_dir: str = "runs"
    """where the run directory is created"""
    checkpoint: bool = True
    """save the network and optimizer to checkpoint.pt at every evaluation"""
    address: str = ""
    """an existing radserve server, or several separated by commas (one sharded session over them); empty starts one on a free localhost port"""
    wait_ready_s: float = 0.0
    """seconds to wait for every server to answer SERVING before starting (a learner started beside its servers, as a Kubernetes Job is); 0: only the connection is waited for, 10 s"""
    workers: int = 0
    """worker processes of a started server (0: one per core)"""
    actor: str = "learner"
    """who acts: "learner" (this process runs the policy and steps the envs over gRPC) or "server" (before each rollout the policy is exported to ONNX and sent; the servers act num_steps steps with it, recording each action's log-probability and value, and evaluate; this process only reads rollouts and learns; docs/actors.md)"""


def layer_init(layer: nn.Module, std: float = np.sqrt(2), bias: float = 0.0) -> nn.Module:
    nn.init.orthogonal_(layer.weight, std)
    nn.init.constant_(layer.bias, bias)
    return layer


class ResidualBlock(nn.Module):
    def __init__(self, channels: int):
        super().__init__()
        self.conv0 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x):
        return x + self.conv1(F.relu(self.conv0(F.relu(x))))


class ConvSequence(nn.Module):
    """IMPALA's block: conv, 3x3 max-pool with stride 2, two residual blocks."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.res0, self.res1 = ResidualBlock(out_channels), ResidualBlock(out_channels)

    def forward(self, x):
        x = F.max_pool2d(self.conv(x), kernel_size=3, stride=2, padding=1)
        return self.res1(self.res0(x))


class Agent(nn.Module):
    def __init__(self, obs_shape, num_actions: int, amp: bool, depths=(16, 32, 32)):
        super().__init__()
        self.amp = amp
        channels, blocks = obs_shape[0], []
        for depth in depths:
            blocks.append(ConvSequence(channels, depth))
            channels = depth
        self.convs = nn.Sequential(*blocks).to(memory_format=torch.channels_last)
        with torch.no_grad():
            features = self.conv_features(torch.zeros(1, *obs_shape, dtype=torch.uint8)).shape[1]
        self.hidden = layer_init(nn.Linear(features, 256))
        self.actor = layer_init(nn.Linear(256, num_actions), std=0.01)
        self.critic = layer_init(nn.Linear(256, 1), std=1.0)

    def conv_features(self, obs: torch.Tensor) -> torch.Tensor:
        dtype = torch.bfloat16 if self.amp else torch.float32
        x = obs.contiguous(memory_format=torch.channels_last).to(dtype).mul_(1.0 / 255.0)
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16, enabled=self.amp):
            x = self.convs(x)
        return F.relu(x.float().flatten(1))

    def forward(self, obs: torch.Tensor):
        """(action logits, state value)."""
        hidden = F.relu(self.hidden(self.conv_features(obs)))
        return self.actor(hidden), self.critic(hidden).squeeze(-1)


class ServerPolicy(nn.Module):
    """The agent as the servers run it (head categorical with a value output): uint8 observations ->
    (logits, value), fp32 (no autocast: ONNX Runtime's CPU convolutions are fp32)."""

    def __init__(self, agent: Agent):
        super().__init__()
        self.agent = agent

    def forward(self, obs: torch.Tensor):
        x = obs.float() * (1.0 / 255.0)
        hidden = F.relu(self.agent.hidden(F.relu(self.agent.convs(x).flatten(1))))
        return self.agent.actor(hidden), self.agent.critic(hidden).squeeze(-1)


def policy_model(agent: Agent, obs_shape) -> bytes:
    """The agent now, as ONNX bytes (an fp32 copy on the CPU, exported)."""
    module = ServerPolicy(copy.deepcopy(agent).cpu().float())
    return radserve.actors.export_onnx(module, np.zeros((1, *obs_shape), dtype=np.uint8))


class RewardNormalizer:
    """Scales rewards by the running standard deviation of each env's discounted return (baselines'
    VecNormalize with ob=False)."""

    def __init__(self, num_envs: int, gamma: float, clip: float = 10.0, epsilon: float = 1e-8):
        self.returns = np.zeros(num_envs)
        self.gamma, self.clip, self.epsilon = gamma, clip, epsilon
        self.mean, self.var, self.count = 0.0, 1.0, epsilon

    def __call__(self, rewards: np.ndarray, dones: np.ndarray) -> np.ndarray:
        self.returns = self.returns * self.gamma + rewards
        batch_mean, batch_var, batch_count = self.returns.mean(), self.returns.var(), len(self.returns)
        delta, total = batch_mean - self.mean, self.count + batch_count
        self.mean += delta * batch_count / total
        self.var = (self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total) / total
        self.count = total
        self.returns[dones] = 0.0
        return np.clip(rewards / np.sqrt(self.var + self.epsilon), -self.clip, self.clip)


def train(args: Args, address: str) -> RunLog:
    device = select_device(args.device)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    view = evaluation_view(args.aug)
    batch_size = args.num_envs * args.num_steps
    minibatch_size = batch_size // args.num_minibatches
    num_updates = max(1, args.total_timesteps // batch_size)

    client = radserve.Client(address, wait_ready_s=args.wait_ready_s or None)
    game = {"distribution_mode": args.distribution_mode}
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           rollout_steps=args.num_steps,
                           observation_view=view, num_levels=args.num_levels, start_level=args.start_level,
                           delivery=args.delivery, **game)
    # Zero-shot: the full level distribution, seeded away from the training envs.
    eval_envs = client.make_vec(args.env, num_envs=min(args.eval_episodes, 16), seed=args.seed + 10_000,
                                observation_view=view, num_levels=0, start_level=args.start_level + 1_000_000,
                                autoreset_mode="SameStep", delivery=args.delivery, **game)
    obs_shape, num_actions = envs.single_observation_space.shape, int(envs.single_action_space.n)
    agent = Agent(obs_shape, num_actions, args.amp).to(device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    normalizer = RewardNormalizer(args.num_envs, args.gamma) if args.norm_reward else None
    log = RunLog(args.runs_dir, run_name(args.env, "ppo_procgen", args.seed), args)
    print(f"PPO on {args.env} ({args.num_levels} training levels, {args.distribution_mode}): aug {args.aug} "
          f"({'per env' if args.per_env_augmentation else 'per sample'}), acting on {obs_shape}, {num_updates} rollouts of "
          f"{args.num_envs}x{args.num_steps}, minibatch {minibatch_size}, {device}")
    print(f"run directory: {log.dir}")

    @torch.no_grad()
    def policy(obs: np.ndarray) -> np.ndarray:
        logits, _ = agent(torch.as_tensor(np.array(obs), device=device))
        return torch.distributions.Categorical(logits=logits).sample().cpu().numpy()

    def returns_here() -> "list[float]":
        return evaluate(eval_envs, policy, args.eval_episodes)

    def returns_on_servers() -> "list[float]":
        return evaluate_on_servers(eval_envs, policy_model(agent, obs_shape), "categorical", args.eval_episodes,
                                   seed=args.seed + 10_000, deterministic=False)

    # Where evaluation episodes are acted: chosen once, as the rollouts' actor below.
    evaluation_returns = returns_here if args.actor == "learner" else returns_on_servers

    def run_evaluation(steps: int) -> float:
        returns = evaluation_returns()
        log.scalars(steps, **{"charts/eval_return": np.mean(returns), "charts/eval_return_std": np.std(returns)})
        log.flush()
        if args.checkpoint:
            torch.save({"agent": agent.state_dict(), "optimizer": optimizer.state_dict(), "env_steps": steps,
                        "args": vars(args)}, log.dir / "checkpoint.pt")
        return float(np.mean(returns))

    actions = torch.zeros((args.num_steps, args.num_envs), dtype=torch.long, device=device)
    logprobs = torch.zeros((args.num_steps, args.num_envs), device=device)
    values = torch.zeros((args.num_steps, args.num_envs), device=device)
    rewards = torch.zeros((args.num_steps, args.num_envs), device=device)
    dones = torch.zeros((args.num_steps, args.num_envs), device=device)
    progress = ActorProgress(envs)
    last_return, steps = float("nan"), 0

    def act_here(obs: np.ndarray, update: int) -> "tuple[np.ndarray, list[tuple[int, dict]]]":
        """A rollout acted here: the server records every env's observations as the rollout, we
        keep the rest. Returns the observations after it and the episodes that ended (env steps, scalars)."""
        ended = []
        for t in range(args.num_steps):
            with torch.no_grad():
                logits, value = agent(torch.as_tensor(np.array(obs), device=device))
                distribution = torch.distributions.Categorical(logits=logits)
                action = distribution.sample()
            actions[t], logprobs[t], values[t] = action, distribution.log_prob(action), value
            obs, reward, terminated, truncated, infos = envs.step(action.cpu().numpy())
            done = terminated | truncated
            reward = normalizer(reward, done) if normalizer else reward
            rewards[t] = torch.as_tensor(reward, dtype=torch.float32, device=device)
            dones[t] = torch.as_tensor(done, dtype=torch.float32, device=device)
            ended += [(steps + (t + 1) * args.num_envs, {"charts/episodic_return": r, "charts/episodic_length": length})
                      for r, length in episode_stats(infos)]
        return obs, ended

    def act_on_servers(_obs: None, update: int) -> "tuple[np.ndarray, list[tuple[int, dict]]]":
        """A rollout acted by the servers: the current policy is sent, each env acts num_steps steps
        with it (the servers record the rollout with each action's log-probability and value), then one
        pass over the rollout, in the acting view, gives what act_here keeps (rewards normalized in
        step order as act_here does) and the observations after the last step."""
        envs.set_policy(policy_model(agent, obs_shape), head="categorical")
        envs.start_acting(steps_per_env=args.num_steps, seed=args.seed * 1_000_003 + update)
        progress.restarted()
        ended = [(steps + acted, {"charts/episodic_return": r}) for acted, _, r in progress.until_stopped()]
        raw_rewards = np.zeros((args.num_steps, args.num_envs), dtype=np.float32)
        raw_dones = np.zeros((args.num_steps, args.num_envs), dtype=bool)
        last_obs = np.zeros((args.num_envs, *obs_shape), dtype=np.uint8)
        with envs.sample_batches(minibatch_size, source="rollout", augment=view or "none",
                                   include_next_obs=True, seed=update, delivery=args.delivery) as stream:
            for batch in stream:
                t, env = batch.t.astype(np.int64), batch.env_index.astype(np.int64)
                actions[t, env] = torch.as_tensor(batch.action, dtype=torch.long, device=device)
                logprobs[t, env] = torch.as_tensor(batch.log_prob, device=device)
                values[t, env] = torch.as_tensor(batch.value, device=device)
                raw_rewards[t, env], raw_dones[t, env] = batch.reward, batch.terminated | batch.truncated
                last = t == args.num_steps - 1
                last_obs[env[last]] = batch.next_obs[last]
        for t in range(args.num_steps):
            reward = normalizer(raw_rewards[t], raw_dones[t]) if normalizer else raw_rewards[t]
            rewards[t] = torch.as_tensor(reward, dtype=torch.float32, device=device)
            dones[t] = torch.as_tensor(raw_dones[t], dtype=torch.float32, device=device)
        return last_obs, ended

    # Who acts the rollouts: chosen once; the loop below reads the same either way.
    act = act_here if args.actor == "learner" else act_on_servers
    obs = envs.reset()[0] if args.actor == "learner" else None
    last_eval = run_evaluation(0)
    next_eval = args.eval_every
    start = time.perf_counter()
    try:
        bar = tqdm(total=num_updates * batch_size, unit="step", unit_scale=True, dynamic_ncols=True)
        for update in range(num_updates):
            if args.anneal_lr:
                optimizer.param_groups[0]["lr"] = args.learning_rate * (1.0 - update / num_updates)
            obs, ended = act(obs, update)
            for at, episode in ended:
                last_return = episode["charts/episodic_return"]
                log.scalars(at, **episode)
            steps += batch_size
            bar.update(batch_size)

            # Generalized advantage estimation; dones[t] says whether obs t+1 starts a new episode.
            with torch.no_grad():
                _, next_value = agent(torch.as_tensor(np.array(obs), device=device))
                advantages = torch.zeros_like(rewards)
                last_gae = torch.zeros(args.num_envs, device=device)
                for t in reversed(range(args.num_steps)):
                    following = next_value if t == args.num_steps - 1 else values[t + 1]
                    not_done = 1.0 - dones[t]
                    delta = rewards[t] + args.gamma * following * not_done - values[t]
                    last_gae = delta + args.gamma * args.gae_lambda * not_done * last_gae
                    advantages[t] = last_gae
                returns = advantages + values

            # Learn: the server shuffles the rollout into minibatches and augments their observations.
            stream = envs.sample_batches(minibatch_size, source="rollout", epochs=args.update_epochs,
                                           augment=args.aug, per_env_augmentation=args.per_env_augmentation,
                                           seed=args.seed * 1_000_003 + update, delivery=args.delivery)
            clip_fractions, approx_kls = [], []
            with stream:
                for batch in stream:
                    batch = to_tensors(batch, device)
                    t, env = batch.t.long(), batch.env_index.long()
                    if not torch.equal(batch.action.long(), actions[t, env]):
                        raise RuntimeError("rollout batch does not match the actions taken: (t, env) pairing is broken")
                    logits, new_value = agent(batch.obs)
                    distribution = torch.distributions.Categorical(logits=logits)
                    new_logprob = distribution.log_prob(actions[t, env])
                    log_ratio = new_logprob - logprobs[t, env]
                    ratio = log_ratio.exp()
                    with torch.no_grad():
                        approx_kls.append(((ratio - 1) - log_ratio).mean().item())
                        clip_fractions.append(((ratio - 1.0).abs() > args.clip_coef).float().mean().item())
                    advantage = advantages[t, env]
                    if args.norm_adv:
                        advantage = (advantage - advantage.mean()) / (advantage.std() + 1e-8)
                    policy_loss = torch.max(-advantage * ratio,
                                            -advantage * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                    target, old_value = returns[t, env], values[t, env]
                    if args.clip_vloss:
                        clipped = old_value + (new_value - old_value).clamp(-args.clip_coef, args.clip_coef)
                        value_loss = 0.5 * torch.max((new_value - target) ** 2, (clipped - target) ** 2).mean()
                    else:
                        value_loss = 0.5 * ((new_value - target) ** 2).mean()
                    entropy = distribution.entropy().mean()
                    loss = policy_loss - args.ent_coef * entropy + args.vf_coef * value_loss
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                    optimizer.step()

            explained = 1 - (returns - values).var().item() / (returns.var().item() + 1e-8)
            sps = steps / (time.perf_counter() - start)
            log.scalars(steps, **{"losses/value_loss": value_loss.item(), "losses/policy_loss": policy_loss.item(),
                                  "losses/entropy": entropy.item(), "losses/approx_kl": float(np.mean(approx_kls)),
                                  "losses/clipfrac": float(np.mean(clip_fractions)), "losses/explained_variance": explained,
                                  "charts/learning_rate": optimizer.param_groups[0]["lr"], "charts/SPS": sps})
            if steps >= next_eval:
                next_eval += args.eval_every
                last_eval = run_evaluation(steps)
            bar.set_postfix(ret=f"{last_return:.1f}", eval=f"{last_eval:.1f}", sps=f"{sps:.0f}")
        bar.close()
        if steps % args.eval_every:
            last_eval = run_evaluation(steps)
    finally:
        envs.close()
        eval_envs.close()
        client.close()
        log.close()
    curve = plot_curves({f"PPO ({args.aug})": log.dir}, log.dir / "curve.png",
                        title=f"{args.env}: zero-shot evaluation on unseen levels, aug {args.aug}")
    print(f"final evaluation return {last_eval:.2f} after {steps} steps; curve: {curve}")
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
