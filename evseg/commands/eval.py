"""Accuracy evaluation: run a stage on held-out simulated scenes and write a markdown table.

Each target is a function ``evaluate(quick: bool) -> list[dict]`` in the stage's package,
returning one row per scene (or preset) and a final summary row. Simulated scenes for
evaluation use seeds >= 1000; training only ever sees seeds < 1000.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

from evseg.commands.bench import machine_line, markdown_table
from evseg.errors import EvsegError

HELP = "evaluate accuracy on held-out simulated scenes and write a markdown table"

# target -> "module:function" returning a list of row dicts (same keys).
TARGETS = {
    "seg": "evseg.segmentation.evaluate:evaluate_oracle",
    "flow": "evseg.train.evaluate:evaluate_flow",
    "flow-real": "evseg.train.evaluate:evaluate_flow_real",
    "pipeline": "evseg.pipeline_eval:evaluate_pipeline",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", choices=sorted(TARGETS), help="what to evaluate")
    p.add_argument("--quick", action="store_true", help="fewer and shorter scenes (smoke run)")
    p.add_argument("--out", type=Path, default=None, help="write the markdown table here too")


def run(args: argparse.Namespace) -> int:
    module, func = TARGETS[args.target].split(":")
    try:
        fn = getattr(importlib.import_module(module), func)
    except ModuleNotFoundError as exc:
        raise EvsegError(f"evaluation '{args.target}' is not available in this build ({exc})") from None
    rows = fn(quick=args.quick)
    text = f"{machine_line()}\n\n{markdown_table(rows)}"
    sys.stdout.write(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_suffix(args.out.suffix + ".tmp")
        tmp.write_text(text)
        tmp.replace(args.out)
    return 0
