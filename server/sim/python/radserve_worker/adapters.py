"""The worker's entry points (worker.rs calls them): the ids it hosts, an env's spec, the group for a
session's envs, and the process's set-up."""

import os

from radserve_worker.common import _quiet_absl
from radserve_worker.dmc import DmcEnv
from radserve_worker.envpool_engine import EnvpoolGroup
from radserve_worker.group import Group
from radserve_worker.gymnasium_tasks import GYM_IDS, GymEnv
from radserve_worker.procgen_games import PROCGEN_GAMES, ProcgenGroup, ProcgenSpec


ADAPTERS = {"dmc": DmcEnv, "gym": GymEnv, "procgen": ProcgenSpec}


def list_names():
    from dm_control import suite

    return {
        "dmc": [f"{domain}-{task}" for domain, task in suite.ALL_TASKS],
        "gym": list(GYM_IDS),
        "procgen": list(PROCGEN_GAMES),
    }


def spec(family, name, options):
    if options.get("engine") == "envpool":
        group = EnvpoolGroup(family, name, options, [0])
        try:
            return group.spec()
        finally:
            group.close()
    env = ADAPTERS[family](name, options, 0)
    try:
        return env.spec()
    finally:
        env.close()


def make_group(family, name, options, seeds):
    """The group the worker hosts for one session's envs in this worker (called from worker.rs)."""
    if options.get("engine") == "envpool":
        return EnvpoolGroup(family, name, options, seeds)
    if family == "procgen":
        return ProcgenGroup(name, options, seeds)
    return Group(ADAPTERS[family], name, options, seeds)


def configure():
    _quiet_absl()
    os.environ.setdefault("PYOPENGL_PLATFORM", os.environ.get("MUJOCO_GL", "egl"))
