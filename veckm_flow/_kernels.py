"""Compiled (numba) loops of the O(N) encoding and of target selection.

numpy alone cannot do the scatter and the running-sum pass within the speed budget
(``np.cumsum`` over a 346x260x32 complex grid alone takes ~40 ms); these loops take a few ms.
Callers are :mod:`evseg.veckm_flow.encoding` and :mod:`evseg.veckm_flow.targets`, which validate
inputs; nothing here checks bounds.

Complex values are stored planar, ``[..., 0, m]`` real and ``[..., 1, m]`` imaginary part
(float32), so that the inner loops over the ``d`` features are plain float arithmetic that
LLVM vectorises (numba's interleaved complex64 arithmetic does not, and ran ~4x slower).

The field and its box sums live in reusable workspaces ``(H, W, 2, d)`` that are never zeroed as
a whole: the scatter initialises a pixel on its first event (``count == 0``) and the box pass
reads the field only where ``count > 0``. This saves a 23 MB memset (and page faults) per slice
at 346x260, d = 32.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True, fastmath=True)
def scatter(x, y, dt, pol, hi, lo, lo_bits, field, count, row_used, bands):  # pragma: no cover
    """Per-pixel sum of the time (and polarity) phases ``hi[dt >> b] * lo[pol, dt & mask]``.

    x, y: uint16 (N,) px; dt: int64 (N,) us; pol: int8 (N,) index into ``lo`` (0 when the
    encoding ignores polarity); hi (., 2, d), lo (P, 1024, 2, d): float32 planar tables;
    field: (H, W, 2, d) float32 out; count (H, W) int32 must be zero on entry; row_used (H,)
    bool is set. Thread c owns rows ``bands[c]:bands[c + 1]`` (chosen to hold similar numbers
    of events), so no two threads write the same pixel.
    """
    d = field.shape[3]
    n = x.shape[0]
    mask = (1 << lo_bits) - 1
    for c in prange(bands.shape[0] - 1):
        y0 = bands[c]
        y1 = bands[c + 1]
        for j in range(n):
            yy = y[j]
            if yy < y0 or yy >= y1:
                continue
            xx = x[j]
            h = dt[j] >> lo_bits
            l = dt[j] & mask
            q = pol[j]
            row_used[yy] = True
            if count[yy, xx] == 0:
                for m in range(d):
                    field[yy, xx, 0, m] = hi[h, 0, m] * lo[q, l, 0, m] - hi[h, 1, m] * lo[q, l, 1, m]
                    field[yy, xx, 1, m] = hi[h, 0, m] * lo[q, l, 1, m] + hi[h, 1, m] * lo[q, l, 0, m]
            else:
                for m in range(d):
                    field[yy, xx, 0, m] += hi[h, 0, m] * lo[q, l, 0, m] - hi[h, 1, m] * lo[q, l, 1, m]
                    field[yy, xx, 1, m] += hi[h, 0, m] * lo[q, l, 1, m] + hi[h, 1, m] * lo[q, l, 0, m]
            count[yy, xx] += 1


@njit(cache=True, parallel=True, fastmath=True)
def box_pass(field, count, row_used, phase_xy, k, cum, ccum, nblk):  # pragma: no cover
    """One pass over the grid: ``cum[y, x]`` = sum over rows ``<= y`` of the box sums along x
    (``|dx| <= k``) of ``field * phase_xy``; ``ccum`` the same for ``count``.

    The running sums along y only accumulate row-box sums (bounded by the events of a 2k+1
    pixel wide strip), which keeps float32 rounding small. Threads own blocks of columns and
    read (never write) the ``k`` columns beyond their block. (A variant that keeps only a
    rolling row and picks up the targets' sums on the way, writing no full grid, measured
    ~1.5x slower; a running sum along x instead of the sliding box ~1.2x slower.)
    """
    H, W = count.shape
    d = field.shape[3]
    for c in prange(nblk):
        x0 = c * W // nblk
        x1 = (c + 1) * W // nblk
        box = np.empty((2, d), np.float32)
        for yy in range(H):
            if not row_used[yy]:
                for xx in range(x0, x1):
                    ccum[yy, xx] = 0 if yy == 0 else ccum[yy - 1, xx]
                    for m in range(d):
                        cum[yy, xx, 0, m] = 0.0 if yy == 0 else cum[yy - 1, xx, 0, m]
                        cum[yy, xx, 1, m] = 0.0 if yy == 0 else cum[yy - 1, xx, 1, m]
                continue
            # Sliding box along x: start with the window of column x0 - 1, then per column add
            # the pixel entering at x + k and remove the one leaving at x - k - 1 (only pixels
            # with events contribute, so empty pixels cost nothing here).
            for m in range(d):
                box[0, m] = 0.0
                box[1, m] = 0.0
            cb = 0
            for u in range(max(x0 - 1 - k, 0), min(x0 - 1 + k, W - 1) + 1):
                if count[yy, u] > 0:
                    cb += count[yy, u]
                    for m in range(d):
                        fr = field[yy, u, 0, m]
                        fi = field[yy, u, 1, m]
                        pr = phase_xy[yy, u, 0, m]
                        pi = phase_xy[yy, u, 1, m]
                        box[0, m] += fr * pr - fi * pi
                        box[1, m] += fr * pi + fi * pr
            for xx in range(x0, x1):
                u = xx + k
                if u < W and count[yy, u] > 0:
                    cb += count[yy, u]
                    for m in range(d):
                        fr = field[yy, u, 0, m]
                        fi = field[yy, u, 1, m]
                        pr = phase_xy[yy, u, 0, m]
                        pi = phase_xy[yy, u, 1, m]
                        box[0, m] += fr * pr - fi * pi
                        box[1, m] += fr * pi + fi * pr
                u = xx - k - 1
                if u >= 0 and count[yy, u] > 0:
                    cb -= count[yy, u]
                    for m in range(d):
                        fr = field[yy, u, 0, m]
                        fi = field[yy, u, 1, m]
                        pr = phase_xy[yy, u, 0, m]
                        pi = phase_xy[yy, u, 1, m]
                        box[0, m] -= fr * pr - fi * pi
                        box[1, m] -= fr * pi + fi * pr
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
def target_features(cum, ccum, k, tx, ty, tdt, tpol, slot, phase_xy, hi, lo, lo_bits):  # pragma: no cover
    """Features (T, 2d+1) float32 of the targets; row ``slot[r]`` holds target r.

    Window sum = column sum at row ``min(ty + k, H - 1)`` minus the one at row ``ty - k - 1``;
    then the target's own absolute phase is removed (multiply by ``conj(phase_xy * hi * lo)``),
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
            pr = phase_xy[yy, xx, 0, m] * tr - phase_xy[yy, xx, 1, m] * ti
            pi = -(phase_xy[yy, xx, 0, m] * ti + phase_xy[yy, xx, 1, m] * tr)
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
