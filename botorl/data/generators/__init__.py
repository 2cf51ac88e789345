"""Dataset generators botorl can run itself, by task name: ``"module:function"`` entries, imported
only when used, ``generate(steps, seed, progress=True) -> Dataset``, deterministic for a seed.
"""

from __future__ import annotations

import importlib
from typing import Callable

from botorl.errors import ConfigError

# task -> (generator in this package, default dataset size in transitions / env steps). Sizes:
# pointmaze as D4RL maze2d-large (1M); antmaze D4RL's / Minari's 1M per dataset
# (create_antmaze_dataset.py); door: BC rollout steps on top of the 25 demos (our choice);
# bandits: enough samples for the figures, few enough that Minari's one-group-per-episode files
# stay quick to write (botorl.data.minari_io: about 0.7 ms per episode) (our choice).
_TABLE: dict[str, tuple[str, int]] = {
    "pointmaze-umaze": ("pointmaze:generate_umaze", 1_000_000),
    "pointmaze-medium": ("pointmaze:generate_medium", 1_000_000),
    "pointmaze-large": ("pointmaze:generate_large", 1_000_000),
    "door-binary-local": ("door:generate", 100_000),
    "bandit-pinwheel": ("bandit:generate_pinwheel", 5_000),
    "bandit-1d": ("bandit:generate_1d", 1_000),
    "antmaze-large-diverse-local": ("antmaze:generate_large_diverse", 1_000_000),
    "antmaze-large-play-local": ("antmaze:generate_large_play", 1_000_000),
    "antmaze-medium-diverse-local": ("antmaze:generate_medium_diverse", 1_000_000),
    "antmaze-medium-play-local": ("antmaze:generate_medium_play", 1_000_000),
    "antmaze-umaze-diverse-local": ("antmaze:generate_umaze_diverse", 1_000_000),
}
GENERATORS: dict[str, str] = {task: f"botorl.data.generators.{entry}" for task, (entry, _) in _TABLE.items()}
DEFAULT_STEPS: dict[str, int] = {task: steps for task, (_, steps) in _TABLE.items()}


def get_generator(task: str) -> Callable:
    """The generator function of ``task``; a ConfigError naming the tasks with one if it has none."""
    if task not in GENERATORS:
        raise ConfigError(f"botorl cannot generate data for {task!r}; tasks with a generator: "
                          f"{', '.join(GENERATORS)}. Other tasks read downloaded data (see `botorl tasks`).")
    module_name, func_name = GENERATORS[task].split(":")
    return getattr(importlib.import_module(module_name), func_name)
