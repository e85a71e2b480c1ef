"""Normal flow: VecKM-style O(N) local event encoder + small head, plane-fit baseline, ONNX.

Public API::

    from evseg.veckm_flow import (EncodingConfig, encode_targets, encode_targets_looks, select_targets, FlowHead,
                                  PlaneFitNormalFlow, OnnxNormalFlow, NormalFlow,
                                  head_output_to_flow, flow_to_head_units, load_head_checkpoint,
                                  FastEdges, SlowEdges)

``FlowHead`` / ``load_head_checkpoint`` (torch) and ``OnnxNormalFlow`` (onnxruntime) are imported
lazily, so ``import evseg.veckm_flow`` and the ONNX inference path never import torch.
"""

from evseg.veckm_flow.baseline import PlaneFitNormalFlow, plane_fit_normal_flow, time_surface
from evseg.veckm_flow.encoding import EncodingConfig, encode_targets, encode_targets_looks, encoding_matrix
from evseg.veckm_flow.result import NormalFlow, flow_to_head_units, head_output_to_flow
from evseg.veckm_flow.targets import select_targets

_LAZY = {
    "FlowHead": "evseg.veckm_flow.model",
    "build_head": "evseg.veckm_flow.model",
    "load_head_checkpoint": "evseg.veckm_flow.model",
    "save_head_checkpoint": "evseg.veckm_flow.model",
    "OnnxNormalFlow": "evseg.veckm_flow.inference",
    "FastEdges": "evseg.veckm_flow.fast_edges",
    "SlowEdges": "evseg.veckm_flow.slow_edges",
}

__all__ = [
    "EncodingConfig", "encode_targets", "encode_targets_looks", "encoding_matrix", "select_targets", "NormalFlow",
    "head_output_to_flow", "flow_to_head_units", "PlaneFitNormalFlow", "plane_fit_normal_flow",
    "time_surface", *_LAZY,
]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'evseg.veckm_flow' has no attribute {name!r}")
