"""The BOTO phase (stage 2b): train the critic with the BOTO objective on D_BOTO.

``boto_updates`` trains a population (agents/population.py), member i with its own alpha on
D_offline u D_warmup_i, all members in one jitted call: the pipeline's stage runs it in its loop,
``train_boto`` in its own, and ``run_boto`` is a population of one. The actor (and SAC temperature) stay frozen unless
``config.train_actor``; an IQL agent comes back changed only in its critics and rng, for
``SACAgent.from_pretrained`` to carry into fine-tuning (converting it first would put a fresh
SAC temperature into the target; set ``backup_entropy=False`` then).

Resumable: the batches of call c come from ``np.random.default_rng([seed, c])`` and the noise
from the agent's rng, so a phase resumed at ``start_step`` (a multiple of ``steps_per_call``)
sees the same data stream as an uninterrupted one.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from botorl.agents.population import member_metrics, member_of, stack
from botorl.batch import TRANSITION_KEYS
from botorl.boto.config import BOTOConfig
from botorl.boto.objective import ObjectiveSettings, check_alpha, population_update_many
from botorl.errors import ConfigError, TrainingDivergedError

__all__ = ["BOTOConfig", "run_boto", "train_boto", "boto_batches", "boto_updates"]


def boto_batches(d_offline, d_warmups: Sequence, rngs: Sequence[np.random.Generator], batch_size: int,
                 num_batches: int) -> dict:
    """Batches (N, K, B, ...) from D_BOTO = D_offline u D_warmup_i per member i, as
    ``d_offline.concat(d_warmups[i]).sample`` draws them, without copying the offline data."""
    out = []
    n_off = 0 if d_offline is None else len(d_offline)
    for rng, d_w in zip(rngs, d_warmups):
        n_w = 0 if d_w is None else len(d_w)
        if n_off + n_w == 0:
            raise ConfigError("BOTO got no data: D_offline and D_warmup are both empty; pass the offline dataset.")
        idx = rng.integers(0, n_off + n_w, size=(num_batches, batch_size))
        if n_w == 0:
            b = d_offline.batch_at(idx)
        elif n_off == 0:
            b = d_w.batch_at(idx)
        else:
            off = idx < n_off
            b_off = d_offline.batch_at(np.where(off, idx, 0))
            b_w = d_w.batch_at(np.where(off, 0, idx - n_off))
            b = {k: np.where(off.reshape(off.shape + (1,) * (b_off[k].ndim - 2)), b_off[k], b_w[k]) for k in TRANSITION_KEYS}
        out.append({k: b[k] for k in TRANSITION_KEYS})
    return {k: np.stack([o[k] for o in out]) for k in TRANSITION_KEYS}


def boto_updates(agents, d_offline, d_warmups: Sequence, config: BOTOConfig, alphas: Sequence[float],
                 seeds: Sequence[int]) -> Callable:
    """``update(agents, step, k)`` -> (agents, stacked metrics): k BOTO steps of every member in
    one jitted call, member i with ``alphas[i]`` on D_offline u ``d_warmups[i]`` (None: none),
    the batches of the call at ``step`` from ``default_rng([seeds[i], step // steps_per_call])``;
    ``alphas`` as checked where they entered (the run's config: configs.resolve.validate; ``train_boto``)."""
    settings = ObjectiveSettings.resolve(config, member_of(agents, 0))
    alphas = np.asarray(alphas, np.float32)

    def update(agents, step: int, k: int):
        rngs = [np.random.default_rng([s, step // config.steps_per_call]) for s in seeds]
        return population_update_many(agents, boto_batches(d_offline, d_warmups, rngs, config.batch_size, k),
                                      alphas, settings)
    return update


def train_boto(agents, d_offline, d_warmups: Sequence, config: BOTOConfig, alphas: Sequence[float],
               seeds: Sequence[int], *, start_step: int = 0, end_step: int | None = None,
               on_call: Callable[[int, int, Any, list], None] | None = None, progress: bool = True):
    """BOTO for every member of ``agents`` (stacked), member i with ``alphas[i]`` on
    D_offline u ``d_warmups[i]`` (None: none), its batches from ``seeds[i]``; returns the agents.

    ``on_call(prev_step, step, agents, metrics)`` runs after every call with the call's new
    agents and one dict of floats per member (the means over the call's steps of
    ``boto_update_many``'s metrics); it may raise to stop (the agents before the call are then
    the last good ones)."""
    check_alpha(alphas[0] if len(alphas) == 1 else alphas)  # once, not at every call's update
    update = boto_updates(agents, d_offline, d_warmups, config, alphas, seeds)
    end = config.boto_steps if end_step is None else end_step
    step = start_step
    label = f"BOTO alpha={alphas[0]:+.2f}" if len(alphas) == 1 else f"BOTO x {len(alphas)} members"
    with tqdm(total=end, initial=start_step, desc=label, unit="step", dynamic_ncols=True, disable=not progress,
              mininterval=1.0, smoothing=0.05) as bar:
        while step < end:
            k = min(config.steps_per_call, end - step)
            new, metrics = update(agents, step, k)
            ms = member_metrics(metrics)
            if on_call is not None:
                on_call(step, step + k, new, ms)
            agents, step = new, step + k
            bar.update(k)
            bar.set_postfix(loss=f"{ms[0]['critic_loss']:.3g}", q_data=f"{ms[0]['q_data']:.3g}",
                            q_unif=f"{ms[0]['q_uniform']:.3g}")
    return agents


def run_boto(agent, d_offline, d_warmup, config: BOTOConfig, *, alpha: float, seed: int = 0, start_step: int = 0,
             num_steps: int | None = None, callback: Callable[[int, Any, dict], None] | None = None,
             progress: bool = True) -> tuple[Any, list[dict]]:
    """Train one agent's critic with BOTO at bias controller ``alpha`` in [-1, 1] (> 0 lowers Q
    far from the data, < 0 raises it; 1 is Oh & Lee's NAMDP); returns ``(agent, history)``.

    ``history`` has one dict per call: ``step``, ``seconds`` and the metrics of
    ``boto_update_many``; ``callback(step, agent, metrics)`` runs after every call. A NaN/inf
    loss raises TrainingDivergedError (the last callback's agent is the last good one).
    """
    config.validate()
    if start_step < 0 or start_step > config.boto_steps:
        raise ConfigError(f"run_boto start_step={start_step} must be in [0, boto_steps={config.boto_steps}].")
    end = config.boto_steps if num_steps is None else min(config.boto_steps, start_step + int(num_steps))
    history: list[dict] = []
    t0 = time.perf_counter()

    def on_call(prev: int, step: int, agents, ms: list[dict]) -> None:
        if not math.isfinite(ms[0]["critic_loss"]):
            raise TrainingDivergedError(
                f"BOTO diverged between steps {prev} and {step} (critic loss {ms[0]['critic_loss']}, "
                f"alpha={alpha}). Check the reward scale of the data, or lower the critic learning "
                "rate; the last good agent is the one given to the last callback."
            )
        history.append({"step": step, "seconds": time.perf_counter() - t0, **ms[0]})
        if callback is not None:
            callback(step, member_of(agents, 0), history[-1])

    agents = train_boto(stack([agent]), d_offline, [d_warmup], config, [alpha], [seed],
                        start_step=start_step, end_step=end, on_call=on_call, progress=progress)
    return member_of(agents, 0), history
