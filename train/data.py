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

from evseg.errors import ConfigError, FormatError
from evseg.events import EVENT_DTYPE
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
    - ``sensor_size``: ``[width, height]``;
    - flow, one of
        * ``flow``: (N, 2) per-event optical flow, or
        * ``flow_maps``: (K, height, width, 2) dense optical flow and ``flow_t_us``: (K,)
          increasing start times; map k applies to events with
          ``flow_t_us[k] <= t < flow_t_us[k+1]`` (the last map to the end; events before
          ``flow_t_us[0]`` have no ground truth). DSEC's forward
          flow (a displacement in px over the interval dt) becomes px/s by dividing by dt;
          EVIMO2's per-frame flow the same way.

    Raises:
        FormatError: a missing key, a field of the wrong shape or dtype (the message names
            both), or no event with a finite flow.
    """
    path = Path(path)
    try:
        z = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable .npz file ({exc})") from None
    with z:
        keys = set(z.files)
        if "events" in keys:
            ev = z["events"]
            if ev.dtype != EVENT_DTYPE:
                raise FormatError(f"{path}: field 'events' has dtype {ev.dtype}, expected {EVENT_DTYPE}")
        elif {"x", "y", "t", "p"} <= keys:
            from evseg.events import make_events

            t = z["t"]
            if not np.issubdtype(t.dtype, np.integer):
                # Casting would truncate seconds (or any fraction) silently; evseg's readers take
                # float time as seconds, but this layout's time is microseconds: say so.
                raise FormatError(f"{path}: field 't' must be integer microseconds, got dtype {t.dtype} "
                                  "(time in seconds: store np.round(t * 1e6).astype(np.int64))")
            ev = make_events(z["x"], z["y"], t.astype(np.int64), z["p"])
        else:
            raise FormatError(f"{path}: needs field 'events' or fields 'x', 'y', 't', 'p' (has {sorted(keys)})")
        if "sensor_size" not in keys or z["sensor_size"].shape != (2,):
            raise FormatError(f"{path}: field 'sensor_size' must be [width, height]")
        w, h = (int(v) for v in z["sensor_size"])
        n = len(ev)
        if "flow" in keys:
            flow = np.asarray(z["flow"], np.float32)
            if flow.shape != (n, 2):
                raise FormatError(f"{path}: field 'flow' has shape {flow.shape}, expected ({n}, 2)")
        elif "flow_maps" in keys and "flow_t_us" in keys:
            maps, t_maps = z["flow_maps"], np.asarray(z["flow_t_us"], np.int64)
            if maps.ndim != 4 or maps.shape[1:] != (h, w, 2) or len(t_maps) != len(maps):
                raise FormatError(
                    f"{path}: field 'flow_maps' has shape {maps.shape}, expected (K, {h}, {w}, 2) "
                    f"with K = len(flow_t_us) = {len(t_maps)}"
                )
            if np.any(np.diff(t_maps) <= 0):
                raise FormatError(f"{path}: field 'flow_t_us' must be strictly increasing")
            k = np.searchsorted(t_maps, ev["t"], side="right") - 1
            flow = np.asarray(maps[np.maximum(k, 0), ev["y"], ev["x"]], np.float32)
            flow[k < 0] = np.nan  # before the first map's time: no ground truth
        else:
            raise FormatError(f"{path}: needs field 'flow' (N, 2) or fields 'flow_maps' and 'flow_t_us'")
    from evseg.events import validate_events

    validate_events(ev, (w, h), source=str(path))
    if not np.isfinite(flow).all(axis=1).any():
        raise FormatError(f"{path}: no event has a finite ground-truth flow (every 'flow' row is NaN), "
                          "so the recording adds nothing to training")
    return FlowSlice(ev, (w, h), None, flow)


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
        train = list(range(*train_seeds))
        val = list(range(*val_seeds))
        check_training_seeds(train, "data.train_seeds")
        check_training_seeds(val, "data.val_seeds")
        if set(train) & set(val):
            raise ConfigError(f"data.val_seeds {val_seeds} overlap data.train_seeds {train_seeds}")
        for r in real_recordings:
            if not Path(r).is_file():
                raise ConfigError(f"data.real_recordings: file not found: {r}")
        # All fields spelled out (defaults filled in): the shard key and the features then
        # never depend on defaults that may change between versions.
        self.encoding = _encoding_config(dict(encoding or {})).to_dict()
        self.presets = list(presets)
        self.train_seeds, self.val_seeds = train, val
        self.duration_us = int(duration_us)
        self.slices = slices
        self.augment = augment
        self.real_recordings = [str(r) for r in real_recordings]
        self.real_repeats = int(real_repeats)
        self.cache_dir = Path(cache_dir)
        self.batch_size = int(batch_size)
        self.build_workers = build_workers or os.cpu_count() or 1
        self.num_workers = int(num_workers)
        self.train_set: FlowTargetDataset | None = None
        self.val_set: FlowTargetDataset | None = None

    def _jobs(self, train: bool) -> list[tuple]:
        augment = self.augment if train else NO_AUGMENTATION
        key = shard_key(self.encoding, self.slices, augment, {"duration_us": self.duration_us})
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

    def prepare_data(self) -> None:
        build_shards(self._jobs(True) + self._jobs(False), self.build_workers, progress=True)

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
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
