"""Synthetic normal flow with known motions, for tests and benchmarks (no simulator needed).

A scene is a background motion over the whole sensor plus K objects (discs) with their own
affine motions. Flow positions are uniform random pixels, each with a random unit gradient
g; its normal flow is n = (u . g) g with u the flow of the topmost region containing it.
Optionally a share of the flows is replaced by random outliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.segmentation.motion_model import normal_flow_of


@dataclass(frozen=True)
class SyntheticFlow:
    """Normal flow of a synthetic scene (N flows, K objects).

    Attributes:
        x, y: (N,) float64 positions, px. t: (N,) int64 microseconds. nx, ny: (N,) px/s.
        label: (N,) int64 true label: 0 background, k object, -1 outlier.
        models: (K+1, 4) true models about ``origin_px``. centers: (K, 2) px. radii: (K,) px.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    label: np.ndarray
    models: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    origin_px: tuple[float, float]
    sensor_size: tuple[int, int]


def random_models(rng: np.random.Generator, k: int, speed_px_s: float = 300.0) -> np.ndarray:
    """(k, 4) random models: translation ~ speed, small divergence/rotation rates (<= 0.5 /s)."""
    ang = rng.uniform(0, 2 * np.pi, k)
    spd = speed_px_s * rng.uniform(0.5, 1.5, k)
    rho = 1.0 + rng.uniform(-0.5, 0.5, k)
    theta = rng.uniform(-0.5, 0.5, k)
    return np.column_stack([rho, theta, spd * np.cos(ang), spd * np.sin(ang)])


def synthetic_scene(
    n_flows: int = 3000,
    n_objects: int = 2,
    sensor_size: tuple[int, int] = (346, 260),
    seed: int = 0,
    outlier_fraction: float = 0.0,
    window_us: int = 10_000,
    radius_px: tuple[float, float] = (25.0, 45.0),
    models: np.ndarray | None = None,
) -> SyntheticFlow:
    """Random scene; objects' motions differ clearly from the background (>= 150 px/s at centre).

    Args:
        n_flows: number of flows N. n_objects: K. seed: RNG seed (deterministic).
        outlier_fraction: share of flows replaced by uniform random vectors (label -1).
        models: optional (K+1, 4) models to use instead of random ones.
    """
    rng = np.random.default_rng(seed)
    w, h = sensor_size
    origin = ((w - 1) / 2.0, (h - 1) / 2.0)
    if models is None:
        bg = random_models(rng, 1, 150.0)
        objs = []
        while len(objs) < n_objects:
            cand = random_models(rng, 1, 400.0)[0]
            # Keep objects whose translation differs clearly from the background's and each other's.
            if all(np.hypot(*(cand[2:] - o[2:])) > 150.0 for o in [bg[0], *objs]):
                objs.append(cand)
        models = np.concatenate([bg, np.array(objs).reshape(-1, 4)])
    models = np.asarray(models, dtype=np.float64)
    k = len(models) - 1
    radii = rng.uniform(*radius_px, k)
    centers = np.column_stack([rng.uniform(radii + 5, w - radii - 5), rng.uniform(radii + 5, h - radii - 5)])
    x = rng.uniform(0, w - 1, n_flows)
    y = rng.uniform(0, h - 1, n_flows)
    label = np.zeros(n_flows, dtype=np.int64)
    for i in range(k):  # later objects are in front
        inside = np.hypot(x - centers[i, 0], y - centers[i, 1]) <= radii[i]
        label[inside] = i + 1
    ang = rng.uniform(0, 2 * np.pi, n_flows)
    gx, gy = np.cos(ang), np.sin(ang)
    nx, ny = normal_flow_of(models, label, x - origin[0], y - origin[1], gx, gy)
    n_out = int(round(outlier_fraction * n_flows))
    if n_out:
        out = rng.choice(n_flows, n_out, replace=False)
        scale = np.percentile(np.hypot(nx, ny), 90)
        nx[out] = rng.uniform(-scale, scale, n_out)
        ny[out] = rng.uniform(-scale, scale, n_out)
        label[out] = -1
    t = np.sort(rng.integers(0, window_us, n_flows)).astype(np.int64)
    return SyntheticFlow(x=x, y=y, t=t, nx=nx, ny=ny, label=label, models=models,
                         centers=centers, radii=radii, origin_px=origin, sensor_size=(w, h))
