"""The BOTO phase (stage 2b): train the critic with the BOTO objective on D_BOTO.

``run_boto(agent, d_offline, d_warmup, config)`` trains for ``config.boto_steps`` critic steps
on D_BOTO = D_offline u D_warmup, each batch drawn uniformly (with replacement) from the union
of the rows, ``config.steps_per_call`` steps per jitted ``lax.scan`` call. The actor (and SAC
temperature) stay frozen unless ``config.train_actor``.

Agents: any SAC-family agent (SAC, CQL, Cal-QL) and IQL. For IQL, which has an AWR
tanh-Gaussian actor and no SAC temperature, the target's next action a~ comes from IQL's own
actor and tau = 0 (no entropy term); the IQL fields (value network included) are returned
unchanged except the critic, its target and the rng, so ``SACAgent.from_pretrained`` then
takes the BOTO-trained critic into online fine-tuning. (Converting first with
``SACAgent.from_pretrained`` would instead put a fresh temperature -- ``init_temp``, or the
stationary rule's value when probe observations are given (agents/temperature.py) -- into
the target; set ``backup_entropy=False`` if you do that.)

Resumable: ``start_step`` says how many steps were done before (e.g. restored from a
checkpoint) and ``num_steps`` how many to do now (default: up to ``boto_steps``). The batches
of call c are drawn from ``np.random.default_rng([seed, c])`` and the noise from the agent's
own rng, so a resumed phase sees the same data stream as an uninterrupted one when it is cut
at a multiple of ``steps_per_call``.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable

import numpy as np

from botorl.boto.config import BOTOConfig
from botorl.boto.objective import ObjectiveSettings, boto_update_many, check_alpha
from botorl.errors import ConfigError, TrainingDivergedError

__all__ = ["BOTOConfig", "run_boto", "boto_dataset"]

Callback = Callable[[int, Any, dict], None]


def boto_dataset(d_offline, d_warmup=None):
    """D_BOTO = D_offline u D_warmup as one Dataset (rows of both; uniform sampling over them)."""
    if d_offline is None or len(d_offline) == 0:
        if d_warmup is None or len(d_warmup) == 0:
            raise ConfigError("run_boto got no data: D_offline and D_warmup are both empty; pass the offline dataset.")
        return d_warmup
    if d_warmup is None or len(d_warmup) == 0:
        return d_offline
    return d_offline.concat(d_warmup)


def run_boto(
    agent,
    d_offline,
    d_warmup,
    config: BOTOConfig,
    *,
    start_step: int = 0,
    num_steps: int | None = None,
    callback: Callback | None = None,
    progress: bool = True,
) -> tuple[Any, list[dict]]:
    """Train ``agent``'s critic with BOTO; returns ``(agent, history)``.

    ``history`` has one dict per call: ``step`` (steps done after the call), ``seconds`` (wall
    time since this invocation started) and the metrics of ``boto_update_many`` (means over the
    call's steps: critic_loss, q_perturbed, target, penalty, sq_dist, uniform_share; at its
    end: q_data, q_uniform). ``callback(step, agent, metrics)`` runs after every call (logging,
    checkpointing). A NaN/inf loss raises TrainingDivergedError (the agent passed to the last
    callback is the last good one).
    """
    config.validate()
    check_alpha(config.alpha)
    if start_step < 0 or start_step > config.boto_steps:
        raise ConfigError(f"run_boto start_step={start_step} must be in [0, boto_steps={config.boto_steps}].")
    end = config.boto_steps if num_steps is None else min(config.boto_steps, start_step + int(num_steps))
    data = boto_dataset(d_offline, d_warmup)
    settings = ObjectiveSettings.resolve(config, agent)
    history: list[dict] = []
    t0 = time.perf_counter()
    step = start_step
    bar = None
    if progress and end > start_step:
        from tqdm.auto import tqdm

        bar = tqdm(total=end - start_step, desc=f"BOTO alpha={config.alpha:+.2f}", unit="step", dynamic_ncols=True)
    try:
        while step < end:
            k = min(config.steps_per_call, end - step)
            call_index = step // config.steps_per_call
            rng = np.random.default_rng([config.seed, call_index])
            batches = data.sample(rng, config.batch_size, num_batches=k)
            new_agent, metrics = boto_update_many(agent, batches, config.alpha, settings)
            metrics = {name: float(v) for name, v in metrics.items()}
            if not math.isfinite(metrics["critic_loss"]):
                raise TrainingDivergedError(
                    f"BOTO diverged between steps {step} and {step + k} (critic loss {metrics['critic_loss']}, "
                    f"alpha={config.alpha}). Check the reward scale of the data, or lower the critic learning "
                    "rate; the last good agent is the one given to the last callback."
                )
            agent = new_agent
            step += k
            record = {"step": step, "seconds": time.perf_counter() - t0, **metrics}
            history.append(record)
            if bar is not None:
                bar.update(k)
                bar.set_postfix(loss=f"{metrics['critic_loss']:.3g}", q_data=f"{metrics['q_data']:.3g}",
                                q_unif=f"{metrics['q_uniform']:.3g}")
            if callback is not None:
                callback(step, agent, record)
    finally:
        if bar is not None:
            bar.close()
    return agent, history
