"""Compiled 2D Delaunay triangulation by sweep-hull insertion (numba).

Qhull (``scipy.spatial.Delaunay``) lifts the points onto a paraboloid and builds a 3D convex
hull with general-dimension bookkeeping: ~8.5 ms for the ~3.3 k nodes of a 10 ms window at
1 M events/s, the largest single cost of the pre-processing. This is the sweep-hull scheme
(Sinclair's s-hull; the idea also behind the Delaunator library), written here for numba:

1. Seed: the point nearest the bounding-box centre, its nearest point, and the point that
   makes the smallest circumcircle with both (counter-clockwise).
2. The other points are inserted in order of distance to the seed's circumcentre, so each new
   point lies outside the current convex hull. It is joined to every hull edge it sees; a hash
   of the hull vertices by their angle about the circumcentre finds a visible edge in O(1).
3. Every new triangle is made Delaunay by Lawson edge flips (in-circle test), as usual.

Triangles are stored counter-clockwise as half-edges: half-edge ``3 t + k`` runs from vertex
``tri[3 t + k]`` to ``tri[3 t + (k + 1) % 3]``; ``twin[h]`` is the opposite half-edge (-1 on the
hull). The predicates are plain float64, not exact: the caller breaks lattice ties with a
sub-pixel offset first, and any point the sweep cannot insert (a near-degenerate case) is
reported, so the caller can use Qhull for that window instead.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _cross(ax, ay, bx, by, cx, cy):  # pragma: no cover
    """Twice the signed area of (a, b, c): > 0 counter-clockwise (x right, y up)."""
    return (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)


@njit(cache=True, inline="always")
def _in_circle(ax, ay, bx, by, cx, cy, px, py):  # pragma: no cover
    """> 0 when p lies inside the circumcircle of the counter-clockwise triangle (a, b, c)."""
    dx, dy = ax - px, ay - py
    ex, ey = bx - px, by - py
    fx, fy = cx - px, cy - py
    ap = dx * dx + dy * dy
    bp = ex * ex + ey * ey
    cp = fx * fx + fy * fy
    return dx * (ey * cp - bp * fy) - dy * (ex * cp - bp * fx) + ap * (ex * fy - ey * fx)


@njit(cache=True, inline="always")
def _circumradius2(ax, ay, bx, by, cx, cy):  # pragma: no cover
    dx, dy = bx - ax, by - ay
    ex, ey = cx - ax, cy - ay
    bl = dx * dx + dy * dy
    cl = ex * ex + ey * ey
    d = dx * ey - dy * ex
    if d == 0.0:
        return np.inf
    x = (ey * bl - dy * cl) * 0.5 / d
    y = (dx * cl - ex * bl) * 0.5 / d
    return x * x + y * y


@njit(cache=True, inline="always")
def _angle_key(dx, dy, size):  # pragma: no cover
    """Hash bucket of a direction: a pseudo-angle in [0, 1) (monotone in the angle) x size."""
    s = abs(dx) + abs(dy)
    p = dx / s if s > 0 else 0.0
    a = (3.0 - p) / 4.0 if dy > 0 else (1.0 + p) / 4.0
    k = int(a * size)
    return k % size


@njit(cache=True, nogil=True)
def _legalize(h0, px, py, tri, twin, hull_tri, stack):  # pragma: no cover
    """Lawson flips from half-edge ``h0``, whose opposite vertex is the new point."""
    top = 0
    stack[top] = h0
    top += 1
    while top > 0:
        top -= 1
        a = stack[top]
        b = twin[a]
        if b == -1:
            continue
        a0 = a - a % 3
        b0 = b - b % 3
        ak, bk = a % 3, b % 3
        # triangle A = (v_k, v_k1, p0), a = v_k -> v_k1; B = (v_k1, v_k, pl), b = v_k1 -> v_k
        vk = tri[a]
        vk1 = tri[a0 + (ak + 1) % 3]
        p0 = tri[a0 + (ak + 2) % 3]
        pl = tri[b0 + (bk + 2) % 3]
        if _in_circle(px[vk], py[vk], px[vk1], py[vk1], px[p0], py[p0], px[pl], py[pl]) <= 0.0:
            continue
        # Flip: A' = (pl, v_k1, p0) in A's slots, B' = (p0, v_k, pl) in B's slots.
        a_prev = a0 + (ak + 2) % 3  # p0 -> v_k (moves to B's slot b)
        b_prev = b0 + (bk + 2) % 3  # pl -> v_k1 (moves to A's slot a)
        t_ap = twin[a_prev]
        t_bp = twin[b_prev]
        tri[a] = pl
        tri[b] = p0
        # slot a now pl -> v_k1 (was b_prev), slot b now p0 -> v_k (was a_prev)
        twin[a] = t_bp
        if t_bp != -1:
            twin[t_bp] = a
        else:
            hull_tri[pl] = a
        twin[b] = t_ap
        if t_ap != -1:
            twin[t_ap] = b
        else:
            hull_tri[p0] = b
        # the new diagonal: A' slot a_prev is p0 -> pl, B' slot b_prev is pl -> p0
        twin[a_prev] = b_prev
        twin[b_prev] = a_prev
        # edges opposite p0 in the two new triangles
        stack[top] = a
        top += 1
        stack[top] = b0 + (bk + 1) % 3
        top += 1


@njit(cache=True, nogil=True)
def _add_triangle(t, a, b, c, ha, hb, hc, tri, twin):  # pragma: no cover
    """Triangle (a, b, c) in slot t; ha, hb, hc: twins of a->b, b->c, c->a (-1 = none)."""
    h = 3 * t
    tri[h] = a
    tri[h + 1] = b
    tri[h + 2] = c
    twin[h] = ha
    twin[h + 1] = hb
    twin[h + 2] = hc
    if ha != -1:
        twin[ha] = h
    if hb != -1:
        twin[hb] = h + 1
    if hc != -1:
        twin[hc] = h + 2
    return h


@njit(cache=True, nogil=True)
def sweep_delaunay(px, py):  # pragma: no cover
    """Delaunay triangulation of n >= 3 distinct, not all collinear points.

    Returns ``(simplices (T, 3), neighbors (T, 3), inserted)``: counter-clockwise triangles,
    the triangle opposite each vertex (-1 on the hull, as Qhull's ``neighbors``), and the
    number of points that made it into the triangulation (``n`` unless a near-degenerate
    point could not be inserted; the result is then incomplete and must not be used).
    """
    n = px.shape[0]
    empty = np.empty((0, 3), dtype=np.int64)
    x_min, x_max, y_min, y_max = np.inf, -np.inf, np.inf, -np.inf
    for i in range(n):
        x_min = min(x_min, px[i])
        x_max = max(x_max, px[i])
        y_min = min(y_min, py[i])
        y_max = max(y_max, py[i])
    cx0 = 0.5 * (x_min + x_max)
    cy0 = 0.5 * (y_min + y_max)
    i0, best = -1, np.inf
    for i in range(n):
        d = (px[i] - cx0) ** 2 + (py[i] - cy0) ** 2
        if d < best:
            i0, best = i, d
    i1, best = -1, np.inf
    for i in range(n):
        if i == i0:
            continue
        d = (px[i] - px[i0]) ** 2 + (py[i] - py[i0]) ** 2
        if d < best and d > 0:
            i1, best = i, d
    i2, best = -1, np.inf
    for i in range(n):
        if i == i0 or i == i1:
            continue
        r = _circumradius2(px[i0], py[i0], px[i1], py[i1], px[i], py[i])
        if r < best:
            i2, best = i, r
    if i1 == -1 or i2 == -1 or best == np.inf:
        return empty, empty, 0
    if _cross(px[i0], py[i0], px[i1], py[i1], px[i2], py[i2]) < 0:
        i1, i2 = i2, i1
    # circumcentre of the seed triangle
    ax, ay = px[i0], py[i0]
    dx, dy = px[i1] - ax, py[i1] - ay
    ex, ey = px[i2] - ax, py[i2] - ay
    bl, cl, dd = dx * dx + dy * dy, ex * ex + ey * ey, dx * ey - dy * ex
    ccx = ax + (ey * bl - dy * cl) * 0.5 / dd
    ccy = ay + (dx * cl - ex * bl) * 0.5 / dd

    dist = np.empty(n)
    for i in range(n):
        dist[i] = (px[i] - ccx) ** 2 + (py[i] - ccy) ** 2
    order = np.argsort(dist, kind="mergesort")

    max_tri = max(2 * n - 5, 1)
    tri = np.full(3 * max_tri, -1, dtype=np.int64)
    twin = np.full(3 * max_tri, -1, dtype=np.int64)
    hull_next = np.full(n, -1, dtype=np.int64)
    hull_prev = np.full(n, -1, dtype=np.int64)
    hull_tri = np.full(n, -1, dtype=np.int64)
    hash_size = max(int(np.ceil(np.sqrt(n))), 1)
    hull_hash = np.full(hash_size, -1, dtype=np.int64)
    stack = np.empty(3 * max_tri + 8, dtype=np.int64)

    hull_next[i0] = i1
    hull_prev[i2] = i1
    hull_next[i1] = i2
    hull_prev[i0] = i2
    hull_next[i2] = i0
    hull_prev[i1] = i0
    hull_tri[i0] = 0
    hull_tri[i1] = 1
    hull_tri[i2] = 2
    hull_hash[_angle_key(px[i0] - ccx, py[i0] - ccy, hash_size)] = i0
    hull_hash[_angle_key(px[i1] - ccx, py[i1] - ccy, hash_size)] = i1
    hull_hash[_angle_key(px[i2] - ccx, py[i2] - ccy, hash_size)] = i2
    n_tri = 1
    _add_triangle(0, i0, i1, i2, -1, -1, -1, tri, twin)
    inserted = 3
    on_hull = np.zeros(n, dtype=np.bool_)
    on_hull[i0] = True
    on_hull[i1] = True
    on_hull[i2] = True

    for k in range(n):
        i = order[k]
        if i == i0 or i == i1 or i == i2:
            continue
        x, y = px[i], py[i]
        # a hull vertex near i's direction, then forward to the first edge i sees
        key = _angle_key(x - ccx, y - ccy, hash_size)
        start = -1
        for j in range(hash_size):
            s = hull_hash[(key + j) % hash_size]
            if s != -1 and on_hull[s]:
                start = s
                break
        if start == -1:
            continue
        start = hull_prev[start]
        e = start
        found = False
        for _ in range(n + 1):
            q = hull_next[e]
            if _cross(px[e], py[e], px[q], py[q], x, y) < 0.0:
                found = True
                break
            e = q
            if e == start:
                break
        if not found:
            continue
        # triangle on the visible edge e -> q: (q, e, i)
        q = hull_next[e]
        h = _add_triangle(n_tri, q, e, i, hull_tri[e], -1, -1, tri, twin)
        n_tri += 1
        hull_tri[i] = h + 2  # i -> q
        hull_tri[e] = h + 1  # e -> i
        _legalize(h, px, py, tri, twin, hull_tri, stack)
        # forward: i sees q -> next
        nxt = hull_next[q]
        while _cross(px[q], py[q], px[nxt], py[nxt], x, y) < 0.0:
            # triangle (nxt, q, i): nxt->q (twin: hull edge hull_tri[q]), q->i (twin: hull edge
            # hull_tri[i]), i->nxt (new hull edge)
            h = _add_triangle(n_tri, nxt, q, i, hull_tri[q], hull_tri[i], -1, tri, twin)
            n_tri += 1
            hull_tri[i] = h + 2
            on_hull[q] = False
            _legalize(h, px, py, tri, twin, hull_tri, stack)
            q = nxt
            nxt = hull_next[q]
        # backward: i sees prev -> e (only possible when the forward search found its first
        # visible edge right at its start; otherwise the edges before e were seen not visible)
        if e == start:
            prv = hull_prev[e]
            while _cross(px[prv], py[prv], px[e], py[e], x, y) < 0.0:
                # triangle (e, prv, i): e->prv (twin hull_tri[prv]), prv->i (new hull edge),
                # i->e (twin hull_tri[e], which is e->i)
                h = _add_triangle(n_tri, e, prv, i, hull_tri[prv], -1, hull_tri[e], tri, twin)
                n_tri += 1
                hull_tri[prv] = h + 1
                on_hull[e] = False
                _legalize(h, px, py, tri, twin, hull_tri, stack)
                e = prv
                prv = hull_prev[e]
        # hull: e -> i -> q
        hull_next[e] = i
        hull_prev[i] = e
        hull_next[i] = q
        hull_prev[q] = i
        on_hull[i] = True
        hull_hash[_angle_key(x - ccx, y - ccy, hash_size)] = i
        hull_hash[_angle_key(px[e] - ccx, py[e] - ccy, hash_size)] = e
        inserted += 1

    simplices = np.empty((n_tri, 3), dtype=np.int64)
    neighbors = np.empty((n_tri, 3), dtype=np.int64)
    for t in range(n_tri):
        for k in range(3):
            simplices[t, k] = tri[3 * t + k]
            # the edge opposite vertex k is half-edge (k + 1) % 3
            o = twin[3 * t + (k + 1) % 3]
            neighbors[t, k] = -1 if o == -1 else o // 3
    return simplices, neighbors, inserted
