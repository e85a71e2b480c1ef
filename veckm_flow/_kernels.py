"""Compiled (numba) loops of the O(N) encoding and of target selection.

numpy alone cannot do the scatter and the running-sum pass within the speed budget
(``np.cumsum`` over a 346x260x32 complex grid alone takes ~40 ms); these loops take a few ms.
Callers are :mod:`evseg.veckm_flow.encoding` and :mod:`evseg.veckm_flow.targets`, which validate
inputs; nothing here checks bounds.

Complex values are stored planar, ``[..., 0, m]`` real and ``[..., 1, m]`` imaginary part
(float32), so that the inner loops over the ``d`` features are plain float arithmetic that
LLVM vectorises (numba's interleaved complex64 arithmetic does not, and ran ~4x slower).

The per-pixel complex field is never stored: events are sorted by pixel (counting sort, O(N))
and each pixel's value is computed when the pass reaches it. Only the current row's box sums
of a block of columns are kept (per thread, 25 KB per look); each is added at once to the
window sums of the targets whose window holds that row, and a target's features are finished
as soon as its window is complete.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# Only re-association of float sums (what lets LLVM vectorise the loops over the d features),
# not all of fastmath: its 'contract' flag (fused multiply-add) is applied differently when a
# kernel is compiled in the running process and when it is loaded from numba's cache, so the
# first run after an install gave other features (~1e-6) and, rarely, other labels (58 of 6 M
# events over 12 simulated scenes) than every later run. 'reassoc' alone gives the same bits
# either way (tests/veckm_flow/test_encoding.py) and costs ~0-5 % of the encoding time.
_FASTMATH = {"reassoc"}


@njit(cache=True, nogil=True)
def slice_extent(x, y, t):  # pragma: no cover
    """``(max x, max y, min t, max t)`` of a non-empty slice; reads the event fields in place
    (strided views of the structured array are fine), so no field is copied."""
    mx = np.int64(x[0])
    my = np.int64(y[0])
    t_lo = t[0]
    t_hi = t[0]
    for j in range(1, x.shape[0]):
        if x[j] > mx:
            mx = np.int64(x[j])
        if y[j] > my:
            my = np.int64(y[j])
        if t[j] < t_lo:
            t_lo = t[j]
        if t[j] > t_hi:
            t_hi = t[j]
    return mx, my, t_lo, t_hi


_TIME_MASK = np.int32((1 << 30) - 1)
"""Times since the slice's start (us) are kept as int32 with the polarity in bit 30, so a slice
spans at most 2^30 - 1 us (``encoding.MAX_SLICE_SPAN_US``, checked by the caller)."""


@njit(cache=True, parallel=True, nogil=True)
def pixel_lists(x, y, t, p, t0, polarity, width, height):  # pragma: no cover
    """Counting sort of the events by pixel: ``(start (H*W + 1,) int32, sdt (N,) int32, spol
    (N,) int8, row_used (H,))``; the events of pixel ``q = y * W + x`` have times
    ``sdt[start[q]:start[q+1]]`` (us since ``t0``, input order) and polarity indices ``spol[...]``
    (1 for ``p > 0`` when ``polarity``, else 0). Times and polarities are copied in pixel order
    so that the box pass reads them sequentially. O(N + W H). Coordinates must lie on the
    sensor and times within 2^30 - 1 us of ``t0`` (callers check with :func:`slice_extent`).

    The event fields are read once, in parallel, into compact int32 arrays (pixel; time with
    the polarity in bit 30): the two serial counting passes then touch 8 bytes per event
    instead of the strided 13-byte records, which halved the time (100 k events: 1.34 ->
    0.67 ms; 1 M: 15.1 -> 7.1 ms on 2 cores). The result does not depend on the thread count."""
    n = x.shape[0]
    npix = width * height
    pix = np.empty(n, np.int32)
    tp = np.empty(n, np.int32)
    for j in prange(n):
        pix[j] = np.int32(np.int64(y[j]) * width + x[j])
        v = np.int32(t[j] - t0)
        if polarity and p[j] > 0:
            v |= np.int32(1 << 30)
        tp[j] = v
    start = np.zeros(npix + 1, np.int32)
    for j in range(n):
        start[pix[j] + 1] += 1
    row_used = np.zeros(height, np.bool_)
    for q in range(npix):
        if start[q + 1] > 0:
            row_used[q // width] = True
        start[q + 1] += start[q]
    fill = start[:-1].copy()
    sdt = np.empty(n, np.int32)
    spol = np.empty(n, np.int8)
    for j in range(n):
        q = pix[j]
        f = fill[q]
        v = tp[j]
        sdt[f] = v & _TIME_MASK
        spol[f] = np.int8(v >> 30)
        fill[q] = f + 1
    return start, sdt, spol, row_used


@njit(cache=True, nogil=True)
def order_targets(targets, x, y, t, p, t0, polarity, width, height, nblk):  # pragma: no cover
    """The targets in the order the box pass completes them: grouped by column block (block
    ``c`` spans columns ``c W // nblk`` to ``(c + 1) W // nblk``), by row within a block, input
    order among equals (a stable counting sort). Returns ``(order, tx, ty, tdt, tpol,
    blk_start)``: ``order[r]`` is the row of ``targets`` placed r-th, then that target's column,
    row, time since ``t0`` (us) and polarity index, and the first position of each block
    (``nblk + 1``)."""
    block_of = np.empty(width, np.int64)
    for c in range(nblk):
        for col in range(c * width // nblk, (c + 1) * width // nblk):
            block_of[col] = c
    nkey = nblk * height
    first = np.zeros(nkey + 1, np.int64)
    nt = targets.shape[0]
    key = np.empty(nt, np.int64)
    for r in range(nt):
        i = targets[r]
        key[r] = block_of[np.int64(x[i])] * height + y[i]
        first[key[r] + 1] += 1
    for k in range(nkey):
        first[k + 1] += first[k]
    blk_start = np.empty(nblk + 1, np.int64)
    for c in range(nblk + 1):
        blk_start[c] = first[c * height]
    order = np.empty(nt, np.int64)
    for r in range(nt):
        order[first[key[r]]] = r
        first[key[r]] += 1
    tx = np.empty(nt, np.int64)
    ty = np.empty(nt, np.int64)
    tdt = np.empty(nt, np.int64)
    tpol = np.zeros(nt, np.int8)
    for o in range(nt):
        i = targets[order[o]]
        tx[o] = x[i]
        ty[o] = y[i]
        tdt[o] = t[i] - t0
        if polarity and p[i] > 0:
            tpol[o] = 1
    return order, tx, ty, tdt, tpol, blk_start


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _pixel_phase(rows, cols, look, yy, xx):  # pragma: no cover
    """Look ``look``'s spatial phase factors of pixel ``(xx, yy)``, planar ``(2, d)`` each:
    ``rows[look][yy, xx or 0]`` and ``cols[look][xx, 0]`` (``encoding.SpatialPhase``), whose
    complex product is the phase. Taken once per pixel, outside the loops over the d features:
    a tuple indexed by a variable inside them kept LLVM from vectorising (8 looks took 43
    instead of ~25 ms)."""
    ra = rows[look]
    return ra[yy, xx if ra.shape[1] > 1 else 0], cols[look][xx, 0]


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _event_sum(p, start, sdt, spol, hi, lo, lo_bits, acc):  # pragma: no cover
    """``acc = sum over pixel p's events of hi * lo`` (planar (2, d)): the pixel's time and
    polarity phases, the same in every look."""
    d = acc.shape[1]
    mask = (1 << lo_bits) - 1
    for m in range(d):
        acc[0, m] = 0.0
        acc[1, m] = 0.0
    for q in range(start[p], start[p + 1]):
        h = sdt[q] >> lo_bits
        l = sdt[q] & mask
        b = spol[q]
        for m in range(d):
            acc[0, m] += hi[h, 0, m] * lo[b, l, 0, m] - hi[h, 1, m] * lo[b, l, 1, m]
            acc[1, m] += hi[h, 0, m] * lo[b, l, 1, m] + hi[h, 1, m] * lo[b, l, 0, m]


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _enter_box(start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, row0, ring, box, ev):  # pragma: no cover
    """Pixel ``(u, yy)`` enters the sliding box of every look: its value ``phase_look * sum
    over its events of hi * lo`` goes to its ``ring`` slot and is added to ``box`` (the event
    sum, in ``ev``, is computed once for all looks); returns its event count (0: nothing to do)."""
    n = start[row0 + u + 1] - start[row0 + u]
    if n > 0:
        s = u % ring.shape[1]
        _event_sum(row0 + u, start, sdt, spol, hi, lo, lo_bits, ev)
        for look in range(len(rows)):
            ra, ca = _pixel_phase(rows, cols, look, yy, u)
            rg = ring[look, s]
            bx = box[look]
            for m in range(box.shape[2]):
                pr = ra[0, m] * ca[0, m] - ra[1, m] * ca[1, m]
                pi = ra[0, m] * ca[1, m] + ra[1, m] * ca[0, m]
                vr = ev[0, m] * pr - ev[1, m] * pi
                vi = ev[0, m] * pi + ev[1, m] * pr
                rg[0, m] = vr
                rg[1, m] = vi
                bx[0, m] += vr
                bx[1, m] += vi
    return n


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _row_box(start, sdt, spol, hi, lo, lo_bits, rows, cols, k, yy, x0, x1, W, ring, box, ev, out, cnt):  # pragma: no cover
    """Row ``yy``'s box sums along x (``|dx| <= k``) of each look's per-pixel field ``phase_look
    * sum_events hi * lo`` for columns ``x0 <= x < x1``: ``out[look, x - x0]`` (planar) and
    counts ``cnt[x - x0]``.

    The field is never stored: a pixel's value is computed from its events (``pixel_lists``)
    when it enters the sliding box and kept in the small ``ring`` until it leaves, so only
    pixels with events cost anything."""
    n_looks = len(rows)
    d = box.shape[2]
    ring_n = ring.shape[1]
    row0 = yy * W
    for look in range(n_looks):
        for m in range(d):
            box[look, 0, m] = 0.0
            box[look, 1, m] = 0.0
    cb = 0
    for u in range(max(x0 - 1 - k, 0), min(x0 - 1 + k, W - 1) + 1):
        cb += _enter_box(start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, row0, ring, box, ev)
    for xx in range(x0, x1):
        u = xx + k
        if u < W:
            cb += _enter_box(start, sdt, spol, hi, lo, lo_bits, rows, cols, yy, u, row0, ring, box, ev)
        u = xx - k - 1
        if u >= 0:
            n = start[row0 + u + 1] - start[row0 + u]
            if n > 0:
                cb -= n
                s = u % ring_n
                for look in range(n_looks):
                    for m in range(d):
                        box[look, 0, m] -= ring[look, s, 0, m]
                        box[look, 1, m] -= ring[look, s, 1, m]
        cnt[xx - x0] = cb
        for look in range(n_looks):
            for m in range(d):
                out[look, xx - x0, 0, m] = box[look, 0, m]
                out[look, xx - x0, 1, m] = box[look, 1, m]


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _gather(col, row_sums, row_cnt, acc, cnt, a):  # pragma: no cover
    """Adds the row box sums at block column ``col`` of every look to a target's window sums
    ``acc[a]`` (looks, planar) and its event count to ``cnt[a]``."""
    cnt[a] += row_cnt[col]
    for look in range(row_sums.shape[0]):
        for m in range(row_sums.shape[3]):
            acc[a, look, 0, m] += row_sums[look, col, 0, m]
            acc[a, look, 1, m] += row_sums[look, col, 1, m]


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _emit(r, o, xx, yy, g, cnt, tdt, tpol, rows, cols, hi, lo, lo_bits, out, tmp):  # pragma: no cover
    """Features of target ``r`` (pixel ``(xx, yy)``) into ``out[look, o]`` for every look: its
    window sums ``g`` (looks, planar) times ``conj(phase * hi * lo)`` of the target itself,
    rescaled to norm sqrt(d), then ``log(1 + cnt)``. Each look is computed in the (2, d)
    scratch ``tmp``: working on ``g``'s strided rows directly let LLVM round the norm's sum
    differently for different look counts (1 ulp), and a look's features must not depend on
    how many looks are computed with it."""
    d = hi.shape[2]
    mask = (1 << lo_bits) - 1
    h = tdt[r] >> lo_bits
    l = tdt[r] & mask
    q = tpol[r]
    for look in range(len(rows)):
        for m in range(d):
            tmp[0, m] = g[look, 0, m]
            tmp[1, m] = g[look, 1, m]
        s = np.float32(0.0)
        ra, ca = _pixel_phase(rows, cols, look, yy, xx)
        for m in range(d):
            gr = tmp[0, m]
            gi = tmp[1, m]
            tr = hi[h, 0, m] * lo[q, l, 0, m] - hi[h, 1, m] * lo[q, l, 1, m]
            ti = hi[h, 0, m] * lo[q, l, 1, m] + hi[h, 1, m] * lo[q, l, 0, m]
            sr = ra[0, m] * ca[0, m] - ra[1, m] * ca[1, m]
            si = ra[0, m] * ca[1, m] + ra[1, m] * ca[0, m]
            pr = sr * tr - si * ti
            pi = -(sr * ti + si * tr)
            vr = gr * pr - gi * pi
            vi = gr * pi + gi * pr
            tmp[0, m] = vr
            tmp[1, m] = vi
            s += vr * vr + vi * vi
        f = np.float32(np.sqrt(np.float32(d))) / max(np.sqrt(s), np.float32(1e-12))
        for m in range(d):
            out[look, o, m] = tmp[0, m] * f
            out[look, o, d + m] = tmp[1, m] * f
        out[look, o, 2 * d] = np.log1p(np.float32(cnt))


@njit(cache=True, nogil=True)
def _most_active(ty, r0, r1, k):  # pragma: no cover
    """Most targets of ``ty[r0:r1]`` (sorted) whose windows ``ty +- k`` share a row."""
    most = 1
    j = r0
    for i in range(r0, r1):
        while ty[j] < ty[i] - 2 * k:
            j += 1
        most = max(most, i - j + 1)
    return most


@njit(cache=True, parallel=True, fastmath=_FASTMATH, nogil=True)
def window_features(start, sdt, spol, hi, lo, lo_bits, row_used, rows, cols, k, nblk,
                    tx, ty, tdt, tpol, slot, blk_start):  # pragma: no cover
    """Features (L, T, 2d+1) float32 of the targets in L looks: for each, the sum over its
    (2k+1)^2 pixel window of ``phase_look * sum_events hi * lo``, with its own phase removed;
    row ``slot[r]`` holds target r. ``rows`` and ``cols`` are tuples of the L looks' spatial
    phase tables (``encoding.SpatialPhase``); the looks share the time and polarity phases
    ``hi``, ``lo`` (mirror images of the slice, ``mirrors.py``), so each pixel's sum over its
    events, most of the work, is computed once for all of them.

    One pass down the rows per block of columns (threads own blocks; block c spans columns
    ``c W // nblk`` to ``(c + 1) W // nblk``). A row's box sums along x are added to the
    window sums of the targets whose window holds the row (rows ``ty - k .. ty + k``, in
    increasing order: each window sum is a fresh sum of 2k+1 row sums, not a difference of
    two long running sums, so float32 rounding stays small), and a target's features are
    finished when the pass leaves its window. So no H x W x d grid of running sums is written
    and read back (23 MB per slice at 346x260, d = 32), only one row of box sums is held at a
    time (8 looks: 200 KB, within a core's cache; a ring of the last 2k+1 rows outgrew it),
    and rows no target's window reaches are skipped. Targets come grouped by block
    (``blk_start``) and sorted by row within a block.
    """
    n_looks = len(rows)
    H = row_used.shape[0]
    W = (start.shape[0] - 1) // H
    d = hi.shape[2]
    nt = tx.shape[0]
    out = np.empty((n_looks, nt, 2 * d + 1), np.float32)
    for c in prange(nblk):
        x0 = c * W // nblk
        x1 = (c + 1) * W // nblk
        bw = x1 - x0
        r_begin = blk_start[c]
        r_end = blk_start[c + 1]
        if r_begin == r_end:
            continue
        box = np.empty((n_looks, 2, d), np.float32)
        ev = np.empty((2, d), np.float32)
        tmp = np.empty((2, d), np.float32)
        ring = np.empty((n_looks, 2 * k + 2, 2, d), np.float32)
        row_sums = np.empty((n_looks, bw, 2, d), np.float32)
        row_cnt = np.empty(bw, np.int64)
        # Window sums of the targets whose window the pass is in: a contiguous run of the
        # row-sorted targets, kept in a ring of slots r % cap.
        cap = _most_active(ty, r_begin, r_end, k)
        acc = np.empty((cap, n_looks, 2, d), np.float32)
        cnt = np.empty(cap, np.int64)
        r_done = r_begin  # targets before it are finished
        r_open = r_begin  # targets before it have their window open
        for yy in range(H):
            while r_open < r_end and ty[r_open] - k <= yy:
                acc[r_open % cap] = 0.0
                cnt[r_open % cap] = 0
                r_open += 1
            if row_used[yy] and r_done < r_open:
                _row_box(start, sdt, spol, hi, lo, lo_bits, rows, cols, k, yy, x0, x1, W, ring, box, ev,
                         row_sums, row_cnt)
                for r in range(r_done, r_open):
                    _gather(tx[r] - x0, row_sums, row_cnt, acc, cnt, r % cap)
            while r_done < r_end and ty[r_done] + k <= yy:
                _emit(r_done, slot[r_done], tx[r_done], ty[r_done], acc[r_done % cap], cnt[r_done % cap],
                      tdt, tpol, rows, cols, hi, lo, lo_bits, out, tmp)
                r_done += 1
            if r_done == r_end:
                break
        while r_done < r_end:  # windows cut by the bottom edge
            _emit(r_done, slot[r_done], tx[r_done], ty[r_done], acc[r_done % cap], cnt[r_done % cap],
                  tdt, tpol, rows, cols, hi, lo, lo_bits, out, tmp)
            r_done += 1
    return out


@njit(cache=True, nogil=True)
def latest_per_cell(cell, n_cells):  # pragma: no cover
    """Position of the last event in each cell (-1 where none): int64 (n_cells,)."""
    last = np.full(n_cells, -1, np.int64)
    for j in range(cell.shape[0]):
        last[cell[j]] = j
    return last
