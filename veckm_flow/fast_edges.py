"""Fast edges: a second, time-stretched look at the targets whose flow is fast.

The encoder's time phases ``exp(i a_t dt / t_scale_us)`` resolve about ``t_scale_us / alpha``;
an edge that crosses the 7x7 px window in a millisecond or two leaves almost no timing
difference between its events, and the head regresses its speed towards the common, slower
speeds it was trained on. On the EED-like ball (simulated, validation seeds 900-903) the
flows come out at 0.50x their true normal speed.

Stretching time by ``s`` (an encoding with ``t_scale_us / s``: the events look ``s`` times
slower) puts such an edge back into the speeds the head resolves; the head output, converted
with the stretched encoding's unit, is again in px/s. The stretched look keeps only the last
``span / s`` of the slice, so that the slice the head sees spans as long as those it was
trained on (its time-stretch augmentation covers such slices), but at least ``min_keep_us``
of it (the whole of a shorter slice): a slice of 10 ms, where a recording starts without
context, keeps all of it and looks 20 ms long, the shortest slice the head was trained on,
rather than 5 ms that look 10. On the ball it gives 0.72x the
true speed and a median angular error of 8.2 deg instead of 10.1; on slow edges it is worse
(their few events spread over less time), which is why it is used only where the first look
already sees fast flow:

1. ``gate_weights``: 0 below ``speed_from``, 1 from ``speed_full``, linear in between, on each
   target's first-look speed (model units, see :class:`FastEdges`).
2. ``combine``: where the gate is open, the two looks are averaged with weights
   ``1 / uncertainty^2`` (the head's predicted angular error): on a fast ball the stretched look
   is the more certain one (0.40 against 0.56 rad), on the slower background edges the first
   look is (0.18 against 0.65 rad).

The rule and its constants were chosen on learned-flow validation scenes (seeds 900-919, never
the held-out seeds): see docs/normal_flow.md for the figures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.errors import ConfigError


@dataclass(frozen=True)
class FastEdges:
    """Settings of the time-stretched second look (module docstring).

    Attributes:
        stretch: time stretch ``s`` of the second look (> 1): the encoding's ``t_scale_us / s``,
            on the last ``1 / s`` of the slice's time span.
        min_keep_us: the stretched look keeps at least this much of the slice's end (us; the
            whole slice when it is shorter): the shortest training slice (20 ms) over the
            stretch.
        speed_from, speed_full: gate on the target's first-look speed, in the model's flow
            units (``xy_scale_px`` per ``t_scale_us``: 300 px/s for the shipped model, so 150
            and 220 px/s): no second look below ``speed_from``, full weight from
            ``speed_full``.
    """

    stretch: float = 2.0
    speed_from: float = 0.5
    speed_full: float = 11.0 / 15.0
    min_keep_us: float = 10_000.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.stretch) or self.stretch <= 1.0:
            raise ConfigError(f"FastEdges.stretch must be a number > 1, got {self.stretch!r}")
        if not (np.isfinite(self.speed_from) and np.isfinite(self.speed_full) and 0 <= self.speed_from < self.speed_full):
            raise ConfigError(f"FastEdges: need 0 <= speed_from < speed_full, got {self.speed_from!r} and {self.speed_full!r}")
        if not (np.isfinite(self.min_keep_us) and self.min_keep_us >= 0):
            raise ConfigError(f"FastEdges.min_keep_us must be a number >= 0 (us), got {self.min_keep_us!r}")


def gate_weights(speed: np.ndarray, speed_from: float, speed_full: float) -> np.ndarray:
    """0 below ``speed_from``, 1 from ``speed_full``, linear in between.

    >>> gate_weights(np.array([0.2, 0.5, 0.75, 1.0]), 0.5, 1.0).tolist()
    [0.0, 0.0, 0.5, 1.0]
    """
    return np.clip((np.asarray(speed, dtype=np.float64) - speed_from) / (speed_full - speed_from), 0.0, 1.0)


def combine(
    first: tuple[np.ndarray, np.ndarray, np.ndarray],
    second: tuple[np.ndarray, np.ndarray, np.ndarray],
    weight: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(nx, ny, uncertainty)`` of two looks at the same targets: their ``1 / u^2``-weighted
    mean, mixed into the first look with ``weight`` (the gate). Uncertainties in rad (floored
    at 1e-3 for the weights), flows in any common unit.

    Example (equal uncertainty: the plain mean at full weight):
        >>> one = (np.array([1.0]), np.array([0.0]), np.array([0.25]))
        >>> two = (np.array([3.0]), np.array([0.0]), np.array([0.25]))
        >>> [a.tolist() for a in combine(one, two, np.array([1.0]))]
        [[2.0], [0.0], [0.25]]
    """
    (x1, y1, u1), (x2, y2, u2) = first, second
    a1 = 1.0 / np.maximum(np.asarray(u1, dtype=np.float64), 1e-3) ** 2
    a2 = 1.0 / np.maximum(np.asarray(u2, dtype=np.float64), 1e-3) ** 2
    s = a1 + a2
    bx, by, bu = (a1 * x1 + a2 * x2) / s, (a1 * y1 + a2 * y2) / s, (a1 * u1 + a2 * u2) / s
    w = np.asarray(weight, dtype=np.float64)
    out = ((1 - w) * x1 + w * bx, (1 - w) * y1 + w * by, (1 - w) * u1 + w * bu)
    return tuple(a.astype(np.float32) for a in out)


def stretched_start(t: np.ndarray, stretch: float, min_keep_us: float = 0.0) -> int:
    """Index of the first event of the last ``max(span / stretch, min_keep_us)`` of a sorted
    slice (``t`` in us), the part the stretched look keeps.

    >>> stretched_start(np.array([0, 10, 20, 30]), 2.0)  # keeps t >= 15
    2
    >>> stretched_start(np.array([0, 10, 20, 30]), 2.0, min_keep_us=25)  # keeps t >= 5
    1
    """
    if len(t) == 0:
        return 0
    t_last = int(t[-1])
    keep = max((t_last - int(t[0])) / stretch, float(min_keep_us))
    return int(np.searchsorted(t, t_last - keep, side="left"))
