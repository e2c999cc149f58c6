"""DrQ-v2 from pixels on dm_control, trained through radserve.

DDPG with DrQ-v2's encoder, actor and critic (Yarats et al. 2021, "Mastering Visual Continuous
Control: Improved Data-Augmented Reinforcement Learning", section 3 and appendix B; every default
below is its hyperparameter table's). The server steps the environments, keeps the replay buffer,
sums the n-step returns (n = 3) and shifts every observation (shift(4): DrQ-v2's `RandomShiftsAug`,
replicate padding 4, docs/augmentations.md) on its own cores; this file acts, learns, evaluates and
logs. We follow the semantics of facebookresearch/drqv2 (`drqv2.py`: the encoder trained by the
critic only, the actor on detached features, clipped target noise, a linear exploration schedule);
the code is our own.

    python client-py/examples/drqv2_pixels.py --env dmc/walker-walk
    python client-py/examples/drqv2_pixels.py --env dmc/cartpole-swingup --actor server   # the servers act

Results go to runs/<env>__drqv2_pixels__<seed>__<time>/: metrics.csv, TensorBoard events
(`tensorboard --logdir runs`), curve.png and checkpoint.pt.
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
from radserve.training import episode_stats, evaluate, evaluate_on_servers, learn_while_servers_act
from runs import RunLog, run_name, select_device


@dataclass
class Args:
    env: str = "dmc/walker-walk"
    """a dm_control task in pixels (`radserve envs --prefix dmc/`)"""
    total_env_steps: int = 1_000_000
    """environment steps (frames: agent steps x action repeat) to train for"""
    action_repeat: int = 2
    """environment steps per agent step"""
    frame_stack: int = 3
    """frames stacked on the channel axis"""
    image_size: int = 84
    """side of the rendered square frames"""
    pad: int = 4
    """the server's random shift, shift(pad), of obs and next_obs"""
    n_step: int = 3
    """rewards summed per transition by the server (n-step returns)"""
    gamma: float = 0.99
    """discount"""
    num_envs: int = 1
    """environments acting together; each vector step takes num_envs / update_every updates"""
    seed: int = 1
    """seed of the environments (env i gets seed + i), the sampler and torch"""
    num_expl_steps: int = 2000
    """agent steps of uniform random actions before the policy acts (and learning starts)"""
    replay_capacity: int = 100_000
    """transitions kept by the server's replay buffer (DrQ-v2's 1M takes 20 GiB of 84x84 frames: raise the server's limits.replay_memory_bytes for it)"""
    batch_size: int = 256
    """transitions per minibatch"""
    update_every: int = 2
    """agent steps per update"""
    lr: float = 1e-4
    """learning rate of encoder, actor and critic"""
    feature_dim: int = 50
    """features of the actor's and critic's trunks (Linear, LayerNorm, tanh)"""
    hidden_dim: int = 1024
    """units of the actor's and critic's MLP layers"""
    num_filters: int = 32
    """filters of the encoder's four 3x3 conv layers (the first with stride 2)"""
    critic_tau: float = 0.01
    """EMA rate of the target critic"""
    std_start: float = 1.0
    """exploration noise's standard deviation at the start of the linear schedule"""
    std_end: float = 0.1
    """... and at its end"""
    std_steps: int = 500_000
    """environment steps over which the standard deviation goes from std_start to std_end (DrQ-v2: 500k frames for medium tasks, 100k for easy ones)"""
    std_clip: float = 0.3
    """clip of the noise added to the target's and the actor loss's actions"""
    eval_every: int = 10_000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation, on a separate session with other seeds"""
    render_profile: str = "default"
    """dm_control look: "default" or "fast" (cheaper software rendering)"""
    prefetch: int = 2
    """minibatches the server prepares ahead of the learner"""
    delivery: str = "auto"
    """how minibatches and steps travel: "shared_memory", "grpc", "auto" (shared memory when it can be mapped)"""
    device: str = "auto"
    """torch device: auto (cuda when present), cpu, cuda, cuda:1 ..."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default)"""
    log_every: int = 250
    """agent steps between loss logs"""
    runs_dir: str = "runs"
    """where the run directory is created"""
    checkpoint: bool = True
    """save encoder, actor, critic and optimizers to checkpoint.pt at every evaluation"""
    address: str = ""
    """an existing radserve server, or several separated by commas (one sharded session over them); empty starts one on a free localhost port"""
    workers: int = 0
    """worker processes of a started server (0: one per core)"""
    actor: str = "learner"
    """who acts: "learner" (this process runs the policy and steps the envs) or "server" (the actor is exported to ONNX with the `deterministic_noise` head and sent with the schedule's current std; the servers step and evaluate; docs/actors.md)"""
    policy_every: int = 50
    """with --actor server: updates between two policy versions sent to the servers"""


def linear_std(args: Args, env_steps: int) -> float:
    """DrQ-v2's `linear(std_start, std_end, std_steps)` schedule, over environment steps."""
    mix = min(max(env_steps / max(args.std_steps, 1), 0.0), 1.0)
    return (1.0 - mix) * args.std_start + mix * args.std_end


class Encoder(nn.Module):
    """Four 3x3 convs (the first with stride 2) on frames scaled to [-0.5, 0.5], flattened."""

    def __init__(self, obs_shape, num_filters: int):
        super().__init__()
        self.convs = nn.Sequential(
            nn.Conv2d(obs_shape[0], num_filters, 3, stride=2), nn.ReLU(),
            nn.Conv2d(num_filters, num_filters, 3, stride=1), nn.ReLU(),
            nn.Conv2d(num_filters, num_filters, 3, stride=1), nn.ReLU(),
            nn.Conv2d(num_filters, num_filters, 3, stride=1), nn.ReLU(),
        )
        with torch.no_grad():
            self.repr_dim = self.convs(torch.zeros(1, *obs_shape)).numel()

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """`obs`: frames as floats in 0..255."""
        return self.convs(obs / 255.0 - 0.5).flatten(1)


def orthogonal_init(module: nn.Module) -> None:
    """DrQ-v2's initialisation (its utils.weight_init): orthogonal weights (with the ReLU gain for
    convs) and zero biases, instead of PyTorch's uniform defaults."""
    if isinstance(module, (nn.Linear, nn.Conv2d)):
        gain = nn.init.calculate_gain("relu") if isinstance(module, nn.Conv2d) else 1.0
        nn.init.orthogonal_(module.weight, gain)
        if module.bias is not None:
            nn.init.zeros_(module.bias)


def trunk(repr_dim: int, feature_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(repr_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())


def mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden),
                         nn.ReLU(inplace=True), nn.Linear(hidden, outputs))


class Actor(nn.Module):
    def __init__(self, repr_dim: int, action_dim: int, feature_dim: int, hidden_dim: int):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.policy = mlp(feature_dim, hidden_dim, action_dim)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """The deterministic action, tanh(mu), in [-1, 1]."""
        return torch.tanh(self.policy(self.trunk(features)))


class Critic(nn.Module):
    def __init__(self, repr_dim: int, action_dim: int, feature_dim: int, hidden_dim: int):
        super().__init__()
        self.trunk = trunk(repr_dim, feature_dim)
        self.q1 = mlp(feature_dim + action_dim, hidden_dim, 1)
        self.q2 = mlp(feature_dim + action_dim, hidden_dim, 1)

    def forward(self, features: torch.Tensor, action: torch.Tensor):
        h = torch.cat([self.trunk(features), action], dim=-1)
        return self.q1(h), self.q2(h)


def noisy(mu: torch.Tensor, std: float, clip: "float | None") -> torch.Tensor:
    """DrQ-v2's truncated normal draw: mu + N(0, std) (the noise clipped to +-clip when given),
    kept inside (-1, 1); the gradient flows to mu as if nothing were clamped (straight through)."""
    noise = torch.randn_like(mu) * std
    if clip is not None:
        noise = noise.clamp(-clip, clip)
    action = mu + noise
    clamped = action.clamp(-1.0 + 1e-6, 1.0 - 1e-6)
    return action - action.detach() + clamped.detach()


class ServerPolicy(nn.Module):
    """The actor as the servers run it (head deterministic_noise): float32 frames 0..255 -> the
    deterministic action; the server adds the schedule's noise, clips and scales it."""

    def __init__(self, encoder: Encoder, actor: Actor):
        super().__init__()
        self.encoder, self.actor = encoder, actor

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.actor(self.encoder(obs))


class DrQV2:
    def __init__(self, obs_shape, action_dim: int, args: Args, device: torch.device):
        self.args, self.device, self.obs_shape = args, device, obs_shape
        self.encoder = Encoder(obs_shape, args.num_filters).to(device)
        repr_dim = self.encoder.repr_dim
        self.actor = Actor(repr_dim, action_dim, args.feature_dim, args.hidden_dim).to(device)
        self.critic = Critic(repr_dim, action_dim, args.feature_dim, args.hidden_dim).to(device)
        for module in (self.encoder, self.actor, self.critic):
            module.apply(orthogonal_init)
        self.critic_target = copy.deepcopy(self.critic)
        self.encoder_optimizer = torch.optim.Adam(self.encoder.parameters(), lr=args.lr)
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=args.lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=args.lr)

    @torch.no_grad()
    def act(self, obs: np.ndarray, std: "float | None") -> np.ndarray:
        """An action per row of `obs`: the deterministic one (std None), or with exploration noise."""
        mu = self.actor(self.encoder(torch.as_tensor(np.array(obs), device=self.device).float()))
        return (mu if std is None else noisy(mu, std, None)).cpu().numpy()

    def update(self, batch, env_steps: int) -> dict:
        """One update from a batch the server shifted and summed: `reward` the 3-step return,
        `discount` its bootstrap factor (0 after a termination), `next_obs` 3 steps on."""
        args, std = self.args, linear_std(self.args, env_steps)
        obs = self.encoder(batch.obs.float())
        with torch.no_grad():
            next_features = self.encoder(batch.next_obs.float())
            next_action = noisy(self.actor(next_features), std, args.std_clip)
            target_q1, target_q2 = self.critic_target(next_features, next_action)
            target_q = batch.reward.float().unsqueeze(1) + batch.discount.float().unsqueeze(1) * torch.min(target_q1, target_q2)
        q1, q2 = self.critic(obs, batch.action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.encoder_optimizer.zero_grad(set_to_none=True)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()
        self.encoder_optimizer.step()

        # The actor on detached features: its loss does not reach the encoder.
        features = obs.detach()
        action = noisy(self.actor(features), std, args.std_clip)
        policy_q1, policy_q2 = self.critic(features, action)
        actor_loss = -torch.min(policy_q1, policy_q2).mean()
        self.actor_optimizer.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_optimizer.step()

        with torch.no_grad():
            for param, target in zip(self.critic.parameters(), self.critic_target.parameters()):
                target.lerp_(param, args.critic_tau)
        return {"losses/critic_loss": critic_loss.item(), "losses/actor_loss": actor_loss.item(),
                "losses/q_mean": q1.mean().item(), "losses/batch_reward": batch.reward.float().mean().item(),
                "losses/std": std}

    def policy_model(self) -> bytes:
        """The actor now, as ONNX bytes (an fp32 copy on the CPU)."""
        module = ServerPolicy(copy.deepcopy(self.encoder).cpu().float(), copy.deepcopy(self.actor).cpu().float())
        return radserve.actors.export_onnx(module, np.zeros((1, *self.obs_shape), dtype=np.float32))

    def state_dict(self) -> dict:
        return {name: getattr(self, name).state_dict() for name in
                ("encoder", "actor", "critic", "critic_target", "encoder_optimizer", "actor_optimizer", "critic_optimizer")}


def train(args: Args, address: str) -> RunLog:
    device = select_device(args.device)
    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    torch.manual_seed(args.seed)
    options = {"frame_stack": args.frame_stack, "render_profile": args.render_profile, "action_repeat": args.action_repeat,
               "height": args.image_size, "width": args.image_size}
    client = radserve.Client(address)
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           replay_capacity=args.replay_capacity, delivery=args.delivery, **options)
    eval_envs = client.make_vec(args.env, num_envs=min(args.eval_episodes, 10), seed=args.seed + 10_000,
                                autoreset_mode="SameStep", delivery=args.delivery, **options)
    obs_shape = envs.single_observation_space.shape
    low, high = envs.single_action_space.low, envs.single_action_space.high
    action_dim = low.shape[0]
    env_steps_per_step = args.action_repeat * args.num_envs

    log = RunLog(args.runs_dir, run_name(args.env, "drqv2_pixels", args.seed), args)
    agent = DrQV2(obs_shape, action_dim, args, device)
    agent_steps = max(1, args.total_env_steps // env_steps_per_step)
    print(f"DrQ-v2 on {args.env}: shift({args.pad}) and {args.n_step}-step returns on the server, frames {obs_shape}, "
          f"action repeat {args.action_repeat}, {agent_steps} agent steps, batch {args.batch_size}, {device}")
    print(f"run directory: {log.dir}")

    def scaled(action: np.ndarray) -> np.ndarray:
        return (low + (action + 1.0) * 0.5 * (high - low)).astype(np.float32)

    def record(env_steps: int, returns: "list[float]") -> float:
        checkpoint = agent.state_dict() | {"env_steps": env_steps, "args": vars(args)} if args.checkpoint else None
        return log.evaluation(env_steps, returns, checkpoint)

    shift = f"shift({args.pad})"
    # Sampling starts with the warm-up's transitions, less the last n - 1 of each env, whose n-step
    # windows are not complete yet (they do not count towards min_size).
    min_size = max(1, min(args.num_expl_steps, args.replay_capacity // args.num_envs) - (args.n_step - 1)) * args.num_envs
    sampling = dict(views={"obs": shift, "next_obs": shift}, n_step=args.n_step, discount=args.gamma,
                    seed=args.seed, prefetch=args.prefetch, min_size=min_size, delivery=args.delivery)
    try:
        if args.actor == "server":
            train_server_side(args, envs, eval_envs, agent, log, device, sampling, record)
        else:
            train_learner_side(args, envs, eval_envs, agent, log, device, sampling, record, scaled, agent_steps)
    finally:
        envs.close()
        eval_envs.close()
        client.close()
        log.close()
    log.summarize(args.env, "DrQ-v2", f"{args.env}, DrQ-v2", args.eval_episodes, log.started)
    return log


def train_learner_side(args, envs, eval_envs, agent: DrQV2, log, device, sampling, record, scaled, agent_steps) -> None:
    """--actor learner: this process acts (uniform random for num_expl_steps, then the actor with the
    schedule's noise), steps the envs over gRPC and updates every update_every agent steps."""
    env_steps_per_step = args.action_repeat * args.num_envs
    stream = envs.sample_batches(args.batch_size, **sampling)
    batches = iter(stream)
    rng = np.random.default_rng(args.seed)
    action_dim = envs.single_action_space.shape[0]
    obs, _ = envs.reset()
    last_return = float("nan")
    last_eval = record(0, evaluate(eval_envs, lambda o: scaled(agent.act(o, None)), args.eval_episodes))
    next_eval, start, metrics = args.eval_every, time.perf_counter(), {}
    try:
        bar = tqdm(range(agent_steps), unit="step", dynamic_ncols=True)
        for step in bar:
            env_steps = step * env_steps_per_step
            if step < args.num_expl_steps:
                action = rng.uniform(-1.0, 1.0, size=(args.num_envs, action_dim)).astype(np.float32)
            else:
                action = agent.act(obs, linear_std(args, env_steps))
            obs, _, _, _, infos = envs.step(scaled(action))
            env_steps += env_steps_per_step
            for episode_return, episode_length in episode_stats(infos):
                last_return = episode_return
                log.scalars(env_steps, **{"charts/episodic_return": episode_return,
                                          "charts/episodic_length": episode_length * args.action_repeat})
            if step >= args.num_expl_steps and step % args.update_every == 0:
                for _ in range(args.num_envs):
                    metrics = agent.update(to_tensors(next(batches), device), env_steps)
                if step % args.log_every < args.update_every:
                    log.scalars(env_steps, **metrics, **{"charts/SPS": env_steps / (time.perf_counter() - start)})
            if env_steps >= next_eval:
                next_eval += args.eval_every
                last_eval = record(env_steps, evaluate(eval_envs, lambda o: scaled(agent.act(o, None)), args.eval_episodes))
            bar.set_postfix(env_steps=env_steps, ret=f"{last_return:.0f}", eval=f"{last_eval:.0f}",
                            sps=f"{env_steps / (time.perf_counter() - start):.0f}")
        total = agent_steps * env_steps_per_step
        if total % args.eval_every:
            record(total, evaluate(eval_envs, lambda o: scaled(agent.act(o, None)), args.eval_episodes))
    finally:
        stream.close()


def train_server_side(args, envs, eval_envs, agent: DrQV2, log, device, sampling, record) -> None:
    """--actor server: the servers act with the exported actor and the deterministic_noise head
    (uniform random for num_expl_steps agent steps), each version sent with the schedule's std at
    that point; this process streams batches and updates. Reverb's rate limiter on both sides keeps
    batch_size / update_every samples per transition acted, as the learner-side loop does."""
    ratio = float(args.batch_size) / args.update_every
    slack = float(args.batch_size * max(args.num_envs, 4) * 4)
    acted = {"env_steps": 0}

    def noise_now() -> "tuple[float, float, int, float]":
        # DrQ-v2 acts with unclipped noise (std_clip is the target's and the actor loss's): a clip of
        # 2 is the same once the action is clamped to [-1, 1].
        std = linear_std(args, acted["env_steps"])
        return std, std, 1, 2.0

    def send(model: bytes) -> None:
        envs.set_policy(model, head="deterministic_noise", noise=noise_now())

    send(agent.policy_model())
    envs.start_acting(random_steps=args.num_expl_steps * args.num_envs, samples_per_insert=ratio, error_buffer=slack,
                      min_size=sampling["min_size"], seed=args.seed)

    def evaluate_at(env_steps: int) -> float:
        acted["env_steps"] = env_steps
        returns = evaluate_on_servers(eval_envs, agent.policy_model(), "deterministic_noise", args.eval_episodes,
                                      seed=args.seed + 10_000)
        return record(env_steps, returns)

    def update(batch) -> dict:
        return agent.update(to_tensors(batch, device), acted["env_steps"])

    def progress(env_steps: int) -> None:
        acted["env_steps"] = env_steps

    stream = envs.sample_batches(args.batch_size, samples_per_insert=ratio, error_buffer=slack, **sampling)
    with stream:
        learn_while_servers_act(envs, stream, update=update, policy=agent.policy_model, head="deterministic_noise",
                                policy_every=args.policy_every, total_env_steps=args.total_env_steps,
                                eval_every=args.eval_every, evaluate_at=evaluate_at, log=log,
                                env_steps_per_acted=args.action_repeat, log_every=args.log_every,
                                noise=lambda: noise_now(), on_progress=progress)


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
