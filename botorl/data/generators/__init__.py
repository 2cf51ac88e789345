"""Dataset generators botorl can run itself, by task name.

Each entry is ``"module:function"``, imported only when used, with the signature
``generate(steps: int, seed: int, progress: bool = True) -> Dataset`` (deterministic for a
seed). ``botorl.data.generate.ensure_dataset`` caches their output as Minari datasets.
"""

from __future__ import annotations

import importlib
from typing import Callable

from botorl.errors import BotorlError, ConfigError

GENERATORS: dict[str, str] = {
    "pointmaze-umaze": "botorl.data.generators.pointmaze:generate_umaze",
    "pointmaze-medium": "botorl.data.generators.pointmaze:generate_medium",
    "pointmaze-large": "botorl.data.generators.pointmaze:generate_large",
    "door-binary-local": "botorl.data.generators.door:generate",
    "bandit-pinwheel": "botorl.data.generators.bandit:generate_pinwheel",
    "bandit-1d": "botorl.data.generators.bandit:generate_1d",
    "antmaze-large-diverse-local": "botorl.data.generators.antmaze:generate_large_diverse",
    "antmaze-large-play-local": "botorl.data.generators.antmaze:generate_large_play",
    "antmaze-medium-diverse-local": "botorl.data.generators.antmaze:generate_medium_diverse",
    "antmaze-medium-play-local": "botorl.data.generators.antmaze:generate_medium_play",
    "antmaze-umaze-diverse-local": "botorl.data.generators.antmaze:generate_umaze_diverse",
}

# Default dataset sizes (transitions / env steps) when none is given; pointmaze as D4RL
# maze2d-large (1M); door: BC rollout steps on top of the 25 demos (our choice); bandits:
# enough samples for the figures, few enough that Minari's one-group-per-episode files
# stay quick to write (botorl.data.minari_io: about 0.7 ms per episode) (our choice).
DEFAULT_STEPS: dict[str, int] = {
    "pointmaze-umaze": 1_000_000,
    "pointmaze-medium": 1_000_000,
    "pointmaze-large": 1_000_000,
    "door-binary-local": 100_000,
    "bandit-pinwheel": 5_000,
    "bandit-1d": 1_000,
    # antmaze: D4RL's / Minari's 1M steps per dataset (create_antmaze_dataset.py)
    "antmaze-large-diverse-local": 1_000_000,
    "antmaze-large-play-local": 1_000_000,
    "antmaze-medium-diverse-local": 1_000_000,
    "antmaze-medium-play-local": 1_000_000,
    "antmaze-umaze-diverse-local": 1_000_000,
}


def get_generator(task: str) -> Callable:
    """The generator function of ``task``; a clear ``BotorlError`` if it is unknown or missing."""
    if task not in GENERATORS:
        raise ConfigError(
            f"botorl cannot generate data for {task!r}; tasks with a generator: "
            f"{', '.join(GENERATORS)}. Other tasks read downloaded data (see `botorl tasks`)."
        )
    module_name, func_name = GENERATORS[task].split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as err:
        if err.name and module_name.startswith(err.name):
            raise BotorlError(
                f"the data generator for {task!r} ({GENERATORS[task]}) is not part of this "
                "botorl installation yet; update botorl, or use another task."
            ) from None
        raise
    func = getattr(module, func_name, None)
    if func is None:
        raise BotorlError(
            f"the data generator for {task!r} ({GENERATORS[task]}) is missing its function "
            f"{func_name!r}; this botorl installation is incomplete."
        )
    return func
