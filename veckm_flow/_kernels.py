"""Compiled (numba) loops of the O(N) encoding and of target selection.

numpy alone cannot do the scatter and the running-sum pass within the speed budget
(``np.cumsum`` over a 346x260x32 complex grid alone takes ~40 ms); these loops take a few ms.
Callers are :mod:`evseg.veckm_flow.encoding` and :mod:`evseg.veckm_flow.targets`, which validate
inputs; nothing here checks bounds.

Complex values are stored planar, ``[..., 0, m]`` real and ``[..., 1, m]`` imaginary part
(float32), so that the inner loops over the ``d`` features are plain float arithmetic that
LLVM vectorises (numba's interleaved complex64 arithmetic does not, and ran ~4x slower).

The per-pixel complex field is never stored: events are sorted by pixel (counting sort, O(N))
and each pixel's value is computed when the box pass reaches it. Only the box sums live in a
reusable workspace ``(H, W, 2, d)``, fully overwritten by each pass (no memset per slice).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True)
def pixel_lists(x, y, dt, pol, width, height):  # pragma: no cover
    """Counting sort of the events by pixel: ``(start (H*W + 1,), sdt (N,), spol (N,),
    row_used (H,))``; the events of pixel ``p = y * W + x`` have times ``sdt[start[p]:start[p+1]]``
    (us, input order) and polarity indices ``spol[...]``. Times and polarities are copied in
    pixel order so that the box pass reads them sequentially. O(N + W H)."""
    n = x.shape[0]
    npix = width * height
    start = np.zeros(npix + 1, np.int64)
    row_used = np.zeros(height, np.bool_)
    for j in range(n):
        start[np.int64(y[j]) * width + x[j] + 1] += 1
        row_used[y[j]] = True
    for p in range(npix):
        start[p + 1] += start[p]
    fill = start[:-1].copy()
    sdt = np.empty(n, np.int64)
    spol = np.empty(n, np.int8)
    for j in range(n):
        p = np.int64(y[j]) * width + x[j]
        sdt[fill[p]] = dt[j]
        spol[fill[p]] = pol[j]
        fill[p] += 1
    return start, sdt, spol, row_used


@njit(cache=True, fastmath=True, inline="always")
def _spatial_phase(rows, cols, yy, xx, m):  # pragma: no cover
    """Feature ``m`` of the spatial phase of pixel ``(xx, yy)``: ``rows[yy, xx or 0] *
    cols[xx, 0]`` (``encoding.SpatialPhase``), as (real, imaginary)."""
    xr = xx if rows.shape[1] > 1 else 0
    ar = rows[yy, xr, 0, m]
    ai = rows[yy, xr, 1, m]
    br = cols[xx, 0, 0, m]
    bi = cols[xx, 0, 1, m]
    return ar * br - ai * bi, ar * bi + ai * br


@njit(cache=True, fastmath=True, inline="always")
def _pixel_value(p, start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, out, slot):  # pragma: no cover
    """``out[slot] = phase(yy, u) * sum over the pixel's events of hi * lo`` (planar), with
    ``phase(yy, u) = rows[yy, u or 0] * cols[u, 0]`` (``encoding.SpatialPhase``)."""
    d = out.shape[2]
    mask = (1 << lo_bits) - 1
    for m in range(d):
        out[slot, 0, m] = 0.0
        out[slot, 1, m] = 0.0
    for q in range(start[p], start[p + 1]):
        h = sdt[q] >> lo_bits
        l = sdt[q] & mask
        b = spol[q]
        for m in range(d):
            out[slot, 0, m] += hi[h, 0, m] * lo[b, l, 0, m] - hi[h, 1, m] * lo[b, l, 1, m]
            out[slot, 1, m] += hi[h, 0, m] * lo[b, l, 1, m] + hi[h, 1, m] * lo[b, l, 0, m]
    for m in range(d):
        fr = out[slot, 0, m]
        fi = out[slot, 1, m]
        pr, pi = _spatial_phase(rows, cols, yy, u, m)
        out[slot, 0, m] = fr * pr - fi * pi
        out[slot, 1, m] = fr * pi + fi * pr


@njit(cache=True, parallel=True, fastmath=True)
def box_pass(start, sdt, spol, hi, lo, lo_bits, row_used, rows, cols, k, cum, ccum, nblk):  # pragma: no cover
    """One pass over the grid: ``cum[y, x]`` = sum over rows ``<= y`` of the box sums along x
    (``|dx| <= k``) of the per-pixel field ``phase * sum_events hi * lo`` (phase from ``rows``,
    ``cols``: see ``_pixel_value``); ``ccum`` the same
    for the event counts.

    The field is never stored: a pixel's value is computed from its events (``pixel_lists``)
    when it enters the sliding box along x and kept in a small ring buffer until it leaves, so
    the events are read in pixel order from a compact index instead of being scattered into a
    W x H x d grid. The running sums along y only accumulate row-box sums (bounded by the
    events of a 2k+1 pixel wide strip), which keeps float32 rounding small. Threads own blocks
    of columns and also evaluate the k columns beyond their block.
    """
    H, W = ccum.shape
    d = cum.shape[3]
    ring_n = 2 * k + 2
    for c in prange(nblk):
        x0 = c * W // nblk
        x1 = (c + 1) * W // nblk
        box = np.empty((2, d), np.float32)
        ring = np.empty((ring_n, 2, d), np.float32)
        for yy in range(H):
            if not row_used[yy]:
                for xx in range(x0, x1):
                    ccum[yy, xx] = 0 if yy == 0 else ccum[yy - 1, xx]
                    for m in range(d):
                        cum[yy, xx, 0, m] = 0.0 if yy == 0 else cum[yy - 1, xx, 0, m]
                        cum[yy, xx, 1, m] = 0.0 if yy == 0 else cum[yy - 1, xx, 1, m]
                continue
            row0 = yy * W
            # Sliding box along x: start with the window of column x0 - 1, then per column add
            # the pixel entering at x + k and remove the one leaving at x - k - 1 (only pixels
            # with events contribute, so empty pixels cost nothing here).
            for m in range(d):
                box[0, m] = 0.0
                box[1, m] = 0.0
            cb = 0
            for u in range(max(x0 - 1 - k, 0), min(x0 - 1 + k, W - 1) + 1):
                n = start[row0 + u + 1] - start[row0 + u]
                if n > 0:
                    cb += n
                    s = u % ring_n
                    _pixel_value(row0 + u, start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, ring, s)
                    for m in range(d):
                        box[0, m] += ring[s, 0, m]
                        box[1, m] += ring[s, 1, m]
            for xx in range(x0, x1):
                u = xx + k
                if u < W:
                    n = start[row0 + u + 1] - start[row0 + u]
                    if n > 0:
                        cb += n
                        s = u % ring_n
                        _pixel_value(row0 + u, start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, ring, s)
                        for m in range(d):
                            box[0, m] += ring[s, 0, m]
                            box[1, m] += ring[s, 1, m]
                u = xx - k - 1
                if u >= 0:
                    n = start[row0 + u + 1] - start[row0 + u]
                    if n > 0:
                        cb -= n
                        s = u % ring_n
                        for m in range(d):
                            box[0, m] -= ring[s, 0, m]
                            box[1, m] -= ring[s, 1, m]
                if yy == 0:
                    ccum[yy, xx] = cb
                    for m in range(d):
                        cum[yy, xx, 0, m] = box[0, m]
                        cum[yy, xx, 1, m] = box[1, m]
                else:
                    ccum[yy, xx] = ccum[yy - 1, xx] + cb
                    for m in range(d):
                        cum[yy, xx, 0, m] = cum[yy - 1, xx, 0, m] + box[0, m]
                        cum[yy, xx, 1, m] = cum[yy - 1, xx, 1, m] + box[1, m]


@njit(cache=True, parallel=True, fastmath=True)
def target_features(cum, ccum, k, tx, ty, tdt, tpol, slot, rows, cols, hi, lo, lo_bits):  # pragma: no cover
    """Features (T, 2d+1) float32 of the targets; row ``slot[r]`` holds target r.

    Window sum = column sum at row ``min(ty + k, H - 1)`` minus the one at row ``ty - k - 1``;
    then the target's own absolute phase is removed (multiply by ``conj(phase * hi * lo)``),
    the vector rescaled to norm sqrt(d) and ``log(1 + n)`` appended. Callers pass the targets
    in row order (``slot`` maps back), so the reads walk the grid forward.
    """
    H = ccum.shape[0]
    d = cum.shape[3]
    mask = (1 << lo_bits) - 1
    nt = tx.shape[0]
    out = np.empty((nt, 2 * d + 1), np.float32)
    scale = np.sqrt(np.float32(d))
    for r in prange(nt):
        o = slot[r]
        xx = tx[r]
        yy = ty[r]
        y1 = min(yy + k, H - 1)
        y0 = yy - k - 1
        h = tdt[r] >> lo_bits
        l = tdt[r] & mask
        q = tpol[r]
        cnt = ccum[y1, xx]
        if y0 >= 0:
            cnt -= ccum[y0, xx]
            for m in range(d):
                out[o, m] = cum[y1, xx, 0, m] - cum[y0, xx, 0, m]
                out[o, d + m] = cum[y1, xx, 1, m] - cum[y0, xx, 1, m]
        else:
            for m in range(d):
                out[o, m] = cum[y1, xx, 0, m]
                out[o, d + m] = cum[y1, xx, 1, m]
        s = np.float32(0.0)
        for m in range(d):
            gr = out[o, m]
            gi = out[o, d + m]
            tr = hi[h, 0, m] * lo[q, l, 0, m] - hi[h, 1, m] * lo[q, l, 1, m]
            ti = hi[h, 0, m] * lo[q, l, 1, m] + hi[h, 1, m] * lo[q, l, 0, m]
            sr, si = _spatial_phase(rows, cols, yy, xx, m)
            pr = sr * tr - si * ti
            pi = -(sr * ti + si * tr)
            vr = gr * pr - gi * pi
            vi = gr * pi + gi * pr
            out[o, m] = vr
            out[o, d + m] = vi
            s += vr * vr + vi * vi
        f = scale / max(np.sqrt(s), np.float32(1e-12))
        for m in range(2 * d):
            out[o, m] *= f
        out[o, 2 * d] = np.log1p(np.float32(cnt))
    return out


@njit(cache=True)
def latest_per_cell(cell, n_cells):  # pragma: no cover
    """Position of the last event in each cell (-1 where none): int64 (n_cells,)."""
    last = np.full(n_cells, -1, np.int64)
    for j in range(cell.shape[0]):
        last[cell[j]] = j
    return last
