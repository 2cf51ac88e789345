"""A run's agent and policy, for use outside botorl: ``load_agent`` and ``load_policy``.

Both read only the run directory (``config.json`` and a checkpoint): the task need not be
registered and its env is never made. ``Policy`` is the chain ``flatten_obs`` -> the agent's
actions in [-1, 1] -> ``action_to_env``, nothing else (docs/own-task.md, "The policy outside
botorl").

JAX (and the configs' schema, which imports it) is imported inside the functions that need it:
botorl.api imports this module, and the API's names stay free of it (tests/test_own_task.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from botorl.configs.custom import register_given
from botorl.envs.registry import get_task
from botorl.envs.user import action_to_env, flatten_obs
from botorl.errors import ConfigError
from botorl.jaxsetup import matmul_precision, setup_jax
from botorl.pipeline.checkpoint import CheckpointManager, check_identity, full_identity
from botorl.pipeline.rundir import POPULATION_FILE, RunDir, read_json


def read_run(run_dir, verb: str = "load", *, validate: bool = False, entry: str | None = None, before=None):
    """(RunDir, RunConfig) of a single run directory, its sizes and counts checked (before any
    template is built from them); ConfigError naming what to give instead for anything else
    (``verb``: what the caller does with it, for the message). ``validate``: check the config as
    `botorl run` does (which needs the run's task here): first ``before(run, cfg)`` (the caller's
    checkpoint identity check), and only then a task of one's own is registered from ``entry``
    (the user's ``--env``), so nothing is imported or read for a directory that fails a check."""
    from botorl.configs import resolve, schema  # lazy: JAX (the agents' configs); botorl.api imports this module

    root = Path(run_dir)
    if (root / POPULATION_FILE).exists():
        members = sorted(p.name for p in root.iterdir() if (p / "config.json").exists())
        raise ConfigError(f"{root} is a population; {verb} one member's run directory, e.g. {root / (members or ['s0'])[0]}.")
    run = RunDir(root)
    if not run.config.exists():
        raise ConfigError(f"{root} is not a botorl run directory (no config.json); give the --out folder of a `botorl run`.")
    try:
        data = read_json(run.config)
        if not isinstance(data, dict):
            raise ValueError("not a JSON object")
        cfg = schema.from_dict(schema.RunConfig, data)
    except (OSError, TypeError, ValueError, KeyError, AttributeError) as err:
        raise ConfigError(f"{run.config} cannot be read as a run config ({err}); was it edited by hand?") from None
    resolve.check_bounds(cfg)
    if validate:
        if before is not None:
            before(run, cfg)
        register_given(cfg, entry)
        resolve.validate(cfg)
    return run, cfg


def check_checkpoint(run, cfg, checkpoint: str | None = None, data: bool = False):
    """(CheckpointManager, name, state) of the checkpoint ``checkpoint`` (default: the latest
    verified one) of a single run, checked to be this run's (``check_identity``; ``data``: with the
    data it was trained on, as `botorl eval` reads them; export and load_policy do not)."""
    from botorl.configs.schema import run_identity  # lazy: JAX, as in read_run

    ckpt = CheckpointManager(run.checkpoints)
    name = ckpt.chosen(checkpoint)
    state = ckpt.state(name)
    check_identity(state, [full_identity(cfg) if data else run_identity(cfg)], run.checkpoints, name)
    return ckpt, name, state


def task_io(cfg) -> dict[str, Any]:
    """The policy's interface of a run's task: obs_keys (None: flat), obs_dim, action_dim, and the
    env's action bounds (botorl's own tasks act in [-1, 1])."""
    e = cfg.env
    if e.max_steps is not None:  # a task of one's own: recorded in config.json
        return {"obs_keys": tuple(e.obs_keys) if e.obs_keys else None, "obs_dim": int(e.obs_dim),
                "action_dim": int(e.action_dim), "action_low": np.asarray(e.action_low, np.float64),
                "action_high": np.asarray(e.action_high, np.float64)}
    spec = get_task(cfg.task)  # botorl's own: the registry is plain data, no env is made
    return {"obs_keys": None, "obs_dim": spec.obs_dim, "action_dim": spec.action_dim,
            "action_low": -np.ones(spec.action_dim), "action_high": np.ones(spec.action_dim)}


def load_agent(run_dir, checkpoint: str | None = None):
    """The whole agent (actor, critics, temperature, optimiser states) of a run's checkpoint:
    ``checkpoint`` names one of ``RUN_DIR/checkpoints`` (default: the latest verified one). A
    checkpoint of fine-tuning holds the fine-tuning learner (SAC for boto/wsrl/rlpd), any earlier
    one the pre-training agent."""
    return _load(run_dir, checkpoint)[0]


def _load(run_dir, checkpoint):
    # lazy: JAX, as in read_run
    from botorl.agents import agent_file
    from botorl.pipeline import stages

    setup_jax()
    run, cfg = read_run(run_dir)
    ckpt, name, state = check_checkpoint(run, cfg, checkpoint)
    io = task_io(cfg)
    like = stages.agent_template(cfg, state["stage"], io["obs_dim"], io["action_dim"], cfg.seed)
    return agent_file.load(ckpt.file(name, "agent.ckpt"), like=like), cfg, io, name


class Policy:
    """``policy(obs)``: (B, obs_dim) -> (B, action_dim), or one (obs_dim,) observation -> (action_dim,),
    in the env's own action bounds; a dict observation (one, or leaves with a batch axis) is
    flattened first. ``deterministic``: the tanh of the Gaussian's mean (as botorl evaluates);
    otherwise a sample, from the checkpoint's random key onwards."""

    def __init__(self, agent, io: dict[str, Any], deterministic: bool = True, checkpoint: str | None = None,
                 precision: str = "tf32"):
        self.agent = agent
        self.precision = precision  # the run's matmul precision (RunConfig.precision)
        self.obs_keys: tuple[str, ...] | None = io["obs_keys"]
        self.obs_dim: int = io["obs_dim"]
        self.action_dim: int = io["action_dim"]
        self.action_low: np.ndarray = io["action_low"]
        self.action_high: np.ndarray = io["action_high"]
        self.deterministic = bool(deterministic)
        self.checkpoint = checkpoint

    def transform_obs(self, obs) -> np.ndarray:
        """The env's observation(s) -> (B, obs_dim) float32 (``flatten_obs``)."""
        if isinstance(obs, Mapping):
            flat = flatten_obs(obs, self.obs_keys or tuple(sorted(obs)), batched=_size(obs) != self.obs_dim)
        else:
            flat = np.asarray(obs, dtype=np.float32)
        flat = np.atleast_2d(flat)
        if flat.ndim != 2 or flat.shape[1] != self.obs_dim:
            raise ConfigError(f"observations of shape {np.shape(obs)}: this policy takes (B, {self.obs_dim}) or "
                              f"({self.obs_dim},)" + (f", or the env's dict observation ({', '.join(self.obs_keys)})"
                                                       if self.obs_keys else "") + ".")
        return flat

    def unit_actions(self, flat_obs: np.ndarray) -> np.ndarray:
        """(B, obs_dim) float32 -> the agent's actions in [-1, 1], (B, action_dim)."""
        with matmul_precision(self.precision):
            if self.deterministic:
                return np.asarray(self.agent.eval_actions(flat_obs))
            actions, self.agent = self.agent.sample_actions(flat_obs)
            return np.asarray(actions)

    def transform_action(self, unit: np.ndarray) -> np.ndarray:
        """[-1, 1] -> the env's bounds (``action_to_env``), float32."""
        return action_to_env(unit, self.action_low, self.action_high).astype(np.float32)

    def __call__(self, obs) -> np.ndarray:
        single = _size(obs) == self.obs_dim if isinstance(obs, Mapping) else np.ndim(obs) == 1
        out = self.transform_action(self.unit_actions(self.transform_obs(obs)))
        return out[0] if single else out

    def __repr__(self) -> str:
        return (f"Policy(obs_dim={self.obs_dim}, action_dim={self.action_dim}, obs_keys={self.obs_keys}, "
                f"deterministic={self.deterministic}, checkpoint={self.checkpoint!r})")


def _size(obs) -> int:
    import jax  # lazy: JAX, as in read_run

    return sum(int(np.size(v)) for v in jax.tree_util.tree_leaves(obs))


def load_policy(run_dir, checkpoint: str | None = None, deterministic: bool = True) -> Policy:
    """A run's policy as a NumPy callable in the env's own action bounds (see ``Policy``)."""
    agent, cfg, io, name = _load(run_dir, checkpoint)
    return Policy(agent, io, deterministic=deterministic, checkpoint=name, precision=cfg.precision)
