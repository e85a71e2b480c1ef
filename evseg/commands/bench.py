"""Benchmarks: time a pipeline stage and write a markdown table.

Each target is a function ``benchmark(repeats: int, quick: bool) -> list[dict]`` in the
stage's own package (those in ``MODEL_TARGETS`` also take ``model_path``, from ``--model``);
every row names its input size (events, nodes, targets) and reports medians over ``repeats``
runs. This command only formats and writes the table.
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import sys
from pathlib import Path

from evseg.errors import EvsegError

HELP = "time a pipeline stage (median over repeated runs) and write a markdown table"

# target -> "module:function"; each function returns a list of row dicts (same keys).
TARGETS = {
    "io": "evseg.io.bench:benchmark",
    "sim": "evseg.simulator.bench:benchmark",
    "flow": "evseg.veckm_flow.bench:benchmark",
    "seg": "evseg.segmentation.bench:benchmark",
    "pipeline": "evseg.pipeline_bench:benchmark",
    "live": "evseg.live_bench:benchmark",
    "memory": "evseg.memory_bench:benchmark",
    "scaling": "evseg.scaling_bench:benchmark",
}


TARGET_HELP = {
    "io": "reader throughput per file format (events/s, file size; 640x480 at ~1 M events/s)",
    "sim": "simulator wall time per scene preset",
    "flow": "normal flows/s of the learned flow and the plane fit, encoding/network split, scaling with "
            "events per slice",
    "seg": "segmentation core per stage (initialization, labeling and fitting) against node and candidate count",
    "pipeline": "whole pipeline per stage, median and p90 ms per window, events/s, real-time factor (simulated "
                "0.3/1/3 M events/s streams and the shared real recordings)",
    "live": "live replay at the sensor's pace: windows segmented vs dropped, label latency",
    "memory": "peak RSS of evseg segment streaming long recordings from disk",
    "scaling": "time per window against the event rate (0.1-5 M events/s), growth exponent",
}
"""One line per target for ``evseg bench --help``."""

# Targets whose function takes ``model_path`` (a normal-flow ONNX file; default the shipped one).
MODEL_TARGETS = ("flow",)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", choices=sorted(TARGETS),
                   help="what to time: " + "; ".join(f"{t}: {TARGET_HELP[t]}" for t in sorted(TARGETS)))
    p.add_argument("--repeats", type=int, default=5, help="timed runs per row (median reported)")
    p.add_argument("--quick", action="store_true", help="fewer and smaller inputs (smoke run)")
    p.add_argument("--out", type=Path, default=None, help="write the markdown table here too")
    p.add_argument("--model", type=Path, default=None,
                   help=f"normal-flow ONNX model (evseg export) instead of the shipped one; targets: {', '.join(MODEL_TARGETS)}")


def model_options(args: argparse.Namespace, model_targets: tuple[str, ...]) -> dict:
    """``{"model_path": ...}`` for a target that takes ``--model`` (checked up front, so a bad
    file fails before a long run), ``{}`` without ``--model``."""
    if args.model is None:
        return {}
    if args.target not in model_targets:
        raise EvsegError(f"--model applies to {', '.join(model_targets)}, not to '{args.target}'")
    from evseg.veckm_flow.inference import read_model_metadata

    read_model_metadata(args.model)  # ModelError naming the file if it is not a normal-flow model
    return {"model_path": args.model}


def speed_reference_ms(repeats: int = 5) -> float:
    """Median wall time (ms) of a fixed single-threaded workload: 2,000 small numpy operations
    (the per-call overhead most of the pipeline pays) and a sort of 200,000 floats.

    Shared and virtual machines change speed between days; the same code's timings compare
    across tables only together with this figure (lower = faster machine).
    """
    import time

    import numpy as np

    a = np.random.default_rng(0).random(1000)
    big = np.random.default_rng(1).random(200_000)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        acc = a
        for _ in range(1000):
            acc = np.maximum(acc * 0.999, a) + 1e-9
        np.sort(big, kind="stable")
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))


NUMERIC_PACKAGES = ("numpy", "numba", "onnxruntime", "torch", "PyMaxflow")
"""Packages whose builds decide the floating-point results (and speed) of the figures."""


def library_versions(packages: tuple[str, ...] = NUMERIC_PACKAGES) -> str:
    """``name version`` of each installed package, read from its metadata (nothing is imported).

    >>> library_versions(("numpy", "no-such-package")).startswith("numpy ")
    True
    """
    from importlib import metadata

    found = []
    for name in packages:
        try:
            found.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return ", ".join(found)


def host_cpu() -> str:
    """The CPU model LLVM compiles the encoder's kernels for (e.g. ``znver4``), or the platform's
    processor name when llvmlite is missing."""
    try:
        import llvmlite.binding as llvm

        return str(llvm.get_host_cpu_name())
    except Exception:  # llvmlite absent or unable to query the host: say what platform knows
        return platform.processor() or platform.machine()


def machine_line() -> str:
    """First line of every bench and eval table. Besides the speed reference it names the CPU
    model and the numeric libraries' versions: the same code gave a label or two differently
    on another day (README, *Robustness*), and those are what can differ between installs."""
    threads = os.environ.get("OMP_NUM_THREADS", "default")
    return (
        f"machine: {platform.processor() or platform.machine()} ({host_cpu()}), {os.cpu_count()} cores, "
        f"Python {platform.python_version()}, {library_versions()}, OMP_NUM_THREADS={threads}, "
        f"speed reference {speed_reference_ms():.1f} ms (lower = faster; `speed_reference_ms` in "
        f"evseg/commands/bench.py)"
    )


def markdown_table(rows: list[dict]) -> str:
    """Format rows of equal keys as a markdown table (floats with 3 significant digits)."""
    if not rows:
        return "(no rows)\n"
    keys = list(rows[0])

    def fmt(v) -> str:
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:,.0f}"
        return str(v)

    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def resolve_target(kind: str, targets: dict[str, str], name: str):
    """The function behind ``targets[name]`` ("module:function"), imported on demand."""
    module, func = targets[name].split(":")
    try:
        return getattr(importlib.import_module(module), func)
    except ModuleNotFoundError as exc:
        raise EvsegError(f"{kind} '{name}' is not available in this build ({exc})") from None


def check_table_out(args: argparse.Namespace) -> None:
    """Check ``--out`` before the run: a run of minutes must not end in an error about where
    its table goes (nor write it over the ``--model`` it ran)."""
    if args.out is not None:
        from evseg.io.output_paths import check_output_path

        check_output_path(args.out, "--out", (), [("the model (--model)", getattr(args, "model", None))])


def emit_table(rows: list[dict], out: Path | None, notes: tuple[str, ...] = ()) -> None:
    """Print the machine line, ``notes`` (one line each, e.g. the model evaluated) and the
    table; also write them to ``out`` (atomically)."""
    from evseg.io._atomic import atomic_path

    head = "\n\n".join([machine_line(), *notes])
    text = f"{head}\n\n{markdown_table(rows)}"
    sys.stdout.write(text)
    if out is not None:
        with atomic_path(out) as tmp:
            tmp.write_text(text)


def run(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise EvsegError(f"--repeats must be at least 1, got {args.repeats}")
    fn = resolve_target("benchmark", TARGETS, args.target)
    check_table_out(args)
    emit_table(fn(repeats=args.repeats, quick=args.quick, **model_options(args, MODEL_TARGETS)), args.out)
    return 0
