"""Scene configuration of the simulator: frozen dataclasses loadable from YAML.

A scene is a stack of 2D layers seen by an event camera:

* the **background** (label 0): a texture under the camera's ego-motion, a time-varying
  affine map (translation, rotation, zoom);
* **independently moving objects** (labels 1..K): textured sprites with alpha masks, each with
  its own affine motion, drawn in a fixed depth order over the background;
* optional **foreground occluders** (label 0, e.g. the net of EED's "what is background"): a
  texture with an alpha mask drawn in front of everything, moving with the camera (the
  background's motion with its translation scaled by a parallax factor).

Numbers given as ``[lo, hi]`` are ranges sampled uniformly per recording from the seed, so one
preset describes a family of scenes. Units: pixels (px), px/s, degrees, microseconds (us).
Every field is documented where it is declared; :func:`scene_from_dict` rejects unknown keys
with a :class:`~evseg.errors.ConfigError` naming the key and the file.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evseg.errors import ConfigError, yaml_problem

Range = tuple[float, float]
"""A closed interval ``(lo, hi)`` sampled uniformly per recording; ``lo == hi`` fixes it."""

TEXTURE_FAMILIES = (
    "noise", "blobs", "edges", "lines", "grid", "wood", "street", "checker", "step", "uniform",
)
"""Procedural texture families (see :mod:`evseg.simulator.textures`)."""

SHAPES = ("ellipse", "disc", "rectangle", "blob", "polygon")
"""Object silhouettes (see :func:`evseg.simulator.textures.shape_alpha`)."""

SENSOR_PRESETS: dict[str, tuple[int, int]] = {
    "240x180": (240, 180),  # DAVIS240 (EED)
    "346x260": (346, 260),  # DAVIS346 (EVIMO)
    "640x480": (640, 480),  # DVXplorer / Prophesee VGA
    "1280x720": (1280, 720),  # Prophesee HD (IMX636)
}
"""Sensor resolutions ``(width, height)`` the presets use."""


@dataclass(frozen=True)
class SensorConfig:
    """The event camera: resolution and the pixel model.

    Attributes:
        width, height: sensor size in px.
        c_pos, c_neg: mean ON / OFF contrast thresholds in log intensity.
        c_sigma: per-pixel standard deviation of both thresholds (fixed-pattern mismatch).
        refractory_us: after an event a pixel is blind for this long; crossings in that time
            are lost (the reference level still follows them, as the reset switch is held).
        noise_rate_hz: background-activity noise, Poisson rate per pixel (label -1).
        hot_pixel_fraction: share of pixels that fire on their own at ``hot_pixel_rate_hz``.
        hot_pixel_rate_hz: Poisson rate of each hot pixel.
        log_eps: offset of the logarithm, ``L = log(I + log_eps)`` with I in [0, 1]: the
            lin-log response that keeps dark pixels from firing on tiny changes.
        random_initial_level: start each pixel's reference at a random phase within its
            threshold band (real sensors are not synchronised at switch-on); False starts
            every reference at the first frame's log intensity.
    """

    width: int = 346
    height: int = 260
    c_pos: float = 0.2
    c_neg: float = 0.2
    c_sigma: float = 0.02
    refractory_us: float = 100.0
    noise_rate_hz: float = 0.1
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 200.0
    log_eps: float = 0.02
    random_initial_level: bool = True

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class TextureConfig:
    """A procedural texture (see :mod:`evseg.simulator.textures`).

    Attributes:
        family: one name or a list of names from :data:`TEXTURE_FAMILIES` (one is drawn).
        scale_px: characteristic feature size in px (blob radius, grid spacing, ...).
        contrast: intensity span of the texture as a share of [0, 1].
        mean: mean intensity in [0, 1].
        angle_deg: orientation for oriented families (step, lines, grid, wood, street).
        thickness_px: stroke width for lines and grids.
        density: relative number of features (1 = about one per scale_px^2 area).
        blur_px: Gaussian blur sigma (the lens), which also keeps bilinear warping alias-free.
    """

    family: tuple[str, ...] = ("noise",)
    scale_px: Range = (6.0, 24.0)
    contrast: Range = (0.5, 0.9)
    mean: Range = (0.35, 0.6)
    angle_deg: Range = (0.0, 180.0)
    thickness_px: Range = (1.5, 3.0)
    density: float = 1.0
    blur_px: float = 0.7

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class MotionConfig:
    """A smooth random affine trajectory: x_img = c(t) + s(t) R(theta(t)) X.

    Translation velocity is ``v0 + a * sin(2 pi f t + phi)`` per axis, with ``|v0|`` drawn from
    ``speed_px_s`` in a direction from ``direction_deg`` and ``|a| = wobble * |v0|``; rotation
    and zoom rates likewise get a sinusoidal wobble. Everything integrates in closed form, so
    ground-truth flow is analytic.

    Attributes:
        speed_px_s: mean translation speed in px/s.
        direction_deg: direction of the mean velocity (0 = +x / right, 90 = +y / down).
        wobble: relative amplitude of the sinusoidal variation of all rates.
        wobble_hz: frequency of that variation in Hz.
        rotation_deg_s: magnitude of the mean rotation rate in deg/s (random sign).
        zoom_per_s: mean zoom rate d(log scale)/dt in 1/s (signed range; > 0 = approaching).
            Zoom compounds: after T s the scale is about exp(zoom T), so a zooming scene
            magnifies (blurs) or minifies (aliases) its texture in long recordings; keep
            zooming recordings to a few seconds.
    """

    speed_px_s: Range = (0.0, 0.0)
    direction_deg: Range = (0.0, 360.0)
    wobble: Range = (0.0, 0.3)
    wobble_hz: Range = (0.5, 3.0)
    rotation_deg_s: Range = (0.0, 0.0)
    zoom_per_s: Range = (0.0, 0.0)

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class BackgroundConfig:
    """The background layer (label 0) under camera ego-motion."""

    texture: TextureConfig = field(default_factory=TextureConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)


@dataclass(frozen=True)
class ObjectConfig:
    """One kind of independently moving object; ``count`` of them are drawn per recording.

    Attributes:
        count: how many objects of this kind (ints, range inclusive).
        shape: one name or a list from :data:`SHAPES` (one is drawn per object).
        size_px: longest extent of the silhouette in px.
        aspect: short / long extent.
        texture: appearance of the object.
        motion: the object's own affine motion in the image.
        in_view: the object's centre passes through a uniform random point of the central
            ``in_view`` share of the frame (per axis) at a uniform random time of the
            recording, so objects may enter or leave the frame but are seen at some point.
        min_log_contrast: the object's mean intensity differs from the background's mean by
            at least this in log intensity (redrawn from ``texture.mean`` up to 20 times, then
            the farthest draw is kept), so that its silhouette is seen by the camera.
    """

    count: tuple[int, int] = (1, 1)
    shape: tuple[str, ...] = ("ellipse", "rectangle", "blob")
    size_px: Range = (40.0, 90.0)
    aspect: Range = (0.5, 1.0)
    texture: TextureConfig = field(default_factory=TextureConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    in_view: float = 0.7
    min_log_contrast: float = 0.45

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class ForegroundConfig:
    """An occluder in front of everything (label 0), e.g. a net; its alpha is the texture's
    stroke mask (families grid or lines). It moves like the background with the translation
    scaled by ``parallax`` (closer to the camera: > 1).

    Attributes:
        texture: family grid or lines; strokes are opaque, the rest transparent.
        parallax: translation-speed factor relative to the background motion.
        probability: chance that the occluder is present in a recording.
    """

    texture: TextureConfig = field(default_factory=lambda: TextureConfig(family=("grid",)))
    parallax: Range = (1.5, 2.5)
    probability: float = 1.0

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class LightingConfig:
    """Global illumination.

    Attributes:
        gain: global intensity multiplier drawn per recording (< 1: dim scene).
        flicker_amplitude: relative sinusoidal gain modulation over time (0 = steady light);
            flicker makes every pixel fire, so presets keep it at 0.
        flicker_hz: frequency of that modulation.
    """

    gain: Range = (0.6, 1.0)
    flicker_amplitude: float = 0.0
    flicker_hz: float = 100.0

    def __post_init__(self) -> None:
        _check(self)


@dataclass(frozen=True)
class SceneConfig:
    """A family of simulated recordings.

    Attributes:
        name, description: for humans and saved files.
        sensor: the camera.
        background: textured background under ego-motion.
        objects: kinds of independently moving objects (may be empty).
        foreground: occluders in front of the objects (may be empty).
        lighting: global gain.
        max_step_px: rendering sub-step so that no point of the image moves further than this
            between two rendered frames (adaptive to the scene's fastest point).
        max_step_us: upper bound of the sub-step in time, whatever the speed.
        gradient_sigma_px: smoothing of the log image before taking the spatial gradient that
            defines the normal-flow direction.
        label_coverage: an event is attributed to the layer whose motion changed its pixel
            most; where none moved (a lighting change), to the frontmost layer that covers at
            least this share of its pixel at the start or the end of the sub-step.
        mask_coverage: a pixel belongs to an object's ground-truth mask when the object
            covers at least this share of it (after occlusion by objects in front).
    """

    name: str = "custom"
    description: str = ""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    objects: tuple[ObjectConfig, ...] = ()
    foreground: tuple[ForegroundConfig, ...] = ()
    lighting: LightingConfig = field(default_factory=LightingConfig)
    max_step_px: float = 0.5
    max_step_us: float = 1000.0
    gradient_sigma_px: float = 1.0
    label_coverage: float = 0.25
    mask_coverage: float = 0.5

    def __post_init__(self) -> None:
        _check(self)

    def with_sensor_size(self, width: int, height: int) -> "SceneConfig":
        """Same scene on a sensor of another resolution (sizes in px are kept)."""
        return dataclasses.replace(
            self, sensor=dataclasses.replace(self.sensor, width=int(width), height=int(height))
        )


# ----------------------------------------------------------------------------- (de)serialising


def _convert(tp: Any, value: Any, where: str, source: str) -> Any:
    """Convert a YAML/JSON value to the annotated type ``tp``, or raise ConfigError."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _from_dict(tp, value, where, source)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:  # tuple[X, ...]: a list, or one item
            items = value if isinstance(value, (list, tuple)) else [value]
            return tuple(_convert(args[0], v, f"{where}[{i}]", source) for i, v in enumerate(items))
        if isinstance(value, (int, float)) and not isinstance(value, bool):  # scalar = fixed range
            value = [value, value]
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise ConfigError(f"{source}: '{where}' must be a list of {len(args)} values, got {value!r}")
        return tuple(_convert(a, v, f"{where}[{i}]", source) for i, (a, v) in enumerate(zip(args, value)))
    if origin in (typing.Union, types.UnionType):
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: '{where}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{source}: '{where}' must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = ""
            if isinstance(value, str):
                try:
                    float(value)
                    hint = " (YAML 1.1 reads a number like 1e9 as text: write 1.0e+9)"
                except ValueError:
                    pass
            raise ConfigError(f"{source}: '{where}' must be a number, got {value!r}{hint}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: '{where}' must be a string, got {value!r}")
        return value
    return value


class _Invalid(ConfigError):
    """A config value out of range: ``key`` and ``problem``, to be placed in a message."""

    def __init__(self, key: str, problem: str, owner: str) -> None:
        super().__init__(f"{owner}: '{key}' {problem}")
        self.key, self.problem = key, problem


def _check(obj: Any) -> None:
    """Raise :class:`ConfigError` for the first value of ``obj`` out of range (the dataclasses
    call it when made, so the Python API refuses what a YAML file would be refused for)."""
    found = _problem(obj)
    if found is not None:
        raise _Invalid(*found, type(obj).__name__)


def _from_dict(cls: type, data: Any, where: str, source: str):
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: '{where or 'scene'}' must be a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        prefix = f"{where}." if where else ""
        raise ConfigError(
            f"{source}: unknown key '{prefix}{unknown[0]}' (allowed in "
            f"'{where or 'scene'}': {', '.join(sorted(names))})"
        )
    kwargs = {
        k: _convert(hints[k], v, f"{where}.{k}" if where else k, source) for k, v in data.items()
    }
    try:
        return cls(**kwargs)
    except _Invalid as exc:
        raise ConfigError(f"{source}: '{where + '.' if where else ''}{exc.key}' {exc.problem}") from None


@functools.lru_cache(maxsize=None)
def _type_hints(cls: type) -> dict:
    return typing.get_type_hints(cls)


def _problem(obj: Any) -> tuple[str, str] | None:
    """``(field, what is wrong)`` for the first value checks that the types alone do not
    catch, or None."""
    def bad(key: str, msg: str) -> tuple[str, str]:
        return key, msg

    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        numbers = value if isinstance(value, tuple) else (value,)
        if any(isinstance(v, float) and not np.isfinite(v) for v in numbers):
            return bad(f.name, f"must be finite, got {value!r}")  # NaN passes every range check below

    if isinstance(obj, TextureConfig):
        for key in ("scale_px", "thickness_px"):
            if not getattr(obj, key)[0] > 0:
                return bad(key, f"must be positive (px), got {list(getattr(obj, key))}")
        for key in ("contrast", "mean"):
            lo, hi = getattr(obj, key)
            if not (0 <= lo and hi <= 1):
                return bad(key, f"must lie in [0, 1] (a share of full brightness), got {[lo, hi]}")
        if not obj.density > 0:
            return bad("density", f"must be positive, got {obj.density}")
        if not obj.blur_px >= 0:
            return bad("blur_px", f"must be >= 0 px, got {obj.blur_px}")
        for fam in obj.family:
            if fam not in TEXTURE_FAMILIES:
                return bad("family", f"has unknown texture family '{fam}' (known: {', '.join(TEXTURE_FAMILIES)})")
        if not obj.family:
            return bad("family", "must name at least one texture family")
    if isinstance(obj, ObjectConfig):
        for s in obj.shape:
            if s not in SHAPES:
                return bad("shape", f"has unknown shape '{s}' (known: {', '.join(SHAPES)})")
        if obj.count[0] < 0 or obj.count[1] < obj.count[0]:
            return bad("count", f"must be a range 0 <= lo <= hi, got {list(obj.count)}")
        if not obj.size_px[0] > 0:
            return bad("size_px", f"must be positive, got {list(obj.size_px)}")
        if not (0 < obj.aspect[0] and obj.aspect[1] <= 1):
            return bad("aspect", f"must lie in (0, 1] (short / long extent), got {list(obj.aspect)}")
        if not 0 <= obj.in_view <= 1:
            return bad("in_view", f"must be in [0, 1], got {obj.in_view}")
        if not obj.min_log_contrast >= 0:
            return bad("min_log_contrast", f"must be >= 0, got {obj.min_log_contrast}")
    if isinstance(obj, ForegroundConfig):
        if not 0 <= obj.probability <= 1:
            return bad("probability", f"must be in [0, 1], got {obj.probability}")
        if not obj.parallax[0] > 0:
            return bad("parallax", f"must be positive (a factor of the background's motion), got {list(obj.parallax)}")
    if isinstance(obj, LightingConfig):
        if not obj.gain[0] > 0:
            return bad("gain", f"must be positive (intensity must stay > 0 for its log), got {list(obj.gain)}")
        if not 0 <= obj.flicker_amplitude < 1:
            return bad("flicker_amplitude", f"must be in [0, 1) (the intensity must stay > 0), got {obj.flicker_amplitude}")
        if not obj.flicker_hz >= 0:
            return bad("flicker_hz", f"must be >= 0, got {obj.flicker_hz}")
    if isinstance(obj, MotionConfig):
        for key in ("speed_px_s", "wobble", "wobble_hz", "rotation_deg_s"):
            if not getattr(obj, key)[0] >= 0:
                return bad(key, f"must be >= 0, got {list(getattr(obj, key))}")
    if isinstance(obj, SensorConfig):
        if obj.width <= 0 or obj.height <= 0:
            return bad("width", f"and height must be positive, got {obj.width}x{obj.height}")
        if not (obj.c_pos > 0 and obj.c_neg > 0 and np.isfinite(obj.c_pos) and np.isfinite(obj.c_neg)):
            return bad("c_pos", f"and c_neg must be positive log-intensity thresholds, got {obj.c_pos} and {obj.c_neg}")
        for key in ("c_sigma", "refractory_us", "noise_rate_hz", "hot_pixel_rate_hz"):
            if not getattr(obj, key) >= 0:
                return bad(key, f"must be >= 0, got {getattr(obj, key)}")
        if not 0 <= obj.hot_pixel_fraction <= 1:
            return bad("hot_pixel_fraction", f"must be in [0, 1], got {obj.hot_pixel_fraction}")
        if not obj.log_eps > 0:
            return bad("log_eps", f"must be positive, got {obj.log_eps}")
    if isinstance(obj, SceneConfig):
        if not 0 < obj.max_step_px <= 2:
            return bad("max_step_px", f"must be in (0, 2] px, got {obj.max_step_px}")
        if not obj.max_step_us >= 1:
            return bad("max_step_us", f"must be >= 1 us (timestamps are whole microseconds), got {obj.max_step_us}")
        if not obj.gradient_sigma_px >= 0:
            return bad("gradient_sigma_px", f"must be >= 0 px, got {obj.gradient_sigma_px}")
        for key in ("label_coverage", "mask_coverage"):
            if not 0 < getattr(obj, key) <= 1:
                return bad(key, f"must be in (0, 1] (a share of the pixel), got {getattr(obj, key)}")
    for f in dataclasses.fields(obj):
        if _type_hints(type(obj))[f.name] == Range:
            lo, hi = getattr(obj, f.name)
            if hi < lo:
                return bad(f.name, f"range must have lo <= hi, got [{lo}, {hi}]")
    return None


def scene_from_dict(data: dict, source: str = "scene config") -> SceneConfig:
    """Build a :class:`SceneConfig` from nested dicts (YAML/JSON); unknown keys raise
    :class:`ConfigError` naming the key and ``source``."""
    return _from_dict(SceneConfig, data, "", source)


def scene_to_dict(cfg: SceneConfig) -> dict:
    """Nested plain dicts/lists (JSON-serialisable) that :func:`scene_from_dict` reads back."""
    def plain(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        return v

    return plain(cfg)


def scene_to_json(cfg: SceneConfig) -> str:
    return json.dumps(scene_to_dict(cfg), sort_keys=True)


def load_scene_file(path: str | Path) -> SceneConfig:
    """Load a scene YAML file (the layout of ``configs/scenes/*.yaml``)."""
    import yaml

    path = Path(path)
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text (YAML) file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read scene config ({exc.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: {yaml_problem(exc)}") from None
    return scene_from_dict(data, source=str(path))
