"""Saving and loading simulated recordings (one ``.npz``).

Layout (all plain arrays, readable without evseg): ``events`` (structured array of
:data:`~evseg.events.EVENT_DTYPE`, so evseg's npz reader reads the file as an ordinary recording),
``label`` int16 (N,), ``flow`` and ``normal_flow`` float32 (N, 2) px/s, ``object_ids`` int32,
``sensor_size`` (width, height), ``seed``, ``duration_us``, ``scene_config`` (JSON text) and
``format`` (``"evseg-sim-1"``), and ``ground_truth_version`` (the simulator's labelling rule,
:data:`~evseg.simulator.ground_truth.GROUND_TRUTH_VERSION`; files written before 2026-12-05 have
none and are version 1, which gave objects' rim events to the background). Masks and boxes are
not stored: they are re-rendered exactly from the scene config, seed and duration.
"""

from __future__ import annotations

import json
import warnings
import zipfile
from pathlib import Path

import numpy as np

from evseg.errors import FormatError
from evseg.events import EVENT_DTYPE, EventStream, validate_events
from evseg.simulator.ground_truth import GROUND_TRUTH_VERSION
from evseg.simulator.recording import SimulatedRecording
from evseg.simulator.scene import scene_from_dict, scene_to_json

FORMAT = "evseg-sim-1"
_OLDER = {1: "an object's anti-aliased rim was labelled background, with the background's flow"}
"""What each earlier ground-truth version got wrong, for the warning on loading it."""
_KEYS = ("events", "label", "flow", "normal_flow", "object_ids", "sensor_size", "seed", "duration_us", "scene_config", "format")


def save_recording(rec: SimulatedRecording, path: str | Path) -> Path:
    """Write ``rec`` to ``path`` (.npz, compressed) atomically: a temporary file in the same
    folder is renamed over the target, so a crash never leaves a half-written file."""
    from evseg.io._atomic import atomic_path

    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # the usual permissions, not mkstemp's 0600
        np.savez_compressed(
            fh,
            events=rec.stream.events,
            label=rec.label,
            flow=rec.flow,
            normal_flow=rec.normal_flow,
            object_ids=np.asarray(rec.object_ids, np.int32),
            sensor_size=np.asarray(rec.stream.sensor_size, np.int64),
            seed=np.int64(rec.seed),
            duration_us=np.int64(rec.duration_us),
            scene_config=np.array(scene_to_json(rec.config)),
            format=np.array(FORMAT),
            ground_truth_version=np.int64(rec.ground_truth_version),
        )
    return path


def load_recording(path: str | Path) -> SimulatedRecording:
    """Read a file written by :func:`save_recording`; FormatError naming the file and the
    missing or malformed entry otherwise."""
    from evseg.io.numpy_files import require_npz

    path = Path(path)
    if not path.exists():
        raise FormatError(f"{path}: no such file")
    # Not numpy's "pickled data" advice for a file that is no .npz at all.
    require_npz(path, "simulated recording", ", as evseg simulate --out writes")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise FormatError(f"{path}: not a readable .npz file ({exc})") from None
    with data:
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise FormatError(f"{path}: expected an .npz archive of a simulated recording")
        missing = [k for k in _KEYS if k not in data.files]
        if missing:
            raise FormatError(f"{path}: not a simulated recording: entry '{missing[0]}' is missing")
        try:
            arrays = {k: data[k] for k in _KEYS}
            version = data["ground_truth_version"] if "ground_truth_version" in data.files else np.int64(1)
        except (ValueError, OSError, zipfile.BadZipFile, EOFError) as exc:
            raise FormatError(f"{path}: corrupt entry ({exc})") from None
    if str(arrays["format"]) != FORMAT:
        raise FormatError(f"{path}: entry 'format' is {str(arrays['format'])!r}, expected {FORMAT!r}")
    events = arrays["events"]
    n = len(events)
    validate_events(events, tuple(int(v) for v in arrays["sensor_size"]), source=f"{path}: events")
    for k, shape, dtype in (("label", (n,), np.int16), ("flow", (n, 2), np.float32), ("normal_flow", (n, 2), np.float32)):
        if arrays[k].shape != shape or arrays[k].dtype != dtype:
            raise FormatError(f"{path}: entry '{k}' has shape {arrays[k].shape} {arrays[k].dtype}, expected {shape} {np.dtype(dtype)}")
    try:
        cfg = scene_from_dict(json.loads(str(arrays["scene_config"])), source=f"{path}: scene_config")
    except json.JSONDecodeError as exc:
        raise FormatError(f"{path}: entry 'scene_config' is not valid JSON ({exc.msg} at position {exc.pos})") from None
    w, h = (int(v) for v in arrays["sensor_size"])
    if version.shape != () or version.dtype.kind not in "iu" or not 1 <= int(version) <= GROUND_TRUTH_VERSION:
        raise FormatError(f"{path}: entry 'ground_truth_version' is {version!r}, expected a whole number from 1 to "
                          f"{GROUND_TRUTH_VERSION} (a file of a newer evseg?)")
    version = int(version)
    if version < GROUND_TRUTH_VERSION:
        warnings.warn(f"{path}: simulated with ground-truth version {version}, before the current {GROUND_TRUTH_VERSION}: "
                      f"{_OLDER.get(version, 'its labels follow an older rule')}. Simulate it again (same config and seed: "
                      f"evseg simulate --config ... --seed {int(arrays['seed'])}) for the current labels", stacklevel=2)
    return SimulatedRecording(
        stream=EventStream(events.astype(EVENT_DTYPE, copy=False), (w, h)),
        label=arrays["label"],
        flow=arrays["flow"],
        normal_flow=arrays["normal_flow"],
        object_ids=[int(i) for i in arrays["object_ids"]],
        config=cfg,
        seed=int(arrays["seed"]),
        duration_us=int(arrays["duration_us"]),
        ground_truth_version=version,
    )
