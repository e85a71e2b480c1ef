"""Translating straight edges with known normal flow: test and benchmark input.

Not a replacement for the project's simulator (:mod:`evseg.simulator`): no intensities, no
noise model, no occlusion order. Each edge is a segment of a straight line that moves along its
normal ``n`` at ``speed_px_s``; a pixel fires when the line crosses its centre, so the ground
truth normal flow of every event of that edge is exactly ``speed_px_s * n`` (px/s) and the time
surface around it is the plane ``t = (n . p - c) / speed``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.events import EVENT_DTYPE


@dataclass(frozen=True)
class EdgeScene:
    """Events of translating edges and their exact normal flow.

    Attributes:
        events: :data:`~evseg.events.EVENT_DTYPE` ``(N,)`` sorted by ``t`` (us).
        nx, ny: float32 ``(N,)`` ground-truth normal flow of each event, px/s.
        sensor_size: ``(width, height)`` px.
    """

    events: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    sensor_size: tuple[int, int]


def edge_events(
    sensor_size: tuple[int, int],
    center_px: tuple[float, float],
    angle_rad: float,
    speed_px_s: float,
    length_px: float,
    duration_us: int,
    events_per_crossing: int = 1,
    t0_us: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Events of one edge: unsorted ``(x, y, t_us)`` int arrays, one set per pixel crossing.

    The edge passes through ``center_px`` at ``t0_us`` and moves along
    ``n = (cos angle_rad, sin angle_rad)`` (x = column, y = row, row 0 at the top). Pixels
    within ``length_px / 2`` of the centre line's midpoint along the edge fire once the line
    reaches them during ``[t0_us, t0_us + duration_us)``; ``events_per_crossing`` events
    per crossing are spaced 1 us apart (several contrast steps of one edge).
    """
    w, h = sensor_size
    n = np.array([np.cos(angle_rad), np.sin(angle_rad)])
    tang = np.array([-n[1], n[0]])
    yy, xx = np.mgrid[0:h, 0:w]
    rel = np.stack([xx.ravel() - center_px[0], yy.ravel() - center_px[1]], axis=1)
    along = rel @ n  # px ahead of the edge at t0
    across = rel @ tang
    t = t0_us + along / speed_px_s * 1e6
    keep = (np.abs(across) <= length_px / 2) & (t >= t0_us) & (t < t0_us + duration_us - events_per_crossing)
    x = xx.ravel()[keep]
    y = yy.ravel()[keep]
    t = np.floor(t[keep]).astype(np.int64)
    reps = np.arange(events_per_crossing)
    return (
        np.repeat(x, events_per_crossing),
        np.repeat(y, events_per_crossing),
        (t[:, None] + reps[None, :]).ravel(),
    )


def translating_edges(
    sensor_size: tuple[int, int] = (346, 260),
    n_edges: int = 40,
    duration_us: int = 20_000,
    speed_px_s: tuple[float, float] = (200.0, 2000.0),
    length_px: tuple[float, float] = (40.0, 160.0),
    events_per_crossing: int = 2,
    seed: int = 0,
) -> EdgeScene:
    """A slice of many edges with random position, direction, speed (log-uniform) and length.

    Overlapping edges make some events' neighbourhoods mix two flows, as in real scenes; the
    ground truth of each event is its own edge's normal flow. Deterministic for a seed.
    """
    rng = np.random.default_rng(seed)
    w, h = sensor_size
    xs, ys, ts, nxs, nys = [], [], [], [], []
    for _ in range(n_edges):
        angle = rng.uniform(-np.pi, np.pi)
        speed = float(np.exp(rng.uniform(np.log(speed_px_s[0]), np.log(speed_px_s[1]))))
        length = rng.uniform(*length_px)
        travel = speed * duration_us * 1e-6
        # Start behind the centre so that the edge sweeps its whole travel inside the slice.
        c = np.array([rng.uniform(0, w), rng.uniform(0, h)]) - 0.5 * travel * np.array([np.cos(angle), np.sin(angle)])
        x, y, t = edge_events(sensor_size, (c[0], c[1]), angle, speed, length, duration_us, events_per_crossing)
        xs.append(x)
        ys.append(y)
        ts.append(t)
        nxs.append(np.full(len(x), speed * np.cos(angle)))
        nys.append(np.full(len(x), speed * np.sin(angle)))
    x, y, t = np.concatenate(xs), np.concatenate(ys), np.concatenate(ts)
    order = np.argsort(t, kind="stable")
    ev = np.empty(len(x), EVENT_DTYPE)
    ev["x"], ev["y"], ev["t"] = x[order], y[order], t[order]
    ev["p"] = 1
    return EdgeScene(
        ev,
        np.concatenate(nxs)[order].astype(np.float32),
        np.concatenate(nys)[order].astype(np.float32),
        (int(w), int(h)),
    )
