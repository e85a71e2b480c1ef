"""Compiled (numba) loops of the initialization: the robust 1-ring translations.

In numpy each IRLS iteration of :func:`evseg.segmentation.initialization.local_translations`
costs five ``bincount`` passes plus temporaries (~1 ms at 1.5 k nodes for four iterations, most
of the initialization budget); one compiled pass per iteration does the same sums in a few
tens of microseconds. The caller validates inputs; nothing here checks bounds.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def ring_translations(centre, hx, hy, norm, m, scale, iterations, min_conditioning, nx, ny):  # pragma: no cover
    """Per-node least-squares translation of its ring pairs ``(centre[k], member k)`` with
    unit normals ``hx, hy`` and magnitudes ``norm`` (member values, px/s): first unweighted,
    then ``iterations`` Cauchy-reweighted passes with ``scale`` (px/s; <= 0 = none).
    Ill-conditioned nodes keep their own flow ``(nx, ny)`` and are flagged False."""
    n_pairs = centre.shape[0]
    tx = np.empty(m)
    ty = np.empty(m)
    ok = np.empty(m, dtype=np.bool_)
    sums = np.zeros((m, 5))
    total = 1 + (iterations if scale > 0 else 0)
    for it in range(total):
        sums[:, :] = 0.0
        for k in range(n_pairs):
            c = centre[k]
            w = 1.0
            if it > 0:
                r = (hx[k] * tx[c] + hy[k] * ty[c] - norm[k]) / scale
                w = 1.0 / (1.0 + r * r)
            sums[c, 0] += w * hx[k] * hx[k]
            sums[c, 1] += w * hx[k] * hy[k]
            sums[c, 2] += w * hy[k] * hy[k]
            sums[c, 3] += w * norm[k] * hx[k]
            sums[c, 4] += w * norm[k] * hy[k]
        for i in range(m):
            a = sums[i, 0]
            b = sums[i, 1]
            cc = sums[i, 2]
            bx = sums[i, 3]
            by = sums[i, 4]
            det = a * cc - b * b
            disc = np.sqrt(max((a + cc) * (a + cc) / 4.0 - det, 0.0))
            lmax = (a + cc) / 2.0 + disc
            lmin = (a + cc) / 2.0 - disc
            good = lmin >= min_conditioning * max(lmax, 1e-300)
            ok[i] = good
            if good:
                tx[i] = (cc * bx - b * by) / det
                ty[i] = (a * by - b * bx) / det
            else:
                tx[i] = nx[i]
                ty[i] = ny[i]
    return tx, ty, ok
