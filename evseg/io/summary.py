"""One streaming pass over a recording: counts, time range, polarity balance, extent."""

from __future__ import annotations

from dataclasses import dataclass

from evseg.io.recording import Recording


@dataclass(frozen=True)
class RecordingSummary:
    """What ``evseg info`` reports.

    Attributes:
        format: registry name of the format.
        sensor_size: ``(width, height)`` px, or ``None`` if unknown (no events, none declared).
        sensor_size_source: ``"file"``, ``"user"``, ``"inferred"`` (max + 1) or ``None``.
        n_events: number of events.
        n_on: events with polarity +1.
        t_first_us, t_last_us: first and last timestamp (us, relative to ``t_offset_us``);
            ``None`` without events.
        t_offset_us: absolute time of ``t == 0`` (us).
        x_range, y_range: ``(min, max)`` coordinates in px, ``None`` without events.
        has_calibration: the file carries usable intrinsics.
        calibration_problem: why the file's intrinsics are unusable, else ``None``.
        topic, message_type: for bags, the topic read and its message type; else ``None``.
    """

    format: str
    sensor_size: tuple[int, int] | None
    sensor_size_source: str | None
    n_events: int
    n_on: int
    t_first_us: int | None
    t_last_us: int | None
    t_offset_us: int
    x_range: tuple[int, int] | None
    y_range: tuple[int, int] | None
    has_calibration: bool
    topic: str | None = None
    message_type: str | None = None
    calibration_problem: str | None = None

    @property
    def duration_us(self) -> int:
        """Last minus first timestamp (us); 0 for fewer than two events."""
        if self.t_first_us is None or self.n_events < 2:
            return 0
        return self.t_last_us - self.t_first_us

    @property
    def rate_ev_s(self) -> float:
        """Mean event rate (events/s); 0 when the duration is 0."""
        return self.n_events / (self.duration_us * 1e-6) if self.duration_us > 0 else 0.0

    @property
    def on_fraction(self) -> float:
        """Fraction of ON (+1) events; 0 without events."""
        return self.n_on / self.n_events if self.n_events else 0.0


def summarize(rec: Recording) -> RecordingSummary:
    """Stream ``rec`` once (memory: one chunk) and summarise it."""
    n = n_on = 0
    t_first = t_last = None
    xmin = ymin = 1 << 30
    xmax = ymax = -1
    for ev in rec.chunks():
        n += len(ev)
        n_on += int((ev["p"] > 0).sum())
        if t_first is None:
            t_first = int(ev["t"][0])
        t_last = int(ev["t"][-1])
        xmin, xmax = min(xmin, int(ev["x"].min())), max(xmax, int(ev["x"].max()))
        ymin, ymax = min(ymin, int(ev["y"].min())), max(ymax, int(ev["y"].max()))
    return RecordingSummary(
        format=rec.format,
        sensor_size=rec.sensor_size,
        sensor_size_source=rec.sensor_size_source,
        n_events=n,
        n_on=n_on,
        t_first_us=t_first,
        t_last_us=t_last,
        t_offset_us=rec.t_offset_us,
        x_range=(xmin, xmax) if n else None,
        y_range=(ymin, ymax) if n else None,
        has_calibration=rec.calibration is not None,
        topic=rec.topic,
        message_type=rec.message_type,
        calibration_problem=rec.calibration_problem,
    )
