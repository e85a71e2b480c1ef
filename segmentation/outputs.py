"""Outputs of a segmented window: object regions (node subsets), boxes, dense masks, and the
propagation of node labels to any points (e.g. every event of the window).

Object region: the nodes of an independently moving object (IMO) that belong to its main
connected part in the Delaunay graph - connected components of the object's own edges, keeping
every component with at least a quarter of the largest one's nodes. A few nodes wrongly given
the object's label far away from it therefore do not blow up its box or hull.

Box: inclusive pixel box (x0, y0, x1, y1) of the region's nodes, grown by ``grow_px`` (nodes
lie on edges and texture, the silhouette reaches a little further) and clipped to the sensor.

Dense mask, ``method``:
* 'hull' (EMSGC's choice): filled convex hull of the region's nodes, dilated by ``grow_px``.
* 'dilate': the region's nodes rasterised, dilated by ``cell_px / 2 + grow_px`` and closed
  with a kernel of 2 * cell_px so that the gaps between nodes fill; follows concave shapes.
"""

from __future__ import annotations

import numpy as np


def object_regions(labels: np.ndarray, edges: np.ndarray, n_objects: int) -> dict[int, np.ndarray]:
    """Node indices of each object's main connected part, {k: (n_k,) int64} for k = 1..K."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    labels = np.asarray(labels, dtype=np.int64)
    m = len(labels)
    same = labels[edges[:, 0]] == labels[edges[:, 1]] if len(edges) else np.zeros(0, dtype=bool)
    e = edges[same]
    adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    _, comp = connected_components(adj, directed=False)
    regions = {}
    for k in range(1, n_objects + 1):
        nodes = np.flatnonzero(labels == k)
        if len(nodes) == 0:
            continue
        ids, sizes = np.unique(comp[nodes], return_counts=True)
        keep = ids[sizes >= 0.25 * sizes.max()]
        regions[k] = nodes[np.isin(comp[nodes], keep)]
    return regions


def region_box(
    x: np.ndarray, y: np.ndarray, grow_px: float, sensor_size: tuple[int, int] | None
) -> tuple[int, int, int, int]:
    """Inclusive px box (x0, y0, x1, y1) of points grown by ``grow_px``, clipped to the sensor."""
    x0 = int(np.floor(x.min() - grow_px))
    y0 = int(np.floor(y.min() - grow_px))
    x1 = int(np.ceil(x.max() + grow_px))
    y1 = int(np.ceil(y.max() + grow_px))
    if sensor_size is not None:
        w, h = sensor_size
        x0, x1 = max(x0, 0), min(x1, w - 1)
        y0, y1 = max(y0, 0), min(y1, h - 1)
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
    """Label of the nearest node for every point (N,), -1 beyond ``max_distance_px`` or no node."""
    from scipy.spatial import cKDTree

    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    out = np.full(len(x), -1, dtype=np.int64)
    if len(node_x) == 0 or len(x) == 0:
        return out
    tree = cKDTree(np.column_stack([node_x, node_y]))
    dist, idx = tree.query(np.column_stack([x, y]), distance_upper_bound=max_distance_px)
    hit = np.isfinite(dist)
    out[hit] = np.asarray(node_labels, dtype=np.int64)[idx[hit]]
    return out
