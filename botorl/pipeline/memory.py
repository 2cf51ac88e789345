"""A population's memory (docs/populations.md): estimated before any work and compared with
what the machine has (``check_fits``). The mapped calls are botorl/agents/population.py; the
members, botorl/configs/members.py.
"""

from __future__ import annotations

import contextlib
import os

import jax
import numpy as np

from botorl.configs.methods import get_method
from botorl.data.dataset import TRANSITION_FIELDS
from botorl.errors import ConfigError
from botorl.pipeline.stages import agent_template, make_pretrain_agent

# ============================================================================ memory
def tree_bytes(tree) -> int:
    return int(sum(np.dtype(x.dtype).itemsize * int(np.prod(x.shape)) for x in jax.tree_util.tree_leaves(tree)
                   if hasattr(x, "shape")))


def available_memory() -> tuple[int, str]:
    """(bytes, what): the accelerator's memory off the CPU, else the host's MemAvailable."""
    if jax.default_backend() != "cpu":
        with contextlib.suppress(Exception):
            stats = jax.devices()[0].memory_stats() or {}
            limit = int(stats.get("bytes_limit", 0)) - int(stats.get("bytes_in_use", 0))
            if limit > 0:
                return limit, f"{jax.devices()[0].device_kind} memory"
    return host_memory()


def host_memory() -> tuple[int, str]:
    with contextlib.suppress(OSError), open("/proc/meminfo") as f:
        for line in f:
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024, "available host memory (MemAvailable)"
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")), "free host memory"


def _rss_bytes() -> int | None:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def env_bytes(make_env, probes: int = 6) -> int:
    """Host memory one more environment takes: the median resident-size growth over ``probes``
    envs, after two that pay for imports, caches and the allocator's first arenas; 0 where unreadable."""
    envs = []

    def one():
        e = make_env(len(envs))
        e.reset(seed=0)
        envs.append(e)

    one()
    one()
    sizes = [_rss_bytes()]
    if sizes[0] is None:
        return 0
    for _ in range(probes):
        one()
        sizes.append(_rss_bytes() or sizes[-1])
    for e in envs:
        with contextlib.suppress(Exception):
            e.close()
    return max(0, int(np.median(np.diff(sizes))))


def estimate_memory(*, num_members: int, agent_bytes: int, buffer_rows: int, warmup_rows: int, obs_dim: int,
                    action_dim: int, batch_rows: int, activation_floats: int, offline_bytes: int,
                    env_bytes_per_member: int = 0) -> dict[str, int]:
    """Bytes the population needs, by part; per member but ``offline_bytes`` (D_offline, held
    once). The agent counts three times: the state, the update's output, the checkpoint copy."""
    row = 4 * (2 * obs_dim + action_dim + 3)
    parts = {
        "agents": 3 * num_members * agent_bytes,
        "replay": num_members * buffer_rows * row,
        "warmup": num_members * warmup_rows * row,
        "batches": 2 * num_members * batch_rows * row,
        "activations": 4 * num_members * activation_floats,
        "offline data": offline_bytes,
        "environments": num_members * env_bytes_per_member,
    }
    parts["total"] = sum(parts.values())
    return parts


def check_memory(parts: dict[str, int], num_members: int, *, available: tuple[int, str] | None = None,
                 headroom: float = 0.85) -> None:
    """ConfigError when the estimate exceeds ``headroom`` of the available memory."""
    have, what = available or available_memory()
    need = parts["total"]
    if need > headroom * have:
        per = (need - parts.get("offline data", 0)) / max(1, num_members)
        fit = max(0, int((headroom * have - parts.get("offline data", 0)) // max(per, 1)))
        detail = ", ".join(f"{k} {v / 2**30:.2f} GiB" for k, v in parts.items() if k != "total" and v)
        raise ConfigError(
            f"a population of {num_members} members needs about {need / 2**30:.1f} GiB ({detail}), more than "
            f"{headroom:.0%} of the {have / 2**30:.1f} GiB of {what}. Use fewer members (about {fit} fit: fewer "
            "--seeds/--alphas, or --population-size for a sweep), a smaller --online.buffer_capacity, or a "
            "smaller --offline.updates_per_call" + (", or fewer --eval.num_envs (each member holds that many "
            "evaluation envs)" if parts.get("environments") else "") + "."
        )


def estimate(cfg, n: int, d_raw, spec) -> dict[str, int]:
    """``estimate_memory`` of a population of ``n`` members of ``cfg``, from one template member,
    the task's (``spec``) environments measured."""
    # envs first: made after JAX has built its first arrays, the first ~16 pointmaze envs grow the
    # process by twice what each later one does (allocator arenas), which would double the estimate.
    # Measured only for populations: one member's envs are a few hundred MB at most.
    per_env = 0 if n < 2 else env_bytes(lambda i: spec.make_env(seed=i, evaluation=True))
    method = get_method(cfg.method)
    O, A = d_raw.obs_dim, d_raw.action_dim
    agent_bytes = tree_bytes(agent_template(cfg, "finetune", O, A, 0))
    if method.pretrains:
        agent_bytes += tree_bytes(make_pretrain_agent(cfg, O, A, 0))
    oc = cfg.online
    warm = cfg.warmup.steps if "warmup" in method.stages else 0
    rows = oc.buffer_capacity or (oc.steps + warm + 1)
    cql = cfg.offline.cql
    width = max(max(cfg.network.critic_hidden_dims), max(cfg.network.actor_hidden_dims))
    layers = len(cfg.network.critic_hidden_dims)
    act = max(cfg.offline.batch_size * (3 * cql.cql_n_actions + 1) * cql.num_critics,
              oc.utd * oc.batch_size * cfg.network.num_critics) * width * layers * 2
    batch_rows = max(cfg.offline.updates_per_call * cfg.offline.batch_size, cfg.boto.steps_per_call * cfg.boto.batch_size,
                     oc.utd * oc.batch_size)
    offline_bytes = 3 * sum(getattr(d_raw, k).nbytes for k in TRANSITION_FIELDS)
    envs = 1 + cfg.eval.envs_per_member
    return estimate_memory(num_members=n, agent_bytes=agent_bytes, buffer_rows=rows, warmup_rows=warm, obs_dim=O,
                           action_dim=A, batch_rows=batch_rows, activation_floats=act, offline_bytes=offline_bytes,
                           env_bytes_per_member=envs * per_env)


def check_fits(cfg, n: int, d_raw, spec) -> None:
    """ConfigError (exit 2) before any work when the population does not fit the machine."""
    parts = estimate(cfg, n, d_raw, spec)
    if jax.default_backend() == "cpu":
        check_memory(parts, n)
    else:  # environments live in host memory, the rest on the accelerator
        envs = parts.pop("environments")
        parts["total"] -= envs
        check_memory(parts, n)
        check_memory({"environments": envs, "total": envs}, n, available=host_memory())
