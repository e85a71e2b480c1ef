"""Augmentation of event slices together with their ground-truth flow.

Every transform acts on a :class:`FlowSlice` (events plus per-event normal flow and/or optical
flow, px/s) and returns a new one; the caller's arrays are never modified. Each transform maps
the flow exactly as it maps the image motion, so the ground truth stays correct:

=====================  ==========================================  ==========================
transform              events                                      flow vectors (px/s)
=====================  ==========================================  ==========================
rotation by ``a``      (x, y) rotated about the sensor centre,     rotated by ``a``
                       rounded to the pixel grid, off-sensor ones
                       dropped
flip                   x -> W-1-x and/or y -> H-1-y                x and/or y component negated
scale by ``s``         (x, y) scaled about the centre, rounded     multiplied by ``s``
time scaling by ``k``  t -> t0 + k (t - t0)                        divided by ``k``
event-rate subsample   a random subset kept                        same subset
extra noise            uniform random events added                 NaN for the added events
=====================  ==========================================  ==========================

Rotation, flips and scaling are linear maps of the image plane, and both optical flow ``u``
and normal flow ``n = (u . g) g`` transform like vectors under them (for a rotation or flip
the gradient direction ``g`` turns with the image; a uniform scale leaves it unchanged), so the
same matrix applies to both. Rows are image rows (y down); the rotation matrix is applied in
(x, y) pixel coordinates, so a positive angle turns clockwise on screen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.events import EVENT_DTYPE


@dataclass(frozen=True)
class FlowSlice:
    """A short slice of events with per-event ground truth.

    Attributes:
        events: (N,) :data:`~evseg.events.EVENT_DTYPE`, sorted by ``t`` (microseconds).
        sensor_size: ``(width, height)`` in px.
        normal_flow: (N, 2) float32 ground-truth normal flow, px/s (x = column, y = row), NaN
            where unknown (noise events); None when the source has no normal flow.
        optical_flow: (N, 2) float32 ground-truth optical flow, px/s, NaN where unknown; None
            when the source has none.
        label: (N,) int16 ground-truth motion label (the simulator's: 0 background, k >= 1
            object k, -1 noise); None when the source has none.
    """

    events: np.ndarray
    sensor_size: tuple[int, int]
    normal_flow: np.ndarray | None = None
    optical_flow: np.ndarray | None = None
    label: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.events)

    def take(self, idx: np.ndarray) -> "FlowSlice":
        """The events at ``idx`` (indices or boolean mask), flows alike (copies)."""
        return FlowSlice(
            self.events[idx],
            self.sensor_size,
            None if self.normal_flow is None else self.normal_flow[idx],
            None if self.optical_flow is None else self.optical_flow[idx],
            None if self.label is None else self.label[idx],
        )


def _map_flows(s: FlowSlice, matrix: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Apply a 2x2 linear map to both flow fields (rows are (fx, fy) vectors)."""
    m = np.asarray(matrix, dtype=np.float64)

    def f(v):
        return None if v is None else (v.astype(np.float64) @ m.T).astype(np.float32)

    return f(s.normal_flow), f(s.optical_flow)


def _affine_events(s: FlowSlice, matrix: np.ndarray) -> FlowSlice:
    """Map pixel positions by ``matrix`` about the sensor centre, round, drop off-sensor events.

    Flows are mapped by the same matrix. Rounding to the nearest pixel keeps events on the
    integer grid the encoder expects.
    """
    w, h = s.sensor_size
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    x = s.events["x"].astype(np.float64) - cx
    y = s.events["y"].astype(np.float64) - cy
    xn = np.rint(matrix[0, 0] * x + matrix[0, 1] * y + cx)
    yn = np.rint(matrix[1, 0] * x + matrix[1, 1] * y + cy)
    keep = (xn >= 0) & (xn <= w - 1) & (yn >= 0) & (yn <= h - 1)
    nf, of = _map_flows(s, matrix)
    ev = s.events[keep].copy()
    ev["x"] = xn[keep].astype(np.uint16)
    ev["y"] = yn[keep].astype(np.uint16)
    return FlowSlice(
        ev,
        s.sensor_size,
        None if nf is None else nf[keep],
        None if of is None else of[keep],
        None if s.label is None else s.label[keep],
    )


def rotate_slice(s: FlowSlice, angle_rad: float) -> FlowSlice:
    """Rotate events about the sensor centre by ``angle_rad`` (flow rotated alike).

    Events that leave the sensor are dropped; positions are rounded to whole pixels.
    """
    c, sn = np.cos(angle_rad), np.sin(angle_rad)
    return _affine_events(s, np.array([[c, -sn], [sn, c]]))


def scale_slice(s: FlowSlice, factor: float) -> FlowSlice:
    """Scale positions about the sensor centre by ``factor`` (flow multiplied by it too)."""
    if factor <= 0:
        raise ValueError(f"scale factor must be positive, got {factor}")
    return _affine_events(s, np.array([[factor, 0.0], [0.0, factor]]))


def flip_slice(s: FlowSlice, horizontal: bool, vertical: bool) -> FlowSlice:
    """Mirror columns (``horizontal``) and/or rows (``vertical``); exact, no event lost."""
    w, h = s.sensor_size
    ev = s.events.copy()
    if horizontal:
        ev["x"] = (w - 1) - ev["x"]
    if vertical:
        ev["y"] = (h - 1) - ev["y"]
    nf, of = _map_flows(s, np.diag([-1.0 if horizontal else 1.0, -1.0 if vertical else 1.0]))
    return FlowSlice(ev, s.sensor_size, nf, of, s.label)


def time_scale_slice(s: FlowSlice, factor: float) -> FlowSlice:
    """Stretch time by ``factor`` about the first event: the scene moves ``factor`` times slower.

    Timestamps become ``t0 + round(factor * (t - t0))`` (us) and flows are divided by
    ``factor``.
    """
    if factor <= 0:
        raise ValueError(f"time scale factor must be positive, got {factor}")
    ev = s.events.copy()
    if len(ev):
        t0 = ev["t"][0]
        ev["t"] = t0 + np.rint((ev["t"] - t0) * float(factor)).astype(np.int64)
    nf, of = _map_flows(s, np.eye(2) / factor)
    return FlowSlice(ev, s.sensor_size, nf, of, s.label)


def subsample_slice(s: FlowSlice, keep_fraction: float, rng: np.random.Generator) -> FlowSlice:
    """Keep each event independently with probability ``keep_fraction`` (lower event rate)."""
    if not 0 < keep_fraction <= 1:
        raise ValueError(f"keep_fraction must be in (0, 1], got {keep_fraction}")
    return s.take(rng.random(len(s)) < keep_fraction)


def add_noise_events(s: FlowSlice, rate_ev_px_s: float, rng: np.random.Generator) -> FlowSlice:
    """Add uniform background-activity noise at ``rate_ev_px_s`` events per pixel per second.

    Noise events are spread uniformly over the sensor and the slice's time span, with random
    polarity; their flows are NaN (they are never training targets, only neighbours) and their
    label -1.
    """
    if len(s) == 0 or rate_ev_px_s <= 0:
        return s
    w, h = s.sensor_size
    t0, t1 = int(s.events["t"][0]), int(s.events["t"][-1])
    n = int(rng.poisson(rate_ev_px_s * w * h * max(t1 - t0, 1) * 1e-6))
    if n == 0:
        return s
    noise = np.empty(n, dtype=EVENT_DTYPE)
    noise["x"] = rng.integers(0, w, n)
    noise["y"] = rng.integers(0, h, n)
    noise["t"] = rng.integers(t0, t1 + 1, n)
    noise["p"] = rng.choice(np.array([-1, 1], dtype=np.int8), n)
    ev = np.concatenate([s.events, noise])
    order = np.argsort(ev["t"], kind="stable")
    nan = np.full((n, 2), np.nan, dtype=np.float32)

    def f(v):
        return None if v is None else np.concatenate([v, nan])[order]

    label = None if s.label is None else np.concatenate([s.label, np.full(n, -1, s.label.dtype)])[order]
    return FlowSlice(ev[order], s.sensor_size, f(s.normal_flow), f(s.optical_flow), label)


@dataclass(frozen=True)
class AugmentConfig:
    """Random augmentation drawn per slice (all ranges inclusive, uniform unless stated).

    Attributes:
        rotation: rotate by a random angle (the head must be rotation equivariant in practice;
            VecKM_flow trains with the same augmentation).
        rotation_step_deg: 0 draws the angle uniformly in [0, 360) deg; a step such as 90
            draws a multiple of it. Right angles (with ``flip``, the 8 symmetries of the pixel
            grid) move events exactly; other angles round positions to the grid, which merges
            and skips pixels: a resampling pattern real sensors never show, which a network
            can pick up (the same holds for ``scale_range`` away from 1).
        flip: mirror columns and rows, each with probability 1/2.
        scale_range: spatial scale factor (log-uniform).
        time_scale_range: time stretch factor (log-uniform); flow divides by it.
        keep_range: fraction of events kept (event-rate subsampling).
        noise_rate_range: added noise, events per pixel per second.
    """

    rotation: bool = True
    rotation_step_deg: float = 0.0
    flip: bool = True
    scale_range: tuple[float, float] = (0.8, 1.25)
    time_scale_range: tuple[float, float] = (0.5, 2.0)
    keep_range: tuple[float, float] = (0.5, 1.0)
    noise_rate_range: tuple[float, float] = (0.0, 2.0)


NO_AUGMENTATION = AugmentConfig(
    rotation=False,
    flip=False,
    scale_range=(1.0, 1.0),
    time_scale_range=(1.0, 1.0),
    keep_range=(1.0, 1.0),
    noise_rate_range=(0.0, 0.0),
)
"""Identity augmentation (validation, evaluation)."""


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    if lo == hi:
        return float(lo)
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


@dataclass(frozen=True)
class AugmentDraw:
    """One concrete draw of :class:`AugmentConfig`: the parameters applied to one slice.

    Drawn before the slice is cut, because the time scale decides how long a stretch of the
    recording to cut (``slice_us / time_scale``) so that every augmented slice spans the
    same duration.
    """

    keep_fraction: float = 1.0
    time_scale: float = 1.0
    scale: float = 1.0
    angle_rad: float = 0.0
    flip_horizontal: bool = False
    flip_vertical: bool = False
    noise_rate_ev_px_s: float = 0.0


def _draw_angle(cfg: AugmentConfig, rng: np.random.Generator) -> float:
    if not cfg.rotation:
        return 0.0
    if cfg.rotation_step_deg > 0:
        steps = max(1, int(round(360.0 / cfg.rotation_step_deg)))
        return float(np.radians(int(rng.integers(steps)) * 360.0 / steps))
    return float(rng.uniform(0.0, 2 * np.pi))


def draw_augmentation(cfg: AugmentConfig, rng: np.random.Generator) -> AugmentDraw:
    """Draw the parameters of one augmentation from ``cfg``."""
    return AugmentDraw(
        keep_fraction=float(rng.uniform(*cfg.keep_range)),
        time_scale=_log_uniform(rng, *cfg.time_scale_range),
        scale=_log_uniform(rng, *cfg.scale_range),
        angle_rad=_draw_angle(cfg, rng),
        flip_horizontal=bool(rng.integers(2)) if cfg.flip else False,
        flip_vertical=bool(rng.integers(2)) if cfg.flip else False,
        noise_rate_ev_px_s=float(rng.uniform(*cfg.noise_rate_range)),
    )


def apply_augmentation(s: FlowSlice, d: AugmentDraw, rng: np.random.Generator) -> FlowSlice:
    """Apply ``d`` to ``s`` (a new slice; input untouched); ``rng`` drives subsampling and noise.

    The order is rate subsampling, time scaling, scale, rotation, flips, then noise, so that
    noise is uniform in the final image.
    """
    if d.keep_fraction < 1.0:
        s = subsample_slice(s, d.keep_fraction, rng)
    if d.time_scale != 1.0:
        s = time_scale_slice(s, d.time_scale)
    if d.scale != 1.0:
        s = scale_slice(s, d.scale)
    if d.angle_rad != 0.0:
        s = rotate_slice(s, d.angle_rad)
    if d.flip_horizontal or d.flip_vertical:
        s = flip_slice(s, d.flip_horizontal, d.flip_vertical)
    if d.noise_rate_ev_px_s > 0:
        s = add_noise_events(s, d.noise_rate_ev_px_s, rng)
    return s


def augment_slice(s: FlowSlice, cfg: AugmentConfig, rng: np.random.Generator) -> FlowSlice:
    """Draw one augmentation from ``cfg`` and apply it (a new slice; input untouched)."""
    return apply_augmentation(s, draw_augmentation(cfg, rng), rng)
