"""Export a trained normal-flow head to ONNX for ``evseg flow`` / ``OnnxNormalFlow``.

CHECKPOINT is a Lightning ``.ckpt`` written by ``evseg train`` (hyper-parameters ``encoding``
and ``head``, weights under ``head.``) or the plain form of
:func:`evseg.veckm_flow.model.save_head_checkpoint`. The ONNX file holds the head (opset 17,
or ``--opset`` 9-20; dynamic number of targets) and, in its metadata, the encoding constants and
random matrix, so it is all inference needs. After writing, the export is checked: torch and
onnxruntime outputs are compared on a synthetic slice (max abs difference printed; must be
below ``--tolerance``, > 0). A checkpoint with NaN or infinite weights is refused first.
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "export a trained normal-flow checkpoint to ONNX (with encoding metadata and a parity check)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", type=Path, help="Lightning .ckpt (evseg train) or plain head checkpoint")
    p.add_argument("--out", type=Path, required=True, help="output .onnx")
    p.add_argument("--opset", type=int, default=17, help="ONNX opset (9-20)")
    p.add_argument("--tolerance", type=float, default=1e-4,
                   help="max abs difference torch vs onnxruntime on the check slice (head units; > 0)")
    p.add_argument("--note", default=None, help="free text stored in the metadata (evseg.note)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from evseg.errors import EvsegError, ModelError
    from evseg.export import export_onnx, parity
    from evseg.export.onnx import check_opset, non_finite_parameters
    from evseg.io._atomic import atomic_path
    from evseg.io.output_paths import check_output_path
    from evseg.veckm_flow import encode_targets, load_head_checkpoint, select_targets
    from evseg.veckm_flow.synthetic import translating_edges

    check_output_path(args.out, "--out", (".onnx",), [("the checkpoint", args.checkpoint)])
    check_opset(args.opset, "--opset")
    check_tolerance(args.tolerance)
    head, cfg = load_head_checkpoint(args.checkpoint)
    bad = non_finite_parameters(head)
    if bad:
        raise ModelError(f"{args.checkpoint}: non-finite weights in the checkpoint (NaN or infinity in "
                         f"{', '.join(bad[:3])}); its training run diverged: export an earlier checkpoint")
    extra = {"checkpoint": args.checkpoint.name}
    if args.note:
        extra["note"] = args.note
    scene = translating_edges(n_edges=10, seed=12345)
    targets = select_targets(scene.events, scene.sensor_size, cell_px=2)
    feats = encode_targets(scene.events, targets, scene.sensor_size, cfg)
    # The parity check runs on a temporary file: a model that fails it never replaces a
    # model already at --out.
    with atomic_path(args.out) as tmp:
        try:
            export_onnx(head, cfg, tmp, opset=args.opset, extra_metadata=extra)
            diff = parity(head, cfg, tmp, feats)
        except EvsegError as exc:
            # The temporary file's name means nothing to the user: name --out.
            raise type(exc)(str(exc).replace(str(tmp), str(args.out))) from None
        if not np.isfinite(diff) or diff > args.tolerance:
            raise ModelError(f"{args.out}: onnxruntime differs from torch by {diff:.3g} (> --tolerance "
                             f"{args.tolerance}); nothing written")
    n_params = sum(int(p.numel()) for p in head.parameters())
    print(
        f"{args.out}: FlowHead({head.kwargs()}) {n_params} parameters, encoding {cfg.to_dict()}, "
        f"opset {args.opset}; parity on {len(feats)} targets: max |torch - onnxruntime| = {diff:.2g}"
    )
    return 0


def check_tolerance(tolerance: float) -> None:
    """``--tolerance`` must be a finite number > 0 (head units): 0 or less would refuse every
    model, NaN would pass every one."""
    import math

    from evseg.errors import ConfigError

    if not math.isfinite(tolerance) or tolerance <= 0:
        raise ConfigError(f"--tolerance {tolerance}: must be a number > 0 (max |torch - onnxruntime| in head "
                          "units; default 1e-4)")
