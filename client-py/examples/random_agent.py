"""The smallest radserve program: start a server on localhost and drive a
vectorized dm_control pixel environment through it with random actions.

    python client-py/examples/random_agent.py --env dmc/cheetah-run --num-envs 4 --steps 2000
"""

import time
from dataclasses import dataclass

import numpy as np
import tyro
from tqdm import tqdm

import radserve


@dataclass
class Args:
    env: str = "dmc/cheetah-run"
    """environment id (see `radserve envs`)"""
    num_envs: int = 4
    """environments in the session, stepped together"""
    steps: int = 1200
    """environment steps in total (summed over the envs)"""
    seed: int = 1
    """environment i is seeded with seed + i"""
    render_profile: str = "default"
    """dm_control look: "default" (the paper's pixels) or "fast" (no shadows/reflections/multisampling)"""
    address: str = ""
    """an existing server to use; empty starts one on a free localhost port"""
    wait_ready_s: float = 0.0
    """seconds to wait for every server to answer SERVING before starting (a learner started beside its servers, as a Kubernetes Job is); 0: only the connection is waited for, 10 s"""
    workers: int = 0
    """worker processes of the started server (0: one per core)"""


def run(args: Args, address: str) -> None:
    client = radserve.Client(address, wait_ready_s=args.wait_ready_s or None)
    options = {"render_profile": args.render_profile} if args.env.startswith("dmc/") else {}
    envs = client.make_vec(args.env, num_envs=args.num_envs, seed=args.seed, **options)
    print(f"{args.env}: {args.num_envs} envs, observation {envs.single_observation_space}, "
          f"action {envs.single_action_space}")
    rng = np.random.default_rng(args.seed)
    low, high = envs.single_action_space.low, envs.single_action_space.high
    envs.reset()
    returns = []
    start = time.perf_counter()
    with tqdm(total=args.steps, unit="step", dynamic_ncols=True) as bar:
        while bar.n < args.steps:
            actions = rng.uniform(low, high, size=(args.num_envs,) + low.shape).astype(np.float32)
            _, _, _, _, infos = envs.step(actions)
            if "radserve_episode" in infos:
                returns.extend(infos["radserve_episode"]["r"][infos["_radserve_episode"]].tolist())
            bar.update(args.num_envs)
            elapsed = time.perf_counter() - start
            bar.set_postfix(sps=f"{bar.n / elapsed:.1f}", episodes=len(returns),
                            last_return=f"{returns[-1]:.1f}" if returns else "-")
    elapsed = time.perf_counter() - start
    print(f"{bar.n} steps in {elapsed:.1f} s: {bar.n / elapsed:.1f} steps/s; {len(returns)} episodes"
          + (f", mean return {np.mean(returns):.1f}" if returns else ""))
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
