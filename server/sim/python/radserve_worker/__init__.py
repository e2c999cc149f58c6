"""The environment adapters that run inside a radserve worker process.

The worker (server/sim/src/worker.rs) embeds CPython, loads these modules once (this package first,
`adapters` last) and calls `adapters` from the one thread that owns every environment of the process for
its whole life (OpenGL contexts are bound to the thread that created them). One call steps a whole group
of environments while holding the GIL, and frames are written straight into shared memory that the server
reads after the call returns.

Each family's adapter (`dmc`, `gymnasium_tasks`, `procgen_games`) turns one simulator into the same small
contract:
    spec() -> {"observation": space, "action": space}      (one frame, before stacking)
    reset(seed or None) -> (frame, info)                      (numpy array of the observation space)
    step(action) -> (frame, reward, terminated, truncated, info)
and a group (`group.Group`, `procgen_games.ProcgenGroup`, `envpool_engine.EnvpoolGroup`) steps a
session's envs of this worker together. Outside the worker (tests, benchmarks), import
`radserve_worker.adapters` with server/sim/python on sys.path.
"""

import warnings

warnings.filterwarnings("ignore")
