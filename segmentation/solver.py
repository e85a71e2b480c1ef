"""Segment one window of normal flow: alternate labeling (alpha-expansion) and fitting (LM).

Paper Sec. III-B/C: with the candidate models fixed, the labeling minimises the energy
(:mod:`.energy`) by alpha-expansion with label costs (:mod:`.expansion`); with the labeling
fixed, each label's model is refitted (:mod:`.fitting`); repeat until the models converge.

Order of the steps (our choice where the paper is silent):

1. Nodes and Delaunay graph (:mod:`.preprocessing`).
2. Candidates: motion prediction from the previous window's objects (and its background
   model), then fast sampling (``n_sampled``, or ``n_sampled_with_prediction`` when prediction
   gave a candidate), plus ``n_sampled_normal`` farthest-point candidates over the nodes' own
   normal flows (:func:`.initialization.farthest_candidates`).
3. Round 0: every sampled candidate is fitted by LM to its voters (the nodes whose 1-ring
   translation fell within two sampling bins of it), then every node takes its cheapest
   candidate (no smoothness). A sampled candidate is a pure translation; its voters are the
   nodes moving like it - for a small, fast-spinning object, the object itself - so one robust
   fit turns it into that object's full motion before the label cost can delete it. When the
   object's motion is far from a translation (a spinning, zooming ball), its voters are a few
   of its nodes and their fit explains only part of it: ``round0_refits`` times, every
   candidate that explains ``min_object_nodes`` to ``round0_refit_max_nodes`` nodes is
   refitted to them and the nodes choose again, which grows it over the whole object (a
   refit after which the candidate explains no more nodes than before is undone).
   Round 0b: the nodes that no fitted candidate explains (data cost at the truncation) that
   form connected regions of the graph (at least ``min_object_nodes``; the ``n_resampled``
   largest) each give one more candidate: the best of 64 exact fits to 4 random nodes of the
   region (sample consensus, :func:`.initialization.consensus_models`: such a region can hold
   as many stray flows as object flows, which drag a least-squares start), then LM on the
   region: a small object whose translations drown among the background's variations, or whose
   1-rings are too mixed to vote (a small spinning ball), is exactly such a region, while
   scattered outlier flows are not (flows that contradict a 1-ring moving as one are left out
   of the regions).
4. On precise flow (relative 1-ring noise under ``contrast_max_noise``), the Potts weight of
   each edge across which no round-0 candidate explains both nodes drops to as little as
   ``contrast_min_weight`` (:func:`.energy.contrast_weights`), for the rest of the window.
   Rounds 1..max_rounds: alpha-expansion from the current labeling, drop empty labels, LM refit,
   merge near-duplicate models (only when that lowers the energy);
   a refitted model replaces the old one only if it lowers its label's data energy, so the
   energy never increases. Stop when the labeling is unchanged and no model's flow moved more
   than ``model_tol_px_s``.
5. The label with the most nodes is the background (label 0; with ``static_camera``, the
   labels that do not move, zero motion being always a candidate); the others are
   independently moving objects 1..K by decreasing node count; objects under ``min_object_nodes`` nodes
   become -1 (unassigned). A label spread over more than ``max_object_extent`` of the image
   (:func:`.outputs.background_layers`) is a background layer - e.g. a net in front of the scene,
   which the EED ground truth counts as background - and joins label 0 (the model of label 0
   stays the largest cluster's). Finally every sizeable connected part of an object label is an
   object of its own (two objects moving alike share a model but are two objects;
   :func:`.outputs.split_objects`; parts that both touch one other object, which hides the
   middle of the one behind it, stay one object up to ``occlusion_gap_px`` apart), numbered by
   decreasing size; a label that falls apart into
   more than ``max_object_parts`` far-apart parts is a scattered background layer and joins
   label 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from evseg.errors import ConfigError
from evseg.segmentation.config import SegmentationConfig
from evseg.segmentation.energy import contrast_weights, energy
from evseg.segmentation.expansion import alpha_expansion
from evseg.segmentation.fitting import fit_lm
from evseg.segmentation.initialization import consensus_models, motion_prediction
from evseg.segmentation.motion_model import flow_field, model_change_px_s
from evseg.segmentation.outputs import (
    background_layers, nearest_node_labels, region_box, region_mask, split_objects,
)
from evseg.segmentation.window import (
    PreparedWindow, lm_kwargs, prepare_window, refit_to_labels, sample_candidates, window_costs,
)


@dataclass(frozen=True)
class SegmentationResult:
    """Segmentation of one window (M nodes, K objects).

    Attributes:
        node_index: (M,) int64 index into the input arrays of each node's flow.
        node_x, node_y: (M,) float64 node positions, px (column, row, as given).
        node_t: (M,) int64 node timestamps, microseconds.
        node_labels: (M,) int64; 0 = background, 1..K = objects (IMOs), -1 = unassigned.
        models: (K+1, 4) float64 (rho, theta, t_x, t_y) per label, row 0 = background. The
            flow is u(x) = (rho R(theta) - I)(x - origin) + t in px/s: t in px/s,
            rho cos(theta) - 1 the divergence rate (1/s), rho sin(theta) the rotation rate
            (rad/s for small rates).
        origin_px: (column, row) origin of the models, px.
        boxes: {k: (x0, y0, x1, y1)} inclusive px box per object.
        masks: {k: bool (H, W)} dense mask per object (empty dict without sensor size).
        edges: (E, 2) int64 Delaunay edges of the nodes.
        energy: final energy (dimensionless, see :mod:`.energy`).
        n_rounds: alternation rounds run (after round 0).
        n_candidates: candidate models at the start (predicted + sampled).
        n_predicted: candidates that came from motion prediction.
        sigma_px_s: residual scale used, px/s.
        t_ref_us: reference time of the window (middle of the nodes' time span), microseconds;
            boxes and masks show the objects at this time (nodes moved along their model).
        sensor_size: (width, height) or None.
        timings: wall-clock ms per stage: 'preprocessing', 'initialization', 'labeling_fitting',
            'outputs'; the same keys with '_cpu' give the process CPU time (ms), which is what a
            stage costs on a machine where other processes compete for the cores.
        max_propagation_px: distance limit used by :func:`propagate_labels`.
    """

    node_index: np.ndarray
    node_x: np.ndarray
    node_y: np.ndarray
    node_t: np.ndarray
    node_labels: np.ndarray
    models: np.ndarray
    origin_px: tuple[float, float]
    boxes: dict
    masks: dict
    edges: np.ndarray
    energy: float
    n_rounds: int
    n_candidates: int
    n_predicted: int
    sigma_px_s: float
    t_ref_us: int
    sensor_size: tuple[int, int] | None
    timings: dict = field(default_factory=dict)
    max_propagation_px: float = 12.0

    @property
    def n_objects(self) -> int:
        """Number of independently moving objects K."""
        return len(self.models) - 1 if len(self.models) else 0


def propagate_labels(result: SegmentationResult, x: np.ndarray, y: np.ndarray,
                     max_distance_px: float | None = None) -> np.ndarray:
    """Label of the nearest node for every point (px), -1 beyond the distance limit.

    Args:
        result: a window's segmentation. x, y: (N,) points, px (same frame as the nodes).
        max_distance_px: limit (px); default the config's ``max_propagation_px``.
    Returns:
        (N,) int64 labels (0 = background, k = object k, -1 = unassigned / too far).
    """
    limit = result.max_propagation_px if max_distance_px is None else float(max_distance_px)
    return nearest_node_labels(result.node_x, result.node_y, result.node_labels, x, y, limit)


def segment_normal_flow(
    x: np.ndarray,
    y: np.ndarray,
    t: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    uncertainty: np.ndarray | None = None,
    config: SegmentationConfig = SegmentationConfig(),
    sensor_size: tuple[int, int] | None = None,
    previous: SegmentationResult | None = None,
    tracked_objects: tuple[np.ndarray, np.ndarray] | None = None,
    event_xy: tuple[np.ndarray, np.ndarray] | None = None,
) -> SegmentationResult:
    """Segment one window of normal flow into background and independently moving objects.

    Args:
        x, y: (N,) flow positions, px (column, row; may be undistorted, non-integer).
        t: (N,) int64 timestamps, microseconds.
        nx, ny: (N,) normal flow, px/s (NaN or slower than ``min_flow_px_s`` = no flow).
        uncertainty: (N,) optional; larger = less certain.
        config: parameters. sensor_size: (width, height) px; needed for masks and the
            default origin. previous: the previous window's result (motion prediction).
        tracked_objects: optional ``(boxes (K, 4), models (K, 4))``: objects a tracker expects
            in this window, boxes already moved to it (inclusive px, absolute) and their last
            models (about the same origin). They replace the prediction from ``previous``'s
            objects, so an object missed in one window still gets its candidate in the next
            (the pipeline passes its tracks); ``previous`` still gives the background candidate.
        event_xy: optional ``(x, y)`` of all the window's events (px, the flows' coordinates),
            for each node's support (``config.support_exponent``): pass them when flow was
            computed for a subset of the events. None: each usable flow counts as one event.
    Returns:
        :class:`SegmentationResult`. Inputs are not modified.

    Raises:
        EventDataError: arrays of different lengths or not 1-D, a position that is NaN or
            infinite or far off the sensor (more than a quarter of its size), a time that is
            not whole microseconds (seconds would all fall into one microsecond), a negative
            uncertainty; the message names the argument and the row.
    """
    _check_on_sensor(x, y, sensor_size)
    prepared = prepare_window(x, y, t, nx, ny, uncertainty, config, sensor_size, event_xy)
    return segment_prepared(prepared, previous, tracked_objects)


OFF_SENSOR_MARGIN = 0.25
"""How far (a share of the sensor's width / height) :func:`segment_normal_flow` lets positions
lie beyond the sensor: undistorted positions do, a little; farther means another frame."""


def _check_on_sensor(x, y, sensor_size) -> None:
    """Refuse flow positions far off the ``sensor_size`` grid: a swapped (height, width) or
    positions of another frame gave boxes clipped to the border and lost objects, silently."""
    from evseg.errors import EventDataError
    from evseg.events import checked_sensor_size

    if sensor_size is None or len(np.asarray(x)) == 0:
        return
    w, h = checked_sensor_size(sensor_size)
    for name, a, size in (("x", x, w), ("y", y, h)):
        a = np.asarray(a, dtype=np.float64)
        lo, hi = -OFF_SENSOR_MARGIN * size, (1 + OFF_SENSOR_MARGIN) * size
        bad = np.flatnonzero((a < lo) | (a > hi))
        if len(bad):
            i = int(bad[0])
            raise EventDataError(
                f"segment_normal_flow: '{name}' = {a[i]:g} at row {i} lies far off the {w}x{h} sensor "
                f"(sensor_size is (width, height); positions may stray {OFF_SENSOR_MARGIN:.0%} of it beyond the "
                "edges, as undistorted ones do; pass sensor_size=None for positions in another frame)")


def _check_window_arrays(x, y, t, nx, ny, uncertainty) -> None:
    """What :func:`segment_normal_flow` needs of its arrays (the pipeline builds them itself)."""
    from evseg.errors import EventDataError

    arrays = {"x": x, "y": y, "t": t, "nx": nx, "ny": ny, "uncertainty": uncertainty}
    n = len(np.asarray(x))
    for name, a in arrays.items():
        if a is None:
            continue
        a = np.asarray(a)
        if a.ndim != 1 or len(a) != n:
            raise EventDataError(f"segment_normal_flow: '{name}' has shape {a.shape}, expected ({n},) like 'x'")
        if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
            raise EventDataError(f"segment_normal_flow: '{name}' must hold real numbers, got dtype {a.dtype}")
    for name in ("x", "y"):
        a = np.asarray(arrays[name], dtype=np.float64)
        if n and not np.isfinite(a).all():
            i = int(np.flatnonzero(~np.isfinite(a))[0])
            raise EventDataError(f"segment_normal_flow: '{name}' = {a[i]} at row {i} is not a finite position (px)")
    t = np.asarray(t)
    if n and not np.issubdtype(t.dtype, np.integer):
        whole = np.isfinite(t) & (t == np.round(t))
        if not whole.all():
            i = int(np.flatnonzero(~whole)[0])
            raise EventDataError(f"segment_normal_flow: 't' = {t[i]} at row {i} is not whole microseconds "
                                 "(time in seconds: multiply by 1e6)")
    if uncertainty is not None and n:
        u = np.asarray(uncertainty, dtype=np.float64)
        if np.any(u < 0):
            i = int(np.flatnonzero(u < 0)[0])
            raise EventDataError(f"segment_normal_flow: 'uncertainty' = {u[i]} at row {i} is negative "
                                 "(larger = less certain, 0 = certain)")
        if np.isnan(u).any():
            i = int(np.flatnonzero(np.isnan(u))[0])
            raise EventDataError(f"segment_normal_flow: 'uncertainty' is NaN at row {i} (inf marks a flow to ignore)")


def _tracked(tracked_objects) -> tuple[np.ndarray, np.ndarray, float]:
    """``(boxes (K, 4), models (K, 4), 0.0)`` of a ``tracked_objects`` pair, checked."""
    try:
        boxes, models = tracked_objects
        boxes, models = np.asarray(boxes, dtype=np.float64), np.asarray(models, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError("segment: tracked_objects must be a pair (boxes (K, 4), models (K, 4)) of numbers") from None
    for name, a in (("boxes", boxes), ("models", models)):
        if a.size and (a.ndim != 2 or a.shape[1] != 4):
            raise ConfigError(f"segment: tracked_objects {name} must be (K, 4), got shape {a.shape}")
    boxes, models = boxes.reshape(-1, 4), models.reshape(-1, 4)
    if len(boxes) != len(models):
        raise ConfigError(f"segment: tracked_objects has {len(boxes)} boxes and {len(models)} models")
    if not (np.isfinite(boxes).all() and np.isfinite(models).all()):
        raise ConfigError("segment: tracked_objects boxes and models must be finite")
    return boxes, models, 0.0


def segment_prepared(
    prepared: PreparedWindow,
    previous: SegmentationResult | None = None,
    tracked_objects: tuple[np.ndarray, np.ndarray] | None = None,
) -> SegmentationResult:
    """Segment a window prepared by :func:`prepare_window` (``previous``, ``tracked_objects``
    as in :func:`segment_normal_flow`, which is ``segment_prepared(prepare_window(...))``)."""
    pw = prepared
    cfg, sensor_size, origin, graph = pw.config, pw.sensor_size, pw.origin, pw.graph
    xr, yr, grown, lambda_m, sigma = pw.xr, pw.yr, pw.grown, pw.lambda_m, pw.sigma
    edge_w, radius, t_ref, conf = pw.edge_w, pw.radius, pw.t_ref, pw.conf
    fit_w, suspect = pw.fit_w, pw.suspect
    m = len(graph)
    timings = dict(pw.timings)
    tic, cpu = time.perf_counter(), time.process_time()
    lm_kw = lm_kwargs(pw)
    predicted = np.empty((0, 4))
    n_object_candidates = 0
    # Objects to predict: the caller's tracks (boxes already at this window) or the previous
    # window's objects (boxes moved here by their models over the time between the windows).
    expected = None
    if previous is not None and not isinstance(previous, SegmentationResult):
        raise ConfigError(f"segment: previous must be the previous window's SegmentationResult or None, got "
                          f"{type(previous).__name__}")
    if tracked_objects is not None:
        expected = _tracked(tracked_objects)
    elif previous is not None and previous.n_objects > 0 and previous.origin_px == origin and previous.boxes:
        ids = sorted(previous.boxes)
        expected = (np.array([previous.boxes[k] for k in ids], dtype=np.float64), previous.models[ids],
                    (t_ref - previous.t_ref_us) * 1e-6)
    if expected is not None and m and len(expected[0]):
        boxes, box_models, dt_s = expected
        predicted = motion_prediction(
            graph.x, graph.y, graph.nx, graph.ny, boxes, box_models, origin, dt_s,
            cfg.prediction_margin_px, cfg.min_prediction_nodes, weights=fit_w, loss=cfg.robust_loss,
            loss_scale_px_s=cfg.robust_scale * sigma, iterations=cfg.lm_iterations,
            affine_prior_px=cfg.affine_prior_px)
        n_object_candidates = len(predicted)
    if cfg.static_camera:
        # A still camera: zero motion (the background's) is always a candidate.
        predicted = np.concatenate([STILL_MODEL[None], predicted])
    elif previous is not None and len(previous.models) and previous.origin_px == origin:
        # The previous background model is a free, usually excellent candidate.
        predicted = np.concatenate([previous.models[:1], predicted])
    n_sample = cfg.n_sampled_with_prediction if n_object_candidates else cfg.n_sampled
    # Round 0's sampled candidates (fast sampling and the fit to their voters) need no earlier
    # window: a streaming caller may have computed them already (with_sampled_candidates).
    ready = [c for c in pw.sampled if c.n_asked == n_sample]
    sampled = ready[0] if ready else sample_candidates(pw, n_sample)
    models = np.concatenate([predicted, sampled.models]) if m else np.empty((0, 4))
    n_candidates = len(models)
    # The prepared share (1-ring noise, votes) and the model-dependent share (prediction, sampling).
    timings["initialization"] += (time.perf_counter() - tic) * 1e3
    timings["initialization_cpu"] += (time.process_time() - cpu) * 1e3
    if ready:  # sampled on another thread: its time still counts in this window's stages
        timings["initialization"] += sampled.sampling_ms
        timings["initialization_cpu"] += sampled.sampling_cpu_ms
    else:  # sampled and fitted just now: the fits count under labeling and fitting below
        timings["initialization"] -= sampled.fitting_ms
        timings["initialization_cpu"] -= sampled.fitting_cpu_ms

    tic, cpu = time.perf_counter(), time.process_time()
    labels = np.zeros(m, dtype=np.int64)
    n_rounds = 0
    e_final = 0.0
    if m and len(models):
        def costs(mod):
            return window_costs(pw, mod)

        ar = np.arange(m)
        # Label costs: a candidate predicted from a tracked object pays tracked_label_cost x
        # lambda_m (it existed a window ago, so a new motion is less of a surprise).
        h = np.full(len(models), lambda_m)
        h[len(predicted) - n_object_candidates : len(predicted)] *= cfg.tracked_label_cost
        if cfg.static_camera:
            h[0] = 0.0  # the still background is always there
        # Round 0 (see module docstring): each sampled candidate fitted to the nodes that voted
        # for it (sample_candidates), then every node takes its cheapest candidate.
        data = np.concatenate([costs(predicted), sampled.data], axis=1)
        labels = np.argmin(data, axis=1)
        if cfg.round0_refits:
            models, data, labels = _round0_refits(models, data, labels, pw, lm_kw, costs)
        models, data, labels, h = _merge_duplicates(models, data, labels, h, cfg.merge_tol * sigma,
                                                    radius, graph.edges, edge_w)
        if cfg.n_resampled > 0:
            # Round 0b: regions no fitted model explains (see module docstring).
            # Likely outliers are unexplained by every model but form no region of their own.
            lost = (data[ar, labels] >= 0.99 * cfg.truncation ** 2 * conf) & ~suspect
            region = _unexplained_regions(lost, graph.edges, cfg.min_object_nodes, cfg.n_resampled)
            n_extra = int(region.max()) + 1 if len(region) else 0
            if n_extra:
                keep = region >= 0
                start = consensus_models(xr[keep], yr[keep], graph.nx[keep], graph.ny[keep],
                                         region[keep], n_extra, cfg.truncation * sigma)
                extra = fit_lm(xr[keep], yr[keep], graph.nx[keep], graph.ny[keep], region[keep],
                               start, **{**lm_kw, "weights": fit_w[keep]})
                models = np.concatenate([models, extra])
                h = np.concatenate([h, np.full(n_extra, lambda_m)])
                data = costs(models)
                labels = np.argmin(data, axis=1)
                models, data, labels, h = _merge_duplicates(
                    models, data, labels, h, cfg.merge_tol * sigma, radius, graph.edges, edge_w)
                n_candidates += n_extra
        strength = contrast_strength(pw.flow_noise_rel, cfg.contrast_max_noise) if cfg.contrast_min_weight < 1 else 0.0
        if strength > 0:
            # From here on the window's energy has contrast-sensitive Potts weights (from all
            # of round 0's candidates, fixed for the alternation so that it still descends).
            edge_w = edge_w * contrast_weights(data, graph.edges, cfg.contrast_min_weight, strength)
        for n_rounds in range(1, cfg.max_rounds + 1):
            res = alpha_expansion(labels, data, graph.edges, edge_w, h, cfg.expansion_cycles)
            used = np.flatnonzero(np.bincount(res.labels, minlength=len(models)))
            remap = np.full(len(models), -1, dtype=np.int64)
            remap[used] = np.arange(len(used))
            new_labels = remap[res.labels]
            changed = len(used) != len(models) or not np.array_equal(new_labels, labels)
            models, data, labels, h = models[used], data[:, used], new_labels, h[used]
            old = models
            models, data = refit_to_labels(models, data, labels, xr, yr, graph, lm_kw, costs, ar)
            models, data, labels, h = _merge_duplicates(models, data, labels, h, cfg.merge_tol * sigma,
                                                        radius, graph.edges, edge_w)
            if len(models) != len(old):
                changed = True
                old = models  # merged: the tolerance test is meaningless this round
            moved = float(model_change_px_s(old, models, radius).max())
            if not changed and moved <= cfg.model_tol_px_s:
                break
        e_final = energy(labels, data, graph.edges, edge_w, h)
        # Background = largest cluster (a still camera: the still labels); objects by
        # decreasing size.
        if cfg.static_camera:
            labels, models, sizes = _still_background(labels, models, radius, cfg.still_px_s)
        else:
            sizes = np.bincount(labels, minlength=len(models))
            order = np.argsort(-sizes, kind="stable")
            rank = np.empty(len(order), dtype=np.int64)
            rank[order] = np.arange(len(order))
            labels, models, sizes = rank[labels], models[order], sizes[order]
        small = np.flatnonzero(sizes < cfg.min_object_nodes)
        small = small[small > 0]
        if len(small):
            keep = np.setdiff1d(np.arange(len(models)), small)
            remap = np.full(len(models), -1, dtype=np.int64)
            remap[keep] = np.arange(len(keep))
            labels, models = remap[labels], models[keep]
    # Round 0's fits of the sampled candidates count here wherever they ran.
    timings["labeling_fitting"] = (time.perf_counter() - tic) * 1e3 + sampled.fitting_ms
    timings["labeling_fitting_cpu"] = (time.process_time() - cpu) * 1e3 + sampled.fitting_cpu_ms

    tic, cpu = time.perf_counter(), time.process_time()
    if sensor_size is not None and len(models) > 1 and not cfg.static_camera:
        layers = background_layers(labels, graph.x, graph.y, sensor_size, cfg.max_object_extent)
        if len(layers):
            keep = np.setdiff1d(np.arange(len(models)), layers)
            remap = np.full(len(models), -1, dtype=np.int64)
            remap[keep] = np.arange(len(keep))
            remap[layers] = 0
            labels = np.where(labels >= 0, remap[np.maximum(labels, 0)], -1)
            models = models[keep]
    labels, models, regions = split_objects(labels, graph.edges, models, cfg.min_object_nodes,
                                            graph.x, graph.y, cfg.split_gap_px * grown,
                                            cfg.max_object_parts, isolated_out=cfg.static_camera,
                                            occlusion_gap_px=cfg.occlusion_gap_px * grown)
    boxes, masks = {}, {}
    for k, nodes in regions.items():  # loop over objects (a handful), arrays inside
        # Motion compensation: move each node along its object's flow to the window's mid-time,
        # so a fast object's region is its outline at t_ref, not the smear over the window.
        ux, uy = flow_field(models[k : k + 1], xr[nodes], yr[nodes])
        dt_s = (t_ref - graph.t[nodes]) * 1e-6
        px, py = graph.x[nodes] + ux[:, 0] * dt_s, graph.y[nodes] + uy[:, 0] * dt_s
        if sensor_size is not None and not _any_on_sensor(px, py, sensor_size):
            # Moved wholly off the sensor by t_ref (a fast object leaving the frame): its outline
            # is where its events were, not a sliver on the edge with an empty mask.
            px, py = graph.x[nodes], graph.y[nodes]
        boxes[k] = region_box(px, py, cfg.mask_dilate_px, sensor_size)
        if sensor_size is not None:
            masks[k] = region_mask(px, py, sensor_size, cfg.mask_method, cfg.mask_dilate_px, graph.cell_px)
    timings["outputs"] = (time.perf_counter() - tic) * 1e3
    timings["outputs_cpu"] = (time.process_time() - cpu) * 1e3
    return SegmentationResult(
        node_index=graph.index, node_x=graph.x, node_y=graph.y, node_t=graph.t,
        node_labels=labels, models=np.asarray(models, dtype=np.float64).reshape(-1, 4),
        origin_px=origin, boxes=boxes, masks=masks, edges=graph.edges, energy=e_final,
        n_rounds=n_rounds, n_candidates=n_candidates, n_predicted=len(predicted),
        sigma_px_s=sigma, t_ref_us=t_ref,
        sensor_size=None if sensor_size is None else (int(sensor_size[0]), int(sensor_size[1])),
        timings=timings, max_propagation_px=pw.max_propagation_px,
    )


def contrast_strength(noise_rel: float, max_noise: float) -> float:
    """Strength in [0, 1] of contrast-sensitive Potts for a window whose relative flow noise is
    ``noise_rel``: 1 up to ``max_noise / 2``, 0 from ``max_noise`` on (and when not measured).

    >>> contrast_strength(0.01, 0.06), contrast_strength(0.045, 0.06), contrast_strength(0.07, 0.06)
    (1.0, 0.5, 0.0)
    """
    if not np.isfinite(noise_rel) or max_noise <= 0:
        return 0.0
    return float(np.clip((max_noise - noise_rel) / (0.5 * max_noise), 0.0, 1.0))


def _round0_refits(models, data, labels, pw: PreparedWindow, lm_kw, costs):
    """Round 0's refits of the small candidates (``SegmentationConfig.round0_refits``, module
    docstring step 3): models, data and argmin labels after them."""
    cfg = pw.config
    ar = np.arange(len(labels))
    cap = 0.99 * cfg.truncation ** 2 * pw.conf  # a node's data cost at the truncation

    def explained_counts(data, labels):
        explained = data[ar, labels] < cap
        return explained, np.bincount(labels[explained], minlength=len(models))

    for _ in range(cfg.round0_refits):
        # Only candidates that explain few nodes: a large one's fit to its voters is already
        # sound, and refitting it to its nodes turns depth bands of a background into labels of
        # their own (learned flow, validation: false objects 13.7 -> 18.7 %). Those explaining
        # fewer than min_object_nodes are mostly stray and are left alone (each LM call costs
        # ~0.1 ms per iteration however few its nodes).
        explained, n_before = explained_counts(data, labels)
        small = np.flatnonzero((n_before >= max(cfg.min_object_nodes, 1))
                               & (n_before <= cfg.round0_refit_max_nodes))
        if not len(small):
            break
        # Fit and cost only the small candidates, on their own nodes (a few dozen each).
        index = np.full(len(models), -1, dtype=np.int64)
        index[small] = np.arange(len(small))
        on = explained & (index[labels] >= 0)
        new = fit_lm(pw.xr[on], pw.yr[on], pw.graph.nx[on], pw.graph.ny[on], index[labels[on]],
                     models[small], **{**lm_kw, "weights": pw.fit_w[on],
                                       "iterations": ROUND0_REFIT_ITERATIONS})
        refit_models, refit_data = models.copy(), data.copy()
        refit_models[small] = new
        refit_data[:, small] = costs(new)
        refit_labels = np.argmin(refit_data, axis=1)
        # A refit is kept only where the candidate now explains more nodes: growing over an
        # object is its purpose, while one that does not grow was fitted to its nodes already and
        # a refit only sharpens it on their noise (real one-motion recordings: windows with a
        # false object 16.8 -> 19.5 % without this rule; simulated scenes unchanged).
        _, n_after = explained_counts(refit_data, refit_labels)
        back = small[n_after[small] <= n_before[small]]
        if len(back):
            refit_models[back] = models[back]
            refit_data[:, back] = data[:, back]
            refit_labels = np.argmin(refit_data, axis=1)
        models, data, labels = refit_models, refit_data, refit_labels
    return models, data, labels


ROUND0_REFIT_ITERATIONS = 2
"""LM iterations of each round-0 refit (``SegmentationConfig.round0_refits``): a refit only has
to move a small candidate toward the nodes it explains before they choose again, and the
rounds' refits finish the fit. Same labels as with ``lm_iterations`` (5) on the validation
seeds (ground-truth and learned flow), ~0.7 ms less per window at 1.5 k nodes (a torch LM call
costs ~0.1 ms per iteration however few its nodes)."""

STILL_MODEL = np.array([1.0, 0.0, 0.0, 0.0])
"""The affine model of zero motion (rho, theta, t_x, t_y): a still camera's background."""


def _still_background(labels: np.ndarray, models: np.ndarray, radius_px: float, still_px_s: float):
    """Labels, models and sizes with label 0 = every label moving less than ``still_px_s``
    over ``radius_px`` (merged; model: zero motion; it may hold no node) and 1..K the moving
    labels by decreasing size."""
    n = len(models)
    sizes = np.bincount(labels, minlength=n)
    speed = model_change_px_s(np.tile(STILL_MODEL, (n, 1)), models, radius_px)
    moving = np.flatnonzero(speed > still_px_s)
    moving = moving[np.argsort(-sizes[moving], kind="stable")]
    remap = np.zeros(n, dtype=np.int64)  # still labels -> 0
    remap[moving] = np.arange(1, len(moving) + 1)
    new_sizes = np.concatenate([[sizes[speed <= still_px_s].sum()], sizes[moving]])
    return remap[labels], np.concatenate([STILL_MODEL[None], models[moving]]), new_sizes


def _unexplained_regions(lost, edges, min_nodes, max_regions):
    """Connected regions (graph edges between two unexplained nodes) of unexplained nodes.

    Returns (M,) region ids 0..R-1 for the ``max_regions`` largest regions of at least
    ``min_nodes`` nodes, -1 elsewhere.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = len(lost)
    out = np.full(m, -1, dtype=np.int64)
    if lost.sum() < min_nodes:
        return out
    e = edges[lost[edges[:, 0]] & lost[edges[:, 1]]]
    _, comp = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)),
                                   directed=False)
    sizes = np.bincount(comp[lost], minlength=comp.max() + 1)
    big = np.flatnonzero(sizes >= min_nodes)
    big = big[np.argsort(-sizes[big], kind="stable")][:max_regions]
    rank = np.full(comp.max() + 1, -1, dtype=np.int64)
    rank[big] = np.arange(len(big))
    out[lost] = rank[comp[lost]]
    return out


def _merge_duplicates(models, data, labels, h, tol_px_s, radius_px, edges, edge_w):
    """Merge labels whose flow fields differ by less than ``tol_px_s`` over the sensor.

    Near-identical models (several sampled candidates converging to the background) are
    exactly what the label cost removes, but an expansion move between two near-identical
    labels is the slowest kind of max-flow (every node's two costs almost tie). The smaller
    label of such a pair joins the larger; the merge is kept only if the exact energy drops.
    """
    n = len(models)
    if n < 2:
        return models, data, labels, h
    from evseg.segmentation.motion_model import linear_parameters

    q = linear_parameters(models)
    dq = q[:, None, :] - q[None, :, :]
    diff = np.hypot(dq[..., 2], dq[..., 3]) + radius_px * np.hypot(dq[..., 0], dq[..., 1])
    sizes = np.bincount(labels, minlength=n)
    target = np.arange(n)
    for a in np.argsort(-sizes, kind="stable"):  # small loop over labels (L <= ~20), not nodes
        if target[a] != a:
            continue
        dup = np.flatnonzero((diff[a] < tol_px_s) & (target == np.arange(n)) & (np.arange(n) != a)
                             & (sizes <= sizes[a]))
        target[dup] = a
    if np.all(target == np.arange(n)):
        return models, data, labels, h
    keep = np.flatnonzero(target == np.arange(n))
    remap = np.full(n, -1, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    new_labels = remap[target[labels]]
    # A merged label keeps the lowest label cost of its members (a tracked object stays tracked).
    h_new = np.full(len(keep), np.inf)
    np.minimum.at(h_new, remap[target], h)
    if energy(new_labels, data[:, keep], edges, edge_w, h_new) < energy(labels, data, edges, edge_w, h):
        return models[keep], data[:, keep], new_labels, h_new
    return models, data, labels, h


def _any_on_sensor(x: np.ndarray, y: np.ndarray, sensor_size: tuple[int, int]) -> bool:
    """Whether any point (px) rounds to a pixel of the sensor."""
    w, h = sensor_size
    return bool(np.any((x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)))
