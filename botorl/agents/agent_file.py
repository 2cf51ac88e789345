"""Save and restore any agent to one msgpack file (no pickle of code objects).

The file holds a header (format tag, agent class, config as JSON) and every array of the
agent's pytree (``flax.serialization.to_state_dict``); the static parts come from ``like``, a
template agent built with the same config, so an update after ``load(path, like=agent)`` is
bit-identical to one without the round trip. Writes are atomic. Format v2 stores the state's
msgpack bytes with their sha256 and ``load`` refuses a file that no longer matches; v1 files
(no checksum) are still read.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import jax
import numpy as np
from flax import serialization

from botorl.errors import DataFormatError
from botorl.io import atomic_write_bytes, read_bounded_bytes

FORMAT = "botorl-agent-v2"
FORMATS = ("botorl-agent-v1", FORMAT)
AGENT_LIMIT = 1 << 36  # bytes of one agent file: a population of large agents, far under any real one


def save(path: str | os.PathLike, agent) -> Path:
    state = jax.tree_util.tree_map(np.asarray, serialization.to_state_dict(agent))
    state_bytes = serialization.msgpack_serialize(state)
    payload = {
        "format": FORMAT,
        "agent_class": type(agent).__name__,
        "config": json.dumps(dataclasses.asdict(agent.config), sort_keys=True, default=str),
        "state_msgpack": state_bytes,
        "sha256": hashlib.sha256(state_bytes).hexdigest(),
    }
    return atomic_write_bytes(path, serialization.msgpack_serialize(payload))  # makes the parent folders too


def load(path: str | os.PathLike, like):
    """Restore the agent saved at ``path`` into the structure of the template ``like``."""
    path = Path(path)
    if not path.is_file():
        raise DataFormatError(f"checkpoint {path} does not exist; give the path of a file written by botorl.agents.agent_file.save.")
    try:
        # a regular file only (no link, FIFO or device), and not more than a population's agents hold
        payload = serialization.msgpack_restore(read_bounded_bytes(path, AGENT_LIMIT))
    except Exception as err:  # truncated / not msgpack
        raise DataFormatError(
            f"checkpoint {path} cannot be read ({type(err).__name__}: {err}); the file is damaged or not a botorl "
            f"checkpoint. Use an earlier checkpoint of the run or retrain."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") not in FORMATS:
        raise DataFormatError(f"{path} is not a botorl agent checkpoint (expected format tag {FORMAT!r}).")
    if payload["format"] == FORMAT:
        raw = payload.get("state_msgpack")
        if not isinstance(raw, bytes) or hashlib.sha256(raw).hexdigest() != payload.get("sha256"):
            raise DataFormatError(
                f"checkpoint {path} fails its sha256 check: the file changed after it was written. Use an "
                f"earlier checkpoint of the run (`botorl resume RUN_DIR --from NAME`) or retrain."
            )
        try:
            payload["state"] = serialization.msgpack_restore(raw)
        except Exception as err:
            raise DataFormatError(f"checkpoint {path}: state cannot be decoded ({type(err).__name__}).") from None
    elif "state" not in payload:
        raise DataFormatError(f"{path} is not a botorl agent checkpoint (no state).")
    if payload["agent_class"] != type(like).__name__:
        raise DataFormatError(
            f"checkpoint {path} holds a {payload['agent_class']}, but the template is a {type(like).__name__}; "
            f"build the template with the same agent class and config as the saved run."
        )
    state = payload["state"]
    # Shapes only: a fresh template holds Python ints (step 0) where a trained agent has int32.
    want = jax.tree_util.tree_map(np.shape, serialization.to_state_dict(like))
    try:
        got = jax.tree_util.tree_map(np.shape, state)
        same = jax.tree_util.tree_structure(want) == jax.tree_util.tree_structure(got) and want == got
    except Exception:
        same = False
    if not same:
        raise DataFormatError(
            f"checkpoint {path} does not match the template agent (network sizes, ensemble size or optimiser "
            f"differ). Saved config: {payload['config']}. Build the template from that config."
        )
    # Device arrays with the saved dtypes, like the agent that was saved.
    return jax.tree_util.tree_map(jax.numpy.asarray, serialization.from_state_dict(like, state))
