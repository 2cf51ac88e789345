"""``door-binary-local``: Cal-QL-style door data made from the 25 DAPG human demos.

Cal-QL's door-binary-v0 data are the human demos plus rollouts of a behaviour-cloned policy;
both halves are made here with Cal-QL's binary reward and loading rule (``_binary_trajectory``).
The recipe, why the demos are used as recorded rather than replayed, and the measured BC success
rates are in docs/tasks.md ("Generated data").
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm import tqdm

from botorl.data.dataset import Dataset
from botorl.data.loaders import calql_cut, dapg_trajectories, door_success, join_episodes
from botorl.envs.registry import get_task
from botorl.errors import DatasetNotFoundError, DataFormatError

ENV_VAR = "BOTORL_DOOR_DEMOS"
HIDDEN = (256, 256)


# The 25 demos ship inside the package (botorl/data/assets, Apache-2.0, see its README.md).
SHIPPED_DEMOS = Path(__file__).resolve().parents[1] / "assets" / "door_human_demos.npz"


def find_demos(demos_path: str | os.PathLike | None = None) -> Path:
    """The demo file: the argument, else ``$BOTORL_DOOR_DEMOS``, else the copy shipped in the package."""
    where = demos_path or os.environ.get(ENV_VAR)
    if not where:
        if SHIPPED_DEMOS.is_file():
            return SHIPPED_DEMOS
        raise DatasetNotFoundError("door-binary-local needs the 25 DAPG door demonstrations (door_human_demos.npz); "
                                   f"the copy that ships with botorl ({SHIPPED_DEMOS}) is missing from this install. "
                                   f"Reinstall botorl, or set {ENV_VAR}=/path/to/door_human_demos.npz or pass "
                                   "--data.demos PATH.")
    path = Path(where).expanduser()
    if not path.is_file():
        raise DatasetNotFoundError(
            f"door demos file {path} does not exist (from {'--data.demos / demos_path' if demos_path else ENV_VAR}). "
            f"Point it at door_human_demos.npz, or unset it to use the copy shipped with botorl ({SHIPPED_DEMOS})."
        )
    return path


def load_demos(path: Path) -> list[dict[str, np.ndarray]]:
    demos = dapg_trajectories(path, ("observations", "actions"))
    for d in demos:
        obs, act = d["observations"], d["actions"]
        if obs.ndim != 2 or obs.shape[1] != 39 or act.shape != (obs.shape[0], 28):
            raise DataFormatError(f"{path}: expected observations (N, 39) and actions (N, 28); got a demo with "
                                  f"{obs.shape}, {act.shape}.")
    return [{k: d[k].astype(np.float64) for k in ("observations", "actions")} for d in demos]


def _binary_trajectory(obs, act, next_obs, drop_unsuccessful: bool) -> dict | None:
    """Reward success - 1 (door opened), cut by Cal-QL's rule (``calql_cut``)."""
    success = door_success(next_obs)
    return calql_cut({"observations": obs, "actions": act, "next_observations": next_obs,
                      "rewards": success.astype(np.float32) - 1.0}, success, drop_unsuccessful)


# ---------------------------------------------------------------------------- behaviour cloning
def train_bc(demos, steps: int, seed: int, progress: bool = True) -> list[tuple[np.ndarray, np.ndarray]]:
    """Fit a tanh MLP to the demos (MSE); returns [(W, b), ...] as numpy arrays."""
    x = jnp.asarray(np.concatenate([d["observations"] for d in demos]), dtype=jnp.float32)
    y = jnp.asarray(np.clip(np.concatenate([d["actions"] for d in demos]), -1, 1), dtype=jnp.float32)
    sizes = (x.shape[1], *HIDDEN, y.shape[1])
    keys = jax.random.split(jax.random.PRNGKey(seed), len(sizes))
    params = [(jax.random.normal(k, (i, o)) * jnp.sqrt(1.0 / i), jnp.zeros(o))
              for k, i, o in zip(keys[1:], sizes[:-1], sizes[1:])]
    opt = optax.adam(1e-3)

    def forward(p, obs):
        h = obs
        for w, b in p[:-1]:
            h = jax.nn.relu(h @ w + b)
        return jnp.tanh(h @ p[-1][0] + p[-1][1])

    def loss_fn(p, xb, yb):
        return jnp.mean((forward(p, xb) - yb) ** 2)

    @partial(jax.jit, static_argnums=3)
    def run(p, state, key, n):
        def body(carry, k):
            p, state = carry
            idx = jax.random.randint(k, (256,), 0, x.shape[0])
            loss, g = jax.value_and_grad(loss_fn)(p, x[idx], y[idx])
            upd, state = opt.update(g, state, p)
            return (optax.apply_updates(p, upd), state), loss

        (p, state), losses = jax.lax.scan(body, (p, state), jax.random.split(key, n))
        return p, state, losses[-1]

    state = opt.init(params)
    key = keys[0]
    bar = tqdm(total=steps, desc="door BC", unit="step", disable=not progress)
    for done in range(0, steps, 500):
        n = min(500, steps - done)
        key, sub = jax.random.split(key)
        params, state, loss = run(params, state, sub, n)  # compiled once per chunk length
        bar.update(n)
        if progress:
            bar.set_postfix(loss=float(loss))
    bar.close()
    return [(np.asarray(w, np.float64), np.asarray(b, np.float64)) for w, b in params]


def bc_policy(params):
    def act(obs: np.ndarray) -> np.ndarray:
        h = obs
        for w, b in params[:-1]:
            h = np.maximum(h @ w + b, 0.0)
        return np.tanh(h @ params[-1][0] + params[-1][1])

    return act


def rollout(policy, steps: int, seed: int, noise_std: float, progress: bool = True):
    """Roll ``policy`` out in the door-binary env until ``steps`` env steps are collected
    (whole episodes). Returns (one trajectory per episode, number of successes)."""
    env = get_task("door-binary-local").make_env(seed)
    rng = np.random.default_rng(seed)
    trajs, n_succ, collected = [], 0, 0
    bar = tqdm(total=steps, desc="door BC rollouts", unit="step", disable=not progress)
    while collected < steps:
        obs, _ = env.reset()
        o, a, no = [], [], []
        while True:
            action = np.clip(policy(obs.astype(np.float64)) + noise_std * rng.standard_normal(28), -1, 1)
            nobs, _, term, trunc, info = env.step(action)
            o.append(obs), a.append(action), no.append(nobs)
            obs = nobs
            if term or trunc:
                break
        n_succ += int(info["success"] > 0)
        collected += len(o)
        bar.update(len(o))
        trajs.append((np.array(o, np.float64), np.array(a, np.float64), np.array(no, np.float64)))
    bar.close()
    env.close()
    return trajs, n_succ


def generate(steps: int, seed: int, progress: bool = True, demos_path: str | os.PathLike | None = None,
             bc_steps: int = 3000, noise_std: float = 0.1, drop_unsuccessful: bool = False) -> Dataset:
    if steps < 0:
        raise ValueError("steps must be >= 0")
    path = find_demos(demos_path)
    demos = load_demos(path)

    parts = [t for d in demos if (t := _binary_trajectory(d["observations"][:-1], d["actions"][:-1],
                                                          d["observations"][1:], drop_unsuccessful))]
    n_demo_kept = len(parts)

    bc_rate, trajs = float("nan"), []
    if steps > 0:
        params = train_bc(demos, bc_steps, seed, progress)
        trajs, n_succ = rollout(bc_policy(params), steps, seed, noise_std, progress)
        bc_rate = n_succ / max(len(trajs), 1)
        parts += [t for o, a, no in trajs if (t := _binary_trajectory(o, a, no, drop_unsuccessful))]
    if not parts:
        raise DataFormatError(f"{path}: no demonstration and no rollout succeeded; nothing to keep.")
    ds = join_episodes(parts, {
        "source": f"generated: door-binary-local (steps={steps}, seed={seed}, demos={path})",
        "task": "door-binary-local", "generator": "botorl.data.generators.door", "steps": int(steps),
        "seed": int(seed), "demos_kept": n_demo_kept, "demos_total": len(demos), "bc_steps": int(bc_steps),
        "noise_std": float(noise_std), "drop_unsuccessful": bool(drop_unsuccessful),
        "bc_episodes": len(trajs), "bc_success_rate": bc_rate, "bc_trajectories_kept": len(parts) - n_demo_kept})
    ds.infos["is_demo"] = np.zeros(len(ds), dtype=np.float32)
    ds.infos["is_demo"][: sum(len(p["rewards"]) for p in parts[:n_demo_kept])] = 1.0
    return ds
