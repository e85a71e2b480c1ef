"""SegmentationConfig: every parameter of the segmentation, with units, and YAML loading.

The energy minimised per window (paper Eq. 10, method.md section 4) is

    E(L, M) = sum_k c_k * min((r_k / sigma)^2, tau^2)            data term
            + lambda_p * sum_{(i,j) in Delaunay} w_ij [L_i != L_j]  Potts smoothness
            + lambda_m * (number of labels in use)                  label cost

with r_k the |n|-normalised normal-flow residual in px/s (see :mod:`.motion_model`), sigma the
residual scale (px/s), tau the truncation (in units of sigma), c_k a per-node confidence from
the optional flow uncertainty and w_ij an optional distance weight of the graph edge. Data
costs are dimensionless (squared residuals in units of sigma), so lambda_p and lambda_m are
too: lambda_m is "how many sigma^2 of fitting error a new motion must save to exist".

Presets live in ``configs/segmentation/*.yaml`` (``eed_like``, ``evimo_like``,
``outdoor_like``); :func:`load_segmentation_config` reads a preset name or a YAML path and
rejects unknown keys with :class:`evseg.errors.ConfigError`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evseg.checks import is_whole
from evseg.errors import ConfigError, yaml_problem
from evseg.segmentation.preprocessing import CELL_RULES

_PRESET_DIR = Path(__file__).resolve().parents[1] / "configs" / "segmentation"

ROBUST_LOSSES = ("none", "huber", "cauchy", "truncated")
MASK_METHODS = ("hull", "dilate")
POTTS_WEIGHTINGS = ("uniform", "distance")
SAMPLING_FLOWS = ("local", "normal")
UNCERTAINTY_USES = ("confidence", "scale", "ignore")


@dataclass(frozen=True)
class SegmentationConfig:
    """All parameters of :func:`evseg.segmentation.segment_normal_flow` (units in comments).

    The defaults work without tuning on the simulated scene families (oracle flow) and are
    scale free where possible: the residual scale follows the median flow magnitude.
    """

    # --- pre-processing (nodes and graph) ---------------------------------------------
    cell_px: float = 3.0
    """Side of the square cell (px) that keeps one node; 3 px gives ~1.5 k nodes for a 10 ms
    window of a textured 346x260 scene. 0 keeps every flow (duplicate positions still merged)."""
    max_nodes: int | None = None
    """Node budget per window, None = no limit. When the flows occupy more cells than this, the
    cell grows (x 1.25 steps) until they do not (:func:`.preprocessing.node_cell_px`), and the
    label cost, ``split_gap_px`` and ``max_propagation_px`` follow the growth g (label cost / g,
    lengths x g). It bounds the work per window on large sensors at a cost in accuracy: on
    1280x720 simulated windows (oracle flow, ~53 k nodes at 3 px) a budget of 12,000 took the
    segmentation from 0.40 to 0.11 s and the detection rate from 0.97 to 0.88. A 346x260 sensor
    has ~10 k cells of 3 px, so budgets above that never change it."""
    cell_rule: str = "confirmed"
    """Which flow of a cell becomes its node: 'confirmed' = the most certain, then latest one
    that another flow of the cell agrees with (a lone stray flow is passed over),
    'preferred' = the most certain, then latest one (see :mod:`.preprocessing`)."""
    node_window_us: int | None = None
    """Only flows with t >= t_max - node_window_us become nodes (the latest slice of the
    window); None uses every flow given."""
    min_flow_px_s: float = 1.0
    """Flows slower than this (px/s) carry no usable direction and are dropped."""
    support_exponent: float = 0.25
    """A node's data term and fitting weight are multiplied by (s / median s)^support_exponent,
    clipped to [1/4, 4], s = the number of events in its cell (:func:`.preprocessing.cell_support`):
    a node stands for the events of its cell, so a small textured object whose few nodes each
    summarise ~20 events outweighs as many nodes of a sparse edge. 0 = every node weighs 1
    (the paper's downsampled energy). 0.25 chosen on validation seeds (docs/segmentation.md):
    exact flow, seeds 900-920: clean detection 0.957 -> 0.974, with 30 % outliers 0.934 ->
    0.941; learned flow, seeds 900-909: detection 68.5 -> 72.5 %, windows with a false object
    12.2 -> 13.7 % (ego-motion only 10.0 -> 9.7 %). 0.5 scored as well on exact flow but
    doubled the learned flow's false objects."""
    max_uncertainty: float | None = None
    """Flows with uncertainty above this are dropped (VecKM_flow uses 0.3 rad); None keeps all."""
    uncertainty_use: str = "scale"
    """How a flow's uncertainty enters the energy. 'confidence': the node's data term and
    fitting weight are multiplied by c = 1 / (1 + (uncertainty / uncertainty_scale)^2).
    'scale': the node's residual scale grows with the expected error of its flow,
    sigma_k = sqrt(sigma^2 + (uncertainty_gain * |n_k| * uncertainty_k)^2) (uncertainty an
    angular error in rad, as the shipped model predicts; |n| tan(err) ~ |n| err is the error it
    causes along the normal), and its fitting weight is (sigma / sigma_k)^2: an uncertain flow
    tolerates a larger residual but a gross outlier still costs tau^2, so fast objects, whose
    flows are the least certain, keep their pull. 'ignore': every node counts alike."""
    uncertainty_scale: float = 0.3
    """'confidence' mode: the uncertainty (same unit) at which the confidence is 1/2."""
    uncertainty_gain: float = 1.0
    """'scale' mode: multiplier of |n| * uncertainty in the node's residual scale."""
    uncertainty_angle_gain: float = 1.0
    """'scale' mode: the flow's angular uncertainty propagated through each motion model.
    A normal-flow direction off by delta changes node k's residual under model l by about
    delta * (h_k^perp . u_l(x_k)), the model's flow along the edge (h_k = n_k / |n_k|), so
    with a = uncertainty_angle_gain * uncertainty_k the cost becomes the Gaussian negative log
    likelihood r^2 / s_kl^2 + log(s_kl^2 / sigma_k^2), s_kl^2 = sigma_k^2 + (a h_k^perp .
    u_l(x_k))^2, truncated at tau^2 as before. Under a slow background model a fast object's
    uncertain flows keep their full residual (sigma_k alone); under a model that moves along
    the edge the same residual is tolerated, at the price of the log term. The fits keep the
    model-free weight (sigma / sigma_k)^2. 0 = off (the data term of 'scale' alone).
    Validation (learned flow, seeds 900-909 / 910-919, docs/segmentation.md): windows with a
    false object fall with these defaults and in the eed_like and evimo_like presets, for
    about the same detection; the outdoor_like and static_camera presets lost detection and
    set it to 0. It assumes the uncertainty is about as large as the flow's real error: for a
    flow more accurate than its stated uncertainty set 0."""
    origin_px: tuple[float, float] | None = None
    """Origin (column, row) in px of the affine model's x; None = sensor centre
    ((w-1)/2, (h-1)/2) when the sensor size is known, else (0, 0)."""

    # --- data term ---------------------------------------------------------------------
    residual_scale_px_s: float = 2.0
    """Floor of the residual scale sigma (px/s)."""
    residual_scale_rel: float = 0.06
    """sigma = max(residual_scale_px_s, residual_scale_rel * median |n| of the nodes,
    residual_scale_noise * ring noise): the residual scale follows the speed of the scene,
    so one setting serves slow indoor and fast outdoor data."""
    residual_scale_noise: float = 1.5
    """Gain on the window's measured flow noise in sigma (0 = not used): the ring noise is
    1.4826 x the median |n_hat . t_ring - |n|| over the nodes whose 1-ring translation is well
    conditioned, i.e. how far flows stray from their neighbourhood's translation (px/s).
    Exact flow gives ~1 px/s, a learned estimator ~10-15, so sigma adapts to the flow's
    quality instead of a fixed share of its speed. With 1.5 (and ``residual_scale_rel``
    0.06, both chosen on validation seeds 900-920) sigma is ~1.5 x 12 px/s for the shipped
    model's flow, close to the former 0.2 x median |n|, and a few px/s for exact flow."""
    truncation: float = 3.0
    """tau: a node's data cost saturates at tau^2 (residual beyond tau sigma = outlier)."""

    # --- smoothness and label cost -----------------------------------------------------
    lambda_p: float = 2.0
    """Potts weight per cut Delaunay edge (in sigma^2 units of the data term)."""
    potts_weighting: str = "distance"
    """'uniform': every edge weighs 1; 'distance': w = min(1, edge_scale_px / length), so
    long edges across empty space (between separate objects) are cheap to cut."""
    edge_scale_px: float = 12.0
    """Length (px) up to which a Delaunay edge has full Potts weight ('distance' weighting)."""
    lambda_m: float = 80.0
    """Label cost (Delong et al. 2012) paid once per motion model in use (sigma^2 units)."""
    contrast_min_weight: float = 0.85
    """Contrast-sensitive Potts on precise flow (beyond the paper, whose Potts weight is one
    constant): after round 0, an edge whose two nodes each fit some candidate but cost c more
    (sigma^2 units) when forced onto one common candidate has its Potts weight multiplied by
    max(contrast_min_weight, exp(-(c - 2) / 3)) for c > 2 (:func:`.energy.contrast_weights`):
    a boundary between two motions is cheaper to cut, so a small object whose few nodes all lie
    on its outline (a textureless ball: each node has ~3 background neighbours) still pays less
    Potts than it saves. Only for precise flow: the effect fades out as the window's relative
    flow noise (ring noise / median |n|) goes from contrast_max_noise / 2 to contrast_max_noise.
    1 disables. Chosen on validation seeds 900-920, ground-truth flow: detection 0.980 -> 0.981
    clean (IoU 0.902 -> 0.905), 0.947 -> 0.956 with 30 % outliers (IoU 0.841 -> 0.838); 0.7
    and 0.5 gave 0.954 with outliers at IoU 0.828 and 0.809, 0.1 (without the fade) 0.922."""
    contrast_max_noise: float = 0.06
    """Relative flow noise (ring noise / median |n|) from which contrast-sensitive Potts is off
    (see ``contrast_min_weight``). Ground-truth flow measures 0.01 (median window; 0.02 with
    30 % outliers), the shipped learned model >= 0.068 on every window of the moving-camera
    validation scenes: with the learned flow the contrast is noise (Potts weights from it
    raised validation windows with a false object from 13.7 to 15.2-17.8 %), so it stays off
    there (a few still-camera windows measure less)."""

    tracked_label_cost: float = 1.0
    """Share of lambda_m that a candidate from motion prediction (an object tracked in the
    previous window) pays: below 1, an object once found is kept while its evidence dips
    (hysteresis); 1 = every label pays alike (the paper)."""

    # --- optimisation ------------------------------------------------------------------
    max_rounds: int = 2
    """Maximum alternations of labeling (alpha-expansion) and fitting (LM). On the oracle
    validation (seeds 900-906) 2 rounds give the same detection, IoU and count as 3 (and 3 the
    same as 8); with the learned flow, whose noise keeps a few nodes flipping so that the
    alternation rarely converges, 2 rounds scored as well as 3 on the validation scenes
    (detection 67 % against 65 %) for a quarter less time (EMSGC uses 5)."""
    expansion_cycles: int = 1
    """Maximum sweeps over all labels in one labeling step (EMSGC uses 2; the alternation
    sweeps again in the next round anyway, so 1 is as good and half the max-flows)."""
    model_tol_px_s: float = 0.5
    """The alternation stops when no model's flow changes by more than this (px/s, measured
    over the sensor's half-diagonal) and the labeling is unchanged."""
    merge_tol: float = 1.0
    """Labels whose flow fields differ by less than merge_tol * sigma over the sensor are
    merged after each fit (only when that lowers the energy); 0 disables."""
    lm_iterations: int = 5
    """Levenberg-Marquardt iterations per fitting step (all labels in one batch)."""
    lm_damping: float = 1e-3
    """Initial LM damping mu (relative to the diagonal of J^T W J)."""
    robust_loss: str = "cauchy"
    """IRLS weights of the fitter: 'none', 'huber', 'cauchy' or 'truncated' (at tau)."""
    robust_scale: float = 1.0
    """Scale of the robust loss in units of sigma (the Huber / Cauchy constant)."""
    affine_prior_px: float = 0.0
    """r0 (px): the fits charge a label's divergence and rotation rates as if each of its nodes
    had an extra residual of |(rho cos - 1, rho sin)| * r0 px/s (see
    :func:`.fitting.fit_lm`), so a small object's few noisy flows cannot buy a wild zoom or
    spin that then misleads motion prediction; 0 = no prior."""

    # --- initialization ----------------------------------------------------------------
    n_sampled: int = 12
    """Fast sampling: candidate models from distinct normal flows without prediction."""
    n_sampled_with_prediction: int = 6
    """Fast sampling: candidates when motion prediction supplied at least one candidate."""
    n_sampled_normal: int = 0
    """Fast sampling: this many more candidates by farthest-point sampling over the nodes' own
    normal flows (not their 1-ring translations), away from the other sampled candidates: a
    small fast object whose 1-rings mix its nodes with the background's gets no usable
    translation vote, but its normal flows lie apart from the background's, around its
    translation (0 = off; the ``eed_like`` preset uses 2)."""
    round0_refits: int = 2
    """Round 0: after every node took its cheapest candidate, refit each candidate that
    explains at least ``min_object_nodes`` and at most ``round0_refit_max_nodes`` nodes to the
    nodes that took it, this many times (nodes no candidate explains left out); a refit is kept
    only where the candidate then explains more nodes than before. A small object that moves
    unlike a translation (a spinning or zooming ball) gets a few voters only, whose fit explains
    part of it; each refit on the nodes it explains grows it to the whole object before the
    label cost can delete it (0 = off)."""
    round0_refit_max_nodes: int = 48
    """See ``round0_refits``: larger candidates keep their fit to their voters."""
    n_resampled: int = 4
    """Round 0b: at most this many extra candidates, fitted to the largest connected regions of
    nodes no fitted candidate explains (0 = off)."""
    sampling_flow: str = "local"
    """Translation vector of a node for fast sampling: 'local' = least-squares translation of
    its Delaunay 1-ring (resolves the aperture problem; see initialization.py), 'normal' = its
    normal flow as such (the paper's wording)."""
    ring_consistency: bool = True
    """Down-weigh flows that contradict a Delaunay 1-ring which otherwise moves as one (mean
    Cauchy weight of the neighbours >= 0.5): confidence times 1 / (1 + (r / (truncation
    sigma))^2), r = the flow's residual under its ring's translation (likely outliers; needs
    sampling_flow 'local')."""
    sampling_bin: float = 4.0
    """Fast sampling counts translation vectors in square bins of sampling_bin * sigma (px/s)."""
    min_candidate_separation: float = 4.0
    """Sampled translations differ by at least min_candidate_separation * sigma (px/s)."""
    prediction_margin_px: float = 8.0
    """Motion prediction: the box of an object is grown by this margin (px) each side."""
    min_prediction_nodes: int = 8
    """Motion prediction: a predicted box needs this many nodes to fit a candidate."""

    # --- camera ------------------------------------------------------------------------
    static_camera: bool = False
    """The camera does not move: the background is still, and every motion found is an
    object. Zero motion is always a candidate (with no label cost: the still background is
    always there); labels whose flow stays below ``still_px_s`` form the background (label 0,
    which may hold no node at all: a still scene fires few events), every other label is an
    object however much of the image it covers (no background layers). False (the paper's
    setting, a moving camera): the label with the most nodes is the background. Also leaves
    scattered nodes out of each object's box and mask (``outputs.split_objects``'
    ``isolated_out``)."""
    min_cell_events: int = 1
    """Node cells holding fewer events than this give no node (needs the window's events:
    ``event_xy``). With a still camera, lone events in their cell are mostly sensor noise;
    with a moving one, sparse textures fire lone events too (keep 1)."""
    still_px_s: float = 10.0
    """With ``static_camera``: a label whose flow stays below this speed (px/s) over the
    sensor's half-diagonal counts as still background (flicker, sensor noise)."""

    # --- outputs -----------------------------------------------------------------------
    max_object_extent: float = 0.25
    """A label holding >= 2 nodes in more than this share of the occupied cells of an 8x8
    grid over the image is a background layer (a net or fence in front of the scene, with its
    own parallax; a stretch of a textured background whose learned flow is off), not an
    object: its nodes join the background (needs the sensor size). So objects are assumed to
    cover at most about a quarter of what moves in the image; raise it for objects that fill
    more of the view. 0.35 instead of 0.5 (validation seeds 900-909, learned flow): windows with
    false objects 16.8 -> 12.2 % (ego-motion-only 12.7 -> 10.0 %), detection 67.9 -> 68.5 %;
    real one-motion recordings of ``evseg eval pipeline-real`` 29.8 -> 15.9 %. Then 0.25
    instead of 0.35 (2026-11-25; learned flow, validation seeds 900-919, 20 scenes per
    preset): most ego-motion-only false objects were a third to half of the background whose
    learned flow no single affine model follows; ego-motion-only windows with a false object
    7.7 -> 4.8 %, EED-like / EVIMO-like / driving-like detection 87.3 / 68.6 / 73.7 -> 87.1 /
    68.7 / 73.9 % with false-object windows 3.2 / 10.8 / 36.3 -> 2.5 / 10.3 / 34.2 %; real
    one-motion recordings 16.4 -> 12.6 %, the EED ball unchanged; ground-truth validation
    (seeds 900-920) clean unchanged, 0.9562 -> 0.9553 with 30 % outliers. 0.3 gave half the
    gain; 0.2 lost detection (EVIMO-like 62.8 %, driving-like 68.2 %). Rerun the comparison with
    ``evaluate_pipeline(seeds=range(900, 910), overrides={"max_object_extent": 0.35})`` (and
    ``range(910, 920)``) from :mod:`evseg.pipeline_eval`."""
    min_object_nodes: int = 6
    """Objects (IMOs) with fewer nodes are set to -1 (unassigned) in the result."""
    split_gap_px: float = 12.0
    """Parts of one motion label closer than this (px, box to box) are one object (an object
    seen through a net falls apart into nearby pieces); farther parts are separate objects."""
    occlusion_gap_px: float = 48.0
    """Parts of one motion label farther apart than ``split_gap_px`` but within this (px, box to
    box), each of ``min_object_nodes``, are still one object when both touch one other object:
    the object in front splits the one behind it. 0 disables. Oracle validation (seeds
    900-920, 100 ms): detection 0.974 -> 0.978 clean, 0.941 -> 0.944 with 30 % outliers; the
    held-out scenes have no such occlusion and are unchanged."""
    max_object_parts: int = 2
    """A motion label that falls apart into more separate objects than this (each of
    ``min_object_nodes``, farther apart than ``split_gap_px``) is a scattered background layer
    (a stretch of a net whose parallax differs slightly from the rest) and joins the background;
    two objects moving alike stay two objects. 0 = no limit."""
    mask_method: str = "hull"
    """'hull': convex hull of the object's nodes, dilated by mask_dilate_px; 'dilate':
    the object's nodes rasterised and dilated by cell_px/2 + mask_dilate_px, holes closed."""
    mask_dilate_px: float = 0.0
    """Extra growth (px) of the dense mask: nodes sit on edges, the silhouette a bit outside."""
    max_propagation_px: float = 12.0
    """propagate_labels gives -1 to points farther than this (px) from every node."""

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            _check_type(self, f)
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            # NaN passes every comparison below, then poisons the energy; inf has no meaning
            # in any field but the two limits.
            if isinstance(value, float) and not math.isfinite(value) and not (
                    value == math.inf and f.name in ("max_uncertainty", "max_propagation_px")):
                raise ConfigError(f"SegmentationConfig.{f.name} must be a finite number, got {value}")
        _check_choice("robust_loss", self.robust_loss, ROBUST_LOSSES)
        _check_choice("mask_method", self.mask_method, MASK_METHODS)
        _check_choice("potts_weighting", self.potts_weighting, POTTS_WEIGHTINGS)
        _check_choice("sampling_flow", self.sampling_flow, SAMPLING_FLOWS)
        _check_choice("uncertainty_use", self.uncertainty_use, UNCERTAINTY_USES)
        _check_choice("cell_rule", self.cell_rule, CELL_RULES)
        for name in ("n_resampled", "round0_refits", "round0_refit_max_nodes", "n_sampled_normal", "cell_px",
                     "min_flow_px_s", "residual_scale_px_s",
                     "residual_scale_rel", "residual_scale_noise", "lambda_p", "lambda_m",
                     "lm_damping", "mask_dilate_px", "merge_tol", "split_gap_px", "occlusion_gap_px",
                     "uncertainty_gain", "uncertainty_angle_gain", "affine_prior_px", "max_object_parts",
                     "tracked_label_cost", "support_exponent", "contrast_max_noise", "n_sampled_with_prediction",
                     "min_object_nodes", "min_prediction_nodes", "prediction_margin_px"):
            if getattr(self, name) < 0:
                raise ConfigError(f"SegmentationConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 < self.contrast_min_weight <= 1:
            raise ConfigError(f"SegmentationConfig.contrast_min_weight must be in (0, 1], got {self.contrast_min_weight}")
        for name in ("truncation", "uncertainty_scale", "sampling_bin", "max_object_extent", "edge_scale_px", "robust_scale",
                     "max_propagation_px", "model_tol_px_s", "still_px_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"SegmentationConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_rounds", "expansion_cycles", "lm_iterations", "n_sampled", "min_cell_events",
                     "max_object_parts"):
            if getattr(self, name) < 1:
                raise ConfigError(f"SegmentationConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.residual_scale_px_s == 0 and self.residual_scale_rel == 0:
            raise ConfigError("SegmentationConfig: residual_scale_px_s and residual_scale_rel are both 0")
        if self.max_nodes is not None and (isinstance(self.max_nodes, bool) or int(self.max_nodes) != self.max_nodes
                                           or self.max_nodes < 1):
            raise ConfigError(f"SegmentationConfig.max_nodes must be a positive integer or None, got {self.max_nodes!r}")
        if self.max_uncertainty is not None and not self.max_uncertainty > 0:
            raise ConfigError(f"SegmentationConfig.max_uncertainty must be > 0 or None (keep every flow), got "
                              f"{self.max_uncertainty!r}: no flow would be kept")
        if self.node_window_us is not None and not self.node_window_us > 0:
            raise ConfigError(f"SegmentationConfig.node_window_us must be > 0 (us) or None, got {self.node_window_us!r}")
        if self.origin_px is not None:
            if not (isinstance(self.origin_px, (list, tuple, np.ndarray)) and len(self.origin_px) == 2):
                raise ConfigError(f"SegmentationConfig.origin_px must be [column, row] in px, got {self.origin_px!r}")
            object.__setattr__(self, "origin_px", tuple(float(v) for v in self.origin_px))
            if not all(math.isfinite(v) for v in self.origin_px):
                raise ConfigError(f"SegmentationConfig.origin_px must be finite [column, row] px, got {self.origin_px}")


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"SegmentationConfig.{name} must be one of {choices}, got {value!r}")


_OPTIONAL_FIELDS = ("node_window_us", "max_uncertainty", "origin_px", "max_nodes")
_OPTIONAL_INT_FIELDS = ("node_window_us", "max_nodes")  # None or a whole number


def _check_type(cfg: "SegmentationConfig", f: dataclasses.Field) -> None:
    """The field's value has the type of its default (numpy scalars become Python numbers): a
    string "80", a float 2.5 for a count or "false" for a switch would fail later, or act
    wrongly, far from where they were given."""
    value, default = getattr(cfg, f.name), f.default
    if value is None and f.name in _OPTIONAL_FIELDS:
        return
    if f.name == "origin_px" or default is dataclasses.MISSING:
        return
    bad = None
    if isinstance(default, bool):
        if isinstance(value, np.bool_):
            value = bool(value)
        bad = not isinstance(value, bool)
    elif isinstance(default, int) or f.name in _OPTIONAL_INT_FIELDS:
        bad = not is_whole(value)
        if not bad:
            value = int(value)
    elif isinstance(default, float) or (default is None and f.name in _OPTIONAL_FIELDS):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            bad = True
        else:
            value = float(value)
    elif isinstance(default, str):
        bad = not isinstance(value, str)
    if bad:
        kind = (type(default).__name__ if default is not None
                else "int" if f.name in _OPTIONAL_INT_FIELDS else "number")
        raise ConfigError(f"SegmentationConfig.{f.name} must be {'an' if kind == 'int' else 'a'} {kind}, got {value!r}")
    object.__setattr__(cfg, f.name, value)


def config_from_dict(d: dict, source: str = "config") -> SegmentationConfig:
    """Build a config from a mapping; unknown keys and wrong types raise ConfigError."""
    if not isinstance(d, dict):
        raise ConfigError(f"{source}: expected a mapping of segmentation parameters, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(SegmentationConfig)}
    unknown = sorted(set(d) - set(fields))
    if unknown:
        raise ConfigError(f"{source}: unknown segmentation parameter(s) {unknown}; known: {sorted(fields)}")
    defaults = SegmentationConfig()
    kwargs = {}
    for key, value in d.items():
        default = getattr(defaults, key)
        kwargs[key] = _coerce(key, value, default, source)
    try:
        return SegmentationConfig(**kwargs)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _coerce(key: str, value, default, source: str):
    """Check a YAML value against the type of the field's default (ints may stand for floats)."""
    optional = key in ("node_window_us", "max_uncertainty", "origin_px", "max_nodes")
    if value is None:
        if optional:
            return None
        raise ConfigError(f"{source}: field '{key}' may not be null")
    if key == "origin_px":
        if not (isinstance(value, (list, tuple)) and len(value) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            raise ConfigError(f"{source}: field 'origin_px' must be [column, row] in px, got {value!r}")
        return tuple(float(v) for v in value)
    if key in ("node_window_us", "max_nodes"):
        kind = int
    elif key == "max_uncertainty":
        kind = float
    else:
        kind = type(default)
    if isinstance(value, np.generic):  # numpy scalars (a mapping built in Python) as Python numbers
        value = value.item()
    if kind is not bool and isinstance(value, bool):
        raise ConfigError(f"{source}: field '{key}' must be {kind.__name__}, got {value!r}")
    if kind is bool and isinstance(value, bool):
        return value
    if kind is float and isinstance(value, (int, float)):
        return float(value)
    if kind is int and is_whole(value):  # 8000.0, as a stored config may write a count
        return int(value)
    if kind is str and isinstance(value, str):
        return value
    hint = ""
    if isinstance(value, str) and kind in (int, float):
        try:
            float(value)
            hint = " (YAML 1.1 reads a number like 1e2 as text: write 1.0e2 or 100.0)"
        except ValueError:
            pass
    raise ConfigError(f"{source}: field '{key}' must be {kind.__name__}, got {value!r}{hint}")


def preset_names() -> list[str]:
    """Names of the bundled presets (configs/segmentation/*.yaml)."""
    return sorted(p.stem for p in _PRESET_DIR.glob("*.yaml"))


def with_overrides(cfg: SegmentationConfig, overrides: dict | None, where: str) -> SegmentationConfig:
    """``cfg`` with the fields in ``overrides`` replaced (validated like any config); an unknown
    field raises :class:`ConfigError` naming ``where`` and the field. How the evaluations
    compare a setting with the presets' own.

    >>> with_overrides(SegmentationConfig(), {"lambda_m": 60.0}, "example").lambda_m
    60.0
    """
    if not overrides:
        return cfg
    unknown = sorted(set(overrides) - {f.name for f in dataclasses.fields(SegmentationConfig)})
    if unknown:
        raise ConfigError(f"{where}: unknown segmentation parameter(s) {unknown}")
    # The same type checks as a YAML file's fields (a string for a number fails here, not deep
    # inside a comparison in the config's own checks).
    defaults = SegmentationConfig()
    values = {k: _coerce(k, v, getattr(defaults, k), where) for k, v in overrides.items()}
    try:
        return dataclasses.replace(cfg, **values)
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def load_segmentation_config(name_or_path) -> SegmentationConfig:
    """Load a preset by name ('evimo_like') or a YAML file path into a SegmentationConfig (a
    config, a mapping of its fields or None are taken as :func:`as_segmentation_config` takes
    them; an existing file without an extension is read as YAML).

    The YAML holds a flat mapping of SegmentationConfig fields; missing fields keep their
    defaults, unknown fields raise :class:`ConfigError` naming the file and the field. The
    whole pipeline configuration a result stores (its ``segmentation:`` part is taken), and
    a ``result.npz`` itself, are read too, so that a run's settings can be reused.
    """
    import yaml

    if not isinstance(name_or_path, (str, Path)):
        # A config, a mapping or None: what the pipeline's `segmentation=` takes as well.
        return as_segmentation_config(name_or_path, source="load_segmentation_config")
    path = Path(name_or_path)
    if not path.suffix and not path.is_file():  # a preset name (a file of that name wins)
        preset = _PRESET_DIR / f"{name_or_path}.yaml"
        if not preset.is_file():
            what = "a folder, and no" if path.is_dir() else "no such file, and no"
            raise ConfigError(f"{name_or_path}: {what} segmentation preset of that name; presets: {preset_names()}")
        path = preset
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder, not a segmentation config file (YAML)")
    if not path.is_file():
        raise ConfigError(f"segmentation config file not found: {path}")
    if path.suffix.lower() == ".npz":
        return _from_result(path)
    try:
        data = yaml.safe_load(path.read_text())
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text (YAML) file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read segmentation config ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: {yaml_problem(exc)}") from None
    return config_from_dict(_segmentation_part({} if data is None else data), source=str(path))


def _segmentation_part(data):
    """The ``segmentation`` mapping of a stored pipeline configuration, or ``data`` itself."""
    if isinstance(data, dict) and isinstance(data.get("segmentation"), dict) and "window_us" in data:
        return data["segmentation"]
    return data


def _from_result(path: Path) -> SegmentationConfig:
    """The segmentation settings stored in a ``result.npz`` of ``evseg segment``."""
    import yaml

    from evseg.results import load_result

    stored = load_result(path).config
    if not stored:
        raise ConfigError(f"{path}: the result stores no configuration")
    try:
        data = yaml.safe_load(stored)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: key 'config': {yaml_problem(exc)}") from None
    return config_from_dict(_segmentation_part(data), source=f"{path}: key 'config'")


def as_segmentation_config(config, source: str = "config") -> SegmentationConfig:
    """A :class:`SegmentationConfig` from one, a preset name or file path, a mapping of its
    fields, or None (the defaults); anything else is a :class:`ConfigError` naming ``source``.

    >>> as_segmentation_config({"lambda_m": 40.0}).lambda_m
    40.0
    """
    if config is None:
        return SegmentationConfig()
    if isinstance(config, SegmentationConfig):
        return config
    if isinstance(config, (str, Path)):
        return load_segmentation_config(config)
    if isinstance(config, dict):
        return config_from_dict(config, source=source)
    raise ConfigError(f"{source} must be a SegmentationConfig, a preset name or a mapping of its fields, "
                      f"got {type(config).__name__}")
