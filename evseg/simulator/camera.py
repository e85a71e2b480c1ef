"""The event camera's pixels: log-intensity threshold crossings, mismatch, refractory period,
background-activity noise and hot pixels.

Each pixel keeps a reference level ``ref`` of log intensity. Between two rendered frames
(t0, L0) and (t1, L1) the log intensity is taken as linear in time, so a pixel with
``L1 - ref >= k C_pos`` crosses the levels ``ref + C_pos, ..., ref + k C_pos`` (k ON events) at
the times where the line L0 -> L1 reaches them (sub-step timestamp interpolation); OFF events
likewise with ``C_neg``. The reference then moves by ``k C``, which keeps
``-C_neg < L1 - ref < C_pos``: several crossings per step are allowed, none is lost to the step.

Refractory period: a crossing within ``refractory_us`` of the pixel's previous *emitted* event
is dropped, and the reference still moves past it (the pixel's reset switch is held closed
during the refractory time, so the change that happened then is lost, as in a real DVS).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.simulator.scene import SensorConfig


@dataclass(frozen=True)
class Crossings:
    """Events of one sub-step, not sorted by time.

    Attributes:
        pixel: int64 (N,) flat pixel index ``y * width + x``.
        t_us: float64 (N,) interpolated timestamps in microseconds.
        p: int8 (N,) polarity +1 / -1.
    """

    pixel: np.ndarray
    t_us: np.ndarray
    p: np.ndarray


class PixelArray:
    """State of all pixels of a DVS: reference levels, thresholds, last event times.

    The state is owned by this object and updated in place by :meth:`step` (callers' arrays are
    never modified). Thresholds are drawn once per recording: ``C ~ N(c, c_sigma)`` per pixel
    and polarity, clipped at 0.01 (fixed-pattern mismatch).
    """

    def __init__(self, sensor: SensorConfig, log0: np.ndarray, rng: np.random.Generator):
        n = sensor.width * sensor.height
        self.width = sensor.width
        self.c_pos = np.maximum(0.01, rng.normal(sensor.c_pos, sensor.c_sigma, n)).astype(np.float32)
        self.c_neg = np.maximum(0.01, rng.normal(sensor.c_neg, sensor.c_sigma, n)).astype(np.float32)
        log0 = np.asarray(log0, np.float32).ravel()
        if sensor.random_initial_level:
            # Random phase: L0 - ref uniform in (-C_neg, C_pos).
            u = rng.random(n).astype(np.float32)
            offset = u * (self.c_pos + self.c_neg) - self.c_neg
            self.ref = log0 - offset
            # float32 rounding can put L0 - ref on a threshold (1 pixel in ~10^5), and a pixel
            # whose intensity never changes would then fire at t = 0; pull those inside the band.
            d = log0 - self.ref
            edge = (d >= self.c_pos) | (d <= -self.c_neg)
            self.ref[edge] = log0[edge] - offset[edge] * np.float32(0.999)
        else:
            self.ref = log0.copy()
        self.last_t_us = np.full(n, -np.inf)
        self.refractory_us = float(sensor.refractory_us)

    def step(self, log0: np.ndarray, log1: np.ndarray, t0_us: float, t1_us: float) -> Crossings:
        """Events of all pixels between frames (t0_us, log0) and (t1_us, log1).

        Args:
            log0, log1: float32 (H, W) log intensity at t0_us and t1_us.
        """
        l0 = log0.ravel()
        l1 = log1.ravel()
        d = l1 - self.ref
        idx = np.flatnonzero((d >= self.c_pos) | (d <= -self.c_neg))
        if len(idx) == 0:
            return Crossings(np.empty(0, np.int64), np.empty(0), np.empty(0, np.int8))
        di = d[idx]
        on = di > 0
        c = np.where(on, self.c_pos[idx], self.c_neg[idx])
        sign = np.where(on, 1.0, -1.0).astype(np.float32)
        n = np.floor(np.abs(di) / c).astype(np.int64)
        # k-th crossing of each pixel (k = 1..n): repeat the pixel, count within its group.
        total = int(n.sum())
        grp = np.repeat(np.arange(len(idx)), n)
        k = np.arange(total) - np.repeat(np.cumsum(n) - n, n) + 1
        ref = self.ref[idx]
        level = ref[grp] + sign[grp] * k * c[grp]
        a, b = l0[idx][grp], l1[idx][grp]
        frac = np.clip((level - a) / (b - a), 0.0, 1.0)
        t = t0_us + frac.astype(np.float64) * (t1_us - t0_us)
        self.ref[idx] = ref + sign * n * c
        pix = idx[grp]
        # Refractory: crossings of one pixel are in time order along k, so go round by round.
        keep = np.ones(total, bool)
        if self.refractory_us > 0:
            for kk in range(1, int(n.max()) + 1):
                sel = np.flatnonzero(k == kk)
                ok = t[sel] - self.last_t_us[pix[sel]] >= self.refractory_us
                keep[sel] = ok
                self.last_t_us[pix[sel[ok]]] = t[sel[ok]]
        else:
            self.last_t_us[pix] = t
        return Crossings(pix[keep], t[keep], np.where(sign[grp][keep] > 0, 1, -1).astype(np.int8))


def noise_events(sensor: SensorConfig, duration_us: int, rng: np.random.Generator) -> Crossings:
    """Background-activity noise (Poisson, ``noise_rate_hz`` per pixel, random polarity) and hot
    pixels (a fixed ``hot_pixel_fraction`` of pixels, each a Poisson source of
    ``hot_pixel_rate_hz`` with one fixed polarity) over ``[0, duration_us)``."""
    n_pix = sensor.width * sensor.height
    dur_s = duration_us * 1e-6
    n_ba = int(rng.poisson(sensor.noise_rate_hz * n_pix * dur_s))
    pix = [rng.integers(0, n_pix, n_ba)]
    t = [rng.uniform(0, duration_us, n_ba)]
    p = [np.where(rng.random(n_ba) < 0.5, 1, -1).astype(np.int8)]
    n_hot = int(round(sensor.hot_pixel_fraction * n_pix))
    if n_hot:
        hot = rng.choice(n_pix, n_hot, replace=False)
        pol = np.where(rng.random(n_hot) < 0.5, 1, -1).astype(np.int8)
        counts = rng.poisson(sensor.hot_pixel_rate_hz * dur_s, n_hot)
        pix.append(np.repeat(hot, counts))
        t.append(rng.uniform(0, duration_us, int(counts.sum())))
        p.append(np.repeat(pol, counts))
    return Crossings(np.concatenate(pix).astype(np.int64), np.concatenate(t), np.concatenate(p))
