"""Motion segmentation of normal flow (the paper's contribution, sections III-B to III-D).

>>> from evseg.segmentation import SegmentationConfig, segment_normal_flow, propagate_labels
>>> # result = segment_normal_flow(x, y, t, nx, ny, sensor_size=(346, 260))

Modules, one idea each: :mod:`.config` (parameters, YAML presets), :mod:`.preprocessing`
(nodes, Delaunay graph), :mod:`.motion_model` (affine model, normal-flow residual),
:mod:`.fitting` (batched least squares and Levenberg-Marquardt in torch), :mod:`.energy`
(data term, Potts, label cost), :mod:`.expansion` (alpha-expansion with label costs),
:mod:`.initialization` (fast sampling, motion prediction), :mod:`.window` (what a window's
flow alone gives: graph, per-node terms, sampled candidates), :mod:`.solver` (alternation),
:mod:`.outputs` (boxes, masks, label propagation), :mod:`.evaluate`, :mod:`.bench`.
"""

from evseg.segmentation.config import SegmentationConfig, load_segmentation_config
from evseg.segmentation.solver import SegmentationResult, propagate_labels, segment_normal_flow, segment_prepared
from evseg.segmentation.window import PreparedWindow, prepare_window

__all__ = [
    "PreparedWindow",
    "SegmentationConfig",
    "SegmentationResult",
    "load_segmentation_config",
    "prepare_window",
    "propagate_labels",
    "segment_normal_flow",
    "segment_prepared",
]
