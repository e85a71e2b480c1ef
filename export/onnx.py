"""ONNX export of the normal-flow head with everything needed to rebuild its encoder.

The exported graph is the head only (the O(N) encoding runs in numpy/numba, see
:mod:`evseg.veckm_flow.encoding`): input ``features`` float32 ``(T, levels (2 d + 1))``, output
``head_out`` float32 ``(T, 3)``, ``T`` dynamic. Opset pinned to 17. The encoding constants and
the random matrix go into ``metadata_props`` (format in :mod:`evseg.veckm_flow.inference`).
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np

from evseg.veckm_flow.encoding import EncodingConfig, encoding_matrix
from evseg.veckm_flow.inference import FORMAT

OPSET = 17

MIN_OPSET, MAX_OPSET = 9, 20
"""ONNX opsets :func:`export_onnx` accepts: torch's TorchScript exporter writes 7-20, below 9 it
warns that the graph may be invalid (and onnxruntime has no Gemm kernel for opset 5), above 20
it is not supported (torch.onnx ``ONNX_TORCHSCRIPT_EXPORTER_MAX_OPSET``)."""


def check_opset(opset, option: str = "opset") -> int:
    """``opset`` as an int when :func:`export_onnx` can write it (:data:`MIN_OPSET` to
    :data:`MAX_OPSET`); else a :class:`~evseg.errors.ConfigError` naming ``option``.

    >>> check_opset(17)
    17
    """
    from evseg.checks import is_whole
    from evseg.errors import ConfigError

    if not is_whole(opset) or not MIN_OPSET <= opset <= MAX_OPSET:
        raise ConfigError(f"{option} {opset}: the ONNX exporter writes opsets {MIN_OPSET}-{MAX_OPSET} "
                          f"(the shipped model uses {OPSET})")
    return int(opset)


def non_finite_parameters(module) -> list[str]:
    """Names of the parameters of a torch ``module`` that hold NaN or infinity (a diverged
    training run); empty when all are finite."""
    import torch

    return [name for name, p in module.named_parameters() if not bool(torch.isfinite(p).all())]


def model_metadata(cfg: EncodingConfig, head_kwargs: dict, extra: dict | None = None) -> dict[str, str]:
    """The ``metadata_props`` written into an exported model (all values strings)."""
    meta = {
        "evseg.format": FORMAT,
        "evseg.encoding": json.dumps(cfg.to_dict(), sort_keys=True),
        # repr-exact floats: the matrix is stored, not re-drawn from the seed at load time.
        "evseg.matrix": json.dumps(encoding_matrix(cfg).tolist()),
        "evseg.flow_unit_px_s": repr(cfg.flow_unit_px_s),
        "evseg.head": json.dumps(head_kwargs, sort_keys=True),
        "evseg.output": "head_out[:, 0:2] normal flow in units of xy_scale_px px per t_scale_us us; head_out[:, 2] log of predicted angular error (rad)",
    }
    for k, v in (extra or {}).items():
        meta[f"evseg.{k}"] = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    return meta


def export_onnx(head, cfg: EncodingConfig, path: str | Path, opset: int = OPSET, extra_metadata: dict | None = None) -> Path:
    """Write ``head`` (a :class:`~evseg.veckm_flow.FlowHead`) to ``path`` as ONNX, atomically.

    Args:
        head: the torch head (put into eval mode; not modified otherwise).
        cfg: its encoding (stored in the metadata).
        path: output ``.onnx`` file.
        opset: ONNX opset (pinned default 17; :data:`MIN_OPSET` to :data:`MAX_OPSET`, else
            :class:`~evseg.errors.ConfigError`).
        extra_metadata: more ``evseg.<key>`` metadata (e.g. training run, seed, accuracy).
    """
    import onnx
    import torch

    opset = check_opset(opset)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    was_training = head.training
    head.eval()
    try:
        dummy = torch.zeros(2, cfg.n_features, dtype=torch.float32)
        with warnings.catch_warnings():
            # The TorchScript exporter is chosen on purpose (no onnxscript dependency, a plain
            # Gemm/Relu graph); silence its deprecation notice.
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(
                head, (dummy,), str(tmp), opset_version=int(opset), input_names=["features"],
                output_names=["head_out"], dynamic_axes={"features": {0: "targets"}, "head_out": {0: "targets"}},
                dynamo=False,
            )
    finally:
        head.train(was_training)
    model = onnx.load(str(tmp))
    kwargs = head.kwargs() if hasattr(head, "kwargs") else {}
    for k, v in model_metadata(cfg, kwargs, extra_metadata).items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    model.producer_name = "evseg"
    onnx.checker.check_model(model)
    onnx.save(model, str(tmp))
    tmp.replace(path)
    return path


def parity(head, cfg: EncodingConfig, onnx_path: str | Path, feats: np.ndarray) -> float:
    """Max absolute difference between torch and onnxruntime head outputs on ``feats`` (T, F)."""
    import torch

    from evseg.veckm_flow.inference import OnnxNormalFlow

    est = OnnxNormalFlow(onnx_path, threads=1)
    with torch.no_grad():
        ref = head.eval()(torch.from_numpy(np.asarray(feats, np.float32))).numpy()
    return float(np.abs(est.predict(feats) - ref).max()) if len(feats) else 0.0
