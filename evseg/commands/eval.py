"""Accuracy evaluation: run a stage on held-out simulated scenes (or, for ``flow-real`` and
``pipeline-real``, on the shared real recordings) and write a markdown table.

Each target is a function ``evaluate(quick: bool) -> list[dict]`` in the stage's package
(those in ``MODEL_TARGETS`` also take ``model_path``, from ``--model``), returning one row per
scene (or preset) and a final summary row. Simulated scenes for
evaluation use seeds >= 1000; training only ever sees seeds < 1000.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg.commands.bench import check_table_out, emit_table, model_options, resolve_target
from evseg.errors import EvsegError
# The evaluations' seed ranges: seeds below FIRST_VALIDATION_SEED are where training configs
# draw their scenes (the shipped model's: SHIPPED_MODEL_TRAIN_SEEDS), so --seeds refuses them for
# the targets that run a trained model; from FIRST_HELD_OUT_SEED on they are the published
# tables' (the default).
from evseg.train.evaluate import HELD_OUT_SEED_START as FIRST_HELD_OUT_SEED
from evseg.train.evaluate import SHIPPED_MODEL_TRAIN_SEEDS
from evseg.train.evaluate import VALIDATION_SEED_START as FIRST_VALIDATION_SEED

HELP = "evaluate accuracy on held-out simulated scenes and write a markdown table"

# target -> "module:function" returning a list of row dicts (same keys).
TARGETS = {
    "seg": "evseg.segmentation.evaluate:evaluate_oracle",
    "flow": "evseg.train.evaluate:evaluate_flow",
    "flow-real": "evseg.train.evaluate:evaluate_flow_real",
    "pipeline": "evseg.pipeline_eval:evaluate_pipeline_and_oracle",
    "pipeline-real": "evseg.pipeline_real:evaluate_pipeline_real",
    "static": "evseg.pipeline_eval:evaluate_static_camera",
    "live": "evseg.live_eval:evaluate_live",
    "flow-errors": "evseg.flow_errors_eval:evaluate_flow_errors",
}

TARGET_HELP = {
    "seg": "segmentation core fed ground-truth normal flow (detection, IoU, object count; clean and with 30 %% "
           "outlier flows)",
    "flow": "learned normal flow against the plane fit on simulated scenes (angular error, sign, uncertainty)",
    "flow-real": "label-free warp sharpness of both flows on the shared real recordings",
    "pipeline": "end to end with the learned flow (detection, IoU, false objects), with the ground-truth-flow rows",
    "pipeline-real": "end to end on the shared real recordings (EED ball, false objects on one-motion scenes)",
    "static": "still-camera scenes, default settings against the static_camera preset",
    "live": "live replay at the sensor's pace: windows segmented and their accuracy",
    "flow-errors": "which error of the learned flow costs detection (learned/ground-truth hybrids)",
}
"""One line per target for ``evseg eval --help``."""

# Targets whose function takes ``model_path`` (a normal-flow ONNX file; default the shipped one).
MODEL_TARGETS = ("flow", "flow-real", "pipeline", "flow-errors")

# Targets whose function takes ``mirrors`` (the learned flow's mirror looks, ``evseg flow --mirrors``).
MIRRORS_TARGETS = ("flow", "flow-real", "pipeline", "pipeline-real", "static")

# Targets whose function takes ``tracked_mirrors`` (PipelineConfig's, ``evseg segment --tracked-mirrors``).
TRACKED_MIRRORS_TARGETS = ("pipeline", "pipeline-real", "static")

# Targets whose function takes ``slow_edges`` (the pipeline's learned flow with the slow-edge look).
SLOW_EDGES_TARGETS = ("pipeline", "pipeline-real", "static")

# Targets whose function takes ``seeds`` (simulated scenes), ``presets`` (a subset of the
# simulator presets) and ``overrides`` (segmentation fields set on every preset it uses).
SEEDS_TARGETS = ("seg", "pipeline", "flow-errors", "static", "flow")
PRESETS_TARGETS = ("seg", "pipeline", "flow-errors", "flow")
OVERRIDES_TARGETS = ("seg", "pipeline", "flow-errors", "static", "pipeline-real")

# Targets that run the shipped normal-flow model on simulated scenes: seeds below the
# validation range were its training scenes.
LEARNED_FLOW_SEED_TARGETS = ("pipeline", "flow-errors", "static", "flow")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("target", choices=sorted(TARGETS),
                   help="what to evaluate: " + "; ".join(f"{t}: {TARGET_HELP[t]}" for t in sorted(TARGETS)))
    p.add_argument("--quick", action="store_true", help="fewer and shorter scenes (smoke run)")
    p.add_argument("--out", type=Path, default=None, help="write the markdown table here too")
    p.add_argument("--model", type=Path, default=None,
                   help=f"normal-flow ONNX model (evseg export) instead of the shipped one; targets: {', '.join(MODEL_TARGETS)}")
    p.add_argument("--slow-edges", action="store_true",
                   help="the pipeline's learned flow with the slow-edge look (PipelineConfig.slow_edges); "
                        f"targets: {', '.join(SLOW_EDGES_TARGETS)}")
    p.add_argument("--mirrors", type=int, choices=[1, 2, 4, 8], default=1,
                   help="the learned flow averaged over this many mirror images of each slice (evseg flow "
                        f"--mirrors); targets: {', '.join(MIRRORS_TARGETS)}")
    p.add_argument("--tracked-mirrors", type=int, choices=[1, 2, 4, 8], default=1,
                   help="the pipeline's learned flow with this many mirror looks inside the boxes the object "
                        f"tracks predict (evseg segment --tracked-mirrors); targets: {', '.join(TRACKED_MIRRORS_TARGETS)}")
    p.add_argument("--seeds", default=None, metavar="SEEDS",
                   help="scene seeds instead of the held-out ones, e.g. 900-909 or 900,905 (validation: "
                        f"choose settings on these, never on the held-out seeds >= 1000); targets: {', '.join(SEEDS_TARGETS)}")
    p.add_argument("--presets", default=None, metavar="NAMES",
                   help="only these simulator presets, comma-separated (e.g. eed_like,ego_only); "
                        f"targets: {', '.join(PRESETS_TARGETS)}")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="a segmentation parameter set on every preset (SegmentationConfig field, YAML value; "
                        f"repeatable), e.g. --set lambda_m=60; targets: {', '.join(OVERRIDES_TARGETS)}")


def run(args: argparse.Namespace) -> int:
    fn = resolve_target("evaluation", TARGETS, args.target)
    options = model_options(args, MODEL_TARGETS)
    if args.slow_edges:
        options["slow_edges"] = _only_for(args.target, "--slow-edges", SLOW_EDGES_TARGETS, True,
                                          "evseg eval flow measures the estimator with the look already")
    if args.mirrors != 1:
        options["mirrors"] = _only_for(args.target, "--mirrors", MIRRORS_TARGETS, args.mirrors,
                                       "it evaluates ground-truth flow")
    if args.tracked_mirrors != 1:
        options["tracked_mirrors"] = _only_for(args.target, "--tracked-mirrors", TRACKED_MIRRORS_TARGETS,
                                               args.tracked_mirrors, "it has no object tracks")
    if args.seeds is not None:
        seeds = _only_for(args.target, "--seeds", SEEDS_TARGETS, parse_seeds(args.seeds),
                          "it runs fixed scenes or recordings")
        check_seed_choice(seeds, args.target, args.model)
        options["seeds"] = seeds
    if args.presets is not None:
        options["presets"] = _only_for(args.target, "--presets", PRESETS_TARGETS,
                                       [p.strip() for p in args.presets.split(",") if p.strip()],
                                       "it runs fixed scenes or recordings")
    if args.overrides:
        options["overrides"] = _only_for(args.target, "--set", OVERRIDES_TARGETS, parse_overrides(args.overrides),
                                         "it segments nothing")
    check_table_out(args)
    # Tables of several trained models side by side must say which is which.
    notes = (f"normal-flow model: {args.model}",) if "model_path" in options else ()
    emit_table(fn(quick=args.quick, **options), args.out, notes)
    return 0


def _shipped_seeds() -> str:
    start, stop = SHIPPED_MODEL_TRAIN_SEEDS
    return f"{start}-{stop - 1}"


def check_seed_choice(seeds: list[int], target: str, model: Path | None) -> None:
    """Refuse ``--seeds`` whose figures would mislead (:class:`EvsegError`, one line):

    - seeds below :data:`FIRST_VALIDATION_SEED` for a target that runs a trained normal-flow
      model (``model``: the user's ``--model``, None: the shipped one), where training
      scenes are drawn;
    - validation seeds mixed with held-out ones (>= :data:`FIRST_HELD_OUT_SEED`): a
      comparison would then be tuned on part of the published tables' scenes.

    >>> check_seed_choice([900, 901], "flow", None)
    """
    low = [s for s in seeds if s < FIRST_VALIDATION_SEED]
    if target in LEARNED_FLOW_SEED_TARGETS and low:
        if model is None:
            whose = f"the shipped normal-flow model was trained on scene seeds {_shipped_seeds()}"
        else:
            whose = (f"training configs draw their scenes there (data.train_seeds; the shipped model's: "
                     f"{_shipped_seeds()}), so {model} may have been trained on them")
        raise EvsegError(f"--seeds: {low[:5]} are below {FIRST_VALIDATION_SEED}; {whose}: use validation "
                         f"seeds (900-999) or the held-out ones (>= {FIRST_HELD_OUT_SEED}, the default)")
    held_out = [s for s in seeds if s >= FIRST_HELD_OUT_SEED]
    if held_out and len(held_out) < len(seeds):
        raise EvsegError(f"--seeds: mixes held-out seeds ({held_out[:5]}, >= {FIRST_HELD_OUT_SEED}) with others; "
                         f"compare settings and models on validation seeds only ({FIRST_VALIDATION_SEED}-"
                         f"{FIRST_HELD_OUT_SEED - 1}), the held-out ones are for the published tables (the "
                         "default without --seeds)")


def parse_seeds(text: str) -> list[int]:
    """Scene seeds from ``"900-909"`` (inclusive), ``"900,905"`` or a mix (``"900-902,950"``).

    >>> parse_seeds("900-902,950")
    [900, 901, 902, 950]
    """
    seeds: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            a = int(lo)
            b = int(hi) if sep else a
        except ValueError:
            raise EvsegError(f"--seeds: '{part.strip()}' is not a seed or a range A-B (e.g. 900-909)") from None
        if b < a:
            raise EvsegError(f"--seeds: range '{part.strip()}' runs backwards")
        seeds += range(a, b + 1)
    if not seeds or min(seeds) < 0 or len(set(seeds)) != len(seeds):
        raise EvsegError(f"--seeds: '{text}' must name distinct non-negative seeds")
    return seeds


def parse_overrides(items: list[str]) -> dict:
    """``["lambda_m=60", "mask_method=hull"]`` -> ``{"lambda_m": 60, "mask_method": "hull"}``
    (values parsed as YAML; field names are checked by the evaluation, before any scene runs).

    >>> parse_overrides(["lambda_m=60", "occlusion_gap_px=24.5"])
    {'lambda_m': 60, 'occlusion_gap_px': 24.5}
    """
    import yaml

    out = {}
    for item in items:
        field, sep, value = item.partition("=")
        if not sep or not field.strip() or not value.strip():
            raise EvsegError(f"--set: expected FIELD=VALUE, got '{item}'")
        try:
            out[field.strip()] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise EvsegError(f"--set: cannot read the value of '{item}'") from None
    return out


def _only_for(target: str, flag: str, targets: tuple[str, ...], value, why: str):
    """``value`` when ``target`` is one of ``targets``, else a one-line error naming ``flag``."""
    if target not in targets:
            raise EvsegError(f"{flag} applies to {', '.join(targets)}, not to '{target}' ({why})")
    return value
