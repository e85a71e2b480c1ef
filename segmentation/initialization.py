"""Initialization (paper Sec. III-D): fast sampling and motion prediction of candidate models.

* Fast sampling: n normal flows with clearly different translation vectors each give a
  candidate (rho = 1, theta = 0, t = that flow's translation vector). "Clearly different" is made
  deterministic by counting the vectors in bins of a few residual scales (sigma): half the
  candidates are the most populated bins, the other half the bins farthest from every
  candidate so far (see :func:`fast_sampling`).

  The translation vector of a node (``sampling_flow = 'local'``, default) is the translation
  that best explains the normal flows of the node and its Delaunay neighbours (least squares
  of n_hat . t = |n| over the 1-ring, a 2x2 system per node accumulated with bincount). A
  single normal flow is only the component of the motion along its gradient, typically
  |u| sin(angle) away from the motion itself; its 1-ring sees several gradient directions and
  resolves the aperture problem, so an object's nodes vote for (nearly) one vector. A few
  Cauchy-reweighted iterations keep outlier flows in a ring from dragging the vote. Nodes
  whose ring is ill-conditioned (all gradients parallel) do not vote.
  ``sampling_flow = 'normal'`` uses the normal flow itself, as the paper's text reads. Populated bins first means random outlier flows, which
  scatter over many sparse bins, rarely become candidates.
* Motion prediction: each independently moving object (IMO) of the previous window is grown
  into a box (the box of its nodes plus ``margin_px`` on every side), the box is moved by the
  object's model flow at the box centre times the time between the windows, and a candidate is
  fitted by Levenberg-Marquardt (started from the previous model) to the current nodes inside
  the moved box. All boxes are fitted in one batched call.
"""

from __future__ import annotations

import numpy as np

from evseg.segmentation._kernels import ring_agreement as _ring_agreement
from evseg.segmentation._kernels import ring_pairs, ring_translations, spread_bins, vote_bins
from evseg.segmentation.fitting import fit_lm
from evseg.segmentation.motion_model import flow_field, models_from_linear, residual_jacobian


def local_translations(
    nx: np.ndarray,
    ny: np.ndarray,
    edges: np.ndarray,
    scale_px_s: float | None = None,
    irls_iterations: int = 3,
    min_conditioning: float = 0.1,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust least-squares translation of every node's 1-ring (the node and its neighbours).

    Solves sum_j w_j n_hat_j n_hat_j^T t = sum_j w_j |n_j| n_hat_j per node (2x2, closed form),
    first with w = 1, then ``irls_iterations`` times with Cauchy weights
    w_j = 1 / (1 + (r_j / scale)^2) of the ring's residuals r_j = n_hat_j . t - |n_j|, so a
    few wrong flows in a ring (outliers, the other side of an object boundary) do not drag
    the node's vote. One compiled pass per iteration over every node's ring (CSR of the
    directed edges, :func:`evseg.segmentation._kernels.ring_pairs`).

    Args:
        nx, ny: (M,) normal flow px/s (|n| > 0). edges: (E, 2) graph edges.
        scale_px_s: Cauchy scale (px/s); None = no reweighting.
        min_conditioning: nodes whose system has eigenvalue ratio below this do not vote.
    Returns:
        (tx, ty, ok): (M,) translations px/s and the (M,) mask of well-conditioned nodes.
    """
    nx = np.asarray(nx, dtype=np.float64)
    ny = np.asarray(ny, dtype=np.float64)
    norm = np.hypot(nx, ny)
    start, member = ring_pairs(np.asarray(edges, dtype=np.int64).reshape(-1, 2), len(nx))
    scale = float(scale_px_s) if scale_px_s is not None else 0.0
    return ring_translations(start, member, nx / norm, ny / norm, norm, scale,
                             int(irls_iterations), float(min_conditioning), nx, ny)


def ring_noise(
    nx: np.ndarray, ny: np.ndarray, edges: np.ndarray, scale_px_s: float,
    translations: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> float:
    """Robust scale (px/s) of the flows about their 1-ring translations.

    1.4826 x the median over well-conditioned nodes of |n_hat . t_ring - |n||, with t_ring the
    robust translation of the node's 1-ring (:func:`local_translations`, Cauchy scale
    ``scale_px_s``); over a ring the motion is nearly a translation, so this measures the
    noise of the flow, not the spread of the scene's motions. As each node is part of its own
    ring the estimate runs ~20-30 % below the noise's standard deviation along the normal (the
    gain ``residual_scale_noise`` absorbs that). Falls back to every node when no
    ring is well conditioned; 0.0 without nodes. ``translations``: the output of
    :func:`local_translations` for these flows and scale, if the caller has it already.
    """
    nx = np.asarray(nx, dtype=np.float64)
    ny = np.asarray(ny, dtype=np.float64)
    if len(nx) == 0:
        return 0.0
    if translations is None:
        translations = local_translations(nx, ny, edges, scale_px_s)
    tx, ty, ok = translations
    norm = np.hypot(nx, ny)
    r = (nx * tx + ny * ty) / norm - norm
    use = ok if ok.any() else np.ones(len(nx), dtype=bool)
    return float(1.4826 * np.median(np.abs(r[use])))


def ring_agreement(
    nx: np.ndarray, ny: np.ndarray, edges: np.ndarray, tx: np.ndarray, ty: np.ndarray, scale_px_s: float
) -> np.ndarray:
    """Mean Cauchy weight of each node's neighbours under the node's ring translation, (M,).

    Near 1 when the ring moves as one (inside the background or an object), low on object
    boundaries, at fast-rotating small objects and where the ring itself is noisy.
    """
    nx = np.asarray(nx, dtype=np.float64)
    ny = np.asarray(ny, dtype=np.float64)
    start, member = ring_pairs(np.asarray(edges, dtype=np.int64).reshape(-1, 2), len(nx))
    return _ring_agreement(start, member, nx, ny, np.hypot(nx, ny), np.asarray(tx, dtype=np.float64),
                           np.asarray(ty, dtype=np.float64), float(scale_px_s))


def fast_sampling(
    nx: np.ndarray,
    ny: np.ndarray,
    n: int,
    bin_px_s: float,
    min_separation_px_s: float,
    min_votes: int = 3,
) -> np.ndarray:
    """Up to ``n`` translation candidates from distinct flow vectors: frequent ones and far ones.

    The flow vectors are counted in square bins of ``bin_px_s`` over the whole flow plane (no
    range clipping). The first ceil(n/2) candidates are the means of the most populated bins
    (the background and large objects), skipping bins closer than ``min_separation_px_s`` to a
    candidate already taken; the rest are chosen by farthest-point sampling among bins with at
    least ``min_votes`` vectors: the bin farthest from every candidate so far, so a small object
    moving unlike anything else (a ball: 1 % of the nodes) is never crowded out by variations of
    the background. Bins with fewer votes (lone outliers) are never farthest-point candidates.

    Args:
        nx, ny: (M,) flow vectors (normal flows or 1-ring translations), px/s.
        n: number of candidates wanted; fewer come back when the flows are not that varied.
    Returns:
        (n', 4) models (1, 0, t_x, t_y), n' <= n.
    """
    if len(nx) == 0 or n < 1:
        return np.empty((0, 4))
    means, count = _vote_bins(nx, ny, bin_px_s)
    dist2 = np.full(len(means), np.inf)
    return _translations(spread_bins(means, count, int(n), (int(n) + 1) // 2, float(min_separation_px_s) ** 2,
                                     int(min_votes), dist2))


def farthest_candidates(
    nx: np.ndarray,
    ny: np.ndarray,
    taken: np.ndarray,
    n: int,
    bin_px_s: float,
    min_separation_px_s: float,
    min_votes: int = 3,
) -> np.ndarray:
    """Up to ``n`` more translation candidates: farthest-point sampling (as in
    :func:`fast_sampling`) over the bins of the vectors (nx, ny) with ``min_votes``, away from
    the translations ``taken`` (K, 2) px/s already chosen.

    Fed with the nodes' own normal flows, this seeds a small fast object whose 1-ring
    translations are unusable (its rings mix its nodes with the background's): a translating
    object's normal flows n = (T . n_hat) n_hat lie on the circle through 0 and its translation
    T, away from the background's, and a candidate among them, refitted to the nodes it takes
    in the first round, can become the object's model.

    Example:
        >>> nx = np.r_[np.full(50, 100.0), [300.0, 301.0, 302.0], [-40.0]]
        >>> ny = np.r_[np.zeros(50), [0.0, 1.0, 2.0], [0.0]]
        >>> farthest_candidates(nx, ny, np.array([[100.0, 0.0]]), 2, 10.0, 40.0).round(1).tolist()
        [[1.0, 0.0, 301.0, 1.0]]
    """
    if len(nx) == 0 or n < 1:
        return np.empty((0, 4))
    means, count = _vote_bins(nx, ny, bin_px_s)
    dist2 = np.full(len(means), np.inf)
    for t in np.asarray(taken, dtype=np.float64).reshape(-1, 2):  # a dozen candidates
        dist2 = np.minimum(dist2, ((means - t) ** 2).sum(axis=1))
    return _translations(spread_bins(means, count, int(n), 0, float(min_separation_px_s) ** 2, int(min_votes), dist2))


def _vote_bins(nx: np.ndarray, ny: np.ndarray, bin_px_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Mean vector (B, 2) and vote count (B,) of each occupied square bin of ``bin_px_s``."""
    return vote_bins(np.asarray(nx, dtype=np.float64), np.asarray(ny, dtype=np.float64), float(bin_px_s))


def _translations(t: list) -> np.ndarray:
    """(K, 4) models (1, 0, t_x, t_y) of the translations ``t``."""
    t = np.array(t).reshape(-1, 2)
    return np.column_stack([np.ones(len(t)), np.zeros(len(t)), t])


def predict_boxes(
    boxes: np.ndarray, models: np.ndarray, origin_px: tuple[float, float], dt_s: float, margin_px: float
) -> np.ndarray:
    """Move object boxes by their model's flow over ``dt_s`` seconds and grow them.

    Args:
        boxes: (K, 4) (x0, y0, x1, y1) px, absolute. models: (K, 4) of those objects.
        origin_px: model origin (column, row). dt_s: time from the previous window, s.
    Returns:
        (K, 4) float boxes, px.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(boxes) == 0:
        return boxes.copy()
    cx = (boxes[:, 0] + boxes[:, 2]) / 2.0 - origin_px[0]
    cy = (boxes[:, 1] + boxes[:, 3]) / 2.0 - origin_px[1]
    ux, uy = flow_field(models, cx, cy)
    k = np.arange(len(boxes))
    dx, dy = ux[k, k] * dt_s, uy[k, k] * dt_s
    return np.column_stack([boxes[:, 0] + dx - margin_px, boxes[:, 1] + dy - margin_px,
                            boxes[:, 2] + dx + margin_px, boxes[:, 3] + dy + margin_px])


def motion_prediction(
    x: np.ndarray,
    y: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    boxes: np.ndarray,
    models: np.ndarray,
    origin_px: tuple[float, float],
    dt_s: float,
    margin_px: float,
    min_nodes: int,
    weights: np.ndarray | None = None,
    loss: str = "cauchy",
    loss_scale_px_s: float = 1.0,
    iterations: int = 6,
    affine_prior_px: float = 0.0,
) -> np.ndarray:
    """Candidate models of the previous window's objects, fitted in their predicted boxes.

    Args:
        x, y: (M,) current node positions, absolute px. nx, ny: (M,) px/s.
        boxes: (K, 4) previous object boxes (inclusive px, absolute); models: (K, 4) their
            models about ``origin_px``. dt_s: seconds between the two windows.
        min_nodes: boxes holding fewer current nodes give no candidate.
    Returns:
        (K', 4) candidate models, K' <= K, in the order of the boxes.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    models = np.asarray(models, dtype=np.float64).reshape(-1, 4)
    if len(boxes) == 0 or len(x) == 0:
        return np.empty((0, 4))
    pred = predict_boxes(boxes, models, origin_px, dt_s, margin_px)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    inside = ((x[:, None] >= pred[:, 0]) & (x[:, None] <= pred[:, 2])
              & (y[:, None] >= pred[:, 1]) & (y[:, None] <= pred[:, 3]))  # (M, K)
    counts = inside.sum(axis=0)
    ok = np.flatnonzero(counts >= min_nodes)
    if len(ok) == 0:
        return np.empty((0, 4))
    node, box = np.nonzero(inside[:, ok])  # a node may lie in several boxes: repeat it
    w = None if weights is None else np.asarray(weights, dtype=np.float64)[node]
    fitted = fit_lm(x[node] - origin_px[0], y[node] - origin_px[1], np.asarray(nx)[node],
                    np.asarray(ny)[node], box, models[ok], weights=w, loss=loss,
                    loss_scale_px_s=loss_scale_px_s, iterations=iterations,
                    affine_prior_px=affine_prior_px)
    return fitted


def consensus_models(
    x: np.ndarray,
    y: np.ndarray,
    nx: np.ndarray,
    ny: np.ndarray,
    region: np.ndarray,
    n_regions: int,
    inlier_px_s: float,
    n_hypotheses: int = 64,
    seed: int = 0,
) -> np.ndarray:
    """One affine model per region by sample consensus over minimal 4-node samples.

    A region of unexplained nodes (round 0b of the solver) can hold as many stray flows as flows
    of the object it outlines; a least-squares or even a Cauchy fit started from least squares
    then lands between the two. Each hypothesis here solves the 4 x 4 linear system of 4 random
    nodes of the region exactly (the residual is linear in q = (a, b, t_x, t_y), see
    :mod:`.motion_model`); the one with the most nodes within ``inlier_px_s`` of their normal
    flow wins. A region's hypotheses are solved and scored in batched numpy calls.

    Args:
        x, y: (M,) px from the model origin. nx, ny: (M,) normal flow, px/s.
        region: (M,) int region id in [0, n_regions), -1 = not in any region.
        inlier_px_s: residual (|n|-normalised, px/s) under which a node supports a hypothesis.
        n_hypotheses: minimal samples per region. seed: of the sampler (deterministic).
    Returns:
        (n_regions, 4) models (rho, theta, t_x, t_y); a region under 4 nodes or without one
        solvable sample gets the identity model (1, 0, 0, 0).
    """
    region = np.asarray(region, dtype=np.int64)
    J, norm = residual_jacobian(x, y, nx, ny)  # residual = J q - |n|
    rng = np.random.default_rng(seed)
    out = np.tile([1.0, 0.0, 0.0, 0.0], (n_regions, 1))
    for r in range(n_regions):  # a handful of regions; the hypotheses inside are batched
        members = np.flatnonzero(region == r)
        if len(members) < 4:
            continue
        pick = members[rng.integers(0, len(members), size=(n_hypotheses, 4))]
        A, b = J[pick], norm[pick]  # (H, 4, 4), (H, 4)
        det = np.linalg.det(A)
        ok = np.abs(det) > 1e-9 * np.abs(A).max(axis=(1, 2)) ** 4
        if not ok.any():
            continue
        q = np.linalg.solve(A[ok], b[ok, :, None])[:, :, 0]  # (H', 4)
        res = J[members] @ q.T - norm[members, None]  # (n, H')
        support = (np.abs(res) <= inlier_px_s).sum(axis=0)
        out[r] = models_from_linear(q[np.argmax(support)][None])[0]
    return out
