"""Mirrored looks: the network's flow averaged over mirror images of the slice.

The head was trained with right-angle rotations and flips of every scene (``weights/MODEL.md``),
so it should answer a mirrored slice with the mirrored flow; it does so only approximately, and
its errors in the mirror images are partly independent. Averaging the looks over a group of
mirror images of the square pixel grid (test-time augmentation) cancels part of them.

No event is moved to get a mirror image. The encoding sees events only through the projection
``A^T p`` of their relative coordinates ``p = (x, y, t, ...)`` (:mod:`evseg.veckm_flow.encoding`),
and its ``(2k+1) x (2k+1)`` window is symmetric, so encoding the mirror image ``M p`` with the
matrix ``A`` is encoding ``p`` with ``M^T A``: the mirror's rows of the matrix, negated or
swapped. The events, targets, neighbourhoods and a calibration's undistorted positions all stay
as they are, and the head's answer ``v'`` (in the mirror image) maps back as ``v = M^T v'``.

A look is identified by an integer ``k`` in 0-7: ``k >= 4`` transposes (swaps x and y) first,
then ``k % 4`` flips: 1 x, 2 y, 3 both (the 180 deg rotation). :data:`MIRROR_GROUPS` lists the
looks of each supported count; each is a group, so the set of looks is the same seen from any
of its mirror images.

:func:`combine_looks` averages the looks' directions with weights ``1 / u^2`` (``u`` each look's
predicted angular error) and their speeds with the same weights; the uncertainty adds the looks'
disagreement (the circular standard deviation of their directions) to their weighted mean
uncertainty. A lone event's encoding is the same in every mirror image, so its looks are one
vector mirrored, which cancels over the group: no direction, and an uncertainty to match. On
learned-flow validation scenes (seeds 900-901, all six presets, ``evseg flow``'s estimator with
both second looks; throwaway script) the median angular error went from 11.7 deg with one look
to 10.8 (2), 10.4 (4) and 10.1 deg (8), the error below the plane fit from 16 % to 24, 29 and
31 %; the sign-correct rate moved less (91.4 -> 92.1 %: a slow edge's missing direction is
missing in every mirror image).

The looks are computed together (:func:`~evseg.veckm_flow.encoding.encode_targets_looks`): the
mirror matrices share their time and polarity rows, so each pixel's sum over its events, most
of the encoding, is computed once for all of them, and each look's result is bit for bit the
one it gets alone. The pass over the pixel grid and the network still run once per look: on
``evseg bench flow``'s slow-edge slice 8 looks took 5.1x the time of one (123 against 23.9 ms
for 10,000 targets; 9.3x when each look was a separate flow computation).
"""

from __future__ import annotations

import numpy as np

from evseg.errors import ConfigError

MIRROR_GROUPS: dict[int, tuple[int, ...]] = {
    1: (0,),
    2: (0, 4),  # identity, transpose (validation: 10.8 deg; the 180 deg rotation 11.0 deg)
    4: (0, 1, 2, 3),  # the flips (10.4 deg; the rotation group with transposes 10.5 deg)
    8: (0, 1, 2, 3, 4, 5, 6, 7),  # the dihedral group of the square
}
"""Looks of each supported ``mirrors`` count (see the module docstring for ``k``)."""


def mirror_looks(mirrors: int) -> tuple[int, ...]:
    """The looks ``k`` of ``mirrors`` mirror images (1, 2, 4 or 8).

    >>> mirror_looks(4)
    (0, 1, 2, 3)
    """
    if isinstance(mirrors, bool) or not isinstance(mirrors, (int, np.integer)) or int(mirrors) not in MIRROR_GROUPS:
        raise ConfigError(f"mirrors must be one of {sorted(MIRROR_GROUPS)}, got {mirrors!r}")
    return MIRROR_GROUPS[int(mirrors)]


def mirror_matrix(k: int) -> np.ndarray:
    """The 2x2 mirror ``M`` of look ``k``, acting on ``(x, y)``: flips after the transpose.

    >>> mirror_matrix(5).tolist()  # transpose, then flip x: (x, y) -> (-y, x)
    [[0.0, -1.0], [1.0, 0.0]]
    """
    if not 0 <= int(k) < 8:
        raise ConfigError(f"mirror look must be in 0-7, got {k!r}")
    k = int(k)
    t = np.array([[0.0, 1.0], [1.0, 0.0]]) if k >= 4 else np.eye(2)
    f = np.diag([-1.0 if k % 4 in (1, 3) else 1.0, -1.0 if k % 4 in (2, 3) else 1.0])
    return f @ t


def mirrored_encoding_matrix(matrix: np.ndarray, k: int) -> np.ndarray:
    """The encoding matrix that encodes the mirror image ``k`` of a slice: rows x and y
    replaced by ``M^T [a_x; a_y]``, the other rows (t, polarity) unchanged.

    >>> A = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    >>> mirrored_encoding_matrix(A, 4).tolist()  # transpose: rows x and y swap
    [[3.0, 4.0], [1.0, 2.0], [5.0, 6.0]]
    """
    out = np.array(matrix, dtype=np.float64, copy=True)
    out[:2] = mirror_matrix(k).T @ out[:2]
    return out


def unmirror_flow(nx: np.ndarray, ny: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Flow ``(nx, ny)`` (px/s) estimated in the mirror image ``k``, mapped back: ``M^T v``.

    >>> [a.tolist() for a in unmirror_flow(np.array([1.0]), np.array([2.0]), 5)]
    [[2.0], [-1.0]]
    """
    m = mirror_matrix(k)
    return m[0, 0] * nx + m[1, 0] * ny, m[0, 1] * nx + m[1, 1] * ny


def combine_looks(
    looks: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One flow ``(nx, ny, uncertainty)`` (px/s, rad) from looks at the same targets, each
    already mapped back: the direction of the ``1 / u^2``-weighted mean of their unit vectors,
    the weighted mean of their speeds, and as uncertainty ``hypot(weighted mean u,
    sqrt(-2 ln R))``, with ``R`` the length of the weighted mean unit vector (1 when the looks
    agree; the second term is the circular standard deviation of their directions, rad).

    Example (equal uncertainty, 90 deg apart: the bisector at the mean speed, R = 0.707):
        >>> a = (np.array([2.0]), np.array([0.0]), np.array([0.5]))
        >>> b = (np.array([0.0]), np.array([4.0]), np.array([0.5]))
        >>> [[round(float(v), 4) for v in x] for x in combine_looks([a, b])]
        [[2.1213], [2.1213], [0.9712]]
    """
    x = np.stack([np.asarray(lk[0], np.float64) for lk in looks])
    y = np.stack([np.asarray(lk[1], np.float64) for lk in looks])
    u = np.stack([np.asarray(lk[2], np.float64) for lk in looks])
    # Weights as the second looks' (fast_edges.combine): the head's uncertainty is its predicted
    # angular error, so 1 / u^2 is an inverse variance; the floor keeps a zero from dominating.
    w = 1.0 / np.maximum(u, 1e-3) ** 2
    speed = np.hypot(x, y)
    unit = np.maximum(speed, 1e-12)
    ex, ey = (w * x / unit).sum(0), (w * y / unit).sum(0)
    norm = np.maximum(np.hypot(ex, ey), 1e-12)
    wsum = w.sum(0)
    s = (w * speed).sum(0) / wsum
    spread = np.sqrt(-2.0 * np.log(np.clip(norm / wsum, 1e-12, 1.0)))  # circular std, rad
    return ((ex / norm * s).astype(np.float32), (ey / norm * s).astype(np.float32),
            np.hypot((w * u).sum(0) / wsum, spread).astype(np.float32))
