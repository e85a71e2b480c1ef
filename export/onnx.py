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
        opset: ONNX opset (pinned default 17).
        extra_metadata: more ``evseg.<key>`` metadata (e.g. training run, seed, accuracy).
    """
    import onnx
    import torch

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
