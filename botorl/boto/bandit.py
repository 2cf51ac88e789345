"""``botorl bandit``: the paper's bandit Figures 2 and 3 and ``bandit.json`` (see
docs/results/bandit.md). Every critic is small, with gamma = 0, from a fresh initialisation (the
BOTO minimiser does not depend on it); the BOTO critics of a figure, one per alpha, are vmapped
in one program and share their initialisation and noise draws, so differences between alphas
are not seed noise. Figure 3's noise is NOT clipped: ``theory.namdp_exact`` is the unclipped
Gaussian's Q* (clipping would put point masses on the box edges), and its cosine-decayed
learning rate lets the regression settle on its minimiser instead of jittering around it.
"Away from the data" (``mean_ood_q``): farther than sigma / 2 from every dataset action.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from functools import partial
from typing import Annotated
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import tyro
from scipy.stats import gaussian_kde
from tqdm.auto import tqdm

from botorl.agents.common import TrainState, jit_agent_q_mean
from botorl.agents.cql import CQLAgent, CQLConfig
from botorl.agents.iql import IQLAgent, IQLConfig
from botorl.agents.population import q_mean
from botorl.agents.sac import SACAgent, SACConfig
from botorl.batch import TRANSITION_KEYS
from botorl.boto.config import BOTOConfig
from botorl.boto.objective import ObjectiveSettings, boto_update_many_fn
from botorl.boto.theory import gaussian_log_density, namdp_exact
from botorl.data.generators.bandit import generate_1d, generate_pinwheel
from botorl.errors import Range, check_ranges
from botorl.io import atomic_save_figure, atomic_write_json, pyplot
from botorl.jaxsetup import setup_jax

FIG3_ALPHAS = (-1.0, -0.5, 0.0, 0.5, 1.0)
FIG3_SIGMA = 0.25
FIG2_ALPHAS = (-1.0, 0.0, 1.0)
OOD_DISTANCE = FIG3_SIGMA / 2


@dataclass
class BanditConfig:
    """Options of ``botorl bandit``."""

    out: str = "runs/bandit"
    """output folder (PNGs and bandit.json)"""
    seed: Annotated[int, Range(0, 2**31 - 1)] = 0
    fig3_transitions: Annotated[int, Range(2, 10**7)] = 1000
    """rows of the bandit-1d dataset"""
    fig3_steps: Annotated[int, Range(1, 10**7)] = 3000
    """BOTO critic steps per alpha (Figure 3)"""
    fig3_batch_size: Annotated[int, Range(1, 1 << 20)] = 256
    fig3_lr: Annotated[float, Range(0, 10)] = 3e-3
    grid_points: Annotated[int, Range(2, 100_000)] = 401
    fig2_transitions: Annotated[int, Range(2, 10**7)] = 2000
    """rows of the bandit-pinwheel dataset"""
    fig2_boto_steps: Annotated[int, Range(1, 10**7)] = 2000
    fig2_offline_steps: Annotated[int, Range(1, 10**7)] = 400
    """CQL / Cal-QL / IQL update steps (Figure 2)"""
    fig2_log_sigma: float = -20.0
    skip_fig2: bool = False
    progress: bool = True


# The small networks of every bandit critic (gamma = 0: every transition is terminal).
SMALL_SAC = dict(actor_hidden_dims=(16,), critic_hidden_dims=(64, 64), actor_layer_norm=False, critic_layer_norm=False,
                 num_critics=2, num_min_critics=2, subsample_replace=False, discount=0.0)


def _in_chunks(state, step, steps: int, chunk: int, desc: str, progress: bool):
    """``state, loss = step(state, k)`` on chunks of at most ``chunk`` of ``steps`` steps, with a progress bar."""
    with tqdm(total=steps, desc=desc, unit="step", dynamic_ncols=True, disable=not progress) as bar:
        for done in range(0, steps, chunk):
            k = min(chunk, steps - done)
            state, loss = step(state, k)
            bar.update(k)
            if progress and loss is not None:
                bar.set_postfix(loss=f"{float(loss):.3g}")
    return state


def train_boto_bandit(dataset, alphas, boto_config, *, steps: int, batch_size: int, seed: int, lr: float,
                      progress: bool, desc: str):
    """One fresh small critic per alpha, vmapped, Adam on a cosine-decayed ``lr``; returns
    ``q_fn(actions (M, A)) -> (len(alphas), M)``, the ensemble-mean Q at a constant observation."""
    agent = SACAgent.create(SACConfig(**SMALL_SAC), dataset.obs_dim, dataset.action_dim, seed=seed)
    tx = optax.adam(optax.cosine_decay_schedule(lr, steps))
    agent = agent.replace(critic=TrainState.create(apply_fn=agent.critic.apply_fn, params=agent.critic.params, tx=tx))
    settings = ObjectiveSettings.resolve(boto_config, agent)
    agents = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (len(alphas),) + jnp.shape(x)), agent)
    alpha_arr = jnp.asarray(alphas, jnp.float32)

    @jax.jit
    def train_chunk(ags, batches):
        return jax.vmap(partial(boto_update_many_fn, settings=settings), in_axes=(0, None, 0))(ags, batches, alpha_arr)

    rng = np.random.default_rng(seed)

    def step(ags, k):
        batches = dataset.sample(rng, batch_size, num_batches=k)
        ags, info = train_chunk(ags, {key: jnp.asarray(batches[key], jnp.float32) for key in TRANSITION_KEYS})
        return ags, info["critic_loss"].mean()

    agents = _in_chunks(agents, step, steps, 500, desc, progress)
    return lambda actions: np.asarray(q_mean(agents, np.zeros((len(actions), dataset.obs_dim), np.float32), actions))


# ----------------------------------------------------------------------------- Figure 3


def run_fig3(cfg: BanditConfig) -> dict:
    """Train the Figure 3 critics and compare them with Q* and the bounds: the bandit.json part."""
    ds = generate_1d(cfg.fig3_transitions, cfg.seed, progress=False)
    boto_cfg = BOTOConfig(noise="gaussian", sigma=FIG3_SIGMA, clip=False, discount=0.0, backup_entropy=False)
    t0 = time.perf_counter()
    q_fn = train_boto_bandit(
        ds, FIG3_ALPHAS, boto_cfg, steps=cfg.fig3_steps, batch_size=cfg.fig3_batch_size, seed=cfg.seed,
        lr=cfg.fig3_lr, progress=cfg.progress, desc="Figure 3 (bandit-1d, 5 alphas)",
    )
    train_s = time.perf_counter() - t0
    grid = np.linspace(-1.0, 1.0, cfg.grid_points)[:, None]
    q_learned = q_fn(grid)
    acts, rews = ds.actions.astype(np.float64), ds.rewards.astype(np.float64)
    ood = np.sqrt(((grid[:, None, :] - acts[None, :, :]) ** 2).sum(-1)).min(axis=1) > OOD_DISTANCE
    per_alpha = []
    for i, alpha in enumerate(FIG3_ALPHAS):
        ex = namdp_exact(grid, acts, rews, alpha, gaussian_log_density(FIG3_SIGMA))
        q = q_learned[i].astype(np.float64)
        violation = max(0.0, float(np.max(ex.lower - q)), float(np.max(q - ex.upper)))
        per_alpha.append({
            "alpha": alpha,
            "sigma": FIG3_SIGMA,
            "actions": acts[:, 0].tolist(),
            "rewards": rews.tolist(),
            "grid": grid[:, 0].tolist(),
            "q_learned": q.tolist(),
            "q_exact": ex.q.tolist(),
            "lower": ex.lower.tolist(),
            "upper": ex.upper.tolist(),
            "max_abs_error_vs_exact": float(np.max(np.abs(q - ex.q))),
            "max_bound_violation": violation,
            "mean_ood_q": float(q[ood].mean()),
            "mean_ood_q_exact": float(ex.q[ood].mean()),
        })
    return {
        "task": "bandit-1d",
        "noise": {"kind": "gaussian", "sigma": FIG3_SIGMA, "clip": False},
        "steps": cfg.fig3_steps,
        "batch_size": cfg.fig3_batch_size,
        "train_seconds": train_s,
        "actions": acts[:, 0].tolist(),
        "rewards": rews.tolist(),
        "grid": grid[:, 0].tolist(),
        "ood_definition": f"grid points farther than {OOD_DISTANCE} (= sigma/2) from every dataset action",
        "ood_points": int(ood.sum()),
        "alphas": per_alpha,
    }


def plot_fig3(res: dict, path: Path) -> None:
    plt = pyplot()

    grid = np.asarray(res["grid"])
    acts, rews = np.asarray(res["actions"]), np.asarray(res["rewards"])
    ua, idx = np.unique(acts, return_index=True)
    ur = rews[idx]
    n = len(res["alphas"])
    cmap = plt.get_cmap("coolwarm")
    colors = [cmap(i / max(n - 1, 1)) for i in range(n)]
    fig = plt.figure(figsize=(16, 8.5))
    gs = fig.add_gridspec(2, n, height_ratios=[1.3, 1.0], hspace=0.35, wspace=0.08)
    ax = fig.add_subplot(gs[0, :])
    for c, r in zip(colors, res["alphas"]):
        ax.plot(grid, r["q_learned"], color=c, lw=2.2, label=f"learned, alpha={r['alpha']:+.1f}")
        ax.plot(grid, r["q_exact"], color="k", lw=0.8, ls=":")
    ax.plot([], [], color="k", lw=0.8, ls=":", label="exact Q* (alpha-NAMDP)")
    ax.scatter(ua, ur, color="red", s=22, zorder=5, label="dataset (a, r)")
    ax.set(xlim=(-1, 1), xlabel="action a", ylabel="Q(a)",
           title=f"bandit-1d: BOTO critics, q = N(a, {res['noise']['sigma']}^2), {res['steps']} steps")
    ax.legend(ncol=4, fontsize=8, loc="lower center")
    ax.grid(alpha=0.3)
    lo = min(min(r["lower"]) for r in res["alphas"]) - 0.05
    hi = max(max(r["upper"]) for r in res["alphas"]) + 0.05
    for j, (c, r) in enumerate(zip(colors, res["alphas"])):
        a = fig.add_subplot(gs[1, j])
        a.fill_between(grid, r["lower"], r["upper"], color=c, alpha=0.12)
        a.plot(grid, r["lower"], color=c, ls="--", lw=1.2, label="Theorem 2 bounds")
        a.plot(grid, r["upper"], color=c, ls="--", lw=1.2)
        a.plot(grid, r["q_exact"], color="k", lw=1.0, ls=":", label="exact Q*")
        a.plot(grid, r["q_learned"], color=c, lw=2.0, label="learned")
        a.scatter(ua, ur, color="red", s=10, zorder=5)
        a.set(ylim=(lo, hi), xlim=(-1, 1), xlabel="action a")
        a.set_xticks([-1, -0.5, 0, 0.5, 1], ["-1", "", "0", "", "1"])
        a.set_title(f"alpha = {r['alpha']:+.1f}  (max |err| {r['max_abs_error_vs_exact']:.3f})", fontsize=9)
        a.grid(alpha=0.3)
        if j:
            a.set_yticklabels([])
        else:
            a.legend(fontsize=7, loc="lower left")
    atomic_save_figure(fig, path, dpi=110, bbox_inches="tight")


# ----------------------------------------------------------------------------- Figure 2


def _offline_agents(ds, cfg: BanditConfig):
    """CQL, Cal-QL and IQL critics (small nets, gamma = 0) trained on the pinwheel data."""
    # CQL weight 5 with a fixed weight (no Lagrange): the one-step problem has no bootstrapping, so
    # the penalty is what shapes Q off the data (Cal-QL's kitchen setting).
    # 5 (not 10) penalty samples of each kind keep `botorl bandit` within its time budget.
    cql_common = dict(SMALL_SAC, max_target_backup=False, cql_lagrange=False, cql_weight=5.0, cql_n_actions=5)
    iql = IQLConfig(actor_hidden_dims=(16,), critic_hidden_dims=(64, 64), value_hidden_dims=(64, 64), discount=0.0,
                    expectile=0.9, awr_beta=10.0)
    configs = {"CQL": (CQLAgent, CQLConfig(**cql_common, calql=False)),
               "Cal-QL": (CQLAgent, CQLConfig(**cql_common, calql=True)), "IQL": (IQLAgent, iql)}
    out = {}
    for name, (agent_cls, config) in configs.items():
        rng = np.random.default_rng(cfg.seed + 1)

        def step(agent, k):
            agent, _ = agent.update_many({key: jnp.asarray(v) for key, v in ds.sample(rng, 256, num_batches=k).items()})
            return agent, None

        agent = agent_cls.create(config, ds.obs_dim, ds.action_dim, cfg.seed)
        out[name] = _in_chunks(agent, step, cfg.fig2_offline_steps, 250, f"Figure 2: {name}", cfg.progress)
    return out


def run_fig2(cfg: BanditConfig) -> dict:
    ds = generate_pinwheel(cfg.fig2_transitions, cfg.seed, progress=False).with_mc_returns(0.0)
    boto_cfg = BOTOConfig(noise="hybrid", log_sigma=cfg.fig2_log_sigma, clip=True, discount=0.0, backup_entropy=False)
    t0 = time.perf_counter()
    q_boto = train_boto_bandit(
        ds, FIG2_ALPHAS, boto_cfg, steps=cfg.fig2_boto_steps, batch_size=256, seed=cfg.seed, lr=1e-3,
        progress=cfg.progress, desc="Figure 2: BOTO (3 alphas)",
    )
    offline = _offline_agents(ds, cfg)
    train_s = time.perf_counter() - t0
    side = 101
    xs = np.linspace(-1.0, 1.0, side)
    grid = np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2).astype(np.float32)
    uniform = np.random.default_rng(cfg.seed + 2).uniform(-1, 1, (4000, 2)).astype(np.float32)
    data_acts = ds.actions.astype(np.float32)
    q_grid_b, q_uni_b, q_data_b = q_boto(grid), q_boto(uniform), q_boto(data_acts)
    methods = {f"BOTO alpha={a:+.0f}": (q_grid_b[i], q_uni_b[i], q_data_b[i]) for i, a in enumerate(FIG2_ALPHAS)}

    def q_of(agent, acts):
        return np.asarray(jit_agent_q_mean(agent, jnp.zeros((len(acts), ds.obs_dim), jnp.float32), jnp.asarray(acts)))

    for name, agent in offline.items():
        methods[name] = (q_of(agent, grid), q_of(agent, uniform), q_of(agent, data_acts))
    r_lo, r_hi = float(ds.rewards.min()), float(ds.rewards.max())
    summary = {name: {
        "mean_q_data": float(qd.mean()),
        "mean_q_uniform": float(qu.mean()),
        "min_q_uniform": float(qu.min()),
        "max_q_uniform": float(qu.max()),
        "share_uniform_outside_reward_range": float(np.mean((qu < r_lo) | (qu > r_hi))),
    } for name, (_, qu, qd) in methods.items()}
    return {
        "task": "bandit-pinwheel",
        "noise": {"kind": "hybrid", "log_sigma": cfg.fig2_log_sigma, "weight_fn": "linear", "clip": True},
        "boto_steps": cfg.fig2_boto_steps,
        "offline_steps": cfg.fig2_offline_steps,
        "train_seconds": train_s,
        "reward_range": [r_lo, r_hi],
        "methods": summary,
        "_plot": {"side": side, "xs": xs, "methods": methods, "data": data_acts, "rewards": ds.rewards},
    }


def plot_fig2(res: dict, path: Path) -> None:
    plt = pyplot()

    p = res["_plot"]
    names = list(p["methods"])
    side, data, rew = p["side"], p["data"], p["rewards"]
    r_lo, r_hi = res["reward_range"]
    # One colour scale for all maps, [r_lo - 0.5, r_hi + 0.5]: values beyond saturate (the
    # colour bar says so); the data dots use the same scale, so Q at a dot can be compared with
    # the dot's reward.
    vlo, vhi = r_lo - 0.5, r_hi + 0.5
    fig, axes = plt.subplots(2, len(names), figsize=(3.2 * len(names), 6.6), gridspec_kw={"height_ratios": [1.15, 1]})
    show = np.random.default_rng(0).choice(len(data), size=min(250, len(data)), replace=False)
    for j, name in enumerate(names):
        qg, qu, qd = p["methods"][name]
        ax = axes[0, j]
        im = ax.imshow(qg.reshape(side, side), origin="lower", extent=(-1, 1, -1, 1), cmap="viridis",
                       vmin=vlo, vmax=vhi, interpolation="bilinear")
        ax.scatter(data[show, 0], data[show, 1], c=rew[show], cmap="viridis", vmin=vlo, vmax=vhi, s=9,
                   edgecolors="k", linewidths=0.4)
        ax.set_title(name, fontsize=10)
        ax.set(xticks=[-1, 0, 1], yticks=[-1, 0, 1] if j == 0 else [])
        k = axes[1, j]
        lo, hi = min(qu.min(), qd.min()), max(qu.max(), qd.max())
        span = max(hi - lo, 1e-3)
        xs = np.linspace(lo - 0.1 * span, hi + 0.1 * span, 300)
        for vals, lab, col in ((qu, "uniform actions", "tab:blue"), (qd, "dataset actions", "tab:red")):
            if np.std(vals) > 1e-6:
                k.fill_between(xs, gaussian_kde(vals)(xs), color=col, alpha=0.35, label=lab)
        k.axvspan(r_lo, r_hi, color="grey", alpha=0.12, label="reward range")
        k.set(xlabel="Q value", yticks=[])
        if j == 0:
            k.legend(fontsize=7)
    fig.colorbar(im, ax=axes[0, :].tolist(), shrink=0.85, label="Q(a) (dots: reward r)", extend="both")
    fig.suptitle("bandit-pinwheel: Q over the action square (top; dots = data, coloured by reward) "
                 "and KDE of Q values (bottom)", fontsize=11)
    atomic_save_figure(fig, path, dpi=110, bbox_inches="tight")


# ----------------------------------------------------------------------------- I/O and CLI


def main(argv: list[str]) -> int:
    cfg = tyro.cli(BanditConfig, args=argv, description="Reproduce the paper's bandit figures 2 and 3.")
    check_ranges(cfg)
    setup_jax()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    fig3 = run_fig3(cfg)
    plot_fig3(fig3, out / "bandit_fig3.png")
    result = {"config": asdict(cfg), "fig3": fig3}
    if not cfg.skip_fig2:
        fig2 = run_fig2(cfg)
        plot_fig2(fig2, out / "bandit_fig2.png")
        fig2.pop("_plot")
        result["fig2"] = fig2
    result["seconds"] = time.perf_counter() - t0
    atomic_write_json(out / "bandit.json", result, indent=1)
    print(f"wrote {out / 'bandit_fig3.png'}" + ("" if cfg.skip_fig2 else f", {out / 'bandit_fig2.png'}") +
          f", {out / 'bandit.json'} in {result['seconds']:.0f} s")
    for r in fig3["alphas"]:
        print(f"  alpha={r['alpha']:+.1f}: max|Q-Q*|={r['max_abs_error_vs_exact']:.4f}  "
              f"bound violation={r['max_bound_violation']:.4f}  mean OOD Q={r['mean_ood_q']:.4f} "
              f"(exact {r['mean_ood_q_exact']:.4f})")
    return 0
