"""Compiled (numba) loops of the segmentation: the robust 1-ring translations and agreement,
the vote bins of fast sampling, the nearest node of a point, the unique edges of a triangulation, the terms of an expansion move, the
data-cost matrix, the connected parts of each label.

In numpy each IRLS iteration of :func:`evseg.segmentation.initialization.local_translations`
costs five ``bincount`` passes plus temporaries (~1 ms at 1.5 k nodes for four iterations, most
of the initialization budget); one compiled pass per iteration does the same sums in a few
tens of microseconds. Where a kernel replaces numpy code it keeps its order of floating-point
operations, so results are bit-identical (fast sampling's bins: ~0.25 ms of ``np.unique`` and
array updates per window before, ~0.1 ms now). The caller validates inputs; nothing here
checks bounds.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def ring_pairs(edges, m):  # pragma: no cover
    """The 1-ring of every node as CSR: ``member[start[i]:start[i + 1]]`` lists node i itself,
    then its neighbours over the (E, 2) ``edges`` as ``e[:, 0] == i`` (in edge order), then as
    ``e[:, 1] == i`` (in edge order): a stable counting sort of the pairs
    ``(centre, member)`` of the node list and both directions of every edge, so each ring's
    sums below run in the same order as a bincount over those pairs would."""
    n_edges = edges.shape[0]
    start = np.zeros(m + 1, dtype=np.int64)
    for i in range(m):
        start[i + 1] = 1
    for k in range(n_edges):
        start[edges[k, 0] + 1] += 1
        start[edges[k, 1] + 1] += 1
    for i in range(m):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    member = np.empty(m + 2 * n_edges, dtype=np.int64)
    for i in range(m):
        member[fill[i]] = i
        fill[i] += 1
    for k in range(n_edges):
        c = edges[k, 0]
        member[fill[c]] = edges[k, 1]
        fill[c] += 1
    for k in range(n_edges):
        c = edges[k, 1]
        member[fill[c]] = edges[k, 0]
        fill[c] += 1
    return start, member


@njit(cache=True, nogil=True)
def ring_translations(start, member, hx, hy, norm, scale, iterations, min_conditioning, nx, ny):  # pragma: no cover
    """Per-node least-squares translation of its 1-ring (``start, member`` from
    :func:`ring_pairs`) with unit normals ``hx, hy`` and magnitudes ``norm`` (per node, px/s):
    first unweighted, then ``iterations`` Cauchy-reweighted passes with ``scale`` (px/s; <= 0 =
    none). Ill-conditioned nodes keep their own flow ``(nx, ny)`` and are flagged False.
    A ring reads only its own node's translation, so each node is solved as soon as its sums
    are complete; the sums stay in registers."""
    m = start.shape[0] - 1
    tx = np.empty(m)
    ty = np.empty(m)
    ok = np.empty(m, dtype=np.bool_)
    total = 1 + (iterations if scale > 0 else 0)
    for it in range(total):
        for i in range(m):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            s4 = 0.0
            for k in range(start[i], start[i + 1]):
                j = member[k]
                w = 1.0
                if it > 0:
                    r = (hx[j] * tx[i] + hy[j] * ty[i] - norm[j]) / scale
                    w = 1.0 / (1.0 + r * r)
                s0 += w * hx[j] * hx[j]
                s1 += w * hx[j] * hy[j]
                s2 += w * hy[j] * hy[j]
                s3 += w * norm[j] * hx[j]
                s4 += w * norm[j] * hy[j]
            det = s0 * s2 - s1 * s1
            disc = np.sqrt(max((s0 + s2) * (s0 + s2) / 4.0 - det, 0.0))
            lmax = (s0 + s2) / 2.0 + disc
            lmin = (s0 + s2) / 2.0 - disc
            good = lmin >= min_conditioning * max(lmax, 1e-300)
            ok[i] = good
            if good:
                tx[i] = (s2 * s3 - s1 * s4) / det
                ty[i] = (s0 * s4 - s1 * s3) / det
            else:
                tx[i] = nx[i]
                ty[i] = ny[i]
    return tx, ty, ok


@njit(cache=True, nogil=True)
def ring_agreement(start, member, nx, ny, norm, tx, ty, scale):  # pragma: no cover
    """Mean Cauchy weight ``1 / (1 + r^2)`` of each node's neighbours (its ring without itself,
    ``start, member`` from :func:`ring_pairs`) under the node's translation ``(tx, ty)``, with
    ``r = (n_j . t_i / |n_j| - |n_j|) / scale``; 0 for a node without neighbours."""
    m = start.shape[0] - 1
    out = np.zeros(m)
    for i in range(m):
        total = 0.0
        for k in range(start[i] + 1, start[i + 1]):
            j = member[k]
            r = ((nx[j] * tx[i] + ny[j] * ty[i]) / norm[j] - norm[j]) / scale
            total += 1.0 / (1.0 + r * r)
        out[i] = total / max(start[i + 1] - start[i] - 1, 1)
    return out


@njit(cache=True, nogil=True)
def vote_bins(vx, vy, bin_px_s):  # pragma: no cover
    """Mean vector (B, 2) and vote count (B,) of each occupied square bin of ``bin_px_s``
    over the vectors ``(vx, vy)``, bins in ascending order of their (column-major) key; the
    sums run in input order (as ``numpy.bincount`` would)."""
    n = vx.shape[0]
    ix = np.empty(n, dtype=np.int64)
    iy = np.empty(n, dtype=np.int64)
    for i in range(n):
        ix[i] = np.int64(np.floor(vx[i] / bin_px_s))
        iy[i] = np.int64(np.floor(vy[i] / bin_px_s))
    ix -= ix.min()
    iy -= iy.min()
    key = ix * (iy.max() + 1) + iy
    order = np.argsort(key, kind="mergesort")
    inverse = np.empty(n, dtype=np.int64)
    b = -1
    prev = np.int64(0)
    for r in range(n):
        k = order[r]
        if r == 0 or key[k] != prev:
            b += 1
            prev = key[k]
        inverse[k] = b
    sx = np.zeros(b + 1)
    sy = np.zeros(b + 1)
    count = np.zeros(b + 1, dtype=np.int64)
    for i in range(n):
        sx[inverse[i]] += vx[i]
        sy[inverse[i]] += vy[i]
        count[inverse[i]] += 1
    means = np.empty((b + 1, 2))
    for j in range(b + 1):
        means[j, 0] = sx[j] / count[j]
        means[j, 1] = sy[j] / count[j]
    return means, count


@njit(cache=True, inline="always")
def _take_bin(means, o, out, k, dist2):  # pragma: no cover
    """Bin ``o``'s mean becomes ``out[k]``; ``dist2`` becomes each bin's squared distance to the
    nearest point taken so far."""
    out[k, 0] = means[o, 0]
    out[k, 1] = means[o, 1]
    for j in range(means.shape[0]):
        dx = means[j, 0] - means[o, 0]
        dy = means[j, 1] - means[o, 1]
        d = dx * dx + dy * dy
        if d < dist2[j]:
            dist2[j] = d


@njit(cache=True, nogil=True)
def spread_bins(means, count, n, n_frequent, min_d2, min_votes, dist2):  # pragma: no cover
    """Up to ``n`` bin means (K, 2) for fast sampling: with ``n_frequent`` > 0, first the most
    populated bin, then bins by decreasing count (ties: lower bin first) until ``n_frequent``
    are taken or counts drop below 2, skipping bins within ``sqrt(min_d2)`` of one taken; then
    farthest-point sampling among bins with ``min_votes`` votes, each at least ``sqrt(min_d2)``
    from every point so far. ``dist2`` (B,): squared distance of each bin to the nearest
    point taken before (inf for none); overwritten."""
    nb = means.shape[0]
    out = np.empty((max(n, 0), 2))
    k = 0
    if n_frequent > 0 and n > 0 and nb > 0:
        order = np.argsort(-count, kind="mergesort")
        for r in range(nb):
            o = order[r]
            if r > 0 and (k >= n_frequent or count[o] < 2):
                break
            if r == 0 or dist2[o] >= min_d2:
                _take_bin(means, o, out, k, dist2)
                k += 1
    while k < n:
        best = -1
        best_score = -np.inf
        for j in range(nb):
            score = dist2[j] if count[j] >= min_votes else -1.0
            if score > best_score:
                best_score = score
                best = j
        if best < 0 or best_score < min_d2:
            break
        _take_bin(means, best, out, k, dist2)
        k += 1
    return out[:k]


@njit(cache=True, nogil=True)
def grid_nearest(node_x, node_y, qx, qy, max_distance, bucket):  # pragma: no cover
    """Index of the nearest node (px coordinates) for every query point, -1 when none lies
    within ``max_distance`` px; ties go to the lowest node index.

    Nodes are bucketed in square cells of ``bucket`` px (a counting sort); each query scans
    rings of cells around its own, nearest first, and stops once the best distance is within
    the ring already scanned: any node in ring r + 1 is at least r * bucket px away. Exact,
    and O(1) per query for the ~1 node per few px^2 of a segmentation graph (a k-d tree
    spends ~0.3 us per query on descending its levels)."""
    m = node_x.shape[0]
    n = qx.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    if m == 0:
        return out
    x0 = node_x.min()
    y0 = node_y.min()
    gw = int((node_x.max() - x0) / bucket) + 1
    gh = int((node_y.max() - y0) / bucket) + 1
    cell = np.empty(m, dtype=np.int64)
    for k in range(m):
        cell[k] = int((node_y[k] - y0) / bucket) * gw + int((node_x[k] - x0) / bucket)
    start = np.zeros(gw * gh + 1, dtype=np.int64)
    for k in range(m):
        start[cell[k] + 1] += 1
    for c in range(gw * gh):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    members = np.empty(m, dtype=np.int64)
    for k in range(m):  # ascending k: each cell lists its nodes in index order
        members[fill[cell[k]]] = k
        fill[cell[k]] += 1
    max_d2 = max_distance * max_distance
    rings = int(max_distance / bucket) + 2
    for q in range(n):
        fx = (qx[q] - x0) / bucket
        fy = (qy[q] - y0) / bucket
        cx = int(np.floor(fx))
        cy = int(np.floor(fy))
        best = np.inf
        best_k = -1
        for r in range(rings):
            for gy in range(cy - r, cy + r + 1):
                if gy < 0 or gy >= gh:
                    continue
                edge_row = gy == cy - r or gy == cy + r
                step = 1 if edge_row else 2 * r  # inner rows: only the ring's two ends
                gx = cx - r
                while gx <= cx + r:
                    if 0 <= gx < gw:
                        c = gy * gw + gx
                        for s in range(start[c], start[c + 1]):
                            k = members[s]
                            dx = node_x[k] - qx[q]
                            dy = node_y[k] - qy[q]
                            d2 = dx * dx + dy * dy
                            if d2 < best or (d2 == best and k < best_k):
                                best = d2
                                best_k = k
                    gx += step
            # Ring r + 1 and beyond lie at least r * bucket px from the query.
            if best_k >= 0 and best <= (r * bucket) * (r * bucket):
                break
        if best_k >= 0 and best <= max_d2:
            out[q] = best_k
    return out


@njit(cache=True, nogil=True)
def triangle_edges(simplices, neighbors, n):  # pragma: no cover
    """Unique edges (E, 2), i < j, in (i, j) order, of a triangulation of ``n`` points.

    ``simplices`` (T, 3) are the triangles, ``neighbors`` (T, 3) the triangle opposite each
    vertex (-1 on the hull), as Qhull gives them. An inner edge is shared by two triangles and
    is taken from the one with the lower index, so each edge is met once without a sort; a
    counting sort by the first end and an insertion sort of each (short) row give the order.
    """
    n_tri = simplices.shape[0]
    a = np.empty(3 * n_tri, dtype=np.int64)
    b = np.empty(3 * n_tri, dtype=np.int64)
    e = 0
    for t in range(n_tri):
        for k in range(3):
            other = neighbors[t, k]
            if other != -1 and other < t:
                continue
            # The edge opposite vertex k joins the two other vertices.
            p = simplices[t, (k + 1) % 3]
            q = simplices[t, (k + 2) % 3]
            if p > q:
                p, q = q, p
            a[e] = p
            b[e] = q
            e += 1
    start = np.zeros(n + 1, dtype=np.int64)
    for k in range(e):
        start[a[k] + 1] += 1
    for i in range(n):
        start[i + 1] += start[i]
    fill = start[:n].copy()
    out = np.empty((e, 2), dtype=np.int64)
    for k in range(e):
        pos = fill[a[k]]
        out[pos, 0] = a[k]
        out[pos, 1] = b[k]
        fill[a[k]] += 1
    for i in range(n):
        for r in range(start[i] + 1, start[i + 1]):
            v = out[r, 1]
            s = r - 1
            while s >= start[i] and out[s, 1] > v:
                out[s + 1, 1] = out[s, 1]
                s -= 1
            out[s + 1, 1] = v
    return out


@njit(cache=True, nogil=True)
def expansion_terms(labels, alpha, data, edges, edge_w):  # pragma: no cover
    """One pass over nodes and edges giving what an expansion move on ``alpha`` needs.

    Returns:
        diff: (M,) cost(s=1) - cost(s=0) of each node with the unary parts of the Potts
            decomposition folded in (see :mod:`evseg.segmentation.expansion`).
        pair_i, pair_j, pair_w: the edges i -> j with a positive pairwise coefficient.
        bound: (M,) D[k, alpha] - D[k, L_k] - (weight of the cut edges at k now): the least
            that switching k can change the energy by, label costs aside.
    """
    m = labels.shape[0]
    diff = np.empty(m)
    bound = np.empty(m)
    for k in range(m):
        d = data[k, alpha] - data[k, labels[k]]
        diff[k] = d
        bound[k] = d
    n_edges = edges.shape[0]
    pair_i = np.empty(n_edges, dtype=np.int64)
    pair_j = np.empty(n_edges, dtype=np.int64)
    pair_w = np.empty(n_edges)
    n_pairs = 0
    for e in range(n_edges):
        i = edges[e, 0]
        j = edges[e, 1]
        li = labels[i]
        lj = labels[j]
        w = edge_w[e]
        e00 = w if li != lj else 0.0
        e01 = w if li != alpha else 0.0
        e10 = w if lj != alpha else 0.0
        diff[i] += e10 - e00
        diff[j] -= e10
        if li != lj:
            bound[i] -= w
            bound[j] -= w
        pair = e01 + e10 - e00
        if pair > 0.0:
            pair_i[n_pairs] = i
            pair_j[n_pairs] = j
            pair_w[n_pairs] = pair
            n_pairs += 1
    return diff, pair_i[:n_pairs], pair_j[:n_pairs], pair_w[:n_pairs], bound


@njit(cache=True, nogil=True)
def confirmed_flows(starts, nx, ny, cert, max_run, rel_tol, abs_tol):  # pragma: no cover
    """Position of each run's node for the 'confirmed' rule of :func:`.preprocessing.select_nodes`.

    Runs ``[starts[c], starts[c+1])`` are sorted by increasing preference, ``starts`` has one
    entry per run plus the end. Candidates: the run's flows of its best certainty ``cert``
    (that of its last flow), at most the last ``max_run``. Returns, per run, the last candidate
    that another candidate confirms (|n_i - n_j| <= rel_tol |n_i| + abs_tol, px/s), or the run's
    last flow when none is confirmed."""
    n_runs = starts.shape[0] - 1
    out = np.empty(n_runs, dtype=np.int64)
    for c in range(n_runs):
        b = starts[c + 1]
        a = b - 1
        while a > starts[c] and b - a < max_run and cert[a - 1] == cert[b - 1]:
            a -= 1
        best = b - 1
        for i in range(b - 1, a - 1, -1):
            tol = rel_tol * np.sqrt(nx[i] * nx[i] + ny[i] * ny[i]) + abs_tol
            confirmed = False
            for j in range(a, b):
                if j != i and (nx[i] - nx[j]) ** 2 + (ny[i] - ny[j]) ** 2 <= tol * tol:
                    confirmed = True
                    break
            if confirmed:
                best = i
                break
        out[c] = best
    return out


@njit(cache=True, nogil=True)
def data_cost_matrix(q, x, y, nx, ny, sigma, node_scale, node_angle, confidence, tau2):  # pragma: no cover
    """(M, L) truncated squared normalised residuals, the operations of
    :func:`evseg.segmentation.energy.data_costs` in the same order (so the same floats) in
    one pass instead of ~10 numpy passes over (M, L) temporaries. ``q``: (L, 4) linear
    parameters (a, b, t_x, t_y); ``node_scale`` / ``node_angle`` / ``confidence``: (M,), ones /
    zeros / ones when unused. A node with ``node_angle`` 0 takes exactly the plain path."""
    m = x.shape[0]
    n_labels = q.shape[0]
    out = np.empty((m, n_labels))
    for k in range(m):
        norm = np.hypot(nx[k], ny[k])
        hx = nx[k] / norm
        hy = ny[k] / norm
        a = node_angle[k] / (sigma * node_scale[k])
        # Two loops, not one with a branch on a: the plain loop (ground-truth flow, flows
        # without uncertainty) stays branch-free and ran 0.26 against 0.36 ms for 4,000 nodes x
        # 14 models in one merged loop.
        if a == 0.0:
            for j in range(n_labels):
                ux = q[j, 0] * x[k] - q[j, 1] * y[k] + q[j, 2]
                uy = q[j, 1] * x[k] + q[j, 0] * y[k] + q[j, 3]
                r = (hx * ux + hy * uy - norm) / sigma
                r = r / node_scale[k]
                d = r * r
                if d > tau2:
                    d = tau2
                out[k, j] = d * confidence[k]
        else:
            # Gaussian NLL with the model's flow along the edge in the scale, relative to the
            # model-free scale (so a = 0 is the plain path above).
            for j in range(n_labels):
                ux = q[j, 0] * x[k] - q[j, 1] * y[k] + q[j, 2]
                uy = q[j, 1] * x[k] + q[j, 0] * y[k] + q[j, 3]
                r = (hx * ux + hy * uy - norm) / sigma
                r = r / node_scale[k]
                s = a * (hx * uy - hy * ux)
                f = 1.0 + s * s
                d = r * r / f
                if d < tau2:  # log(f) >= 0: past tau^2 the cost is truncated anyway
                    d += np.log(f)
                if d > tau2:
                    d = tau2
                out[k, j] = d * confidence[k]
    return out


@njit(cache=True, nogil=True)
def same_label_components(labels, edges):  # pragma: no cover
    """Connected components of the graph restricted to edges whose two ends share a label.

    Returns (M,) int64 component ids numbered in the order of each component's first node
    (the numbering of ``scipy.sparse.csgraph.connected_components``). Union-find with path
    halving, one pass over the edges.
    """
    m = labels.shape[0]
    parent = np.arange(m)
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        if labels[i] != labels[j]:
            continue
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        while parent[j] != j:
            parent[j] = parent[parent[j]]
            j = parent[j]
        if i != j:
            if i < j:
                parent[j] = i
            else:
                parent[i] = j
    comp = np.empty(m, np.int64)
    root_id = np.full(m, -1, np.int64)
    n = 0
    for k in range(m):
        r = k
        while parent[r] != r:
            r = parent[r]
        if root_id[r] < 0:
            root_id[r] = n
            n += 1
        comp[k] = root_id[r]
    return comp


@njit(cache=True, nogil=True)
def labeling_energy(labels, data, edges, edge_w, label_costs):  # pragma: no cover
    """Energy of a labeling in one pass: sum_k data[k, L_k] + the weights of the edges whose
    ends differ + the costs of the labels in use (:func:`evseg.segmentation.energy.energy`).
    NaN when a label lies outside [0, L) or an edge end outside [0, M)."""
    m = labels.shape[0]
    n_labels = label_costs.shape[0]
    d = 0.0
    used = np.zeros(n_labels, dtype=np.bool_)
    for k in range(m):
        lab = labels[k]
        if lab < 0 or lab >= n_labels:
            return np.nan
        d += data[k, lab]
        used[lab] = True
    p = 0.0
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        if i < 0 or i >= m or j < 0 or j >= m:
            return np.nan
        if labels[i] != labels[j]:
            p += edge_w[e]
    h = 0.0
    for lab in range(n_labels):
        if used[lab]:
            h += label_costs[lab]
    return d + p + h


@njit(cache=True, nogil=True)
def label_bound_sums(labels, bound, n_labels):  # pragma: no cover
    """Per label: node count, sum of ``bound`` and sum of min(``bound``, 0) over its nodes, in
    node order (the sums ``np.bincount(labels, weights=...)`` gives)."""
    count = np.zeros(n_labels, dtype=np.int64)
    whole = np.zeros(n_labels)
    part = np.zeros(n_labels)
    for k in range(labels.shape[0]):
        lab = labels[k]
        count[lab] += 1
        whole[lab] += bound[k]
        if bound[k] < 0.0:
            part[lab] += bound[k]
    return count, whole, part


@njit(cache=True, nogil=True)
def lm_steps(p, hq, gq, mu):  # pragma: no cover
    """Levenberg-Marquardt step of every label's (rho, theta, t_x, t_y) from its normal
    equations in q = (rho cos theta - 1, rho sin theta, t_x, t_y) (:func:`.fitting.fit_lm`).

    With T = dq / dp (identity on t_x, t_y): H = T^T Hq T, g = T^T gq, and the step solves
    (H + diag(mu H_ii + 1e-12 (mean H_ii + 1))) step = -g (Gaussian elimination with partial
    pivoting; the 1e-12 keeps a label without nodes solvable, its step is 0).
    Args: p (L, 4), hq (L, 4, 4), gq (L, 4), mu (L,). Returns: (L, 4) steps.
    """
    n = p.shape[0]
    out = np.empty((n, 4))
    t = np.zeros((4, 4))
    a = np.empty((4, 4))
    h = np.empty((4, 5))
    for lab in range(n):
        c = np.cos(p[lab, 1])
        s = np.sin(p[lab, 1])
        t[0, 0] = c
        t[0, 1] = -p[lab, 0] * s
        t[1, 0] = s
        t[1, 1] = p[lab, 0] * c
        t[2, 2] = 1.0
        t[3, 3] = 1.0
        for i in range(4):  # a = hq t
            for j in range(4):
                v = 0.0
                for k in range(4):
                    v += hq[lab, i, k] * t[k, j]
                a[i, j] = v
        dsum = 0.0
        for i in range(4):  # h = t^T a, augmented with -g = -t^T gq
            for j in range(4):
                v = 0.0
                for k in range(4):
                    v += t[k, i] * a[k, j]
                h[i, j] = v
            v = 0.0
            for k in range(4):
                v += t[k, i] * gq[lab, k]
            h[i, 4] = -v
            dsum += h[i, i]
        floor = 1e-12 * (dsum / 4.0 + 1.0)
        for i in range(4):
            h[i, i] += mu[lab] * h[i, i] + floor
        for col in range(4):  # forward elimination, partial pivoting
            piv = col
            for i in range(col + 1, 4):
                if abs(h[i, col]) > abs(h[piv, col]):
                    piv = i
            if piv != col:
                for j in range(5):
                    h[col, j], h[piv, j] = h[piv, j], h[col, j]
            for i in range(col + 1, 4):
                f = h[i, col] / h[col, col]
                for j in range(col, 5):
                    h[i, j] -= f * h[col, j]
        for i in range(3, -1, -1):  # back substitution
            v = h[i, 4]
            for j in range(i + 1, 4):
                v -= h[i, j] * out[lab, j]
            out[lab, i] = v / h[i, i]
    return out


@njit(cache=True, nogil=True)
def edge_contrast(data, edges):  # pragma: no cover
    """(E,) min_l max(D[i, l], D[j, l]) - max(min_l D[i, l], min_l D[j, l]) for each edge (i, j)
    (:func:`evseg.segmentation.energy.contrast_weights`)."""
    m, n_labels = data.shape
    best = np.empty(m)
    for k in range(m):
        v = data[k, 0]
        for lab in range(1, n_labels):
            if data[k, lab] < v:
                v = data[k, lab]
        best[k] = v
    out = np.empty(edges.shape[0])
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        common = max(data[i, 0], data[j, 0])
        for lab in range(1, n_labels):
            v = max(data[i, lab], data[j, lab])
            if v < common:
                common = v
        out[e] = common - max(best[i], best[j])
    return out


@njit(cache=True, nogil=True)
def lm_setup(labels, n_labels, x, y, nx, ny, weights):  # pragma: no cover
    """The per-node arrays of :func:`.fitting.fit_lm` in one pass over the nodes whose label
    lies in [0, n_labels): labels (K,), the residual's Jacobian in q (K, 4) (rows of
    :func:`.motion_model.residual_jacobian`), its outer products (K, 16), |n| (K,), the
    weights (K,) and the label indicator (n_labels, K)."""
    m = labels.shape[0]
    k = 0
    for i in range(m):
        if 0 <= labels[i] < n_labels:
            k += 1
    lab = np.empty(k, dtype=np.int64)
    jq = np.empty((k, 4))
    jj = np.empty((k, 16))
    norm = np.empty(k)
    w = np.empty(k)
    onehot = np.zeros((n_labels, k))
    j = 0
    for i in range(m):
        if not 0 <= labels[i] < n_labels:
            continue
        n = np.hypot(nx[i], ny[i])
        hx = nx[i] / n
        hy = ny[i] / n
        jq[j, 0] = hx * x[i] + hy * y[i]
        jq[j, 1] = hy * x[i] - hx * y[i]
        jq[j, 2] = hx
        jq[j, 3] = hy
        for a in range(4):
            for b in range(4):
                jj[j, 4 * a + b] = jq[j, a] * jq[j, b]
        norm[j] = n
        w[j] = weights[i]
        lab[j] = labels[i]
        onehot[labels[i], j] = 1.0
        j += 1
    return lab, jq, jj, norm, w, onehot
