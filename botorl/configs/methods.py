"""Methods by name (``METHODS``): the stages each runs (pipeline/stages.py) and what fine-tuning
needs from it (how it starts, which rows its batches hold and their layout). The methods stage
by stage: docs/methods.md. ``pretrain`` picks boto's and wsrl's offline algorithm (default
calql); calql, cql and iql pre-train with themselves; rlpd has no pre-training.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from botorl.errors import ConfigError

MethodName = Literal["boto", "wsrl", "calql", "cql", "iql", "rlpd"]  # RunConfig.method: METHODS' keys
PretrainName = Literal["calql", "cql", "iql"]
PRETRAIN_ALGOS = get_args(PretrainName)


@dataclass(frozen=True)
class Method:
    name: MethodName
    stages: tuple[str, ...]
    finetune_start: str  # "warm_start" (WSRL) | "continue" (the pre-trained agent's own loss) | "scratch"
    fixed_pretrain: str | None = None  # the method *is* its pre-training algorithm
    uses_alpha: bool = False
    finished_episodes_only: bool = False  # fine-tuning batches hold rows of finished episodes only
    batch_layout: str = "utd_rows"  # "utd_rows": one update on utd x B rows | "per_update": utd updates of B
    # Fine-tuning SAC's target entropy per action dimension (None: the agent's rule, -|A|), the
    # one place it is set (configs/resolve.py fills it). RLPD's -|A|/2 as WSRL ran it; boto and
    # wsrl -|A|, what WSRL's SAC makes of the 0.0 its config passes (docs/methods.md, its source).
    target_entropy_per_dim: float | None = None
    description: str = ""

    @property
    def pretrains(self) -> bool:
        """Starts from an offline pre-training (every method but RLPD, which starts from nothing)."""
        return "pretrain" in self.stages

    def refuse_alpha(self, flag: str) -> None:
        """ConfigError: ``flag`` (--alpha, --alphas) sets an alpha, which a method without BOTO lacks."""
        if not self.uses_alpha:
            raise ConfigError(f"{flag} sets BOTO's bias controller; --method {self.name} has no BOTO phase. Drop "
                              f"{flag}, or use --method boto.")


METHODS: dict[str, Method] = {
    "boto": Method("boto", ("pretrain", "warmup", "boto", "finetune"), "warm_start", uses_alpha=True,
                   target_entropy_per_dim=-1.0, description="pre-train, warm-up, BOTO critic training, WSRL fine-tuning"),
    "wsrl": Method("wsrl", ("pretrain", "warmup", "finetune"), "warm_start", target_entropy_per_dim=-1.0,
                   description="pre-train, warm-up, WSRL fine-tuning (no BOTO)"),
    # Cal-QL bounds Q by each row's MC return, known once its episode ends: it samples finished
    # episodes only and waits for the first one (WSRL)
    "calql": Method("calql", ("pretrain", "finetune"), "continue", fixed_pretrain="calql",
                    finished_episodes_only=True,
                    description="Cal-QL offline, then its own loss online with the offline data kept"),
    "cql": Method("cql", ("pretrain", "finetune"), "continue", fixed_pretrain="cql",
                  description="CQL offline, then its own loss online with the offline data kept"),
    "iql": Method("iql", ("pretrain", "finetune"), "continue", fixed_pretrain="iql", batch_layout="per_update",
                  description="IQL offline, then its own loss online with the offline data kept"),
    "rlpd": Method("rlpd", ("finetune",), "scratch", target_entropy_per_dim=-0.5,
                   description="SAC from scratch online with 50/50 offline/online batches"),
}


def get_method(name: str) -> Method:
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r} (--method). Choose one of: {', '.join(METHODS)}. "
                          f"For BOTO on top of CQL or IQL use `--method boto --pretrain cql|iql`.")
    return METHODS[name]


def resolve_pretrain(method: str, pretrain: str | None) -> str | None:
    """The offline algorithm a method uses, or None (rlpd)."""
    m = get_method(method)
    if pretrain is not None and pretrain not in PRETRAIN_ALGOS:
        raise ConfigError(f"unknown pre-training algorithm {pretrain!r} (--pretrain). Choose one of: "
                          f"{', '.join(PRETRAIN_ALGOS)}.")
    if m.fixed_pretrain is not None:
        if pretrain is not None and pretrain != m.fixed_pretrain:
            raise ConfigError(f"--method {method} pre-trains with {m.fixed_pretrain}; --pretrain {pretrain} "
                              f"contradicts it. Drop --pretrain, or use `--method boto --pretrain {pretrain}` "
                              f"(or `--method wsrl --pretrain {pretrain}`).")
        return m.fixed_pretrain
    if "pretrain" not in m.stages:
        if pretrain is not None:
            raise ConfigError(f"--method {method} trains from scratch and has no pre-training; drop "
                              f"--pretrain {pretrain}.")
        return None
    return pretrain or "calql"
