"""RAD-SAC from pixels on dm_control, trained through radserve.

SAC with the pixel encoder of SAC-AE/CURL, as in RAD (Laskin et al. 2020, appendix "Implementation
details for DMControl" and its hyperparameter table; every value below defaults to that table). The
server steps the environments, keeps the replay buffer, and samples and augments every minibatch on
its own cores; this file only acts, learns, evaluates and logs. We follow the semantics of RAD's
`curl_sac.py` (tied conv weights between actor and critic, the actor's loss not reaching the convs,
separate EMA rates for the Q heads and the encoder); the code is our own.

    python client-py/examples/sac_pixels.py --env dmc/cartpole-swingup            # translate(108)
    python client-py/examples/sac_pixels.py --env dmc/walker-walk                  # crop(84)
    python client-py/examples/sac_pixels.py --env dmc/cheetah-run --aug "crop(84)|grayscale(p=0.3)"
    python client-py/examples/sac_pixels.py --env dmc/cartpole-balance --aug none  # pixel SAC
    python client-py/examples/sac_pixels.py --actor server                         # the servers act

Results go to runs/<env>__sac_pixels__<seed>__<time>/: metrics.csv, TensorBoard events
(`tensorboard --logdir runs`), curve.png and checkpoint.pt.
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
import tyro
from tqdm import tqdm

import radserve
from radserve.torch import to_tensors
from radserve.training import episode_stats, evaluate, evaluate_on_servers, evaluation_view, learn_while_servers_act
from runs import RunLog, run_name, select_device


@dataclass
class Args:
    env: str = "dmc/cartpole-swingup"
    """a dm_control task in pixels (`radserve envs --prefix dmc/`)"""
    aug: str = "auto"
    """augmentation pipeline the server applies to obs and next_obs (docs/augmentations.md); "auto" is the paper's choice, crop(84) for walker-walk and translate(108) otherwise; "none" is pixel SAC without augmentation"""
    total_env_steps: int = 100_000
    """environment steps to train for, counted like the paper: agent steps x action repeat (DMControl100k)"""
    action_repeat: int = 0
    """0 keeps the paper's value for the task (2 finger-spin and walker-walk, 8 cartpole, 4 otherwise)"""
    frame_stack: int = 3
    """frames stacked on the channel axis"""
    image_size: int = 0
    """side of the rendered square frames (dm_control's height and width options); 0: the env's default (100, the paper's)"""
    num_envs: int = 1
    """environments acting together; each vector step takes num_envs updates, keeping one update per transition"""
    seed: int = 1
    """seed of the environments (env i gets seed + i), the sampler and torch"""
    init_steps: int = 1000
    """agent steps of uniform random actions before learning starts"""
    replay_capacity: int = 100_000
    """transitions kept by the server's replay buffer"""
    batch_size: int = 512
    """transitions per minibatch"""
    hidden_dim: int = 1024
    """units of the actor's and critics' MLP layers"""
    latent_dim: int = 50
    """encoder output features"""
    num_conv_layers: int = 4
    """3x3 conv layers of the encoder (the first with stride 2)"""
    num_filters: int = 32
    """filters of every conv layer"""
    lr: float = 0.0
    """learning rate of actor, critic and encoder; 0 is the paper's: 2e-4 for cheetah-run, 1e-3 otherwise"""
    alpha_lr: float = 1e-4
    """learning rate of the temperature"""
    alpha_beta1: float = 0.5
    """Adam beta1 of the temperature (0.9 for the networks)"""
    init_temperature: float = 0.1
    """initial entropy temperature alpha"""
    gamma: float = 0.99
    """discount"""
    critic_tau: float = 0.01
    """EMA rate of the target Q heads"""
    encoder_tau: float = 0.05
    """EMA rate of the target encoder"""
    actor_update_freq: int = 2
    """updates between actor (and temperature) updates"""
    critic_target_update_freq: int = 2
    """updates between target-network EMA steps"""
    log_std_min: float = -10.0
    """lower bound of the policy's log standard deviation"""
    log_std_max: float = 2.0
    """upper bound of the policy's log standard deviation"""
    eval_every: int = 10_000
    """environment steps between evaluations"""
    eval_episodes: int = 10
    """episodes per evaluation, on a separate session with other seeds, through the evaluation view"""
    render_profile: str = "default"
    """dm_control look: "default" (the paper's pixels) or "fast" (cheaper software rendering)"""
    prefetch: int = 2
    """minibatches the server prepares ahead of the learner"""
    delivery: str = "auto"
    """how minibatches and acting travel: "shared_memory" (learner on the server's host: through memory this process maps), "grpc" (bytes through the socket), "auto" (shared memory when it can be mapped)"""
    amp: bool = False
    """run the encoder's convs in bfloat16 autocast (2-4x faster on CPUs with AMX/AVX512-BF16 and on recent GPUs; the paper used fp32)"""
    device: str = "auto"
    """torch device: auto (cuda when present), cpu, cuda, cuda:1 ..."""
    torch_threads: int = 0
    """CPU threads for torch (0: torch's default)"""
    log_every: int = 250
    """agent steps between loss logs"""
    runs_dir: str = "runs"
    """where the run directory is created"""
    wait_ready_s: float = 0.0
    """seconds to wait for every server to answer SERVING before starting (a learner started beside its servers, as a Kubernetes Job is); 0: only the connection is waited for, 10 s"""
    session_name: str = ""
    """name of the training session on its server(s) (`make_vec(name=...)`): a server that snapshots replay (`[replay] snapshot_dir`) gives a session of this name its replay back after a restart; empty: anonymous"""
    on_server_loss: str = "raise"
    """with several servers, what a lost server does to the run: "raise" stops it, "continue" acts and samples on the others until it is back (docs/deployment.md)"""
    checkpoint: bool = True
    """save actor, critic and optimizers to checkpoint.pt at every evaluation"""
    address: str = ""
    """an existing radserve server, or several separated by commas (one sharded session over them); empty starts one on a free localhost port"""
    workers: int = 0
    """worker processes of a started server (0: one per core)"""
    actor: str = "learner"
    """who acts: "learner" (this process runs the policy and steps the envs over gRPC) or "server" (the policy is exported to ONNX and sent; the servers step the envs with it and evaluate, this process only streams batches and sends new weights; docs/actors.md)"""
    policy_every: int = 50
    """with --actor server: updates between two policy versions sent to the servers"""


def paper_lr(env_id: str) -> float:
    return 2e-4 if env_id.endswith("cheetah-run") else 1e-3


def paper_augmentation(env_id: str) -> str:
    return "crop(84)" if env_id.endswith("walker-walk") else "translate(108)"


class Encoder(nn.Module):
    """Conv stack -> linear -> LayerNorm -> tanh. `convs` may be another encoder's, to tie weights."""

    def __init__(self, obs_shape, num_layers: int, num_filters: int, latent_dim: int, amp: bool = False,
                 convs: "nn.ModuleList | None" = None):
        super().__init__()
        self.amp = amp
        self.convs = convs if convs is not None else nn.ModuleList(
            [nn.Conv2d(obs_shape[0], num_filters, 3, stride=2)]
            + [nn.Conv2d(num_filters, num_filters, 3, stride=1) for _ in range(num_layers - 1)]
        ).to(memory_format=torch.channels_last)
        with torch.no_grad():
            features = self.conv_features(self.prepare(torch.zeros(1, *obs_shape, dtype=torch.uint8))).shape[1]
        self.head = nn.Sequential(nn.Linear(features, latent_dim), nn.LayerNorm(latent_dim))

    def prepare(self, obs: torch.Tensor) -> torch.Tensor:
        """uint8 frames -> [0, 1] floats, channels-last (it suits oneDNN and cuDNN), in bfloat16 with amp.
        Done once per batch, not once per network that reads it."""
        dtype = torch.bfloat16 if self.amp else torch.float32
        return obs.contiguous(memory_format=torch.channels_last).to(dtype).mul_(1.0 / 255.0)

    def conv_features(self, x: torch.Tensor) -> torch.Tensor:
        # With amp only the convs run in bfloat16; the heads and the losses stay fp32.
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16, enabled=self.amp):
            for conv in self.convs:
                x = F.relu(conv(x), inplace=True)
        return x.float().flatten(1)

    def forward(self, obs: torch.Tensor, detach_convs: bool = False) -> torch.Tensor:
        """`obs` as `prepare` returns it."""
        features = self.conv_features(obs)
        if detach_convs:
            features = features.detach()
        return torch.tanh(self.head(features))


def mlp(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs))


class Critic(nn.Module):
    def __init__(self, encoder: Encoder, action_dim: int, hidden: int, latent_dim: int):
        super().__init__()
        self.encoder = encoder
        self.q1 = mlp(latent_dim + action_dim, hidden, 1)
        self.q2 = mlp(latent_dim + action_dim, hidden, 1)

    def forward(self, obs, action, detach_convs: bool = False):
        features = torch.cat([self.encoder(obs, detach_convs), action], dim=1)
        return self.q1(features), self.q2(features)


class Actor(nn.Module):
    """A tanh-squashed Gaussian policy; its log std is squashed into [log_std_min, log_std_max]."""

    def __init__(self, encoder: Encoder, action_dim: int, hidden: int, latent_dim: int, log_std_min: float, log_std_max: float):
        super().__init__()
        self.encoder = encoder
        self.trunk = mlp(latent_dim, hidden, 2 * action_dim)
        self.log_std_min, self.log_std_max = log_std_min, log_std_max

    def forward(self, obs, detach_convs: bool = False):
        """(tanh(mean), tanh(sample), log-probability of the sample, log std)."""
        mean, log_std = self.trunk(self.encoder(obs, detach_convs)).chunk(2, dim=-1)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (torch.tanh(log_std) + 1)
        noise = torch.randn_like(mean)
        sample = mean + noise * log_std.exp()
        log_prob = (-0.5 * noise.pow(2) - log_std).sum(-1, keepdim=True) - 0.5 * math.log(2 * math.pi) * mean.shape[-1]
        squashed = torch.tanh(sample)
        # Change of variables through tanh (SAC, appendix C).
        log_prob = log_prob - torch.log(F.relu(1 - squashed.pow(2)) + 1e-6).sum(-1, keepdim=True)
        return torch.tanh(mean), squashed, log_prob, log_std


class ServerPolicy(nn.Module):
    """The actor as the servers run it (head gaussian_tanh): observations as float32 0..255 -> the
    Gaussian's mean and squashed log std; the server draws tanh(mean + exp(log_std) * N(0, 1)) and
    scales it onto the action bounds, as `RadSac.act` and `scaled` do here. fp32 convs (no autocast):
    ONNX Runtime's CPU convolutions are fp32."""

    def __init__(self, actor: Actor):
        super().__init__()
        self.actor = actor

    def forward(self, obs: torch.Tensor):
        x = obs * (1.0 / 255.0)
        for conv in self.actor.encoder.convs:
            x = F.relu(conv(x))
        features = torch.tanh(self.actor.encoder.head(x.flatten(1)))
        mean, log_std = self.actor.trunk(features).chunk(2, dim=-1)
        log_std = self.actor.log_std_min + 0.5 * (self.actor.log_std_max - self.actor.log_std_min) * (torch.tanh(log_std) + 1)
        return mean, log_std


def policy_model(agent: "RadSac", obs_shape) -> bytes:
    """The agent's actor now, as ONNX bytes (an fp32 copy on the CPU, exported)."""
    module = ServerPolicy(copy.deepcopy(agent.actor).cpu().float())
    return radserve.actors.export_onnx(module, np.zeros((1, *obs_shape), dtype=np.float32))


def soft_update(net: nn.Module, target: nn.Module, tau: float) -> None:
    with torch.no_grad():
        for param, target_param in zip(net.parameters(), target.parameters()):
            target_param.lerp_(param, tau)


class RadSac:
    def __init__(self, obs_shape, action_dim: int, args: Args, lr: float, device: torch.device):
        self.args, self.device = args, device
        critic_encoder = Encoder(obs_shape, args.num_conv_layers, args.num_filters, args.latent_dim, args.amp)
        actor_encoder = Encoder(obs_shape, args.num_conv_layers, args.num_filters, args.latent_dim, args.amp,
                                convs=critic_encoder.convs)
        self.critic = Critic(critic_encoder, action_dim, args.hidden_dim, args.latent_dim).to(device)
        self.critic_target = copy.deepcopy(self.critic)
        self.actor = Actor(actor_encoder, action_dim, args.hidden_dim, args.latent_dim, args.log_std_min, args.log_std_max).to(device)
        self.log_alpha = torch.tensor(math.log(args.init_temperature), device=device, requires_grad=True)
        self.target_entropy = -float(action_dim)
        # The actor's optimizer skips the tied convs: the actor loss never reaches them.
        shared = {id(p) for p in self.critic.encoder.convs.parameters()}
        self.actor_optimizer = torch.optim.Adam([p for p in self.actor.parameters() if id(p) not in shared], lr=lr, fused=True)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=lr, fused=True)
        self.alpha_optimizer = torch.optim.Adam([self.log_alpha], lr=args.alpha_lr, betas=(args.alpha_beta1, 0.999), fused=True)
        self.updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.log_alpha.exp()

    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> np.ndarray:
        obs = self.critic.encoder.prepare(torch.as_tensor(np.array(obs), device=self.device))
        mean, sample, _, _ = self.actor(obs)
        return (mean if deterministic else sample).cpu().numpy()

    def update(self, batch) -> dict:
        args = self.args
        prepare = self.critic.encoder.prepare
        obs, next_obs, action = prepare(batch.obs), prepare(batch.next_obs), batch.action
        reward = batch.reward.float().unsqueeze(1)
        not_done = (~batch.terminated).float().unsqueeze(1)  # bootstrap through time limits
        with torch.no_grad():
            _, next_action, next_log_prob, _ = self.actor(next_obs)
            target_q1, target_q2 = self.critic_target(next_obs, next_action)
            target_v = torch.min(target_q1, target_q2) - self.alpha * next_log_prob
            target_q = reward + not_done * args.gamma * target_v
        q1, q2 = self.critic(obs, action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_optimizer.step()
        metrics = {"losses/critic_loss": critic_loss.item(), "losses/q_mean": q1.mean().item()}

        if self.updates % args.actor_update_freq == 0:
            _, policy_action, log_prob, log_std = self.actor(obs, detach_convs=True)
            policy_q1, policy_q2 = self.critic(obs, policy_action, detach_convs=True)
            actor_loss = (self.alpha.detach() * log_prob - torch.min(policy_q1, policy_q2)).mean()
            self.actor_optimizer.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_optimizer.step()
            alpha_loss = (self.alpha * (-log_prob - self.target_entropy).detach()).mean()
            self.alpha_optimizer.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_optimizer.step()
            metrics.update({"losses/actor_loss": actor_loss.item(), "losses/alpha_loss": alpha_loss.item(),
                            "losses/alpha": self.alpha.item(), "losses/entropy": -log_prob.mean().item()})

        if self.updates % args.critic_target_update_freq == 0:
            soft_update(self.critic.q1, self.critic_target.q1, args.critic_tau)
            soft_update(self.critic.q2, self.critic_target.q2, args.critic_tau)
            soft_update(self.critic.encoder, self.critic_target.encoder, args.encoder_tau)
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
    aug = paper_augmentation(args.env) if args.aug == "auto" else args.aug
    lr = args.lr or paper_lr(args.env)
    view = evaluation_view(aug)
    options = {"frame_stack": args.frame_stack, "render_profile": args.render_profile}
    if args.action_repeat:
        options["action_repeat"] = args.action_repeat
    if args.image_size:
        options["height"] = options["width"] = args.image_size

    client = radserve.Client(address, on_server_loss=args.on_server_loss, wait_ready_s=args.wait_ready_s or None)
    # Acting sees the evaluation view (the centre of what the learner trains on); replay keeps raw frames.
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           replay_capacity=args.replay_capacity, name=args.session_name,
                           observation_view=view, delivery=args.delivery, **options)
    eval_envs = client.make_vec(args.env, num_envs=min(args.eval_episodes, 10), seed=args.seed + 10_000,
                                autoreset_mode="SameStep", observation_view=view, delivery=args.delivery, **options)
    action_repeat = int(envs.info.options["action_repeat"])
    obs_shape = envs.single_observation_space.shape
    low, high = envs.single_action_space.low, envs.single_action_space.high
    action_dim = low.shape[0]

    log = RunLog(args.runs_dir, run_name(args.env, "sac_pixels", args.seed), args)
    agent = RadSac(obs_shape, action_dim, args, lr, device)
    env_steps_per_step = action_repeat * args.num_envs
    agent_steps = max(1, args.total_env_steps // env_steps_per_step)
    print(f"RAD-SAC on {args.env}: aug {aug}, acting/evaluating on {obs_shape} ({view or 'full frame'}), "
          f"action repeat {action_repeat}, {agent_steps} agent steps, batch {args.batch_size}, lr {lr}, {device}")
    print(f"run directory: {log.dir}")

    def scaled(action: np.ndarray) -> np.ndarray:
        return (low + (action + 1.0) * 0.5 * (high - low)).astype(np.float32)

    def run_evaluation(env_steps: int) -> float:
        returns = evaluate(eval_envs, lambda o: scaled(agent.act(o, deterministic=True)), args.eval_episodes)
        return record_evaluation(args, log, agent, env_steps, returns)

    if args.actor == "server":
        try:
            train_server_side(args, client, envs, eval_envs, agent, log, aug, action_repeat, obs_shape, device)
        finally:
            envs.close()
            eval_envs.close()
            client.close()
            log.close()
        return finish(args, log, aug, start=log.started)

    # The server samples uniformly from its replay buffer once it holds the initial steps' transitions,
    # augments obs and next_obs, and keeps `prefetch` minibatches ready.
    stream = envs.sample_batches(args.batch_size, augment=aug, seed=args.seed, prefetch=args.prefetch,
                                   min_size=min(args.init_steps * args.num_envs, args.replay_capacity),
                                   delivery=args.delivery)
    batches = iter(stream)
    rng = np.random.default_rng(args.seed)
    obs, _ = envs.reset()
    last_return, last_eval = float("nan"), run_evaluation(0)
    next_eval = args.eval_every
    start = time.perf_counter()
    metrics: dict = {}
    try:
        bar = tqdm(range(agent_steps), unit="step", dynamic_ncols=True)
        for step in bar:
            if step < args.init_steps:
                action = rng.uniform(-1.0, 1.0, size=(args.num_envs, action_dim)).astype(np.float32)
            else:
                action = agent.act(obs, deterministic=False)
            obs, _, _, _, infos = envs.step(scaled(action))
            env_steps = (step + 1) * env_steps_per_step
            for episode_return, episode_length in episode_stats(infos):
                last_return = episode_return
                log.scalars(env_steps, **{"charts/episodic_return": episode_return,
                                          "charts/episodic_length": episode_length * action_repeat})

            if step >= args.init_steps:
                for _ in range(args.num_envs):
                    metrics = agent.update(to_tensors(next(batches), device))
                if (step - args.init_steps) % args.log_every == 0:
                    sps = env_steps / (time.perf_counter() - start)
                    log.scalars(env_steps, **metrics, **{"charts/SPS": sps})

            if env_steps >= next_eval:
                next_eval += args.eval_every
                last_eval = run_evaluation(env_steps)
            bar.set_postfix(env_steps=env_steps, ret=f"{last_return:.0f}", eval=f"{last_eval:.0f}",
                            sps=f"{env_steps / (time.perf_counter() - start):.0f}")
        if (agent_steps * env_steps_per_step) % args.eval_every:
            last_eval = run_evaluation(agent_steps * env_steps_per_step)
    finally:
        stream.close()
        envs.close()
        eval_envs.close()
        client.close()
        log.close()
    return finish(args, log, aug, start)


def finish(args: Args, log: RunLog, aug: str, start: float) -> RunLog:
    log.summarize(args.env, f"RAD-SAC ({aug})", f"{args.env}, aug {aug}", args.eval_episodes, start)
    return log


def record_evaluation(args: Args, log: RunLog, agent: RadSac, env_steps: int, returns: "list[float]") -> float:
    """Logs an evaluation's returns (and saves the checkpoint); their mean."""
    checkpoint = agent.state_dict() | {"env_steps": env_steps, "args": vars(args)} if args.checkpoint else None
    return log.evaluation(env_steps, returns, checkpoint)


def train_server_side(args: Args, client, envs, eval_envs, agent: RadSac, log: RunLog, aug: str, action_repeat: int,
                      obs_shape, device) -> None:
    """--actor server: the servers act with the exported actor (random actions for the first init_steps
    agent steps) and record into the replay; this process streams batches, updates, and sends the
    actor every `policy_every` updates. Reverb's rate limiter on both sides keeps one update of
    `batch_size` transitions per transition acted, as the learner-side loop does; `error_buffer`
    lets either run ahead by a few updates. No Step call is made: evaluation acts on the servers too."""
    min_size = min(args.init_steps * args.num_envs, args.replay_capacity)
    ratio, slack = float(args.batch_size), float(args.batch_size * max(args.num_envs, 4) * 4)
    envs.set_policy(policy_model(agent, obs_shape), head="gaussian_tanh")
    envs.start_acting(random_steps=args.init_steps * args.num_envs, samples_per_insert=ratio, error_buffer=slack,
                      min_size=min_size, seed=args.seed)

    def run_evaluation(env_steps: int) -> float:
        returns = evaluate_on_servers(eval_envs, policy_model(agent, obs_shape), "gaussian_tanh", args.eval_episodes,
                                      seed=args.seed + 10_000)
        return record_evaluation(args, log, agent, env_steps, returns)

    stream = envs.sample_batches(args.batch_size, augment=aug, seed=args.seed, prefetch=args.prefetch,
                                   min_size=min_size, samples_per_insert=ratio, error_buffer=slack, delivery=args.delivery)
    with stream:
        learn_while_servers_act(envs, stream, update=lambda batch: agent.update(to_tensors(batch, device)),
                                policy=lambda: policy_model(agent, obs_shape), head="gaussian_tanh",
                                policy_every=args.policy_every, total_env_steps=args.total_env_steps,
                                eval_every=args.eval_every, evaluate_at=run_evaluation, log=log,
                                env_steps_per_acted=action_repeat, log_every=args.log_every)


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
