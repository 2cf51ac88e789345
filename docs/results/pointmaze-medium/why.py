"""The Q, entropy and temperature statistics behind the result pages in docs/results/ (why BOTO
does or does not reduce unlearning here), from the members of the study's populations.

    python docs/results/pointmaze-medium/why.py study/pm-medium-boto study/pm-medium-wsrl
    python docs/results/pointmaze-medium/why.py --by-alpha study/alpha-medium/pointmaze-medium/boto/pop-44m-*

Per method, means over members (and the per-member values where they differ):
- q_data / q_uniform at step 0 (probe states of D_offline; after pre-training) and at the
  first fine-tuning evaluation (after the warm-up, and after BOTO for BOTO), and their gap;
- BOTO's first and last logged batch statistics (D_offline u D_warmup rows);
- fine-tuning's entropy and temperature at its first log row and after ~2.5k and ~5k steps,
  and the mean dataset Q (`q_data`) over the first 5k fine-tuning steps against step 0;
- success at 0, the lowest in the first 10k online steps, and final.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np


def rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return [{k: (float(v) if v not in ("", None) and k != "stage" else v) for k, v in r.items()} for r in csv.DictReader(f)]


def at(rs: list[dict], step: float, key: str = "step") -> dict:
    return min(rs, key=lambda r: abs(r[key] - step))


def member(d: Path) -> dict:
    ev = rows(d / "eval.csv")
    ft = rows(d / "metrics" / "finetune.csv")
    out = {"success0": ev[0]["success"], "dip_low": min(r["success"] for r in ev if r["env_step"] <= 10_000),
           "final": ev[-1]["success"], "q_data0": ev[0]["q_data"], "q_unif0": ev[0]["q_uniform"]}
    first_ft = next(r for r in ev if r["stage"] == "finetune")
    out |= {"q_data_ft0": first_ft["q_data"], "q_unif_ft0": first_ft["q_uniform"]}
    for step in (5_000, 7_500, 10_000):  # success at the sweep's evaluation points (nan if not reached)
        out[f"s_{step}"] = next((r["success"] for r in reversed(ev) if r["env_step"] == step), float("nan"))
    out["dip"] = out["dip_low"] - out["success0"]
    start = ft[0]["step"]
    for name, s in (("ft_first", start), ("ft_2k5", start + 2_500), ("ft_5k", start + 5_000)):
        r = at(ft, s)
        out |= {f"entropy_{name}": r["entropy"], f"temp_{name}": r["temperature"], f"qd_{name}": r["q_data"]}
    if (d / "metrics" / "boto.csv").exists():
        b = rows(d / "metrics" / "boto.csv")
        out |= {"boto_qd_first": b[0]["q_data"], "boto_qu_first": b[0]["q_uniform"],
                "boto_qd_last": b[-1]["q_data"], "boto_qu_last": b[-1]["q_uniform"]}
    return out


BY_ALPHA = ("success0", "s_5000", "s_7500", "s_10000", "dip", "q_data0", "q_data_ft0", "q_unif_ft0", "qd_ft_first",
            "qd_ft_5k")


def by_alpha(dirs: list[str]) -> None:
    """One row per alpha of a sweep: means over its seeds (Q after BOTO = q_*_ft0)."""
    import json

    groups: dict[float, list[dict]] = {}
    for pop in map(Path, dirs):
        for m in sorted(p for p in pop.iterdir() if (p / "eval.csv").exists()):
            alpha = json.loads((m / "config.json").read_text())["boto"]["alpha"]
            groups.setdefault(float(alpha), []).append(member(m))
    print(f"{'alpha':>6} {'n':>2} " + " ".join(f"{k:>11}" for k in BY_ALPHA) + "   dip s.e.")
    for a in sorted(groups):
        vals = [np.mean([s[k] for s in groups[a]]) for k in BY_ALPHA]
        dips = np.array([s["dip"] for s in groups[a]])
        se = dips.std(ddof=1) / np.sqrt(len(dips)) if len(dips) > 1 else float("nan")
        print(f"{a:6.2f} {len(groups[a]):2d} " + " ".join(f"{v:11.2f}" for v in vals) + f"   {se:8.2f}")


def main(dirs: list[str]) -> None:
    if dirs and dirs[0] == "--by-alpha":
        return by_alpha(dirs[1:])
    for pop in map(Path, dirs):
        members = sorted(p for p in pop.iterdir() if (p / "eval.csv").exists())
        stats = [member(m) for m in members]
        print(f"== {pop.name}: {len(stats)} members")
        for key in stats[0]:
            vals = np.array([s[key] for s in stats])
            print(f"{key:>16}  mean {vals.mean():9.3f}   " + " ".join(f"{v:.3g}" for v in vals))


if __name__ == "__main__":
    main(sys.argv[1:])
