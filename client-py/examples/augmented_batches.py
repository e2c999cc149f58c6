"""Server-side replay and augmentation without a learner (and without torch): start a radserve
server on localhost, act in a vectorized dm_control pixel environment with random actions
(observations through the centre-crop evaluation view), and, in the learner's loop, draw minibatches that the server samples from the
session's replay buffer and augments (crop 100->84, as RAD does), with a progress bar. sac_pixels.py
takes a gradient step on each batch where this one only checks and counts it.

    python client-py/examples/augmented_batches.py --env dmc/cheetah-run --batches 300
"""

import threading
import time
from dataclasses import dataclass

import numpy as np
import tyro
from tqdm import tqdm

import radserve


@dataclass
class Args:
    env: str = "dmc/cheetah-run"
    """environment id (see `radserve envs`); a dm_control pixel task"""
    num_envs: int = 4
    """environments acting together"""
    seed: int = 1
    """environment i is seeded with seed + i"""
    augment: str = "crop(84)"
    """the augmentation pipeline the server applies to obs and next_obs (docs/augmentations.md)"""
    batch_size: int = 128
    """transitions per minibatch (the paper uses 512)"""
    batches: int = 300
    """minibatches the learner draws"""
    initial_steps: int = 250
    """transitions acted before the learner starts (the paper waits for 1000)"""
    delivery: str = "auto"
    """how minibatches and acting travel: "shared_memory" (learner on the server's host: through memory this process maps), "grpc" (bytes through the socket), "auto" (shared memory when it can be mapped)"""
    replay_capacity: int = 100_000
    """transitions the server's replay buffer keeps"""
    render_profile: str = "fast"
    """dm_control look: "fast" for CPU-only hosts, "default" for the paper's pixels"""
    address: str = ""
    """an existing server to use; empty starts one on a free localhost port"""
    workers: int = 0
    """worker processes of the started server (0: one per core)"""


def act(envs, stop: threading.Event, counters: dict, seed: int) -> None:
    """Random actions until told to stop; the server records every transition."""
    rng = np.random.default_rng(seed)
    low, high = envs.single_action_space.low, envs.single_action_space.high
    envs.reset()
    while not stop.is_set():
        envs.step(rng.uniform(low, high, size=(envs.num_envs,) + low.shape).astype(np.float32))
        counters["steps"] += envs.num_envs


def run(args: Args, address: str) -> None:
    client = radserve.Client(address)
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, autoreset_mode="SameStep",
                           replay_capacity=args.replay_capacity,
                           observation_view="center_crop(84)", render_profile=args.render_profile,
                           delivery=args.delivery)
    print(f"{args.env}: {args.num_envs} envs acting on {envs.single_observation_space}; "
          f"the learner draws {args.batch_size}-transition batches augmented with {args.augment}")
    counters = {"steps": 0}
    stop = threading.Event()
    actor = threading.Thread(target=act, args=(envs, stop, counters, args.seed), daemon=True)
    actor.start()
    start = time.perf_counter()
    stream = envs.sample_batches(args.batch_size, augment=args.augment,
                                   min_size=args.initial_steps, max_batches=args.batches, seed=args.seed,
                                   delivery=args.delivery)
    try:
        with tqdm(total=args.batches, unit="batch", dynamic_ncols=True) as bar:
            for batch in stream:
                # A learner's gradient step goes here; this one checks what it got.
                assert batch.obs.shape[1:] == (9, 84, 84) and batch.next_obs.shape == batch.obs.shape
                bar.update(1)
                elapsed = time.perf_counter() - start
                bar.set_postfix(acted=counters["steps"], env_sps=f"{counters['steps'] / elapsed:.0f}",
                                batch_reward=f"{batch.reward.mean():.3f}")
    finally:
        stream.close()
        stop.set()
        actor.join()
    replay = client.describe_session(envs.session_id).replay
    elapsed = time.perf_counter() - start
    print(f"{args.batches} augmented batches in {elapsed:.1f} s while acting {counters['steps']} steps; "
          f"replay holds {replay.size} transitions at {replay.frames_per_transition:.3f} frames each")
    envs.close()
    client.close()


def main() -> None:
    args = tyro.cli(Args, description=__doc__)
    if args.address:
        run(args, args.address)
        return
    with radserve.LocalServer(workers=args.workers or None) as server:
        run(args, server.address)


if __name__ == "__main__":
    main()
