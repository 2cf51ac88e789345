"""The run configuration: typed nested dataclasses; tyro makes the CLI from them.

Every field can be set as ``--<dotted.path> VALUE`` (``--online.steps 2000``,
``--network.critic_hidden_dims 64 64``) over the preset of the task and profile (presets.py, build.py).

One fact, one field: the network sizes (``network.*``), the UTD ratio (``online.utd``) and the
CQL/Cal-QL switch (``pretrain``) are set here only; ``resolve`` derives the agent configs' copies
(``configs.resolve.DERIVED``), the command line refuses their flags, and a config read back whose
copy differs is refused (``check_derived``); the UTD has no copy, as the online update's batch
carries it. A run's ``seed`` and ``alpha`` are top-level fields (a population's: ``seeds`` and
``alphas``, configs/members.py).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from botorl.agents.cql import CQLConfig
from botorl.agents.iql import IQLConfig
from botorl.agents.sac import SACConfig
from botorl.boto.config import BOTOConfig
from botorl.configs.methods import MethodName, PretrainName


@dataclass
class DataConfig:
    """Where the offline data come from."""

    path: str | None = None
    """Dataset for the task's loader: a Minari folder or id, the Cal-QL folder or
    ``expert.npy,bc.npy`` (adroit binary); None: the task's own (generated tasks: botorl's cache)."""
    steps: int | None = None
    """Generated tasks only: dataset size in env steps (None: the generator's own size)."""
    seed: int = 0
    """Generated tasks only: the dataset's seed (independent of the run seed, like a D4RL file)."""
    demos: str | None = None
    """door-binary-local: the DAPG demos (door_human_demos.npz); None: $BOTORL_DOOR_DEMOS, else the copy
    shipped in botorl (botorl/data/assets)."""
    action_tolerance: float = 1e-3
    """Largest |action| - 1 accepted in the data before the clip to the box (else an error)."""


@dataclass
class EnvConfig:
    """A task of your own (docs/own-task.md), recorded when the run starts: what rebuilds it on
    resume and eval, and what its env is. Filled by ``--env`` and friends; None for botorl's tasks."""

    entry: str | None = None
    """MODULE:FUNCTION, imported again by name (never unpickled); None: make_env was defined in a script."""
    path: str | None = None
    """The folder ``entry``'s module was found in: for the user's information only, never put on sys.path
    (a run directory is data; ``--env`` gives the entry again)."""
    max_steps: int | None = None
    """The episode length limit (--env-max-steps); None: botorl's own task."""
    success_key: str | None = None
    """The info key read as success; None: success is off."""
    success_off: str | None = None
    """Why success is off, when it is."""
    domain: str | None = None
    """The paper domain whose presets the task takes; None: the defaults of the docs' Your own task page."""
    reward_scale: float = 1.0
    reward_bias: float = 0.0
    obs_keys: tuple[str, ...] | None = None
    """A dict observation's leaves in flattening order (sorted, nested as a/b); None: a Box."""
    obs_dim: int | None = None
    action_dim: int | None = None
    action_low: tuple[float, ...] | None = None
    """The env's own action bounds; the policy's [-1, 1] actions are mapped onto them."""
    action_high: tuple[float, ...] | None = None


@dataclass
class MetricConfig:
    """The task's headline metric (botorl/envs/metric.py), recorded when the run starts: what
    summary.json, curve.png, the printed summary and `botorl report` are about. Filled from the
    task, so not a command-line field."""

    name: Literal["success", "return", "score"] = "success"
    """success where the task defines it; else the episode return, or the normalised score
    100 * (return - ref_min_score) / (ref_max_score - ref_min_score) when the task gives both."""
    ref_min_score: float | None = None
    ref_max_score: float | None = None


@dataclass
class NetworkConfig:
    """Network sizes used by pre-training and fine-tuning alike (the docs' Methods page)."""

    actor_hidden_dims: tuple[int, ...] = (256, 256)
    critic_hidden_dims: tuple[int, ...] = (256, 256, 256, 256)
    num_critics: int = 10
    """Critic ensemble size, pre-training and fine-tuning alike (WSRL pre-trains with its 10)."""
    layer_norm: bool = True
    """LayerNorm after each hidden layer of actor and critic (WSRL/RLPD), whatever pre-trains them."""


@dataclass
class OfflineConfig:
    """Stage 1: offline pre-training."""

    steps: int = 1_000_000
    batch_size: int = 256
    updates_per_call: int = 50
    """Gradient steps fused into one jitted lax.scan call."""
    sample_on_device: bool | None = None
    """Draw batches inside the jitted call from D_offline kept on the device; None: on off the CPU."""
    log_every: int = 1_000
    cql: CQLConfig = field(default_factory=CQLConfig)
    """CQL and Cal-QL (``calql`` is set from --pretrain)."""
    iql: IQLConfig = field(default_factory=IQLConfig)
    mc_sparse_negative_reward: float | None = None
    """Raw reward of a never-succeeding sparse trajectory (Cal-QL's MC-return rule); None: off."""
    mc_infinite_horizon: bool = False
    """MC returns assume the last reward repeats forever (Cal-QL on kitchen)."""


@dataclass
class WarmupConfig:
    """Stage 2a: the frozen pre-trained policy collects D_warmup (no updates)."""

    steps: int = 5_000


@dataclass
class OnlineConfig:
    """Stage 3: online fine-tuning."""

    steps: int = 300_000
    """Online env steps (the paper's budget: 300k)."""
    batch_size: int = 256
    """Rows per critic update; an env step's update uses utd x batch_size rows (the actor all)."""
    utd: int = 4
    """Critic updates per env step (WSRL/BOTO 4; Cal-QL/CQL/IQL baselines 1; RLPD 4 here): each
    update's batch is utd minibatches of batch_size rows, the only place the agents read it."""
    offline_ratio: float = 0.0
    """Share of each batch drawn from D_offline (WSRL/BOTO: 0; baselines and RLPD: 0.5)."""
    random_steps: int = 0
    """Env steps of the untrained policy before the first update (RLPD as WSRL ran it: 5,000)."""
    log_every: int = 1_000
    sac: SACConfig = field(default_factory=SACConfig)
    """The SAC learner of the WSRL protocol (boto, wsrl, rlpd)."""
    buffer_capacity: int | None = None
    """Replay capacity; None = everything (warm-up + online steps)."""


@dataclass
class EvalConfig:
    """Evaluation (as WSRL and Cal-QL evaluate; the docs' Methods page, "Evaluation")."""

    episodes: int = 20
    """Deterministic episodes per evaluation (at most 1,000: configs.resolve.BOUNDS)."""
    interval: int = 5_000
    """Online env steps between evaluations (plus one at step 0 and one at the end)."""
    num_envs: int = 20
    """Envs stepped in lockstep (one batched policy call per step; at most 64)."""
    q_pairs: int = 1_000
    """Dataset (s, a) pairs for the q_data / q_uniform statistics."""
    dense_interval: int = 0
    """Env steps between the extra evaluations of the dip window, from the warm-up's end (for
    every method) to dense_until; 0 = none (the quick profile: 500)."""
    dense_until: int = 10_000
    """Last env step of the dense window (the paper's 'unlearning' step)."""

    def due(self, step: int, total: int, dense_from: int) -> bool:
        """Whether fine-tuning evaluates after ``step`` online env steps of ``total``."""
        if step % self.interval == 0 or step == total:
            return True
        return (self.dense_interval > 0 and dense_from <= step <= self.dense_until
                and (step - dense_from) % self.dense_interval == 0)

    @property
    def envs_per_member(self) -> int:
        """Evaluation envs one member holds: no more than it has episodes to run."""
        return min(self.num_envs, self.episodes)


@dataclass
class RunConfig:
    """One run of one method on one task."""

    task: str = "pointmaze-umaze"
    method: MethodName = "boto"
    seed: int = 0
    online_reseed: int = 0
    """k > 0: the online phase (warm-up, BOTO, fine-tuning) draws from a seed made of (seed, k),
    the pre-training unchanged: the noise floor of a paired comparison. 0: from `seed`."""
    alpha: float | None = None
    """BOTO's bias controller in [-1, 1]; None = the preset's (the paper's per-task value)."""
    seeds: str | None = None
    """A population, one member per seed, trained as one program: 0-7 (inclusive), 0,2,5 or 0-3,9."""
    alphas: str | None = None
    """boto: one member per alpha (and seed): -1:1:0.5 (start:stop:step, stop included) or -1,0,1;
    None: `alpha`."""
    pretrain: PretrainName | None = None
    """Offline algorithm of boto/wsrl (None: calql); calql/cql/iql use themselves; rlpd none."""
    pretrained: str | None = None
    """Skip pre-training: start each member from a finished one under this directory (run,
    population or sweep) with the same seed and pre-training settings."""
    profile: Literal["quick", "mid", "full", "smoke"] = "quick"
    out: str | None = None
    """Run directory; None: runs/<task>-<method>-s<seed>-<timestamp>."""
    wandb: bool = False
    """Also log to Weights & Biases (needs `pip install "botorl[wandb]"`); one W&B run per member."""
    tensorboard: bool = True
    """TensorBoard events under DIR/tb when tensorboardX is installed."""
    progress: bool = True
    """tqdm progress bars."""
    checkpoint_every: int = 50_000
    """Steps between checkpoints inside a stage (gradient or env steps); every stage ends with one."""
    precision: Literal["highest", "tf32", "bf16"] = "tf32"
    """Every matmul's precision on a GPU: fp32 (highest), TF32 inputs (what JAX itself does on a
    GPU) or bf16 inputs, fp32 sums; a CPU computes fp32 whatever it says (the docs' Performance
    page, Precision)."""
    data: DataConfig = field(default_factory=DataConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    offline: OfflineConfig = field(default_factory=OfflineConfig)
    warmup: WarmupConfig = field(default_factory=WarmupConfig)
    boto: BOTOConfig = field(default_factory=BOTOConfig)
    online: OnlineConfig = field(default_factory=OnlineConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    env: Annotated[EnvConfig, tyro.conf.Suppress] = field(default_factory=EnvConfig)
    """A task of your own (see EnvConfig); filled from the task, so not a command-line field."""
    metric: Annotated[MetricConfig, tyro.conf.Suppress] = field(default_factory=MetricConfig)
    """The headline metric (see MetricConfig); filled from the task."""

    @property
    def online_seed(self) -> int:
        """The seed of the online phase (see ``online_reseed``)."""
        if not self.online_reseed:
            return self.seed
        return int(np.random.SeedSequence([self.seed, self.online_reseed]).generate_state(1)[0] % 2**31)


# Fields that do not change what a run's checkpoints hold: where and how it logs, how updates
# are chunked into jitted calls (the same numbers either way), where its data and pre-training
# are read from (a run directory moves between machines), the preset's name, evaluation and
# the metric it is reported in.
_NOT_STATE = ("out", "progress", "tensorboard", "wandb", "checkpoint_every", "seeds", "alphas", "pretrained", "profile",
              "seed", "alpha", "data.path", "data.demos", "offline.updates_per_call", "offline.sample_on_device",
              "boto.steps_per_call")


def flatten(d: Mapping, prefix: str = "") -> dict[str, Any]:
    """``{"network": {"layer_norm": False}}`` -> ``{"network.layer_norm": False}``."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, Mapping):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _digest(fields: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(fields, sort_keys=True, default=str).encode()).hexdigest()[:16]


def run_identity(cfg: "RunConfig") -> dict[str, Any]:
    """What every checkpoint of the run ``cfg`` records, so that it is never read as another
    run's: task, method, pre-training (algorithm and a digest of the fields that shape it),
    seed, alpha, and a digest of every config field that shapes the saved state."""
    flat = {k: v for k, v in flatten(to_dict(cfg)).items()
            if k not in _NOT_STATE and not k.startswith(("eval.", "metric.")) and not k.endswith("log_every")}
    if flat.get("precision") == "tf32":
        # the default, and what every run before the field computed (JAX's default on a GPU is
        # TF32): left out, so those runs keep their identity and resume
        del flat["precision"]
    # the UTD the agent configs held before it became the update batch's leading axis (online.utd
    # online, 1 in pre-training): in the digests still, so the runs before keep their identity
    flat.update({"online.sac.utd_ratio": cfg.online.utd, "offline.cql.utd_ratio": 1})
    pre = {k: v for k, v in flat.items() if k.startswith(("data.", "network.", "offline."))}
    return {"task": cfg.task, "method": cfg.method, "pretrain": cfg.pretrain, "pretraining": _digest(pre),
            "seed": cfg.seed, "alpha": cfg.alpha, "config": _digest(flat)}


def to_dict(cfg: Any) -> Any:
    if dataclasses.is_dataclass(cfg):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, tuple):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, float) and math.isinf(cfg):
        return "inf" if cfg > 0 else "-inf"
    return cfg


def from_dict(cls: type, data: dict[str, Any], where: str = "") -> Any:
    """Rebuild a (nested) config dataclass from ``to_dict`` output; unknown keys are ignored. A
    value of the wrong type (a string where a number belongs, null in a field that takes none, a
    number beyond a float) is a TypeError naming its dotted field (``where``: the section's)."""
    hints = typing.get_type_hints(cls)
    if not isinstance(data, Mapping):
        raise TypeError(f"{where.rstrip('.') or cls.__name__} needs a JSON object, not {_shown(data)}")
    return cls(**{f.name: _convert(hints[f.name], data[f.name], where + f.name)
                  for f in dataclasses.fields(cls) if f.name in data})


def _shown(value: Any) -> str:
    text = "null" if value is None else json.dumps(value, default=str) if isinstance(value, (list, dict)) else repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _kind(tp: Any) -> str:
    """What a field of type ``tp`` takes, in the words of a message."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_kind(a) for a in typing.get_args(tp))
    if origin is Literal:
        return "one of " + ", ".join(map(repr, typing.get_args(tp)))
    if origin is tuple:
        return "a list"
    return {str: "a string", int: "an integer", float: "a number", bool: "true or false",
            type(None): "null"}.get(tp, "an object" if dataclasses.is_dataclass(tp) else str(tp))


def _convert(tp: Any, value: Any, name: str) -> Any:
    origin = typing.get_origin(tp)
    wrong = TypeError(f"{name} = {_shown(value)} is invalid: give {_kind(tp)}")
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return None
        for a in [a for a in typing.get_args(tp) if a is not type(None)]:  # the first that fits
            try:
                return _convert(a, value, name)
            except (TypeError, ValueError):
                continue
        raise wrong
    if dataclasses.is_dataclass(tp):
        if value is None:  # a section set to null ("data": null) is no config
            raise TypeError(f"{name!r} is null; it must be an object")
        return from_dict(tp, value, name + ".")
    if origin is tuple:  # tuple[X, ...]
        if not isinstance(value, (list, tuple)):
            raise wrong
        args = typing.get_args(tp)
        return tuple(_convert(args[0] if args else Any, v, f"{name}[{i}]") for i, v in enumerate(value))
    if origin is Literal:
        if isinstance(value, bool) or value not in typing.get_args(tp):
            raise wrong
        return value
    if tp is str or tp is bool:
        if not isinstance(value, tp):
            raise wrong
        return value
    if tp is int:  # 3.0 is 3; 3.5, "3" and true are no integer
        if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                (isinstance(value, float) and not value.is_integer()):
            raise wrong
        return int(value)
    if tp is float:  # a number, or to_dict's "inf" / "-inf"
        if isinstance(value, bool) or not (isinstance(value, (int, float)) or value in ("inf", "-inf")):
            raise wrong
        try:
            return float(value)
        except OverflowError:
            raise TypeError(f"{name} = {_shown(value)} is invalid: the number is beyond a float") from None
    return value
