"""One window's preparation: everything the segmentation derives from a window's normal flow
alone, with no motion model and nothing of the previous window.

:func:`prepare_window` builds the node graph (:mod:`.preprocessing`) and the per-node terms of
the energy (residual scale from the flow's 1-ring noise, confidences, support weights, the
fast-sampling votes); :func:`sample_candidates` adds round 0's sampled candidates and their
fits to their voters (steps 1-3 of :mod:`.solver`). A streaming caller can run both for window
t + 1 in another thread or process while window t is segmented (:func:`.solver.segment_prepared`
does the rest, in window order); the pipeline does.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from evseg.errors import EventDataError
from evseg.segmentation.config import SegmentationConfig
from evseg.segmentation.energy import data_costs, potts_weights
from evseg.segmentation.fitting import fit_lm
from evseg.segmentation.initialization import (
    farthest_candidates, fast_sampling, local_translations, ring_agreement, ring_noise,
)
from evseg.segmentation.preprocessing import NodeGraph, build_node_graph


def _arrays(x, y, t, nx, ny, uncertainty) -> dict[str, np.ndarray]:
    """The window's arrays by name (checked by :func:`.solver._check_window_arrays`)."""
    arrays = {"x": x, "y": y, "t": t, "nx": nx, "ny": ny}
    if uncertainty is not None:
        arrays["uncertainty"] = uncertainty
    return {k: np.asarray(v) for k, v in arrays.items()}


def _uncertainty_terms(
    cfg: SegmentationConfig, graph, uncertainty: np.ndarray | None, sigma: float
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Per-node data-term confidence (M,), residual scale factor (M,) >= 1 or None and angular
    uncertainty (M,) rad or None (``uncertainty_angle_gain``), from the flows' uncertainty as
    ``cfg.uncertainty_use`` says (see :class:`SegmentationConfig`)."""
    m = len(graph)
    if uncertainty is None or cfg.uncertainty_use == "ignore":
        return np.ones(m), None, None
    if cfg.uncertainty_use == "confidence":
        return graph.confidence, None, None
    u = np.nan_to_num(np.asarray(uncertainty, dtype=np.float64)[graph.index], nan=0.0, posinf=1e6)
    spread = cfg.uncertainty_gain * np.hypot(graph.nx, graph.ny) * u
    angle = cfg.uncertainty_angle_gain * u if cfg.uncertainty_angle_gain > 0 else None
    return np.ones(m), np.sqrt(1.0 + (spread / sigma) ** 2), angle


SUPPORT_WEIGHT_RANGE = (0.25, 4.0)
"""Clip of a node's support weight (see ``SegmentationConfig.support_exponent``): a dense
cell can count at most 4 nodes' worth, a lone event a quarter."""


def support_weights(support: np.ndarray | None, exponent: float) -> np.ndarray:
    """Per-node weight (s / median s)^exponent, clipped to :data:`SUPPORT_WEIGHT_RANGE`.

    Example:
        >>> support_weights(np.array([1.0, 4.0, 4.0, 64.0]), 0.5).tolist()
        [0.5, 1.0, 1.0, 4.0]
    """
    s = np.ones(0) if support is None else np.asarray(support, dtype=np.float64)
    if exponent == 0 or len(s) == 0:
        return np.ones(len(s))
    return np.clip((s / np.median(s)) ** exponent, *SUPPORT_WEIGHT_RANGE)


def _event_xy(event_xy) -> tuple[np.ndarray, np.ndarray] | None:
    if event_xy is None:
        return None
    try:
        ex, ey = (np.asarray(v, dtype=np.float64).ravel() for v in event_xy)
    except (TypeError, ValueError) as err:
        raise EventDataError(f"event_xy must be a pair of numeric (N,) arrays: {err}") from None
    if len(ex) != len(ey):
        raise EventDataError(f"event_xy: x has {len(ex)} values, y has {len(ey)}")
    if not (np.isfinite(ex).all() and np.isfinite(ey).all()):
        raise EventDataError("event_xy holds NaN or infinite positions")
    return ex, ey


def _origin(config: SegmentationConfig, sensor_size) -> tuple[float, float]:
    if config.origin_px is not None:
        return config.origin_px
    if sensor_size is not None:
        return ((sensor_size[0] - 1) / 2.0, (sensor_size[1] - 1) / 2.0)
    return (0.0, 0.0)


@dataclass(frozen=True)
class SampledCandidates:
    """The window-local part of round 0 (steps 2-3 of :mod:`.solver`) for one candidate count:
    ``n_asked`` translations by fast sampling, each LM-fitted to its voters.

    Attributes:
        n_asked: candidates asked of fast sampling (``n_sampled`` or ``n_sampled_with_prediction``).
        models: (n', 4) fitted models, n' <= n_asked. data: (M, n') their data costs.
        sampling_ms, fitting_ms: wall time of the sampling and of the fits, ms (reported under
            'initialization' and 'labeling_fitting' like the rest of those stages).
        sampling_cpu_ms, fitting_cpu_ms: the process CPU time over the same spans, ms (the
            stages' '_cpu' timings; they include other threads of the process).
    """

    n_asked: int
    models: np.ndarray
    data: np.ndarray
    sampling_ms: float
    fitting_ms: float
    sampling_cpu_ms: float
    fitting_cpu_ms: float


@dataclass(frozen=True)
class PreparedWindow:
    """What :func:`prepare_window` derives from one window's normal flow alone: the node graph
    and every per-node term of the energy (no motion model, nothing of the previous window).

    Attributes:
        config, sensor_size, origin: as given / chosen (origin px, the models' reference).
        graph: the :class:`~.preprocessing.NodeGraph`. xr, yr: (M,) node positions from the
            origin, px. grown: the node budget's cell growth g (1 without a budget).
        lambda_m: label cost (lambda_m / g). sigma: residual scale, px/s. edge_w: (E,) Potts
            weights. radius: largest node distance from the origin, px. t_ref: reference time
            (middle of the nodes' time span), us.
        conf, node_scale: (M,) data-term weights and per-node residual scale factors (or None).
        fit_w: (M,) fitting weights. vote_x, vote_y, voting: fast-sampling votes (px/s) and
            which nodes vote. suspect: (M,) likely outliers. timings: ms of this step.
        sampled: round 0's sampled candidates already computed (:func:`with_sampled_candidates`),
            one entry per candidate count asked; :func:`.solver.segment_prepared` computes the count
            it needs when it is not there.
        flow_noise_rel: the flow's 1-ring noise over its median magnitude (NaN when not
            measured), which sets the strength of contrast-sensitive Potts.
        node_angle: (M,) angular uncertainty (rad) propagated through each model's flow in the
            data term, or None (``uncertainty_angle_gain`` 0).
    """

    config: SegmentationConfig
    sensor_size: tuple[int, int] | None
    origin: tuple[float, float]
    graph: NodeGraph
    xr: np.ndarray
    yr: np.ndarray
    grown: float
    lambda_m: float
    sigma: float
    edge_w: np.ndarray
    radius: float
    t_ref: int
    conf: np.ndarray
    node_scale: np.ndarray | None
    fit_w: np.ndarray
    vote_x: np.ndarray
    vote_y: np.ndarray
    voting: np.ndarray
    suspect: np.ndarray
    timings: dict
    sampled: tuple[SampledCandidates, ...] = ()
    flow_noise_rel: float = float("nan")
    node_angle: np.ndarray | None = None

    @property
    def max_propagation_px(self) -> float:
        """Label propagation's distance limit (px), grown with the node budget's cells."""
        return self.config.max_propagation_px * self.grown


def lm_kwargs(pw: PreparedWindow) -> dict:
    """Keyword arguments of every LM fit of a window (robust loss, scale, weights)."""
    cfg = pw.config
    return dict(loss=cfg.robust_loss, loss_scale_px_s=cfg.robust_scale * pw.sigma,
                truncation=cfg.truncation / cfg.robust_scale, iterations=cfg.lm_iterations,
                damping=cfg.lm_damping, weights=pw.fit_w, affine_prior_px=cfg.affine_prior_px)


def window_costs(pw: PreparedWindow, models: np.ndarray) -> np.ndarray:
    """(M, L) data costs of ``models`` at the window's nodes."""
    g = pw.graph
    return data_costs(models, pw.xr, pw.yr, g.nx, g.ny, pw.sigma, pw.config.truncation, pw.conf, pw.node_scale,
                      pw.node_angle)


def sample_candidates(prepared: PreparedWindow, n: int) -> SampledCandidates:
    """Fast sampling of ``n`` candidates and their round-0 fits to their voters (steps 2-3 of
    :mod:`.solver`). Needs nothing of the previous window: each candidate's fit sees only
    its own voters, so the result does not depend on the predicted candidates beside it."""
    pw = prepared
    tic, cpu = time.perf_counter(), time.process_time()
    bin_px_s = pw.config.sampling_bin * pw.sigma
    separation = pw.config.min_candidate_separation * pw.sigma
    sampled = fast_sampling(pw.vote_x[pw.voting], pw.vote_y[pw.voting], n, bin_px_s, separation)
    if pw.config.n_sampled_normal > 0 and len(pw.graph):
        extra = farthest_candidates(pw.graph.nx, pw.graph.ny, sampled[:, 2:], pw.config.n_sampled_normal,
                                    bin_px_s, separation)
        sampled = np.concatenate([sampled, extra])
    sampling_ms, sampling_cpu_ms = (time.perf_counter() - tic) * 1e3, (time.process_time() - cpu) * 1e3
    tic, cpu = time.perf_counter(), time.process_time()
    if len(pw.graph) == 0:
        return SampledCandidates(n, np.empty((0, 4)), np.empty((0, 0)), sampling_ms, 0.0, sampling_cpu_ms, 0.0)
    fit_on = round0_voters(pw.vote_x, pw.vote_y, pw.voting, sampled[:, 2:], bin_px_s)
    models, data = refit_to_labels(sampled, window_costs(pw, sampled), fit_on, pw.xr, pw.yr, pw.graph,
                                   lm_kwargs(pw), lambda mod: window_costs(pw, mod), np.arange(len(pw.graph)),
                                   always=True)
    return SampledCandidates(n, models, data, sampling_ms, (time.perf_counter() - tic) * 1e3,
                             sampling_cpu_ms, (time.process_time() - cpu) * 1e3)


def with_sampled_candidates(prepared: PreparedWindow, counts: tuple[int, ...] | None = None) -> PreparedWindow:
    """``prepared`` with round 0's sampled candidates computed for each count in ``counts``
    (default: the config's ``n_sampled`` and ``n_sampled_with_prediction``).

    Which count a window uses depends on whether the previous window's objects gave predicted
    candidates, so a streaming caller preparing window t + 1 while window t is segmented computes
    both; :func:`.solver.segment_prepared` then only picks one (same result as computing it there).
    """
    cfg = prepared.config
    if counts is None:
        counts = (cfg.n_sampled, cfg.n_sampled_with_prediction)
    have = {c.n_asked for c in prepared.sampled}
    extra = tuple(sample_candidates(prepared, int(n)) for n in dict.fromkeys(counts) if int(n) not in have)
    return replace(prepared, sampled=prepared.sampled + extra)


def prepare_window(
    x: np.ndarray,
    y: np.ndarray,
    t: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    uncertainty: np.ndarray | None = None,
    config: SegmentationConfig = SegmentationConfig(),
    sensor_size: tuple[int, int] | None = None,
    event_xy: tuple[np.ndarray, np.ndarray] | None = None,
) -> PreparedWindow:
    """The part of :func:`.solver.segment_normal_flow` that needs no earlier window: pre-processing
    (nodes, Delaunay graph) and the per-node terms (residual scale from the flow's 1-ring
    noise, confidences, fast-sampling votes). Same arguments; a streaming caller can prepare
    window t + 1 on another thread while window t is segmented (:func:`.solver.segment_prepared`).
    """
    from evseg.segmentation.config import as_segmentation_config
    from evseg.segmentation.solver import _check_window_arrays

    _check_window_arrays(x, y, t, nx, ny, uncertainty)
    if sensor_size is not None:
        from evseg.events import checked_sensor_size

        sensor_size = checked_sensor_size(sensor_size)
    a = _arrays(x, y, t, nx, ny, uncertainty)
    cfg = as_segmentation_config(config)
    timings = {}
    tic, cpu = time.perf_counter(), time.process_time()
    graph = build_node_graph(a["x"], a["y"], a["t"], a["nx"], a["ny"], a.get("uncertainty"),
                             cfg.cell_px, cfg.min_flow_px_s, cfg.max_uncertainty,
                             cfg.node_window_us, cfg.uncertainty_scale, cfg.cell_rule, cfg.max_nodes,
                             _event_xy(event_xy), cfg.min_cell_events)
    origin = _origin(cfg, sensor_size)
    # When the node budget made the cell grow by g, each node stands for ~g nodes of the finer
    # grid along an edge: the lengths tied to the node spacing grow by g and the label cost
    # shrinks by g, so the data and Potts totals (which shrink by ~g with the node count) keep
    # their balance against it (on 1280x720 simulated windows, oracle flow, budget 12,000:
    # detection 0.73 with the label cost unchanged, 0.88 scaled; 0.97 without a budget).
    grown = graph.cell_px / cfg.cell_px if cfg.cell_px > 0 else 1.0
    lambda_m = cfg.lambda_m / grown
    xr, yr = graph.x - origin[0], graph.y - origin[1]
    m = len(graph)
    norm = np.hypot(graph.nx, graph.ny)
    sigma = max(cfg.residual_scale_px_s, cfg.residual_scale_rel * float(np.median(norm))) if m else 1.0
    edge_w = potts_weights(graph.edge_length, cfg.lambda_p, cfg.potts_weighting, cfg.edge_scale_px)
    radius = float(np.sqrt(np.max(xr * xr + yr * yr))) if m else 1.0
    # Reference time: the middle of the flows' time span (the window's mid-time).
    t_ref = int((graph.t.min() + graph.t.max()) // 2) if m else 0
    timings["preprocessing"] = (time.perf_counter() - tic) * 1e3
    timings["preprocessing_cpu"] = (time.process_time() - cpu) * 1e3

    tic, cpu = time.perf_counter(), time.process_time()
    # Each node's vote for fast sampling: its 1-ring translation ('local', well-conditioned
    # rings only) or its normal flow ('normal').
    vote_x, vote_y, voting = graph.nx, graph.ny, np.ones(m, dtype=bool)
    suspect = np.zeros(m, dtype=bool)  # flows that contradict a 1-ring moving as one
    # The residual scale also follows the measured noise of the flow (about its 1-ring
    # translations): exact flow can be judged tightly, a learned estimate cannot.
    rings = None
    noise_rel = float("nan")
    if (cfg.residual_scale_noise > 0 or cfg.contrast_min_weight < 1) and m:
        rings = local_translations(graph.nx, graph.ny, graph.edges, sigma)
        noise = ring_noise(graph.nx, graph.ny, graph.edges, sigma, translations=rings)
        noise_rel = noise / float(np.median(norm))
        if cfg.residual_scale_noise * noise > sigma:
            sigma, rings = cfg.residual_scale_noise * noise, None  # the rings' scale changed
    conf, node_scale, node_angle = _uncertainty_terms(cfg, graph, a.get("uncertainty"), sigma)
    conf = conf * support_weights(graph.support, cfg.support_exponent)
    if cfg.sampling_flow == "local" and m:
        if rings is None:
            rings = local_translations(graph.nx, graph.ny, graph.edges, sigma)
        vote_x, vote_y, ring_ok = rings
        # Every node votes when no 1-ring is well conditioned (e.g. one straight edge).
        voting = ring_ok if ring_ok.any() else voting
        if cfg.ring_consistency:
            # A flow that contradicts a 1-ring which otherwise moves as one is likely an outlier:
            # it weighs less in the data term and the fits. Rings that do not agree (object
            # boundaries, small fast-spinning objects) leave their node's weight alone.
            r_self = (graph.nx * vote_x + graph.ny * vote_y) / norm - norm
            agree = ring_agreement(graph.nx, graph.ny, graph.edges, vote_x, vote_y, sigma)
            own = sigma if node_scale is None else sigma * node_scale
            coherent = ring_ok & (agree >= 0.5)
            factor = 1.0 / (1.0 + (r_self / (cfg.truncation * own)) ** 2)
            conf = conf * np.where(coherent, factor, 1.0)
            suspect = coherent & (np.abs(r_self) > cfg.truncation * own)
    # Fitting weight: the confidence, and (sigma / sigma_k)^2 where a node has its own scale.
    fit_w = conf if node_scale is None else conf / node_scale**2
    timings["initialization"] = (time.perf_counter() - tic) * 1e3
    timings["initialization_cpu"] = (time.process_time() - cpu) * 1e3
    return PreparedWindow(
        config=cfg, sensor_size=sensor_size, origin=origin, graph=graph, xr=xr, yr=yr, grown=grown,
        lambda_m=lambda_m, sigma=sigma, edge_w=edge_w, radius=radius, t_ref=t_ref, conf=conf,
        node_scale=node_scale, fit_w=fit_w, vote_x=vote_x, vote_y=vote_y, voting=voting,
        suspect=suspect, timings=timings, flow_noise_rel=noise_rel, node_angle=node_angle)


def round0_voters(vote_x, vote_y, voting, cand_t, bin_px_s):
    """Round-0 fitting labels: each voting node joins the nearest sampled candidate whose
    translation lies within two sampling bins of its vote (label j), else -1.

    The voters of a candidate are the nodes whose 1-ring moves like it - for a small object,
    the object itself - so its first fit sees the object, not every node it happens to fit.
    """
    out = np.full(len(vote_x), -1, dtype=np.int64)
    if len(cand_t) == 0:
        return out
    d2 = (vote_x[:, None] - cand_t[:, 0]) ** 2 + (vote_y[:, None] - cand_t[:, 1]) ** 2
    j = np.argmin(d2, axis=1)
    near = voting & (d2[np.arange(len(j)), j] <= 4.0 * bin_px_s * bin_px_s)
    out[near] = j[near]
    return out


def refit_to_labels(models, data, labels, xr, yr, graph, lm_kw, costs, ar, always=False):
    """LM-refit every label's model to its nodes (label -1: left out).

    A new model replaces the old one only if it lowers its label's data energy, so that the
    alternation never raises the energy; ``always`` (round 0, before any energy is defined)
    takes every label's fit that saw nodes.
    """
    new = fit_lm(xr, yr, graph.nx, graph.ny, labels, models, **lm_kw)  # weights = confidence
    new_data = costs(new)
    n = len(models)
    if always:
        seen = np.bincount(labels[labels >= 0], minlength=n) > 0
        models = models.copy()
        models[seen] = new[seen]
        data = data.copy()
        data[:, seen] = new_data[:, seen]
        return models, data
    e_old = np.bincount(labels, weights=data[ar, labels], minlength=n)
    e_new = np.bincount(labels, weights=new_data[ar, labels], minlength=n)
    better = e_new < e_old - 1e-12 * np.maximum(e_old, 1.0)
    if not better.any():
        return models, data
    models = models.copy()
    models[better] = new[better]
    data = data.copy()
    data[:, better] = new_data[:, better]
    return models, data
