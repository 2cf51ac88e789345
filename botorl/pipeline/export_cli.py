"""``botorl export RUN_DIR [--checkpoint NAME] [--format onnx] [--out FILE] [--force]``.

The run's deterministic policy as an ONNX model and its contract ``FILE.json``
(botorl/pipeline/export.py; the docs' Deploy a policy page). Exit 0: written and verified;
1: the written model does not act as ``botorl.load_policy`` (the gap is named); 2: bad input,
or the export extra is not installed.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

_Flag = tyro.conf.FlagCreatePairsOff[bool]


@dataclass
class ExportArgs:
    """Export a run's policy to ONNX, with its contract (FILE.json), verified against
    `botorl.load_policy` with onnxruntime before it exits. Needs the export extra:
    pip install "botorl[export]"."""

    dir: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_DIR")]
    """the run directory (the --out of `botorl run`)"""
    checkpoint: Annotated[str | None, tyro.conf.arg(metavar="NAME", help_behavior_hint="(default: the latest)")] = None
    """checkpoint folder name in RUN_DIR/checkpoints"""
    format: Literal["onnx"] = "onnx"
    """the model format"""
    out: Annotated[str | None, tyro.conf.arg(metavar="FILE", help_behavior_hint="(default: RUN_DIR/policy.onnx)")] = None
    """the model file; its contract is FILE.json"""
    force: _Flag = False
    """overwrite FILE and FILE.json if they exist"""


def main(argv: list[str]) -> int:
    args = tyro.cli(ExportArgs, args=argv, prog="botorl export")
    from botorl.pipeline.export import contract_path, export_policy

    out = Path(args.out) if args.out else Path(args.dir) / "policy.onnx"
    c = export_policy(args.dir, out, checkpoint=args.checkpoint, format=args.format, force=args.force)
    v = c["verification"]
    print(f"botorl: {c['task']} {c['method']} seed {c['seed']}, checkpoint {c['checkpoint']} (step {c['step']}) "
          f"-> {out} and {contract_path(out).name}", file=sys.stderr)
    print(f"model          {out}\ncontract       {contract_path(out)}\nobservations   (batch, {c['input']['shape'][1]}) "
          f"float32\nactions        (batch, {c['output']['shape'][1]}) float32\nverified       max |onnxruntime - "
          f"load_policy| = {v['max_abs_gap']:.2g} on {v['observations']} {v['source']} observations "
          f"(tolerance {v['tolerance']:g})\nsha256         {c['sha256']}")
    return 0
