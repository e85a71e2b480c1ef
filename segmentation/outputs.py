"""Outputs of a segmented window: object regions (node subsets), boxes, dense masks, and the
propagation of node labels to any points (e.g. every event of the window).

Objects and their regions: an independently moving object (IMO) is a connected part (in the
Delaunay graph, over edges joining two nodes of the same label) of a moving label; sizeable
parts of one label are separate objects sharing its model (:func:`split_objects`), small
fragments stay with the label's largest part but outside its region, so a few nodes wrongly
given the label far away do not blow up a box or hull.

Box: inclusive pixel box (x0, y0, x1, y1) of the region's nodes, grown by ``grow_px`` (nodes
lie on edges and texture, the silhouette reaches a little further) and clipped to the sensor.

Dense mask, ``method``:
* 'hull' (EMSGC's choice): filled convex hull of the region's nodes, dilated by ``grow_px``.
* 'dilate': the region's nodes rasterised, dilated by ``cell_px / 2 + grow_px`` and closed
  with a kernel of 2 * cell_px so that the gaps between nodes fill; follows concave shapes.
"""

from __future__ import annotations

import math

import numpy as np

from evseg.segmentation._kernels import same_label_components


def background_layers(
    labels: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    sensor_size: tuple[int, int],
    max_extent: float,
    grid: int = 8,
) -> np.ndarray:
    """Object labels (>= 1) spread over the image like a background layer.

    The image is cut into ``grid`` x ``grid`` cells; a label's coverage is the share of the
    cells holding any node that hold at least 2 nodes of the label (2, so a few stray nodes
    do not count). A net or fence in front of the scene, or a model that only collected
    scattered outliers, covers most of the image; an object covers its own patch.

    Returns:
        int64 array of the labels whose coverage exceeds ``max_extent``.
    """
    labels = np.asarray(labels, dtype=np.int64)
    w, h = sensor_size
    cx = np.clip((np.asarray(x) * grid / w).astype(np.int64), 0, grid - 1)
    cy = np.clip((np.asarray(y) * grid / h).astype(np.int64), 0, grid - 1)
    cell = cx * grid + cy
    n_labels = int(labels.max()) + 1 if len(labels) else 0
    if n_labels <= 1:
        return np.empty(0, dtype=np.int64)
    valid = labels >= 0
    counts = np.bincount(labels[valid] * grid * grid + cell[valid],
                         minlength=n_labels * grid * grid).reshape(n_labels, grid * grid)
    occupied = max(int(np.count_nonzero(np.bincount(cell, minlength=grid * grid))), 1)
    coverage = (counts >= 2).sum(axis=1) / occupied
    layers = np.flatnonzero(coverage > max_extent)
    return layers[layers >= 1]


def split_objects(
    labels: np.ndarray,
    edges: np.ndarray,
    models: np.ndarray,
    min_nodes: int,
    x: np.ndarray | None = None,
    y: np.ndarray | None = None,
    gap_px: float = 0.0,
    max_parts: int = 0,
    isolated_out: bool = False,
    occlusion_gap_px: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """Make every sizeable separate part of a moving label its own object.

    Two objects moving alike share one motion label; on the image they are separate parts of
    it. A part is a connected component of the label's own graph edges, joined with the label's
    other components whose boxes come within ``gap_px`` (an object seen through a net, or with
    a few outlier nodes inside, falls apart into nearby components). Each part with at least
    ``min_nodes`` nodes (and at least a quarter of the label's largest part) becomes an object
    with a copy of the label's model; smaller fragments keep the label of the label's largest
    part and stay out of its region. A label with no part of ``min_nodes`` nodes is dropped
    and its nodes become -1. A label with more than ``max_parts`` sizeable parts (0 = no limit)
    is a scattered background layer, not objects (a patch of a net whose parallax differs a
    little from the rest of the net): its nodes join the background (label 0).

    Args:
        labels: (M,) 0 = background, 1..K objects, -1 unassigned. edges: (E, 2).
        models: (K+1, 4). min_nodes: minimum size of a separate object.
        x, y: (M,) node positions px (needed when gap_px > 0). gap_px: joining distance, px.
        max_parts: most separate objects one label may make (0 = no limit).
        isolated_out: leave out of each object's region (box, mask) the nodes with no graph
            edge of at most ``gap_px`` to another node of it: scattered nodes that a long
            Delaunay edge ties to the object (sensor noise under a still camera, where nothing
            else fires); they keep the object's label.
    Returns:
        (labels, models, regions): new labels 1..K' by decreasing part size, (K'+1, 4) models,
        and {k: node indices of object k's region}.
    """
    labels = np.asarray(labels, dtype=np.int64)
    m = len(labels)
    if len(models) <= 1 or m == 0:
        return labels.copy(), np.asarray(models).reshape(-1, 4).copy(), {}
    edges = np.ascontiguousarray(np.asarray(edges, dtype=np.int64).reshape(-1, 2))
    comp = same_label_components(labels, edges)
    if gap_px > 0 and x is not None:
        comp = _join_near_components(comp, labels, np.asarray(x, dtype=np.float64),
                                     np.asarray(y, dtype=np.float64), gap_px, edges, occlusion_gap_px, min_nodes)
    parts = []  # (size, label, component id)
    layer = []  # labels scattered into more than max_parts parts
    fragments = {}  # label -> (component ids that stay with its largest part)
    for k in range(1, len(models)):  # loop over labels (a handful), arrays inside
        nodes = np.flatnonzero(labels == k)
        if len(nodes) == 0:
            continue
        ids, sizes = np.unique(comp[nodes], return_counts=True)
        big = (sizes >= min_nodes) & (sizes >= 0.25 * sizes.max())
        if not big.any():
            continue  # scattered nodes only (e.g. outliers one model happens to fit): unassigned
        if 0 < max_parts < int(big.sum()):
            layer.append(k)
            continue
        for c, n in zip(ids[big], sizes[big]):
            parts.append((int(n), k, int(c)))
        fragments[k] = (int(ids[np.argmax(sizes)]), ids[~big])
    parts.sort(key=lambda p: (-p[0], p[1], p[2]))
    new_labels = np.where((labels == 0) | np.isin(labels, layer), 0, -1)
    new_models = [np.asarray(models[0])]
    regions = {}
    part_label = {}
    for j, (_, k, c) in enumerate(parts, start=1):
        nodes = np.flatnonzero((labels == k) & (comp == c))
        new_labels[nodes] = j
        new_models.append(np.asarray(models[k]))
        regions[j] = nodes
        part_label[(k, c)] = j
    for k, (main, small) in fragments.items():
        frag = (labels == k) & np.isin(comp, small)
        new_labels[frag] = part_label[(k, main)]
    if isolated_out and gap_px > 0 and x is not None and regions:
        regions = _without_isolated(regions, m, edges,
                                    np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), gap_px)
    return new_labels, np.array(new_models).reshape(-1, 4), regions


def _without_isolated(regions: dict[int, np.ndarray], m: int, edges: np.ndarray, x: np.ndarray,
                      y: np.ndarray, gap_px: float) -> dict[int, np.ndarray]:
    """Each region without its nodes that have no graph edge of at most ``gap_px`` to another
    node of the region (a region left empty keeps its nodes)."""
    short = np.hypot(x[edges[:, 0]] - x[edges[:, 1]], y[edges[:, 0]] - y[edges[:, 1]]) <= gap_px
    region_of = np.full(m, -1, dtype=np.int64)
    for j, nodes in regions.items():
        region_of[nodes] = j
    same = short & (region_of[edges[:, 0]] == region_of[edges[:, 1]]) & (region_of[edges[:, 0]] >= 0)
    close = np.zeros(m, dtype=bool)
    close[edges[same].ravel()] = True
    return {j: (nodes[close[nodes]] if close[nodes].any() else nodes) for j, nodes in regions.items()}


def _component_boxes(comp, labels, x, y):
    """Per component id: its label and box (x0, y0, x1, y1), px."""
    n = int(comp.max()) + 1
    lab_of = np.full(n, -1, dtype=np.int64)
    lab_of[comp] = labels
    x0 = np.full(n, np.inf)
    y0 = np.full(n, np.inf)
    x1 = np.full(n, -np.inf)
    y1 = np.full(n, -np.inf)
    np.minimum.at(x0, comp, x)
    np.minimum.at(y0, comp, y)
    np.maximum.at(x1, comp, x)
    np.maximum.at(y1, comp, y)
    return lab_of, x0, y0, x1, y1


def _join_components(n, cand, join):
    """(n,) map of component ids: those of ``cand`` linked by the (C, C) bool matrix ``join``
    go to the first id of their group, the rest to themselves.

    Groups by repeated min-label propagation over the small dense matrix (C is a few dozen
    object components), not scipy's connected_components, whose checks cost ~0.2 ms a call.
    """
    c = len(cand)
    link = join | join.T
    group = np.arange(c)
    while True:
        nxt = np.where(link, group[None, :], c).min(axis=1)
        nxt = np.minimum(nxt, group)
        if np.array_equal(nxt, group):
            break
        group = nxt
    new = np.arange(n)
    new[cand] = cand[group]
    return new


def _near_pairs(cand, lab_of, x0, y0, x1, y1, gap_px):
    """(C, C) bool: components of one label whose boxes come within ``gap_px``."""
    a, b = cand[:, None], cand[None, :]
    return ((lab_of[a] == lab_of[b]) & (x0[a] <= x1[b] + gap_px) & (x0[b] <= x1[a] + gap_px)
            & (y0[a] <= y1[b] + gap_px) & (y0[b] <= y1[a] + gap_px))


def _join_near_components(comp, labels, x, y, gap_px, edges=None, occlusion_gap_px=0.0, min_nodes=1):
    """Relabel components so that components of one label with boxes within ``gap_px`` share an
    id; then so do those within ``occlusion_gap_px`` that have ``min_nodes`` nodes each and
    both touch (a graph edge) one component of another object label: the object in front
    splits the object behind it (stray nodes of the label inside the occluder do not count)."""
    lab_of, x0, y0, x1, y1 = _component_boxes(comp, labels, x, y)
    cand = np.flatnonzero(lab_of >= 1)  # components of object labels only
    if len(cand) < 2:
        return comp
    n = len(lab_of)
    to = _join_components(n, cand, _near_pairs(cand, lab_of, x0, y0, x1, y1, gap_px))
    if not (occlusion_gap_px > gap_px and edges is not None and len(edges)):
        return to[comp]
    # The joined groups' sizes and boxes, from their members' (a few dozen components).
    size = np.bincount(to[comp], minlength=n)
    np.minimum.at(x0, to[cand], x0[cand])
    np.minimum.at(y0, to[cand], y0[cand])
    np.maximum.at(x1, to[cand], x1[cand])
    np.maximum.at(y1, to[cand], y1[cand])
    cand = np.flatnonzero((lab_of >= 1) & (to == np.arange(n)) & (size >= min_nodes))
    if len(cand) < 2 or len(np.unique(lab_of[cand])) == len(cand):
        return to[comp]  # no label has two sizeable parts: nothing to join
    comp = to[comp]
    la, lb = labels[edges[:, 0]], labels[edges[:, 1]]
    touch = (la >= 1) & (lb >= 1) & (la != lb)
    if not touch.any():
        return comp
    ca, cb = comp[edges[:, 0]][touch], comp[edges[:, 1]][touch]
    ids, pair = np.unique(np.concatenate([ca, cb]), return_inverse=True)
    t = np.zeros((len(ids), len(ids)), dtype=np.int64)  # components that touch
    t[pair[: len(ca)], pair[len(ca):]] = 1
    t[pair[len(ca):], pair[: len(ca)]] = 1
    at = np.searchsorted(ids, cand)
    seen = (at < len(ids)) & (ids[np.minimum(at, len(ids) - 1)] == cand)
    rows = np.where(seen[:, None], t[np.minimum(at, len(ids) - 1)], 0)
    common = (rows @ rows.T) > 0  # two components, one occluder
    join = common & _near_pairs(cand, lab_of, x0, y0, x1, y1, occlusion_gap_px)
    return _join_components(n, cand, join)[comp]


def region_box(
    x: np.ndarray, y: np.ndarray, grow_px: float, sensor_size: tuple[int, int] | None
) -> tuple[int, int, int, int]:
    """Inclusive px box (x0, y0, x1, y1) of points grown by ``grow_px``, clipped to the sensor
    (both ends of each side, so it is never inverted: points wholly beyond an edge give a
    one-pixel side on that edge).

    >>> region_box(np.array([-20.0, -5.0]), np.array([10.0, 12.0]), 0.0, (346, 260))
    (0, 10, 0, 12)
    """
    x0 = int(np.floor(x.min() - grow_px))
    y0 = int(np.floor(y.min() - grow_px))
    x1 = int(np.ceil(x.max() + grow_px))
    y1 = int(np.ceil(y.max() + grow_px))
    if sensor_size is not None:
        w, h = sensor_size
        x0, x1 = min(max(x0, 0), w - 1), min(max(x1, 0), w - 1)
        y0, y1 = min(max(y0, 0), h - 1), min(max(y1, 0), h - 1)
    return x0, y0, x1, y1


def _disk(radius_px: float) -> np.ndarray:
    import cv2

    r = max(int(round(radius_px)), 0)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def region_mask(
    x: np.ndarray,
    y: np.ndarray,
    sensor_size: tuple[int, int],
    method: str = "hull",
    grow_px: float = 2.0,
    cell_px: float = 4.0,
) -> np.ndarray:
    """Dense boolean mask (height, width) of the points' region (see module docstring)."""
    import cv2

    w, h = sensor_size
    m = np.zeros((h, w), dtype=np.uint8)
    if len(x) == 0:
        return m.astype(bool)
    pts = np.column_stack([np.round(x), np.round(y)]).astype(np.int32)
    if method == "hull":
        cv2.fillConvexPoly(m, cv2.convexHull(pts.reshape(-1, 1, 2)), 1)
        if grow_px > 0:
            m = cv2.dilate(m, _disk(grow_px))
    elif method == "dilate":
        inb = (pts[:, 0] >= 0) & (pts[:, 0] < w) & (pts[:, 1] >= 0) & (pts[:, 1] < h)
        m[pts[inb, 1], pts[inb, 0]] = 1
        m = cv2.dilate(m, _disk(cell_px / 2.0 + grow_px))
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(cell_px))
    else:
        raise ValueError(f"unknown mask method {method!r}")
    return m.astype(bool)


def nearest_node_labels(
    node_x: np.ndarray,
    node_y: np.ndarray,
    node_labels: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    max_distance_px: float,
) -> np.ndarray:
    """Label of the nearest node for every point (N,), -1 beyond ``max_distance_px`` or no node
    (:func:`nearest_node_index`, then :func:`labels_of_nearest`)."""
    return labels_of_nearest(node_labels, nearest_node_index(node_x, node_y, x, y, max_distance_px))


def nearest_node_index(
    node_x: np.ndarray, node_y: np.ndarray, x: np.ndarray, y: np.ndarray, max_distance_px: float
) -> np.ndarray:
    """Index of the nearest node for every point (N,) int64, -1 beyond ``max_distance_px`` or no
    node. It depends on the node positions only, so a streaming caller can find it before the
    window is segmented.

    Exact nearest node (Euclidean, ties to the lowest node index) by a bucket-grid search
    (:func:`evseg.segmentation._kernels.grid_nearest`), about 5x faster than a k-d tree here.
    """
    from evseg.errors import EventDataError
    from evseg.segmentation._kernels import grid_nearest

    x = np.ascontiguousarray(x, dtype=np.float64)
    y = np.ascontiguousarray(y, dtype=np.float64)
    # The compiled search indexes x, y and the nodes without bounds checks: a length mismatch
    # or a NaN would read past the arrays (a crash, or labels from garbage) instead of failing.
    for a, b, what in ((x, y, "the points' x and y"), (node_x, node_y, "the nodes' x and y")):
        if np.ndim(a) != 1 or np.shape(a) != np.shape(b):
            raise EventDataError(f"nearest node: {what} must be 1-D of one length, got shapes "
                                 f"{np.shape(a)} and {np.shape(b)}")
    for a, b, what in ((x, y, "the points'"), (node_x, node_y, "the nodes'")):
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise EventDataError(f"nearest node: {what} x and y must be finite positions (px)")
    if not float(max_distance_px) >= 0:
        raise EventDataError(f"nearest node: max_distance_px must be >= 0 px, got {max_distance_px}")
    if len(node_x) == 0 or len(x) == 0:
        return np.full(len(x), -1, dtype=np.int64)
    node_x = np.ascontiguousarray(node_x, dtype=np.float64)
    node_y = np.ascontiguousarray(node_y, dtype=np.float64)
    reach = float(max_distance_px)
    if not math.isfinite(reach):
        # No limit: no two positions lie farther apart than the diagonal of their joint extent
        # (an infinite radius would size no search grid).
        reach = float(np.hypot(max(x.max(), node_x.max()) - min(x.min(), node_x.min()),
                               max(y.max(), node_y.max()) - min(y.min(), node_y.min()))) + 1.0
    # Buckets of a third of the search radius: a query scans at most 5 rings of cells.
    bucket = max(reach / 3.0, 1.0)
    return np.asarray(grid_nearest(node_x, node_y, x, y, reach, bucket), dtype=np.int64)


def labels_of_nearest(node_labels: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """(N,) int64 label of each point's nearest node (:func:`nearest_node_index`), -1 where none.

    Example:
        >>> labels_of_nearest(np.array([0, 2, 1]), np.array([1, -1, 0, 2])).tolist()
        [2, -1, 0, 1]
    """
    nearest = np.asarray(nearest, dtype=np.int64)
    out = np.full(len(nearest), -1, dtype=np.int64)
    hit = nearest >= 0
    out[hit] = np.asarray(node_labels, dtype=np.int64)[nearest[hit]]
    return out
