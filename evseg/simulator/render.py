"""One draw of a scene (layers with textures and trajectories) and its rendering at a time t.

:func:`sample_scene` turns a :class:`~evseg.simulator.scene.SceneConfig`, a seed and a duration
into a :class:`SceneInstance`: concrete textures, silhouettes and closed-form affine
trajectories, all derived from the seed only (so a saved recording can re-render its masks).

Layers are kept in **depth order, back to front**: index 0 is the background, indices 1..K the
independently moving objects (object id = layer index, so a larger id is nearer the camera), then
the foreground occluders. :func:`render_frame` composites them ("over" operator on linear
intensity) with bilinear warping (OpenCV; sub-pixel positions are resolved to 1/32 px) and keeps
each layer's share of the composite, from which :func:`event_layers` tells which layer's motion
caused an event (what ground-truth labels and flow are read from); it also returns, per pixel,
the frontmost layer that covers at least ``label_coverage`` of it (the label where no layer moved).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from evseg.simulator.motion import AffineTrajectory, sample_trajectory
from evseg.simulator.scene import SceneConfig
from evseg.simulator.textures import TextureParams, make_texture, sample_texture_params, shape_alpha

MAX_TEXTURE_PX = 4096
"""Largest side of a background-role texture; beyond it the texture is mirrored (no seam)."""


def child_rng(seed: int, tag: str) -> np.random.Generator:
    """Independent generator per component, so that changing one part of a scene (say the
    number of objects) does not reshuffle the others for the same seed."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(tag.encode())]))


@dataclass(frozen=True)
class Layer:
    """One textured layer.

    Attributes:
        kind: ``"background"``, ``"object"`` or ``"foreground"``.
        label: ground-truth label of its events: 0 for background and foreground, the object
            id (>= 1) for objects.
        texture: float32 (h, w) linear intensity in [0, 1].
        alpha: float32 (h, w) coverage in [0, 1], or None for an opaque layer.
        origin: layer coordinates (px) of texture pixel (0, 0).
        trajectory: closed-form motion of the layer.
        shape: silhouette name for objects (for humans), else the texture family.
    """

    kind: str
    label: int
    texture: np.ndarray = field(repr=False)
    alpha: np.ndarray | None = field(repr=False)
    origin: tuple[float, float]
    trajectory: AffineTrajectory
    shape: str = ""

    @property
    def border(self) -> int:
        # Background-role layers must fill the frame: mirror beyond the texture (continuous
        # intensity, so no spurious edge); objects are transparent outside their sprite.
        return cv2.BORDER_REFLECT_101 if self.kind != "object" else cv2.BORDER_CONSTANT


@dataclass(frozen=True)
class SceneInstance:
    """A concrete scene: layers in depth order (back to front) and global lighting.

    Attributes:
        width, height: sensor size (px).
        layers: background, objects (ids 1..K), foreground occluders.
        gain: global intensity multiplier; flicker_amplitude / flicker_hz modulate it in time.
        label_coverage, mask_coverage: see :class:`~evseg.simulator.scene.SceneConfig`.
    """

    width: int
    height: int
    layers: tuple[Layer, ...]
    gain: float
    flicker_amplitude: float
    flicker_hz: float
    label_coverage: float
    mask_coverage: float

    @property
    def object_ids(self) -> list[int]:
        return [ly.label for ly in self.layers if ly.kind == "object"]

    @property
    def object_layers(self) -> list[Layer]:
        return [ly for ly in self.layers if ly.kind == "object"]

    def gain_at(self, t_s: float) -> float:
        return self.gain * (1.0 + self.flicker_amplitude * np.sin(2 * np.pi * self.flicker_hz * t_s))

    def max_speed_px_s(self, duration_s: float, n_samples: int = 257) -> float:
        """Largest image speed (px/s) of any visible layer point over the recording, sampled at
        ``n_samples`` times (the rates are smooth sinusoids of at most a few Hz)."""
        t = np.linspace(0.0, duration_s, n_samples)
        frame = np.array([[0, 0], [self.width - 1, 0], [0, self.height - 1], [self.width - 1, self.height - 1]], float)
        vmax = 0.0
        for ly in self.layers:
            if ly.kind == "object":
                h, w = ly.texture.shape
                local = np.array([[0, 0], [w - 1, 0], [0, h - 1], [w - 1, h - 1]], float) + ly.origin
                # The flow is affine, so the extremes over the sprite lie at its corners.
                pts = np.stack([ly.trajectory.center(tt) + local @ ly.trajectory.linear(tt).T for tt in t[:: max(1, n_samples // 32)]])
                pts = pts.reshape(-1, 2)
                lo, hi = pts.min(0), pts.max(0)
                corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [lo[0], hi[1]], [hi[0], hi[1]]])
                corners = np.clip(corners, [0, 0], [self.width - 1, self.height - 1])
                vmax = max(vmax, ly.trajectory.max_speed(corners, t))
            else:
                vmax = max(vmax, ly.trajectory.max_speed(frame, t))
        return vmax


def _texture_extent(traj: AffineTrajectory, width: int, height: int, duration_s: float, margin: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (min, max) in layer coordinates of everything the frame sees over time."""
    frame = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], float)
    pts = np.concatenate([traj.image_to_layer(frame, t) for t in np.linspace(0, duration_s, 65)])
    return pts.min(0) - margin, pts.max(0) + margin


def _background_role_layer(kind, tex_cfg, traj, width, height, duration_s, rng) -> Layer:
    lo, hi = _texture_extent(traj, width, height, duration_s)
    size = np.minimum(np.ceil(hi - lo).astype(int) + 1, MAX_TEXTURE_PX)
    # When capped, centre the texture on the frame at t = 0; mirroring covers the rest.
    origin = lo if np.all(np.ceil(hi - lo) + 1 <= MAX_TEXTURE_PX) else -(size - 1) / 2.0
    params = sample_texture_params(tex_cfg, rng)
    tex, alpha = make_texture(int(size[1]), int(size[0]), params, rng)
    if kind == "background":
        alpha = None
    elif alpha is None:  # an occluder needs strokes; a family without them occludes fully
        alpha = np.ones_like(tex)
    return Layer(kind, 0, tex, alpha, (float(origin[0]), float(origin[1])), traj, params.family)


def _contrasting_mean(params: TextureParams, mean_range: tuple[float, float], bg_mean: float,
                      min_log_contrast: float, rng: np.random.Generator) -> TextureParams:
    """Redraw the texture's mean intensity until it differs from ``bg_mean`` by at least
    ``min_log_contrast`` in log intensity (20 tries; else the farthest draw)."""
    def dist(m: float) -> float:
        return abs(np.log((m + 0.02) / (bg_mean + 0.02)))

    best = params.mean
    for _ in range(20):
        if dist(best) >= min_log_contrast:
            break
        m = float(rng.uniform(*mean_range))
        if dist(m) > dist(best):
            best = m
    return replace(params, mean=best)


def sample_scene(cfg: SceneConfig, seed: int, duration_us: int) -> SceneInstance:
    """Draw a concrete scene from ``cfg`` (deterministic in ``seed`` and ``duration_us``)."""
    width, height = cfg.sensor.width, cfg.sensor.height
    duration_s = duration_us * 1e-6
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)

    rng = child_rng(seed, "background")
    bg_traj = sample_trajectory(cfg.background.motion, rng, c0=centre)
    layers: list[Layer] = [_background_role_layer("background", cfg.background.texture, bg_traj, width, height, duration_s, rng)]

    bg_mean = float(layers[0].texture.mean())
    objects: list[Layer] = []
    for j, ocfg in enumerate(cfg.objects):
        rng = child_rng(seed, f"objects/{j}")
        n = int(rng.integers(ocfg.count[0], ocfg.count[1] + 1))
        for i in range(n):
            r = child_rng(seed, f"objects/{j}/{i}")
            shape = ocfg.shape[int(r.integers(len(ocfg.shape)))]
            long_px = float(r.uniform(*ocfg.size_px))
            aspect = float(r.uniform(*ocfg.aspect))
            alpha = shape_alpha(shape, long_px, aspect, r)
            h, w = alpha.shape
            params = sample_texture_params(ocfg.texture, r)
            params = _contrasting_mean(params, ocfg.texture.mean, bg_mean, ocfg.min_log_contrast, r)
            tex, _ = make_texture(h, w, params, r)
            traj = sample_trajectory(ocfg.motion, r, theta0=float(r.uniform(0, 2 * np.pi)))
            m = (1.0 - ocfg.in_view) / 2.0
            point = (r.uniform(m, 1 - m) * (width - 1), r.uniform(m, 1 - m) * (height - 1))
            traj = traj.anchored(point, float(r.uniform(0, duration_s)))
            origin = (-(w - 1) / 2.0, -(h - 1) / 2.0)
            objects.append(Layer("object", 0, tex, alpha, origin, traj, shape))
    # A fixed random depth order; ids follow it (1 = farthest) so "frontmost" = largest id.
    order = child_rng(seed, "depth").permutation(len(objects))
    for k, idx in enumerate(order, start=1):
        ly = objects[idx]
        layers.append(Layer("object", k, ly.texture, ly.alpha, ly.origin, ly.trajectory, ly.shape))

    for j, fcfg in enumerate(cfg.foreground):
        rng = child_rng(seed, f"foreground/{j}")
        if rng.random() >= fcfg.probability:
            continue
        traj = bg_traj.with_translation_scaled(float(rng.uniform(*fcfg.parallax)))
        layers.append(_background_role_layer("foreground", fcfg.texture, traj, width, height, duration_s, rng))

    rng = child_rng(seed, "lighting")
    return SceneInstance(
        width=width,
        height=height,
        layers=tuple(layers),
        gain=float(rng.uniform(*cfg.lighting.gain)),
        flicker_amplitude=cfg.lighting.flicker_amplitude,
        flicker_hz=cfg.lighting.flicker_hz,
        label_coverage=cfg.label_coverage,
        mask_coverage=cfg.mask_coverage,
    )


# ----------------------------------------------------------------------------- rendering


def _warp_layer(ly: Layer, t_s: float, width: int, height: int, margin: int = 0):
    """Warp a layer into a frame of (width, height) px whose pixel (0, 0) is image pixel
    (-margin, -margin). Returns (x0, y0, texture_roi, alpha_roi or None) in frame pixels, or
    None when the layer is outside; objects are warped only over their bounding box."""
    m = ly.trajectory.layer_to_image(t_s, ly.origin)
    m[:, 2] += margin
    if ly.kind == "object":
        h, w = ly.texture.shape
        corners = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) - [0.5, 0.5, 0]
        img = corners @ m.T
        x0 = max(0, int(np.floor(img[:, 0].min())) - 1)
        y0 = max(0, int(np.floor(img[:, 1].min())) - 1)
        x1 = min(width, int(np.ceil(img[:, 0].max())) + 2)
        y1 = min(height, int(np.ceil(img[:, 1].max())) + 2)
        if x1 <= x0 or y1 <= y0:
            return None
    else:
        x0, y0, x1, y1 = 0, 0, width, height
    m = m.copy()
    m[:, 2] -= (x0, y0)
    size = (x1 - x0, y1 - y0)
    tex = cv2.warpAffine(ly.texture, m, size, flags=cv2.INTER_LINEAR, borderMode=ly.border)
    alpha = None
    if ly.alpha is not None:
        alpha = cv2.warpAffine(ly.alpha, m, size, flags=cv2.INTER_LINEAR, borderMode=ly.border, borderValue=0)
    return x0, y0, tex, alpha


@dataclass(frozen=True)
class LayerSample:
    """One layer's share of a rendered frame, over its region of interest (frame pixels
    ``[y0 : y0 + h, x0 : x0 + w]``), float32 (h, w) each.

    Attributes:
        x0, y0: corner of the region in frame pixels.
        texture: the layer's warped linear intensity.
        alpha: its coverage; None for the opaque background (1 everywhere).
        behind: the composite of the layers behind it (what shows through where alpha < 1);
            None for the background (nothing is behind it).
        front: transmittance of the layers in front of it (how much of it reaches the sensor).
    """

    x0: int
    y0: int
    texture: np.ndarray = field(repr=False)
    alpha: np.ndarray | None = field(repr=False)
    behind: np.ndarray | None = field(repr=False)
    front: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class Frame:
    """A rendered instant.

    Attributes:
        t_s: time (s).
        intensity: float32 (H + 2 margin, W + 2 margin) linear intensity including the global
            gain; sensor pixel (x, y) is at ``[y + margin, x + margin]``.
        layer_map: int16, same shape: index of the frontmost layer covering at least
            ``label_coverage`` of each pixel (0 = background).
        margin: px rendered beyond each side of the sensor (so that image gradients at the
            sensor's border see the scene, not a padding rule).
        samples: per layer (depth order) its :class:`LayerSample`, None where the layer is out
            of the frame; what :func:`motion_causes` needs.
        gain: the global gain at ``t_s`` (``intensity`` includes it, the samples do not).
    """

    t_s: float
    intensity: np.ndarray
    layer_map: np.ndarray
    margin: int = 0
    samples: tuple = field(default=(), repr=False)
    gain: float = 1.0

    @property
    def sensor_intensity(self) -> np.ndarray:
        """View of ``intensity`` on the sensor, (H, W)."""
        m = self.margin
        return self.intensity[m : self.intensity.shape[0] - m, m : self.intensity.shape[1] - m]

    @property
    def sensor_layer_map(self) -> np.ndarray:
        m = self.margin
        return self.layer_map[m : self.layer_map.shape[0] - m, m : self.layer_map.shape[1] - m]


def render_frame(scene: SceneInstance, t_s: float, margin: int = 0) -> Frame:
    """Composite all layers at time ``t_s`` (see :class:`Frame`), ``margin`` px beyond the
    sensor on each side."""
    w, h = scene.width + 2 * margin, scene.height + 2 * margin
    warped = [_warp_layer(ly, t_s, w, h, margin) for ly in scene.layers]
    img = warped[0][2].copy()
    behind: list[np.ndarray | None] = [None] * len(warped)
    for idx in range(1, len(warped)):
        wl = warped[idx]
        if wl is None:
            continue
        x0, y0, tex, alpha = wl
        roi = img[y0 : y0 + tex.shape[0], x0 : x0 + tex.shape[1]]
        behind[idx] = roi.copy()
        roi += alpha * (tex - roi)  # "over": roi (1 - a) + tex a
    layer_map = np.zeros((h, w), np.int16)
    front: list[np.ndarray | None] = [None] * len(warped)
    # Visible weight of a layer = its alpha times the transmittance of all layers in front;
    # walk front to back so the first layer to pass the threshold is the frontmost one.
    trans = np.ones((h, w), np.float32)
    assigned = np.zeros((h, w), bool)
    for idx in range(len(scene.layers) - 1, 0, -1):
        wl = warped[idx]
        if wl is None:
            continue
        x0, y0, _, alpha = wl
        sl = (slice(y0, y0 + alpha.shape[0]), slice(x0, x0 + alpha.shape[1]))
        front[idx] = trans[sl].copy()
        vis = alpha * trans[sl]
        hit = (vis >= scene.label_coverage) & ~assigned[sl]
        layer_map[sl][hit] = idx
        assigned[sl] |= hit
        trans[sl] *= 1.0 - alpha
    front[0] = trans
    samples = tuple(
        None if wl is None else LayerSample(wl[0], wl[1], wl[2], wl[3], behind[i], front[i])
        for i, wl in enumerate(warped)
    )
    gain = float(scene.gain_at(t_s))
    return Frame(t_s, img * np.float32(gain), layer_map, margin, samples, gain)


def _sample_at(sample: LayerSample | None, px: np.ndarray, py: np.ndarray):
    """(texture, alpha, behind, front) of a layer at frame pixels ``(px, py)``, float64 (N,)
    each; a pixel outside the layer's region has alpha 0 (the layer is not there)."""
    n = len(px)
    if sample is None:
        z = np.zeros(n)
        return z, z, z, z
    hh, ww = sample.texture.shape
    cx, cy = px - sample.x0, py - sample.y0
    inside = (cx >= 0) & (cx < ww) & (cy >= 0) & (cy < hh)
    cx, cy = np.where(inside, cx, 0), np.where(inside, cy, 0)

    def at(a, fill=0.0):
        return np.where(inside, a[cy, cx].astype(np.float64) if a is not None else fill, 0.0)

    return at(sample.texture), at(sample.alpha, 1.0), at(sample.behind), at(sample.front)


def motion_causes(prev: Frame, cur: Frame, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """How much each layer's own motion changed the (gain-free) linear intensity of frame
    pixels ``(px, py)`` between two rendered instants: float64 (N, L), depth order.

    Layer k shows ``F (alpha T + (1 - alpha) B)`` (F: transmittance of the layers in front, B:
    the composite behind it). Moving only layer k changes its texture T and coverage alpha;
    to first order, with the other terms at their mean over the two instants, that changes
    the pixel by ``F (delta(alpha T) - delta(alpha) B)``. A layer that does not move
    (a still camera's background) causes nothing, whatever flicker or other layers do; an
    object whose rim sweeps a pixel causes the rim's contrast against what is behind it.
    """
    out = np.zeros((len(px), len(cur.samples)))
    for k, (a, b) in enumerate(zip(prev.samples, cur.samples)):
        if a is None and b is None:
            continue
        t0, a0, b0, f0 = _sample_at(a, px, py)
        t1, a1, b1, f1 = _sample_at(b, px, py)
        # A layer out of the frame at one instant contributes nothing there: its coverage is 0
        # and its other terms are those of the instant where it is in.
        b_mean = np.where((a0 > 0) & (a1 > 0), 0.5 * (b0 + b1), np.where(a1 > 0, b1, b0))
        f_mean = np.where((a0 > 0) & (a1 > 0), 0.5 * (f0 + f1), np.where(a1 > 0, f1, f0))
        out[:, k] = f_mean * ((a1 * t1 - a0 * t0) - (a1 - a0) * b_mean)
    return out


def event_layers(prev: Frame, cur: Frame, px: np.ndarray, py: np.ndarray, min_cause: float = 1e-4) -> np.ndarray:
    """Layer (depth index, int64 (N,)) whose motion caused the events at frame pixels
    ``(px, py)`` between two rendered instants: the layer of largest :func:`motion_causes`.
    Where no layer's motion changed the pixel by ``min_cause`` of its intensity (the change was
    the lighting's), the frontmost layer covering ``label_coverage`` at either instant."""
    causes = np.abs(motion_causes(prev, cur, px, py))
    best = np.argmax(causes, axis=1)
    level = 0.5 * (prev.intensity[py, px] / max(prev.gain, 1e-12) + cur.intensity[py, px] / max(cur.gain, 1e-12))
    covering = np.maximum(prev.layer_map[py, px], cur.layer_map[py, px]).astype(np.int64)
    moved = causes[np.arange(len(best)), best] > min_cause * np.maximum(level, 1e-6)
    return np.where(moved, best, covering)


def object_coverage(scene: SceneInstance, t_s: float) -> np.ndarray:
    """Visible coverage of each object, float32 (K, H, W) in [0, 1], order = object ids.

    Occlusion counts only other *objects* in front; foreground occluders (a net) are ignored,
    so the coverage is the object's silhouette region as seen behind a thin net."""
    w, h = scene.width, scene.height
    objs = scene.object_layers
    out = np.zeros((len(objs), h, w), np.float32)
    trans = np.ones((h, w), np.float32)
    for k in range(len(objs) - 1, -1, -1):
        wl = _warp_layer(objs[k], t_s, w, h)
        if wl is None:
            continue
        x0, y0, _, alpha = wl
        sl = (slice(y0, y0 + alpha.shape[0]), slice(x0, x0 + alpha.shape[1]))
        out[k][sl] = alpha * trans[sl]
        trans[sl] *= 1.0 - alpha
    return out
