"""Target event selection: which events of a slice get a normal flow.

The segmentation needs one flow per small neighbourhood, not one per event, so the default is
the latest event of each ``cell_px x cell_px`` cell of the slice (the event on the newest edge
position there). ``cell_px=None`` selects every event.
"""

from __future__ import annotations

import numpy as np

from evseg.checks import is_whole
from evseg.errors import EventDataError


def select_targets(
    events: np.ndarray,
    sensor_size: tuple[int, int],
    cell_px: int | None = 2,
    max_targets: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Positions of the target events of one slice, sorted ascending (int64 ``(T,)``).

    Args:
        events: :data:`~evseg.events.EVENT_DTYPE` ``(N,)`` sorted by ``t``.
        sensor_size: ``(width, height)`` px.
        cell_px: side of the square cells, px; the latest event of each non-empty cell is a
            target. ``None``: all events.
        max_targets: keep at most this many, a uniform random subset drawn with ``seed``
            (deterministic).
    """
    from evseg.events import checked_sensor_size, first_off_sensor, validate_events

    sensor_size = checked_sensor_size(sensor_size)
    validate_events(events, None, source="select_targets events", check_sorted=False)
    if max_targets is not None and (not is_whole(max_targets) or max_targets < 0):
        raise EventDataError(f"max_targets must be a non-negative integer or None, got {max_targets!r}")
    # Each coordinate on its own: with a swapped width and height the combined cell index can
    # stay in range while the cells are wrong.
    off = first_off_sensor(events, sensor_size)
    if off is not None:
        raise EventDataError(f"select_targets: {off} is outside the {sensor_size[0]}x{sensor_size[1]} sensor "
                             "(sensor_size is (width, height))")
    n = len(events)
    if cell_px is None:
        idx = np.arange(n, dtype=np.int64)
    else:
        if int(cell_px) != cell_px or cell_px < 1:
            raise EventDataError(f"cell_px must be a positive integer or None, got {cell_px!r}")
        from evseg.veckm_flow import _kernels

        c = int(cell_px)
        ncx = (int(sensor_size[0]) + c - 1) // c
        ncy = (int(sensor_size[1]) + c - 1) // c
        cell = (events["y"].astype(np.int64) // c) * ncx + events["x"].astype(np.int64) // c
        last = _kernels.latest_per_cell(cell, ncx * ncy)
        idx = np.sort(last[last >= 0])
    if max_targets is not None and len(idx) > max_targets:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(idx, size=int(max_targets), replace=False))
    return idx
