"""``botorl data``: generate datasets (deterministic for a seed, cached under ``$BOTORL_DATA_DIR``)
and show their statistics (a cached generated dataset, a task's downloaded data, or any dataset
file/folder botorl reads)."""

from __future__ import annotations

import dataclasses
import json
import re
import time
from pathlib import Path
from typing import Annotated, Optional

import tyro

from botorl.data import minari_io  # write_minari looked up when called: the tests replace it
from botorl.data.generate import cache_id, cache_path, cached_datasets, ensure_dataset
from botorl.data.generators import DEFAULT_STEPS, GENERATORS, get_generator
from botorl.data.generators.antmaze import maze_stats, plot_coverage
from botorl.data.loaders import load_minari, load_path
from botorl.data.tasks import load_task_data
from botorl.configs.members import SEED_LIMIT
from botorl.envs.registry import get_task
from botorl.errors import BotorlError, Range, check_ranges

MAX_ROWS = 10**9  # rows a generator makes, as --data.steps allows (configs.resolve.BOUNDS)


@dataclasses.dataclass
class Generate:
    """Generate (or find in the cache) the dataset of a task botorl can make itself."""

    task: Annotated[str, tyro.conf.Positional]
    """task name, e.g. pointmaze-large, door-binary-local, bandit-pinwheel, bandit-1d"""
    steps: Annotated[Optional[int], Range(1, MAX_ROWS)] = None
    """dataset size in env steps (default: the task's default, e.g. 1,000,000 for pointmaze)"""
    seed: Annotated[int, Range(0, SEED_LIMIT - 1)] = 0
    """generator seed"""
    out: Optional[Path] = None
    """also write a copy here: a folder named like name-v0 becomes that Minari dataset;
    any other folder is used as a Minari root (MINARI_DATASETS_PATH=PATH reads it)"""
    overwrite: bool = False
    """regenerate even if cached, and replace an existing --out dataset"""
    no_progress: bool = False
    """hide the progress bar"""


@dataclasses.dataclass
class _Target:
    target: Annotated[str, tyro.conf.Positional]
    """a task name (its cached generated data, or its downloaded data), or a dataset path"""
    steps: Annotated[Optional[int], Range(1, MAX_ROWS)] = None
    """only the cached dataset of this size"""
    seed: Annotated[Optional[int], Range(0, SEED_LIMIT - 1)] = None
    """only the cached dataset of this seed"""


@dataclasses.dataclass
class Info(_Target):
    """Size, episodes, return statistics and success rate of a dataset."""

    json: bool = False
    """print JSON instead of a table"""


@dataclasses.dataclass
class Plot(_Target):
    """Draw the visited (x, y) positions of an antmaze dataset over its maze map (PNG)."""

    out: Optional[Path] = None
    """the PNG to write (default: coverage_<task>.png in the current folder)"""


def _plot(cfg: Plot) -> int:
    name, ds = _load_for_info(cfg)[0]
    out = cfg.out or Path(f"coverage_{Path(cfg.target).name}.png")
    print(f"{plot_coverage(ds, out)} ({name})")
    return 0


def _generate(cfg: Generate) -> int:
    get_generator(cfg.task)  # unknown/missing generator: clear error before any work
    steps = cfg.steps if cfg.steps is not None else DEFAULT_STEPS[cfg.task]
    path = cache_path(cfg.task, steps, cfg.seed)
    cached = (path / "data" / "metadata.json").exists() and not cfg.overwrite
    t0 = time.time()
    ds = ensure_dataset(cfg.task, steps, cfg.seed, progress=not cfg.no_progress, regenerate=cfg.overwrite)
    verb = "found cached" if cached else f"generated in {time.time() - t0:.1f} s"
    print(f"{cfg.task}: {verb}: {len(ds):,} transitions, {ds.num_episodes:,} episodes -> {path}")
    if cfg.out is not None:
        out = cfg.out.expanduser()
        # a folder named like name-v0 becomes that dataset, any other one a Minari root
        where = dict(path=out) if re.fullmatch(r"[-\w]+-v\d+", out.name) else dict(
            dataset_id=cache_id(cfg.task, steps, cfg.seed), root=out)
        dest = minari_io.write_minari(ds, **where, overwrite=cfg.overwrite, metadata=ds.metadata.get("botorl", {}),
                            env_spec=get_task(cfg.task).gym_spec())
        print(f"copy written to {dest}")
    return 0


def _load_for_info(cfg: _Target) -> list[tuple[str, object]]:
    target = cfg.target
    if target in GENERATORS:
        found = cached_datasets(target)
        chosen = cached_datasets(target, cfg.steps, cfg.seed)
        if not chosen:
            sel = "".join(f" --{k} {v}" for k, v in (("steps", cfg.steps), ("seed", cfg.seed)) if v is not None)
            raise BotorlError(f"no generated dataset of {target}{sel or ''} in the cache "
                              f"({Path(found[0]).parent if found else 'BOTORL_DATA_DIR'}); make it with "
                              f"`botorl data generate {target}{sel}`.")
        return [(str(p), load_minari(p)) for p in chosen]
    if Path(target).expanduser().exists():
        return [(target, load_path(target))]
    try:
        task = get_task(target)
    except BotorlError:
        raise BotorlError(f"{target!r} is neither a task name nor an existing dataset path. Tasks with "
                          f"generated data: {', '.join(GENERATORS)}; `botorl tasks` lists all tasks.") from None
    return [(target, load_task_data(task))]


def _info(cfg: Info) -> int:
    results = []
    for name, ds in _load_for_info(cfg):
        st = ds.stats()
        st["dataset"] = name
        meta = ds.metadata.get("botorl") or {}
        st.update({f"meta_{k}": meta[k] for k in ("generator", "steps", "seed") if k in meta})
        # generated antmaze data: coverage of the maze
        st.update({f"maze_{k}": v for k, v in (maze_stats(ds) or {}).items()})
        results.append(st)
    if cfg.json:
        print(json.dumps(results if len(results) > 1 else results[0], indent=2))
        return 0
    for st in results:
        print(st["dataset"])
        sr = st["success_rate"]
        rows = [
            ("transitions", f"{st['transitions']:,}"),
            ("episodes", f"{st['episodes']:,} (mean length {st['episode_length_mean']:.1f})"),
            ("obs / action dim", f"{st['obs_dim']} / {st['action_dim']}"),
            ("terminals", f"{st['terminals']:,}"),
            ("return / episode", f"mean {st['return_mean']:.3f}  std {st['return_std']:.3f}  "
                                 f"min {st['return_min']:.3f}  max {st['return_max']:.3f}"),
            ("reward range", f"[{st['reward_min']:.3f}, {st['reward_max']:.3f}]"),
            ("success rate", "unknown" if sr is None else f"{sr:.3f} (episodes reaching success)"),
        ]
        if "maze_coverage" in st:
            rows.append(("maze coverage", f"{st['maze_cells_covered']}/{st['maze_cells_free']} free cells of the "
                         f"{st['maze_maze']} maze with >= 100 steps ({st['maze_coverage']:.2f}); "
                         f"{st['maze_eval_goal_rows']:,} rows at the evaluation goal"))
        rows += [(k[5:], str(v)) for k, v in st.items() if k.startswith("meta_")]
        for k, v in rows:
            print(f"  {k:<18} {v}")
    return 0


def main(argv: list[str] | None = None) -> int:
    cfg = tyro.extras.subcommand_cli_from_dict(
        {"generate": Generate, "info": Info, "plot": Plot},
        args=argv,
        prog="botorl data",
        description="Generate botorl's own datasets and show dataset statistics.",
    )
    check_ranges(cfg)
    if isinstance(cfg, Generate):
        return _generate(cfg)
    if isinstance(cfg, Plot):
        return _plot(cfg)
    return _info(cfg)
