"""Training data for the normal-flow head: simulated scenes (and users' recordings with optical flow).

Pipeline, per scene (one simulator preset and seed):

1. simulate the scene with ground truth (:func:`evseg.simulator.simulate`);
2. cut ``slices_per_scene`` slices of ``slice_us`` (at random starts), each with a fresh random
   augmentation (:mod:`evseg.train.augment`), which also maps the ground-truth flow;
3. choose target events (:func:`evseg.veckm_flow.select_targets`), keep those with ground truth
   (noise events never are targets, but stay as neighbours), cap them at
   ``max_targets_per_slice``;
4. encode the targets (:func:`evseg.veckm_flow.encode_targets`: no learned parameters, so the
   features are computed once) and store features + targets in one shard per scene
   (``<cache_dir>/<key>/<preset>_s<seed>.npz``; ``key`` hashes everything that changes the
   shard's contents, so a changed config never reuses stale shards).

Epochs then only read features: training costs one small MLP pass per target.

Targets per row: ``normal_flow`` (GT normal flow, px/s, from the simulator) and
``optical_flow`` (GT optical flow, px/s); either can be NaN. The module uses the normal-flow
loss where normal flow is known and VecKM_flow's optical-flow loss where only optical flow is
(users' real recordings: see :func:`load_flow_recording`).

Seeds: training and validation scenes must use seeds < 1000; seeds >= 1000 are held out for
:mod:`evseg.train.evaluate`.
"""

from __future__ import annotations

import hashlib
import json
import os
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from evseg.checks import is_whole
from evseg.errors import ConfigError, EventDataError, FormatError
from evseg.events import EVENT_DTYPE
from evseg.io.numpy_files import LATEST_PLAUSIBLE_US
from evseg.train.augment import (
    NO_AUGMENTATION,
    AugmentConfig,
    FlowSlice,
    apply_augmentation,
    draw_augmentation,
)

HELD_OUT_SEED_START = 1000
"""Seeds at and above this are reserved for evaluation; training refuses them."""

SHARD_FORMAT = 2
"""Bumped whenever the shard layout or the way shards are built changes (2: rows carry
``is_object``)."""


# --------------------------------------------------------------------------- specs


@dataclass(frozen=True)
class SliceSpec:
    """How slices and targets are drawn from one recording.

    Attributes:
        slice_us: ``[min, max]`` duration of one slice in microseconds, drawn uniformly per
            slice (the pipeline estimates flow per 10 ms window, VecKM_flow uses ~20 ms); the
            encoder's neighbourhoods only see events of the same slice.
        slices_per_scene: slices cut from each recording (random starts, each augmented anew).
        max_targets_per_slice: targets kept per slice (uniform subsample of the eligible ones).
        targets: keyword arguments of :func:`evseg.veckm_flow.select_targets`, or a list of
            such dicts of which one is drawn per slice (e.g. latest event per 2 px cell, as
            ``evseg flow`` selects, and all events, as the pipeline's estimator sees them).
        target_us: targets are chosen among the events of the last ``target_us`` of the
            slice only (after augmentation); the earlier events are neighbours only. This is
            how the pipeline sees a window: its events plus ``flow_context_us`` of events
            before it (:mod:`evseg.veckm_flow.context`). None: targets anywhere in the slice.
    """

    slice_us: tuple[int, int] = (10_000, 20_000)
    slices_per_scene: int = 8
    max_targets_per_slice: int = 2048
    targets: dict[str, Any] | list[dict[str, Any]] | None = None
    target_us: int | None = None


@dataclass(frozen=True)
class SceneSpec:
    """One simulated scene to turn into a shard."""

    preset: str
    seed: int
    duration_us: int


def shard_key(encoding: dict, spec: SliceSpec, augment: AugmentConfig, extra: dict | None = None) -> str:
    """Hash of everything (besides the scene) that changes a shard's contents."""
    payload = {
        "format": SHARD_FORMAT,
        "encoding": encoding,
        "slices": asdict(spec),
        "augment": asdict(augment),
        "extra": extra or {},
    }
    return hashlib.sha1(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def scene_rng(name: str, seed: int, salt: int = 0) -> np.random.Generator:
    """Deterministic generator for one scene (independent of worker order and process)."""
    return np.random.default_rng([zlib.crc32(name.encode()), int(seed), int(salt)])


def check_training_seeds(seeds: Sequence[int], what: str) -> None:
    """Refuse held-out evaluation seeds (>= 1000) in training or validation data."""
    bad = [s for s in seeds if s >= HELD_OUT_SEED_START or s < 0]
    if bad:
        raise ConfigError(
            f"{what}: seeds must be in [0, {HELD_OUT_SEED_START}) (seeds >= {HELD_OUT_SEED_START} "
            f"are held out for evaluation), got {bad[:5]}"
        )


def whole_at_least(value, name: str, minimum: int) -> int:
    """``value`` as an int when it is a whole number >= ``minimum``; else a ConfigError naming
    the option ``name``.

    >>> whole_at_least(4096, "data.batch_size", 1)
    4096
    """
    if not is_whole(value) or value < minimum:
        raise ConfigError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def seed_range(value, name: str) -> list[int]:
    """The seeds of ``[start, stop)`` (two whole numbers, start <= stop); else a ConfigError
    naming ``name``."""
    try:
        start, stop = value
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be [start, stop), got {value!r}") from None
    if not (is_whole(start) and is_whole(stop)) or start > stop:
        raise ConfigError(f"{name} must be [start, stop) with whole numbers start <= stop, got {list(value)!r}")
    return list(range(int(start), int(stop)))


def check_slice_spec(spec: SliceSpec, what: str = "data.slices") -> None:
    """Refuse slicing settings that would fail deep inside numpy while shards are built
    (:class:`ConfigError` naming ``what.<field>`` and the value): ``slice_us`` must be
    ``[min, max]`` microseconds with ``0 < min <= max``, the counts whole numbers >= 1,
    ``target_us`` None or > 0 us, ``targets`` keyword arguments of
    :func:`evseg.veckm_flow.select_targets` (a dict or a list of dicts)."""
    try:
        lo, hi = spec.slice_us
    except (TypeError, ValueError):
        raise ConfigError(f"{what}.slice_us must be [min, max] in microseconds, got {spec.slice_us!r}") from None
    if not (is_whole(lo) and is_whole(hi)) or not 0 < lo <= hi:
        raise ConfigError(f"{what}.slice_us must be [min, max] whole microseconds with 0 < min <= max, "
                          f"got {list(spec.slice_us)!r}")
    whole_at_least(spec.slices_per_scene, f"{what}.slices_per_scene", 1)
    whole_at_least(spec.max_targets_per_slice, f"{what}.max_targets_per_slice", 1)
    if spec.target_us is not None:
        whole_at_least(spec.target_us, f"{what}.target_us", 1)
    choices = spec.targets if isinstance(spec.targets, (list, tuple)) else [spec.targets or {}]
    known = ("cell_px", "max_targets", "seed")  # select_targets' options
    for choice in choices:
        if not isinstance(choice, dict):
            raise ConfigError(f"{what}.targets must be a mapping of {', '.join(known)} or a list of them, "
                              f"got {choice!r}")
        unknown = sorted(set(choice) - set(known))
        if unknown:
            raise ConfigError(f"{what}.targets: unknown option(s) {unknown}; known: {', '.join(known)}")


def check_augment_config(augment: AugmentConfig, what: str = "data.augment") -> None:
    """Refuse augmentation ranges that cannot be drawn from (:class:`ConfigError` naming
    ``what.<field>``): each range ``[lo, hi]`` with ``lo <= hi``; scales > 0, ``keep_range``
    in (0, 1], ``noise_rate_range`` >= 0 events/px/s, ``rotation_step_deg`` >= 0."""
    import math

    bounds = {"scale_range": (0.0, math.inf, False), "time_scale_range": (0.0, math.inf, False),
              "keep_range": (0.0, 1.0, False), "noise_rate_range": (0.0, math.inf, True)}
    for name, (low, high, low_ok) in bounds.items():
        value = getattr(augment, name)
        try:
            a, b = (float(v) for v in value)
        except (TypeError, ValueError):
            raise ConfigError(f"{what}.{name} must be [low, high], got {value!r}") from None
        inside = all(math.isfinite(v) and (v >= low if low_ok else v > low) and v <= high for v in (a, b))
        if not inside or a > b:
            limits = f"{'[' if low_ok else '('}{low:g}, {high:g}]"
            raise ConfigError(f"{what}.{name} must be [low, high] with low <= high, both in {limits}, "
                              f"got {list(value)!r}")
    step = augment.rotation_step_deg
    if isinstance(step, bool) or not isinstance(step, (int, float)) or not math.isfinite(step) or step < 0:
        raise ConfigError(f"{what}.rotation_step_deg must be a number of degrees >= 0, got {step!r}")


# --------------------------------------------------------------------------- slices


def recording_slice(s: FlowSlice, t0_us: int, t1_us: int) -> FlowSlice:
    """Events with ``t0_us <= t < t1_us`` (flows alike)."""
    t = s.events["t"]
    i0, i1 = np.searchsorted(t, [t0_us, t1_us], side="left")
    return s.take(slice(int(i0), int(i1)))


def draw_slices(
    rec: FlowSlice, spec: SliceSpec, augment: AugmentConfig, rng: np.random.Generator
) -> list[FlowSlice]:
    """Cut ``spec.slices_per_scene`` augmented slices of ``spec.slice_us`` from a recording.

    The duration ``D`` (uniform in ``spec.slice_us``) and the time scale are drawn first: a
    stretch of ``D / time_scale`` is cut and then stretched, so every slice spans ``D`` after
    augmentation. Starts are uniform over the recording.
    """
    if len(rec) == 0:
        return []
    t_first, t_last = int(rec.events["t"][0]), int(rec.events["t"][-1])
    out = []
    for _ in range(spec.slices_per_scene):
        duration_us = int(rng.integers(spec.slice_us[0], spec.slice_us[1] + 1))
        draw = draw_augmentation(augment, rng)
        length = max(1, int(round(duration_us / draw.time_scale)))
        t0 = int(rng.integers(t_first, max(t_first + 1, t_last - length + 1)))
        s = apply_augmentation(recording_slice(rec, t0, t0 + length), draw, rng)
        if len(s):
            out.append(s)
    return out


def _encoding_config(encoding: dict):
    from evseg.veckm_flow.encoding import EncodingConfig

    return EncodingConfig.from_dict(encoding)


def slice_examples(
    s: FlowSlice, encoding: dict, spec: SliceSpec, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """Features and ground truth of the target events of one slice.

    Returns:
        ``features`` (T, F) float16 encoder output (float16 halves the cache; the encoding
        is normalised to O(1) entries, so 3 significant digits are plenty),
        ``normal_flow`` and ``optical_flow`` (T, 2) float32 px/s (NaN where unknown),
        ``is_object`` (T,) uint8, 1 where the target belongs to an independently moving object
        (ground-truth label >= 1; 0 where the source has no labels).
    """
    from evseg.veckm_flow.encoding import encode_targets
    from evseg.veckm_flow.targets import select_targets

    choice = spec.targets or {}
    if isinstance(choice, (list, tuple)):
        choice = choice[int(rng.integers(len(choice)))] if choice else {}
    first = 0
    if spec.target_us is not None and len(s):
        first = int(np.searchsorted(s.events["t"], int(s.events["t"][-1]) - int(spec.target_us), side="left"))
    idx = first + np.asarray(select_targets(s.events[first:], s.sensor_size, **choice), dtype=np.int64)
    n = len(s)
    nf = s.normal_flow if s.normal_flow is not None else np.full((n, 2), np.nan, np.float32)
    of = s.optical_flow if s.optical_flow is not None else np.full((n, 2), np.nan, np.float32)
    # A target needs ground truth: normal flow where the source has it, else optical flow.
    # Zero flow carries no direction to learn (and makes the angular losses undefined).
    has_nf = np.all(np.isfinite(nf[idx]), axis=1) & (np.linalg.norm(np.nan_to_num(nf[idx]), axis=1) > 0)
    has_of = np.all(np.isfinite(of[idx]), axis=1) & (np.linalg.norm(np.nan_to_num(of[idx]), axis=1) > 0)
    idx = idx[has_nf | has_of]
    if len(idx) > spec.max_targets_per_slice:
        idx = np.sort(rng.choice(idx, spec.max_targets_per_slice, replace=False))
    if len(idx) == 0:
        return empty_examples(0)
    feats = encode_targets(s.events, idx, s.sensor_size, _encoding_config(encoding))
    return {
        "features": np.asarray(feats, dtype=np.float16),
        "normal_flow": nf[idx].astype(np.float32),
        "optical_flow": of[idx].astype(np.float32),
        "is_object": (np.zeros(len(idx), np.uint8) if s.label is None
                      else (s.label[idx] >= 1).astype(np.uint8)),
    }


def empty_examples(n_features: int) -> dict[str, np.ndarray]:
    return {
        "features": np.zeros((0, n_features), np.float16),
        "normal_flow": np.zeros((0, 2), np.float32),
        "optical_flow": np.zeros((0, 2), np.float32),
        "is_object": np.zeros(0, np.uint8),
    }


def concat_examples(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    parts = [p for p in parts if len(p["features"])]
    if not parts:
        return empty_examples(0)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def recording_examples(
    rec: FlowSlice, name: str, seed: int, encoding: dict, spec: SliceSpec, augment: AugmentConfig
) -> dict[str, np.ndarray]:
    """All training rows of one recording: augmented slices, targets, features."""
    rng = scene_rng(name, seed)
    return concat_examples([slice_examples(s, encoding, spec, rng) for s in draw_slices(rec, spec, augment, rng)])


# --------------------------------------------------------------------------- sources


def simulated_recording(scene: SceneSpec) -> FlowSlice:
    """Simulate one scene: events with GT normal flow and optical flow (px/s) and motion label."""
    from evseg.simulator import load_scene_preset, simulate

    rec = simulate(load_scene_preset(scene.preset), seed=scene.seed, duration_us=scene.duration_us)
    return FlowSlice(
        rec.stream.events,
        rec.stream.sensor_size,
        np.asarray(rec.normal_flow, np.float32),
        np.asarray(rec.flow, np.float32),
        np.asarray(rec.label, np.int16),
    )


def load_flow_recording(path: str | Path) -> FlowSlice:
    """Read a user's recording with ground-truth optical flow (EVIMO2/DSEC-like, as one .npz).

    Layout (all flows in px/s, x = column, y = row 0 at the top; NaN = no ground truth):

    - events: ``events`` (:data:`~evseg.events.EVENT_DTYPE`) or the columns ``x``, ``y``,
      ``t`` (integer microseconds), ``p`` (+1/-1 or 0/1);
    - ``sensor_size``: ``[width, height]``, whole pixels > 0;
    - flow (floating point, px/s), one of
        * ``flow``: (N, 2) per-event optical flow, or
        * ``flow_maps``: (K, height, width, 2) dense optical flow and ``flow_t_us``: (K,)
          increasing integer start times in microseconds; map k applies to events with
          ``flow_t_us[k] <= t < flow_t_us[k+1]`` (the last map to the end; events before
          ``flow_t_us[0]`` have no ground truth). DSEC's forward
          flow (a displacement in px over the interval dt) becomes px/s by dividing by dt;
          EVIMO2's per-frame flow the same way.

    Raises:
        FormatError: not an .npz archive, a missing key, a field that cannot be read (pickled
            objects), of the wrong shape or dtype (integer flow: raw DSEC PNG values rather
            than px/s; float times: seconds rather than microseconds), no events, or no event
            with a finite flow; the message names the file and the field.
        EventDataError: events unsorted or off the sensor (file, field and event named).
    """
    path = Path(path)
    with _open_npz(path) as z:
        keys = set(z.files)
        ev = _recording_events(z, path, keys)
        if "sensor_size" not in keys:
            raise FormatError(f"{path}: needs field 'sensor_size' = [width, height] (has {sorted(keys)})")
        w, h = _recording_sensor_size(_npz_field(z, path, "sensor_size"), path)
        from evseg.events import validate_events

        # Before any flow map is indexed with the events' coordinates.
        validate_events(ev, (w, h), source=str(path))
        if len(ev) == 0:
            raise FormatError(f"{path}: holds no events, so the recording adds nothing to training")
        if "flow" in keys:
            flow = _checked_flow(_npz_field(z, path, "flow"), path, "flow")
            if flow.shape != (len(ev), 2):
                raise FormatError(f"{path}: field 'flow' has shape {flow.shape}, expected ({len(ev)}, 2)")
        elif "flow_maps" in keys and "flow_t_us" in keys:
            flow = _flow_from_maps(ev, _npz_field(z, path, "flow_maps"), _npz_field(z, path, "flow_t_us"), (w, h), path)
        else:
            raise FormatError(f"{path}: needs field 'flow' (N, 2) or fields 'flow_maps' and 'flow_t_us' "
                              f"(has {sorted(keys)})")
    if not np.isfinite(flow).all(axis=1).any():
        raise FormatError(f"{path}: no event has a finite ground-truth flow (every 'flow' row is NaN), "
                          "so the recording adds nothing to training")
    return FlowSlice(ev, (w, h), None, flow)


def _open_npz(path: Path):
    """``np.load(path)`` of an .npz archive, without pickles; anything else is a FormatError
    saying what the file is instead."""
    import zipfile

    try:
        with open(path, "rb") as f:
            magic = f.read(6)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or type(exc).__name__})") from None
    if not magic.startswith(b"PK"):
        what = "a single .npy array" if magic.startswith(b"\x93NUMPY") else "not a zip archive"
        raise FormatError(f"{path}: not an .npz file ({what}); a training recording is one archive of "
                          "named arrays, as numpy.savez writes")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable .npz file ({exc})") from None


def _npz_field(z, path: Path, key: str) -> np.ndarray:
    """One array of an open .npz; an unreadable one is a FormatError naming file and field."""
    import zipfile
    import zlib

    try:
        return z[key]
    except ValueError as exc:
        if "allow_pickle" in str(exc) or "Object arrays" in str(exc):
            raise FormatError(f"{path}: field '{key}' holds Python objects (a pickled object array), which "
                              "are not loaded; store plain numeric arrays") from None
        raise FormatError(f"{path}: field '{key}' cannot be read ({exc})") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise FormatError(f"{path}: field '{key}' cannot be read ({exc})") from None


def _recording_events(z, path: Path, keys: set[str]) -> np.ndarray:
    """The events of a training recording: ``events`` or the columns ``x``, ``y``, ``t``, ``p``."""
    if "events" in keys:
        ev = _npz_field(z, path, "events")
        if ev.dtype != EVENT_DTYPE:
            raise FormatError(f"{path}: field 'events' has dtype {ev.dtype}, expected {EVENT_DTYPE}")
        if ev.ndim != 1:
            raise FormatError(f"{path}: field 'events' has shape {ev.shape}, expected (N,)")
        return ev
    if not {"x", "y", "t", "p"} <= keys:
        raise FormatError(f"{path}: needs field 'events' or fields 'x', 'y', 't', 'p' (has {sorted(keys)})")
    from evseg.events import make_events

    t = _integer_microseconds(_npz_field(z, path, "t"), path, "t")
    try:
        return make_events(_npz_field(z, path, "x"), _npz_field(z, path, "y"), t, _npz_field(z, path, "p"))
    except EventDataError as exc:
        raise EventDataError(f"{path}: {str(exc).removeprefix('make_events: ')}") from None


def _integer_microseconds(t: np.ndarray, path: Path, key: str) -> np.ndarray:
    """Times ``t`` (field ``key`` of ``path``) as int64 microseconds; a float array (seconds,
    or any fraction) is a FormatError: casting would truncate it silently."""
    if not np.issubdtype(t.dtype, np.integer):
        # evseg's readers take float time as seconds, but this layout's time is microseconds: say so.
        raise FormatError(f"{path}: field '{key}' must be integer microseconds, got dtype {t.dtype} "
                          f"(time in seconds: store np.round({key} * 1e6).astype(np.int64))")
    beyond = np.abs(t.astype(np.float64)) > LATEST_PLAUSIBLE_US
    if beyond.any():
        i = int(np.argmax(beyond))
        raise FormatError(f"{path}: field '{key}' = {t[i]} at {i} is after the year 2100 as microseconds: "
                          f"nanoseconds? store ({key} + 500) // 1000")
    return t.astype(np.int64)


def _recording_sensor_size(size: np.ndarray, path: Path) -> tuple[int, int]:
    """``sensor_size`` as ``(width, height)``: two whole numbers > 0."""
    from evseg.events import checked_sensor_size

    if size.shape != (2,):
        raise FormatError(f"{path}: field 'sensor_size' must be [width, height], got shape {size.shape}")
    try:
        return checked_sensor_size(tuple(size.tolist()))
    except EventDataError:
        raise FormatError(f"{path}: field 'sensor_size' must be [width, height] in whole pixels > 0, "
                          f"got {size.tolist()}") from None


def _checked_flow(flow: np.ndarray, path: Path, key: str) -> np.ndarray:
    """A flow field as float32 px/s. Integer flow is refused: ground-truth optical flow is a
    float in px/s, and integers are raw encoded values (DSEC's 16-bit PNG: ``flow_px * 128 +
    2**15`` over the interval) or rounded ones."""
    if np.issubdtype(flow.dtype, np.integer) or flow.dtype == np.bool_:
        raise FormatError(f"{path}: field '{key}' has integer dtype {flow.dtype}; optical flow must be "
                          "floating point px/s (DSEC's 16-bit flow PNGs hold (value - 2**15) / 128 px over "
                          "their interval: convert a DSEC sequence with python -m evseg.train.dsec)")
    if not np.issubdtype(flow.dtype, np.floating):
        raise FormatError(f"{path}: field '{key}' must hold floating point px/s, got dtype {flow.dtype}")
    return np.asarray(flow, np.float32)


def _flow_from_maps(ev: np.ndarray, maps: np.ndarray, t_maps: np.ndarray, sensor_size: tuple[int, int],
                    path: Path) -> np.ndarray:
    """Per-event optical flow (N, 2) float32 px/s from dense maps (K, height, width, 2) that
    start at ``t_maps`` (K,) us; ``ev`` already checked to lie on the sensor."""
    w, h = sensor_size
    maps = _checked_flow(maps, path, "flow_maps")
    if t_maps.ndim != 1:
        raise FormatError(f"{path}: field 'flow_t_us' has shape {t_maps.shape}, expected (K,): one start "
                          "time per map")
    t_maps = _integer_microseconds(t_maps, path, "flow_t_us")
    if maps.ndim != 4 or maps.shape[1:] != (h, w, 2) or len(t_maps) != len(maps) or len(maps) == 0:
        raise FormatError(
            f"{path}: field 'flow_maps' has shape {maps.shape}, expected (K, {h}, {w}, 2) "
            f"with K = len(flow_t_us) = {len(t_maps)} > 0"
        )
    if np.any(np.diff(t_maps) <= 0):
        raise FormatError(f"{path}: field 'flow_t_us' must be strictly increasing")
    k = np.searchsorted(t_maps, ev["t"], side="right") - 1
    flow = np.asarray(maps[np.maximum(k, 0), ev["y"], ev["x"]], np.float32)
    flow[k < 0] = np.nan  # before the first map's time: no ground truth
    return flow


# --------------------------------------------------------------------------- shards


def save_shard(path: Path, rows: dict[str, np.ndarray]) -> None:
    """Write a shard atomically (a crash never leaves a half-written shard behind)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **rows)
    tmp.replace(path)


def load_shard(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as z:
        return {k: z[k] for k in ("features", "normal_flow", "optical_flow", "is_object")}


def _build_job(job: tuple) -> str:
    """Worker: build one shard if missing (simulated scene or user recording)."""
    kind, source, seed, duration_us, path, encoding, spec, augment = job
    path = Path(path)
    if path.exists():
        return str(path)
    if kind == "sim":
        rec = simulated_recording(SceneSpec(source, seed, duration_us))
        name = source
    else:
        rec = load_flow_recording(source)
        name = Path(source).name
    save_shard(path, recording_examples(rec, name, seed, encoding, spec, augment))
    return str(path)


def build_shards(jobs: list[tuple], num_workers: int, progress: bool = False) -> list[Path]:
    """Build missing shards, in ``num_workers`` processes (1 = in this process)."""
    todo = [j for j in jobs if not Path(j[4]).exists()]
    if todo:
        if num_workers > 1 and len(todo) > 1:
            import multiprocessing as mp

            # Each worker is single-threaded numpy/torch so that N workers use N cores.
            with mp.get_context("spawn").Pool(min(num_workers, len(todo)), initializer=_single_thread) as pool:
                it = pool.imap_unordered(_build_job, todo)
                if progress:
                    from tqdm import tqdm

                    it = tqdm(it, total=len(todo), desc="building shards")
                for _ in it:
                    pass
        else:
            for j in todo:
                _build_job(j)
    return [Path(j[4]) for j in jobs]


def _single_thread() -> None:
    # Set before numba/torch start their thread pools in this fresh (spawned) process.
    os.environ["OMP_NUM_THREADS"] = "1"
    os.environ["NUMBA_NUM_THREADS"] = "1"
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a core dependency
        pass


# --------------------------------------------------------------------------- datasets


class FlowTargetDataset:
    """In-memory rows (features + GT) with batched indexing.

    ``dataset[i]`` is one row; ``dataset.__getitems__(indices)`` (used by
    :class:`torch.utils.data.DataLoader` for a whole batch at once) returns a dict of tensors:
    ``features`` (B, F) float32, ``normal_flow`` (B, 2) and ``optical_flow`` (B, 2) float32 px/s,
    ``is_object`` (B,) float32 (1 on independently moving objects).
    """

    def __init__(self, rows: dict[str, np.ndarray]):
        self.rows = rows

    def __len__(self) -> int:
        return len(self.rows["features"])

    def __getitems__(self, indices: list[int]) -> dict:
        import torch

        idx = np.asarray(indices, dtype=np.int64)
        return {k: torch.from_numpy(np.ascontiguousarray(v[idx], dtype=np.float32)) for k, v in self.rows.items()}

    def __getitem__(self, i: int) -> dict:
        return {k: v[0] for k, v in self.__getitems__([i]).items()}


def collate_batch(batch: dict) -> dict:
    """Identity collate: :meth:`FlowTargetDataset.__getitems__` already built the batch."""
    return batch


# --------------------------------------------------------------------------- Lightning


def check_presets(presets) -> None:
    """Refuse a preset name the simulator does not ship (:class:`ConfigError` naming
    ``data.presets``) before any scene is simulated."""
    from evseg.simulator.presets import list_scene_presets

    if isinstance(presets, str) or not all(isinstance(p, str) for p in presets):
        raise ConfigError(f"data.presets must be a list of scene preset names, got {presets!r}")
    known = list_scene_presets()
    unknown = [p for p in presets if p not in known]
    if unknown:
        raise ConfigError(f"data.presets: unknown scene preset(s) {unknown}; known: {', '.join(known)}")


def _lightning_datamodule_base():
    import lightning.pytorch as pl

    return pl.LightningDataModule


class NormalFlowDataModule(_lightning_datamodule_base()):
    """LightningDataModule over simulated scenes (and optional real recordings with optical flow).

    Shards are built in :meth:`prepare_data` (once per node, in parallel worker processes) and
    loaded into memory in :meth:`setup`. Validation scenes are never augmented.

    Args:
        encoding: keyword arguments of :class:`evseg.veckm_flow.EncodingConfig` (linked to the
            model's ``encoding`` by the CLI so that both always agree).
        presets: simulator presets to draw scenes from.
        train_seeds: ``[start, stop)`` seeds of training scenes per preset (all < 1000).
        val_seeds: ``[start, stop)`` seeds of validation scenes per preset (all < 1000,
            disjoint from ``train_seeds``).
        duration_us: simulated duration of each scene, microseconds.
        slices: slicing and target selection (see :class:`SliceSpec`).
        augment: training augmentation (see :class:`~evseg.train.augment.AugmentConfig`).
        real_recordings: paths of users' recordings with GT optical flow
            (:func:`load_flow_recording`), added to the training set.
        real_repeats: augmented passes over each real recording (each a different seed).
        cache_dir: where shards are written (reused across runs with the same settings).
        batch_size: targets per optimiser step.
        build_workers: processes that build shards (default: all cores).
        num_workers: DataLoader workers (0: batches are slices of in-memory arrays).
    """

    def __init__(
        self,
        encoding: dict | None = None,
        presets: list[str] = ["eed_like", "evimo_like", "driving_like", "ego_only"],  # noqa: B006
        train_seeds: tuple[int, int] = (0, 64),
        val_seeds: tuple[int, int] = (900, 904),
        duration_us: int = 200_000,
        slices: SliceSpec = SliceSpec(),
        augment: AugmentConfig = AugmentConfig(),
        real_recordings: list[str] = [],  # noqa: B006
        real_repeats: int = 1,
        cache_dir: str = "runs/cache",
        batch_size: int = 4096,
        build_workers: int | None = None,
        num_workers: int = 0,
    ):
        super().__init__()
        train = seed_range(train_seeds, "data.train_seeds")
        val = seed_range(val_seeds, "data.val_seeds")
        check_training_seeds(train, "data.train_seeds")
        check_training_seeds(val, "data.val_seeds")
        if set(train) & set(val):
            raise ConfigError(f"data.val_seeds {val_seeds} overlap data.train_seeds {train_seeds}")
        for r in real_recordings:
            if not Path(r).is_file():
                raise ConfigError(f"data.real_recordings: file not found: {r}")
        check_presets(presets)
        check_slice_spec(slices)
        check_augment_config(augment)
        # All fields spelled out (defaults filled in): the shard key and the features then
        # never depend on defaults that may change between versions.
        self.encoding = _encoding_config(dict(encoding or {})).to_dict()
        self.presets = list(presets)
        self.train_seeds, self.val_seeds = train, val
        self.duration_us = whole_at_least(duration_us, "data.duration_us", 1)
        self.slices = slices
        self.augment = augment
        self.real_recordings = [str(r) for r in real_recordings]
        self.real_repeats = whole_at_least(real_repeats, "data.real_repeats", 1)
        self.cache_dir = Path(cache_dir)
        self.batch_size = whole_at_least(batch_size, "data.batch_size", 1)
        self.build_workers = (os.cpu_count() or 1) if build_workers is None else \
            whole_at_least(build_workers, "data.build_workers", 1)
        self.num_workers = whole_at_least(num_workers, "data.num_workers", 0)
        self.train_set: FlowTargetDataset | None = None
        self.val_set: FlowTargetDataset | None = None

    def _scene_key(self) -> dict:
        """What, besides the seeds, makes the simulated scenes: a change of the simulator's
        ground truth or of a preset must not reuse shards built before it."""
        from evseg.simulator import load_scene_preset, scene_to_dict
        from evseg.simulator.ground_truth import GROUND_TRUTH_VERSION

        return {"duration_us": self.duration_us, "simulator": GROUND_TRUTH_VERSION,
                "scenes": {p: scene_to_dict(load_scene_preset(p)) for p in self.presets}}

    def _jobs(self, train: bool) -> list[tuple]:
        augment = self.augment if train else NO_AUGMENTATION
        key = shard_key(self.encoding, self.slices, augment, self._scene_key())
        root = self.cache_dir / key
        seeds = self.train_seeds if train else self.val_seeds
        jobs = [
            ("sim", p, s, self.duration_us, str(root / f"{p}_s{s}.npz"), self.encoding, self.slices, augment)
            for p in self.presets
            for s in seeds
        ]
        if train:
            for r in self.real_recordings:
                # The file's size and modification time are in the key too: a recording fixed or
                # exported again under the same name is encoded again, not read from the cache.
                st = Path(r).stat()
                ident = f"{Path(r).resolve()}|{st.st_size}|{st.st_mtime_ns}"
                stem = hashlib.sha1(ident.encode()).hexdigest()[:8]
                for rep in range(self.real_repeats):
                    path = root / f"real_{Path(r).stem}_{stem}_r{rep}.npz"
                    jobs.append(("real", r, rep, 0, str(path), self.encoding, self.slices, augment))
        return jobs

    def check_real_recordings(self) -> None:
        """Read every real recording whose shards are not built yet (:func:`load_flow_recording`):
        a broken file fails here, in seconds and naming itself, before any shard is built
        (simulated scenes take minutes). Recordings with shards in the cache were read when
        those were built (the shard key holds the file's size and time)."""
        pending = {job[1] for job in self._jobs(True) if job[0] == "real" and not Path(job[4]).exists()}
        for r in self.real_recordings:
            if r in pending:
                load_flow_recording(r)

    def prepare_data(self) -> None:
        self.check_real_recordings()
        build_shards(self._jobs(True) + self._jobs(False), self.build_workers, progress=True)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            self.check_real_recordings()  # prepare_data may not have run (direct use, other ranks)
            self.train_set = FlowTargetDataset(concat_examples([load_shard(p) for p in build_shards(self._jobs(True), 1)]))
            self.val_set = FlowTargetDataset(concat_examples([load_shard(p) for p in build_shards(self._jobs(False), 1)]))
            if len(self.train_set) == 0:
                raise ConfigError("data: the training scenes produced no target with ground truth")
            from lightning.pytorch.utilities import rank_zero_info

            rank_zero_info(f"normal-flow data: {len(self.train_set):,} training and {len(self.val_set):,} validation targets")

    def _loader(self, ds: FlowTargetDataset, shuffle: bool):
        import torch
        from torch.utils.data import DataLoader

        return DataLoader(
            ds,
            batch_size=self.batch_size,
            shuffle=shuffle,
            drop_last=shuffle and len(ds) >= self.batch_size,
            collate_fn=collate_batch,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            pin_memory=torch.cuda.is_available(),
        )

    def train_dataloader(self):
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self):
        return self._loader(self.val_set, shuffle=False)
