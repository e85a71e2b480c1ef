"""The compiled sweep-hull Delaunay triangulation against Qhull and the empty-circle property."""

import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

import evseg.segmentation.preprocessing as preprocessing
from evseg.segmentation._delaunay import _in_circle, sweep_delaunay
from evseg.segmentation._kernels import triangle_edges


def _tie_break(p: np.ndarray) -> np.ndarray:
    """The sub-pixel offset delaunay_edges adds to lattice points."""
    h = (np.arange(len(p)) * 0.6180339887498949) % 1.0
    return p + np.column_stack([h - 0.5, (h * 7.3) % 1.0 - 0.5]) * 1e-3


def _sweep(p: np.ndarray):
    s, nb, inserted = sweep_delaunay(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]))
    assert inserted == len(p)
    return s, nb


@pytest.mark.parametrize("n, seed", [(3, 0), (4, 1), (10, 2), (100, 3), (2000, 4)])
def test_random_points_give_qhulls_edges(n, seed):
    # Points in general position have one Delaunay triangulation: both must find it.
    p = np.random.default_rng(seed).uniform(0, 100, (n, 2))
    s, nb = _sweep(p)
    tri = Delaunay(p)
    ref = triangle_edges(tri.simplices.astype(np.int64), tri.neighbors.astype(np.int64), n)
    np.testing.assert_array_equal(triangle_edges(s, nb, n), ref)
    assert len(s) == len(tri.simplices)


@pytest.mark.parametrize("seed", range(6))
def test_lattice_points_give_a_delaunay_triangulation_of_the_hull(seed):
    # The pipeline's case: one event position per 3 px cell, integer pixels, tie-broken.
    # Qhull merges near-flat facets here and may drop a sliver triangle on the hull, so the
    # check is the definition itself rather than equality with Qhull.
    rng = np.random.default_rng(seed)
    cells = np.unique(rng.integers(0, 40, (600, 2)), axis=0)
    p = _tie_break((cells * 3 + rng.integers(0, 3, cells.shape)).astype(float))
    s, nb = _sweep(p)
    a, b, c = p[s[:, 0]], p[s[:, 1]], p[s[:, 2]]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert np.all(area2 > 0)  # counter-clockwise, none flat
    # the triangles tile the convex hull: their areas sum to its area, and with h hull
    # vertices a triangulation of n points has 2n - h - 2 triangles
    hull = ConvexHull(p)
    assert area2.sum() / 2 == pytest.approx(hull.volume, rel=1e-9)
    assert len(s) == 2 * len(p) - len(hull.vertices) - 2
    # empty circles: no neighbour's far vertex lies inside a triangle's circumcircle
    for t in range(len(s)):
        for k in range(3):
            o = nb[t, k]
            if o < 0:
                continue
            far = (set(s[o]) - {s[t, (k + 1) % 3], s[t, (k + 2) % 3]}).pop()
            assert _in_circle(*p[s[t, 0]], *p[s[t, 1]], *p[s[t, 2]], *p[far]) <= 0
            # the neighbour opposite vertex k shares the other two vertices
            assert {s[t, (k + 1) % 3], s[t, (k + 2) % 3]} <= set(s[o])


def test_qhull_takes_over_when_the_sweep_cannot_insert_every_point(monkeypatch):
    p = np.random.default_rng(7).uniform(0, 50, (60, 2))
    expected = preprocessing.delaunay_edges(p[:, 0], p[:, 1])

    def incomplete(x, y):
        s, nb, _ = sweep_delaunay(x, y)
        return s[:1], nb[:1], len(x) - 1  # as if one point had been skipped

    monkeypatch.setattr(preprocessing, "sweep_delaunay", incomplete)
    np.testing.assert_array_equal(preprocessing.delaunay_edges(p[:, 0], p[:, 1]), expected)
