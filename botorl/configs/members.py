"""The members of a population: every (seed, alpha) pair of ``--seeds`` / ``--alphas``; the one
parser of seeds and alphas (the population's fields and the sweep's grid alike), each member's
config: the shared one with its own seed and alpha, the only fields members differ in, and
the random streams a member's seeds give (``Streams``, the one seed plan).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, replace
from typing import Sequence

from botorl.boto.config import check_alpha
from botorl.configs.methods import get_method
from botorl.errors import ConfigError


# The most seeds, alphas or members of a population (or a sweep's grid axis): far more than a
# study needs, few enough to build the lists (`--seeds 0-2147483648` is refused, not a MemoryError).
MAX_MEMBERS = 10_000
SEED_LIMIT = 2**31  # NumPy's and JAX's seeds: [0, 2**31)

# every name Member.name makes, and nothing else (population.json's names are checked against it)
MEMBER_NAME = re.compile(r"(alpha[+-][0-9]{1,3}\.[0-9]{2,6}-)?seed[0-9]{1,12}")


@dataclass(frozen=True)
class Member:
    """One member: its seed and, for BOTO, its alpha (None: no BOTO phase)."""

    seed: int
    alpha: float | None = None

    @property
    def name(self) -> str:
        """Its run directory's name inside the population directory."""
        if self.alpha is None:
            return f"seed{self.seed}"
        return f"alpha{self.alpha:+.2f}-seed{self.seed}" if round(self.alpha, 2) == self.alpha else \
            f"alpha{self.alpha:+.6f}-seed{self.seed}"

    def to_json(self) -> dict:
        return {"seed": self.seed, "alpha": self.alpha, "name": self.name}


@dataclass(frozen=True)
class Streams:
    """Every random stream of one member's run, drawn from its ``seed`` (pre-training, evaluation)
    and ``online_seed`` (the online phase; RunConfig.online_seed), each its own, so no two
    streams share draws (docs/populations.md). The constants are the ones runs have always
    used: they keep every run's numbers."""

    pretrain: int  # the pre-training agent: its networks and key
    pretrain_batches: list[int]  # SeedSequence of pre-training's host batches
    pretrain_keys: int  # PRNGKey of its device batches, folded with the step
    boto: int  # BOTO's batches and noise: call c draws from [boto, c] (boto/phase.py)
    scratch: int  # fine-tuning's SAC from nothing (RLPD)
    warm_start: int  # WSRL's SAC from the pre-trained networks
    online_env: int  # the online loop's env and its resets (the warm-up's and fine-tuning's: one loop)
    online_batches: list[int]  # SeedSequence of fine-tuning's batches
    evaluation: int  # the run's evaluation episodes reset from evaluation + episode index
    eval_command: int  # `botorl eval`'s episodes: others than the run's

    PROBE = 12345  # the Q probe's (s, a) pairs: one set for every run, which compares them
    EVAL_ENVS = 10_000  # evaluation env i is made with seed EVAL_ENVS + i in every member

    @classmethod
    def of(cls, cfg) -> "Streams":
        s, o = cfg.seed, cfg.online_seed
        return cls(pretrain=s, pretrain_batches=[s, 1], pretrain_keys=s * 1_000_003 + 1,
                   boto=o, scratch=o, warm_start=o * 7919 + 3, online_env=o * 1000 + 11, online_batches=[o, 3],
                   evaluation=100_000 + 1_000 * s, eval_command=200_000 + s)


def _items(value, flag: str) -> list[str]:
    """The items of a command-line value ("0-3,7") or a YAML one (a list, a number)."""
    if value is None:
        return []
    if isinstance(value, (list, tuple)):
        return [str(v).strip() for v in value]
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return [repr(value)]
    items = [t.strip() for t in str(value).split(",")]
    if not all(items):
        raise ConfigError(f"{flag} {value!r} has an empty item; write e.g. {flag} 0-3 or {flag} 0,2,5.")
    return items


def _no_repeats(values: list, value, flag: str) -> None:
    dup = sorted({v for v in values if values.count(v) > 1})
    if dup:
        raise ConfigError(f"{flag} {value}: {dup} given twice. Two members (or trials) with the same seed and alpha "
                          f"would be the same run; give each value once.")


def parse_seeds(value, flag: str = "--seeds") -> list[int]:
    """``"0-7"`` (inclusive), ``"0,2,5"``, ``"0-2,7"``, a number or a list, in the order given; a
    seed given twice is an error."""
    seeds: list[int] = []
    for item in _items(value, flag):
        try:
            if "-" in item[1:]:
                lo, hi = (int(p) for p in item.split("-", 1))
                if hi < lo:
                    raise ValueError
            else:
                lo = hi = int(item)
        except ValueError:
            raise ConfigError(f"{flag}: cannot read {item!r}. Give a range like 0-7 (both ends included), a list like "
                              f"0,2,5, or both (0-3,9).") from None
        if lo < 0 or hi >= SEED_LIMIT:
            raise ConfigError(f"{flag}: {item!r}: seeds must lie in [0, 2**31), got {lo if lo < 0 else hi}.")
        if len(seeds) + hi - lo + 1 > MAX_MEMBERS:  # counted before the list is built
            raise ConfigError(f"{flag} {value!r} gives {len(seeds) + hi - lo + 1:,} seeds or more; at most "
                              f"{MAX_MEMBERS:,} are allowed. Give fewer seeds (e.g. {flag} 0-7).")
        seeds.extend(range(lo, hi + 1))
    _no_repeats(seeds, value, flag)
    return seeds


def parse_alphas(value, flag: str = "--alphas") -> list[float]:
    """``"-1:1:0.25"`` (start:stop:step, stop included), ``"-0.5,0,0.5"``, a number or a list, in
    the order given, rounded to 1e-6; an alpha given twice is an error."""
    alphas: list[float] = []
    one_range = isinstance(value, str) and ":" in value and "," not in value
    for item in [value.strip()] if one_range else _items(value, flag):
        try:
            if ":" in item:
                start, stop, step = (float(p) for p in item.split(":"))
                if not step > 0 or stop < start:
                    raise ValueError
                n = int(math.floor((stop - start) / step + 1e-9)) + 1
                if len(alphas) + n > MAX_MEMBERS:
                    raise ConfigError(f"{flag} {value!r} gives {len(alphas) + n:,} alphas; at most {MAX_MEMBERS:,} "
                                      f"are allowed. Use a coarser step (e.g. {flag} -1:1:0.25).")
                alphas.extend(round(start + i * step, 6) for i in range(n))
            else:
                alphas.append(round(float(item), 6))
        except (ValueError, OverflowError):
            raise ConfigError(f"{flag}: cannot read {item!r}. Give start:stop:step with the stop included (-1:1:0.25 "
                              "gives 9 values) or a list like -0.5,0,0.5.") from None
    alphas = [0.0 if a == 0 else a for a in alphas]
    bad = [a for a in alphas if math.isnan(a) or not -1.0 <= a <= 1.0]
    if bad:
        check_alpha(bad, flag)
    _no_repeats(alphas, value, flag)
    return alphas


def make_members(seeds: Sequence[int], alphas: Sequence[float | None]) -> list[Member]:
    """Every (seed, alpha) pair, alpha-major. ``alphas`` empty or [None]: one alpha (the preset's);
    a method without BOTO has none (its config was refused, ``configs.resolve.validate``)."""
    alphas = list(alphas) or [None]
    if len(seeds) * len(alphas) > MAX_MEMBERS:
        raise ConfigError(f"{len(seeds):,} seeds x {len(alphas):,} alphas make {len(seeds) * len(alphas):,} members; at "
                          f"most {MAX_MEMBERS:,} are allowed. Give fewer --seeds or --alphas.")
    # never empty nor repeated: parse_seeds and parse_alphas refuse both
    return [Member(int(s), None if a is None else float(a)) for a in alphas for s in seeds]


def member_config(cfg, seed: int, alpha: float | None, out: str | os.PathLike | None = None):
    """The config of member (seed, alpha) of the population ``cfg``: one run, no ``seeds``/``alphas``."""
    if alpha is None or not get_method(cfg.method).uses_alpha:
        alpha = cfg.alpha
    return replace(cfg, seed=int(seed), alpha=None if alpha is None else float(alpha), seeds=None, alphas=None,
                   out=str(out) if out is not None else cfg.out)


def is_population(cfg) -> bool:
    """Whether ``cfg`` asks for a population (``seeds`` or ``alphas``), not one run."""
    return cfg.seeds is not None or cfg.alphas is not None


def population(cfg) -> tuple[list[Member], list]:
    """The members of the population ``cfg`` describes (see ``make_members``) and their configs."""
    seeds = [cfg.seed] if cfg.seeds is None else parse_seeds(cfg.seeds)
    alphas = [None] if cfg.alphas is None else parse_alphas(cfg.alphas)
    members = make_members(seeds, alphas)
    return members, [member_config(cfg, m.seed, m.alpha) for m in members]
