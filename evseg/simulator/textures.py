"""Procedural textures and object silhouettes, generated with numpy/OpenCV from a seed.

A texture is an intensity image in [0, 1] (float32, shape (H, W), row 0 = top), optionally with
an alpha image of the same shape (1 = opaque) for occluders such as a net. Families resemble the
structure of real scenes: multi-scale natural noise, blobs, straight edges (overlapping
polygons), lines, a net/grid, table-like wood grain, a street-like facade, a checkerboard, a
single straight step edge (for calibration and tests) and a uniform patch.

All randomness comes from the ``numpy.random.Generator`` passed in, so textures are
deterministic by seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from evseg.simulator.scene import TextureConfig


@dataclass(frozen=True)
class TextureParams:
    """One draw of a :class:`TextureConfig`: concrete values (px, degrees, intensity)."""

    family: str
    scale_px: float
    contrast: float
    mean: float
    angle_deg: float
    thickness_px: float
    density: float
    blur_px: float


def _uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    lo, hi = r
    return float(lo) if hi == lo else float(rng.uniform(lo, hi))


def sample_texture_params(cfg: TextureConfig, rng: np.random.Generator) -> TextureParams:
    """Draw concrete texture parameters from the ranges of ``cfg``."""
    family = cfg.family[int(rng.integers(len(cfg.family)))]
    return TextureParams(
        family=family,
        scale_px=max(1.0, _uniform(rng, cfg.scale_px)),
        contrast=_uniform(rng, cfg.contrast),
        mean=_uniform(rng, cfg.mean),
        angle_deg=_uniform(rng, cfg.angle_deg),
        thickness_px=max(0.5, _uniform(rng, cfg.thickness_px)),
        density=cfg.density,
        blur_px=cfg.blur_px,
    )


# ----------------------------------------------------------------------------- patterns in [0, 1]


def _normalise(img: np.ndarray) -> np.ndarray:
    """Stretch to [0, 1] by the 1st/99th percentiles (robust to a few extreme values)."""
    lo, hi = np.percentile(img, [1, 99])
    if hi - lo < 1e-9:
        return np.full(img.shape, 0.5, np.float32)
    return np.clip((img - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def value_noise(h: int, w: int, scale_px: float, rng: np.random.Generator, octaves: int = 5) -> np.ndarray:
    """Multi-scale value noise (1/f-like, "natural"): float32 (h, w) in [0, 1].

    Octave o has cells of ``scale_px / 2**o`` px and weight ``0.55**o``; octaves finer than
    1.5 px are skipped (they would alias).
    """
    acc = np.zeros((h, w), np.float32)
    amp = 1.0
    for o in range(octaves):
        cell = scale_px / 2**o
        if cell < 1.5:
            break
        gh, gw = int(np.ceil(h / cell)) + 2, int(np.ceil(w / cell)) + 2
        grid = rng.random((gh, gw)).astype(np.float32)
        up = cv2.resize(grid, (int(gw * cell), int(gh * cell)), interpolation=cv2.INTER_CUBIC)
        acc += amp * up[:h, :w]
        amp *= 0.55
    return _normalise(acc)


def _count(h: int, w: int, scale_px: float, density: float, cap: int = 20000) -> int:
    return int(min(cap, max(1, density * h * w / (scale_px**2))))


def _blobs(h, w, p: TextureParams, rng) -> np.ndarray:
    img = np.full((h, w), 0.5, np.float32)
    for _ in range(_count(h, w, 1.5 * p.scale_px, p.density)):
        c = (int(rng.uniform(0, w) * 16), int(rng.uniform(0, h) * 16))
        axes = (int(p.scale_px * rng.uniform(0.3, 1.0) * 16), int(p.scale_px * rng.uniform(0.3, 1.0) * 16))
        cv2.ellipse(img, c, axes, float(rng.uniform(0, 180)), 0, 360, float(rng.random()), -1, cv2.LINE_8, 4)
    return img


def _edges(h, w, p: TextureParams, rng) -> np.ndarray:
    """Overlapping random polygons: piecewise constant regions with straight edges."""
    img = np.full((h, w), float(rng.random()), np.float32)
    for _ in range(_count(h, w, 2.0 * p.scale_px, p.density)):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        n = int(rng.integers(3, 6))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = p.scale_px * rng.uniform(0.5, 1.6, n)
        pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], 1)
        cv2.fillPoly(img, [np.round(pts * 16).astype(np.int32)], float(rng.random()), cv2.LINE_8, 4)
    return img


def _lines(h, w, p: TextureParams, rng) -> tuple[np.ndarray, np.ndarray]:
    """Random line segments (mostly near ``angle_deg`` and its perpendicular); also the stroke mask."""
    img = np.full((h, w), 0.5, np.float32)
    mask = np.zeros((h, w), np.float32)
    length = 4 * p.scale_px
    for _ in range(_count(h, w, 1.5 * p.scale_px, p.density)):
        a = np.deg2rad(p.angle_deg + 90 * int(rng.integers(2)) + rng.normal(0, 10))
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        half = 0.5 * length * rng.uniform(0.5, 1.5)
        p0 = (cx - half * np.cos(a), cy - half * np.sin(a))
        p1 = (cx + half * np.cos(a), cy + half * np.sin(a))
        q0 = (int(p0[0] * 16), int(p0[1] * 16))
        q1 = (int(p1[0] * 16), int(p1[1] * 16))
        th = max(1, int(round(p.thickness_px * rng.uniform(0.7, 1.3))))
        v = float(rng.choice([0.05, 0.95]) if rng.random() < 0.7 else rng.random())
        cv2.line(img, q0, q1, v, th, cv2.LINE_8, 4)
        cv2.line(mask, q0, q1, 1.0, th, cv2.LINE_8, 4)
    return img, mask


def _grid(h, w, p: TextureParams, rng) -> tuple[np.ndarray, np.ndarray]:
    """A net: two families of parallel strands ``scale_px`` apart, ``thickness_px`` wide,
    rotated by ``angle_deg`` and slightly bent (a real net sags). Returns pattern and strand mask."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = np.deg2rad(p.angle_deg)
    u = np.cos(a) * xx + np.sin(a) * yy
    v = -np.sin(a) * xx + np.cos(a) * yy
    bend = 0.15 * p.scale_px * (value_noise(h, w, 8 * p.scale_px, rng, octaves=1) - 0.5) * 2
    u = u + bend
    v = v + bend[::-1, ::-1]
    period = p.scale_px
    du = np.abs(((u / period + rng.random()) % 1.0) - 0.5) * period  # distance to strand centre
    dv = np.abs(((v / period + rng.random()) % 1.0) - 0.5) * period
    half = 0.5 * p.thickness_px
    # Soft (0.5 px ramp) coverage keeps the strands anti-aliased without super-sampling.
    cov_u = np.clip(half + 0.5 - (0.5 * period - du), 0, 1)
    cov_v = np.clip(half + 0.5 - (0.5 * period - dv), 0, 1)
    mask = np.maximum(cov_u, cov_v).astype(np.float32)
    strand = 0.8 + 0.15 * value_noise(h, w, 4 * p.scale_px, rng, octaves=2)
    behind = 0.5 + 0.3 * (value_noise(h, w, 3 * p.scale_px, rng) - 0.5)
    img = (mask * strand + (1 - mask) * behind).astype(np.float32)
    return img, mask


def _wood(h, w, p: TextureParams, rng) -> np.ndarray:
    """Table-like wood grain: stretched, noise-distorted stripes along ``angle_deg`` plus
    board seams every ~10 stripes."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = np.deg2rad(p.angle_deg)
    across = -np.sin(a) * xx + np.cos(a) * yy
    warp = value_noise(h, w, 8 * p.scale_px, rng, octaves=3) * 2.0 * p.scale_px
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (across + warp) / p.scale_px)
    rings = rings**2.0  # narrow dark late-wood lines, broad light early wood
    fibre = value_noise(h, w, max(2.0, 0.25 * p.scale_px), rng, octaves=2)
    board = 10 * p.scale_px
    seam = (np.abs(((across / board) % 1.0) - 0.5) * board > 0.5 * board - 1.0).astype(np.float32)
    shade = value_noise(h, w, 2 * board, rng, octaves=1)
    img = 0.4 * rings + 0.2 * fibre + 0.4 * shade
    img = img * (1 - 0.8 * seam)
    return img.astype(np.float32)


def _street(h, w, p: TextureParams, rng) -> np.ndarray:
    """Street-like: facades (large axis-aligned rectangles) with window grids, poles and road
    markings over natural noise. Axis-aligned along ``angle_deg`` = 0 (vertical structures)."""
    img = 0.3 + 0.4 * value_noise(h, w, 4 * p.scale_px, rng)
    n_buildings = _count(h, w, 8 * p.scale_px, p.density, cap=400)
    for _ in range(n_buildings):
        bw, bh = p.scale_px * rng.uniform(3, 10), p.scale_px * rng.uniform(4, 14)
        x0, y0 = rng.uniform(-bw / 2, w), rng.uniform(-bh / 2, h)
        shade = float(rng.uniform(0.15, 0.9))
        cv2.rectangle(img, (int(x0), int(y0)), (int(x0 + bw), int(y0 + bh)), shade, -1)
        win = shade + (0.35 if shade < 0.5 else -0.35)
        step = p.scale_px * rng.uniform(0.8, 1.5)
        for wy in np.arange(y0 + step / 2, y0 + bh - step / 2, step):
            for wx in np.arange(x0 + step / 2, x0 + bw - step / 2, step):
                cv2.rectangle(img, (int(wx), int(wy)), (int(wx + 0.5 * step), int(wy + 0.6 * step)), win, -1)
    for _ in range(_count(h, w, 6 * p.scale_px, p.density, cap=400)):  # poles and markings
        x = int(rng.uniform(0, w))
        y0, y1 = int(rng.uniform(0, h)), int(rng.uniform(0, h))
        cv2.line(img, (x, y0), (x, y1), float(rng.choice([0.05, 0.95])), max(1, int(p.thickness_px)))
    return img.astype(np.float32)


def _checker(h, w, p: TextureParams, rng) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    a = np.deg2rad(p.angle_deg)
    u = (np.cos(a) * xx + np.sin(a) * yy) / p.scale_px
    v = (-np.sin(a) * xx + np.cos(a) * yy) / p.scale_px
    return ((np.floor(u) + np.floor(v)) % 2).astype(np.float32)


def _step(h, w, p: TextureParams) -> np.ndarray:
    """A single straight edge through the texture centre with normal at ``angle_deg``:
    pattern 1 (bright) on the side the normal points to, 0 (dark) on the other, with an exact
    half-pixel-wide linear ramp (area coverage of a pixel by the half plane, to first order)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    a = np.deg2rad(p.angle_deg)
    d = np.cos(a) * (xx - (w - 1) / 2) + np.sin(a) * (yy - (h - 1) / 2)
    return np.clip(d + 0.5, 0.0, 1.0).astype(np.float32)


def make_texture(h: int, w: int, p: TextureParams, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
    """Render a texture of shape (h, w).

    Returns:
        intensity: float32 (h, w) in [0.01, 1] (``mean + contrast * (pattern - 0.5)``, blurred
            by ``blur_px``).
        alpha: float32 (h, w) in [0, 1] stroke coverage for ``grid`` and ``lines`` (what an
            occluder uses), else None.
    """
    alpha = None
    fam = p.family
    if fam == "noise":
        pat = value_noise(h, w, p.scale_px, rng)
    elif fam == "blobs":
        pat = _blobs(h, w, p, rng)
    elif fam == "edges":
        pat = _edges(h, w, p, rng)
    elif fam == "lines":
        pat, alpha = _lines(h, w, p, rng)
    elif fam == "grid":
        pat, alpha = _grid(h, w, p, rng)
    elif fam == "wood":
        pat = _normalise(_wood(h, w, p, rng))
    elif fam == "street":
        pat = _street(h, w, p, rng)
    elif fam == "checker":
        pat = _checker(h, w, p, rng)
    elif fam == "step":
        pat = _step(h, w, p)
    elif fam == "uniform":
        pat = np.full((h, w), 0.5, np.float32)
    else:  # guarded by config validation
        raise ValueError(f"unknown texture family {fam!r}")
    img = p.mean + p.contrast * (pat - 0.5)
    if p.blur_px > 0 and fam != "step":  # the step carries its own exact ramp
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), p.blur_px)
        if alpha is not None:
            alpha = cv2.GaussianBlur(alpha, (0, 0), p.blur_px)
    img = np.clip(img, 0.01, 1.0).astype(np.float32)
    return img, (None if alpha is None else np.clip(alpha, 0, 1).astype(np.float32))


# ----------------------------------------------------------------------------- silhouettes


def shape_alpha(shape: str, long_px: float, aspect: float, rng: np.random.Generator, supersample: int = 4) -> np.ndarray:
    """Anti-aliased silhouette of an object, float32 (h, w) coverage in [0, 1].

    The shape's long extent is ``long_px`` (along x), its short extent ``aspect * long_px``; the
    canvas has a 2 px transparent margin. Coverage is the area share of each pixel, computed by
    drawing at ``supersample`` times the resolution and averaging (cv2.INTER_AREA).
    """
    a = max(2.0, long_px / 2)
    b = max(2.0, aspect * long_px / 2)
    if shape == "disc":
        b = a
    margin = 2
    w = int(np.ceil(2 * a)) + 2 * margin
    h = int(np.ceil(2 * (a if shape == "blob" else b))) + 2 * margin
    s = supersample
    canvas = np.zeros((h * s, w * s), np.uint8)
    cx, cy = w * s / 2, h * s / 2
    if shape in ("ellipse", "disc"):
        cv2.ellipse(canvas, (int(cx * 16), int(cy * 16)), (int(a * s * 16), int(b * s * 16)), 0, 0, 360, 255, -1, cv2.LINE_8, 4)
    elif shape == "rectangle":
        cv2.rectangle(canvas, (int(cx - a * s), int(cy - b * s)), (int(cx + a * s) - 1, int(cy + b * s) - 1), 255, -1)
    elif shape in ("blob", "polygon"):
        n = 64 if shape == "blob" else int(rng.integers(3, 8))
        ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
        if shape == "polygon":
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = rng.uniform(0.6, 1.0, n)
        else:  # smooth irregular outline: low-order Fourier series of the radius
            rad = np.ones(n)
            for k in range(2, 6):
                rad += rng.normal(0, 0.12 / k * 2) * np.cos(k * ang + rng.uniform(0, 2 * np.pi))
            rad = np.clip(rad, 0.45, 1.0) / max(1.0, rad.max())
        ry = a if shape == "blob" else b
        pts = np.stack([cx + a * s * rad * np.cos(ang), cy + ry * s * rad * np.sin(ang)], 1)
        cv2.fillPoly(canvas, [np.round(pts * 16).astype(np.int32)], 255, cv2.LINE_8, 4)
    else:
        raise ValueError(f"unknown shape {shape!r}")
    return cv2.resize(canvas.astype(np.float32) / 255.0, (w, h), interpolation=cv2.INTER_AREA)
