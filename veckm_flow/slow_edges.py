"""Slow edges: a second, time-compressed look over a longer slice at the targets whose flow is slow.

An edge that moves less than a pixel in the ~30 ms the first look sees (the pipeline's 10 ms
window plus 20 ms of context) leaves little trace of its direction of travel: on the held-out
simulated scenes the sign of the normal flow is right for 67 % of the targets under 0.25 px per
10 ms and 79 % at 0.25-0.5 px, against 97-98 % from 1 px up (``weights/MODEL.md``).

The remedy is more time. The slow look encodes ``compress`` times the first look's slice
(``history``: the events before the slice) with ``t_scale_us * compress``: in the encoding's
units the longer slice spans as long as the training slices and the edge moves ``compress``
times as far (the time-stretch augmentation of training covers such slices). The head output,
converted with that encoding's unit, is again in px/s. On learned-flow validation scenes (seeds
900-903, all presets, targets the latest event per 2 px cell) the slow look alone, ``compress``
2, turns a median angular error of 27.5 deg into 14.3 deg on the targets whose first-look flow
is under 25 px/s and 22.4 into 16.3 deg at 25-50 px/s; above 100 px/s it is worse (8.9 against
7.4 deg at 100-200 px/s; a fast edge crosses the window within the slice either way and the
longer slice adds events of where it was long ago), which is why it is gated:

1. ``gate``: full weight below ``speed_full`` (100 px/s for the shipped model), none from
   ``speed_to`` (200 px/s), linear in between, on each target's first-look speed.
2. :func:`combine_directions`: the directions of the two looks averaged with weights
   ``1 / uncertainty^2`` (each look's predicted angular error), mixed into the first look's
   direction with the gate's weight; the speed stays the first look's (the slow look's runs
   lower). Averaging the flow vectors instead gave the same flow accuracy, but the
   segmentation split zooming backgrounds into bands where the gate fades
   (docs/normal_flow.md).
3. The uncertainty (``SlowEdges.uncertainty``): ``"combined"``, the ``1 / u^2``-weighted mean of
   the two looks' (as :func:`~evseg.veckm_flow.fast_edges.combine`), ranks the errors best
   (validation: dropping the 20 % most uncertain lowers the median error by 23 % against 20 %
   with the first look's); ``"first"`` keeps the first look's, to which the segmentation's
   residual scales are tuned (the pipeline's ``slow_edges`` uses it: with the combined one it
   reported more false objects on validation).

It costs a second encoding of the gated targets over twice the events: 1.5-2.4x the flow time on
slow scenes (docs/normal_flow.md). The rule and its constants were chosen on validation
scenes (seeds 900-903), never on the held-out seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.errors import ConfigError


@dataclass(frozen=True)
class SlowEdges:
    """Settings of the time-compressed second look (module docstring).

    Attributes:
        compress: time compression ``c`` of the slow look (> 1): the encoding's
            ``t_scale_us * c`` over the last ``c`` times the first look's time span.
        speed_full, speed_to: gate on the target's first-look speed, in the model's flow units
            (``xy_scale_px`` per ``t_scale_us``: 300 px/s for the shipped model, so 100 and
            200 px/s): full weight below ``speed_full``, none from ``speed_to``.
        uncertainty: ``"combined"`` (the looks' weighted mean) or ``"first"`` (the first
            look's; what the segmentation presets are tuned to), see the module docstring.
    """

    compress: float = 2.0
    speed_full: float = 1.0 / 3.0
    speed_to: float = 2.0 / 3.0
    uncertainty: str = "combined"

    def __post_init__(self) -> None:
        if not np.isfinite(self.compress) or self.compress <= 1.0:
            raise ConfigError(f"SlowEdges.compress must be a number > 1, got {self.compress!r}")
        if not (np.isfinite(self.speed_full) and np.isfinite(self.speed_to) and 0 <= self.speed_full < self.speed_to):
            raise ConfigError(f"SlowEdges: need 0 <= speed_full < speed_to, got {self.speed_full!r} and {self.speed_to!r}")
        if self.uncertainty not in ("combined", "first"):
            raise ConfigError(f"SlowEdges.uncertainty must be 'combined' or 'first', got {self.uncertainty!r}")

    def history_us(self, slice_span_us: int) -> int:
        """How much time (us) before a slice of ``slice_span_us`` the slow look needs.

        >>> SlowEdges().history_us(30_000)
        30000
        """
        return int(np.ceil((self.compress - 1.0) * int(slice_span_us)))


def gate(speed: np.ndarray, speed_full: float, speed_to: float) -> np.ndarray:
    """1 below ``speed_full``, 0 from ``speed_to``, linear in between.

    >>> gate(np.array([0.2, 0.5, 0.75, 1.0]), 0.5, 1.0).tolist()
    [1.0, 1.0, 0.5, 0.0]
    """
    return np.clip((speed_to - np.asarray(speed, dtype=np.float64)) / (speed_to - speed_full), 0.0, 1.0)


def compressed_start(t_history: np.ndarray, t_slice: np.ndarray, compress: float) -> int:
    """Index into ``t_history`` (us, sorted, before the slice) of the first event of the slow
    look's slice: the last ``compress`` times the slice's span ``t_slice[-1] - t_slice[0]``.

    >>> compressed_start(np.array([0, 10, 20]), np.array([30, 40, 50]), 2.0)  # keeps t >= 10
    1
    """
    if len(t_slice) == 0 or len(t_history) == 0:
        return len(t_history)
    t_last = int(t_slice[-1])
    t_from = t_last - compress * (t_last - int(t_slice[0]))
    return int(np.searchsorted(t_history, t_from, side="left"))


def combine_directions(
    first: tuple[np.ndarray, np.ndarray, np.ndarray],
    second: tuple[np.ndarray, np.ndarray, np.ndarray],
    weight: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """``(nx, ny)`` of two looks ``(nx, ny, uncertainty)`` at the same targets: the direction of
    the ``1 / u^2``-weighted mean of their unit vectors, mixed in with ``weight``, at the first
    look's speed.

    The slow look's speeds run lower than the first look's (on validation 0.64 against 0.72 of
    the true normal speed at 50-100 px/s): mixing them in bent the speed profile of a zooming
    background where the gate fades, and the segmentation split it into bands, so only the
    direction is taken.

    Example (equal uncertainty, full weight: the bisector at the first look's speed):
        >>> one = (np.array([2.0]), np.array([0.0]), np.array([0.25]))
        >>> two = (np.array([0.0]), np.array([5.0]), np.array([0.25]))
        >>> [[round(float(v), 4) for v in a] for a in combine_directions(one, two, np.array([1.0]))]
        [[1.4142], [1.4142]]
    """
    from evseg.veckm_flow.fast_edges import combine

    (x1, y1, u1), (x2, y2, u2) = first, second
    s1 = np.hypot(np.asarray(x1, np.float64), np.asarray(y1, np.float64))
    s2 = np.hypot(np.asarray(x2, np.float64), np.asarray(y2, np.float64))
    e1 = (x1 / np.maximum(s1, 1e-12), y1 / np.maximum(s1, 1e-12), u1)
    e2 = (x2 / np.maximum(s2, 1e-12), y2 / np.maximum(s2, 1e-12), u2)
    ex, ey, _ = combine(e1, e2, weight)
    norm = np.maximum(np.hypot(ex.astype(np.float64), ey.astype(np.float64)), 1e-12)
    return (ex / norm * s1).astype(np.float32), (ey / norm * s1).astype(np.float32)
