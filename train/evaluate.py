"""Accuracy of the learned normal flow: held-out simulated scenes and real recordings.

Simulated (:func:`evaluate_flow`, ``evseg eval flow``): every simulator preset, seeds >= 1000
(never used in training), cut into back-to-back slices of ``slice_us`` (the pipeline's window),
each with the ``context_us`` of events before it as extra neighbours (as the pipeline does).
Targets are chosen as ``evseg flow`` chooses them (:func:`~evseg.veckm_flow.select_targets`,
latest event per ``cell_px`` cell) among events with ground-truth normal flow (noise events and
flat-gradient pixels have none). The learned model (:class:`~evseg.veckm_flow.OnnxNormalFlow`,
the shipped ONNX file by default) and the plane-fit baseline
(:class:`~evseg.veckm_flow.PlaneFitNormalFlow`) see the same slices and the same targets.

Columns (angles in degrees; "common" = the targets where the baseline gives a flow, because
it rejects some fits and the comparison must be on the same events):

- ``targets``: targets with ground truth; ``baseline_kept``: share the baseline accepts;
- ``ae_learned``: median angular error of the learned flow vs GT normal flow (all targets);
- ``ae_learned_common``, ``ae_baseline``: the same on the common targets;
- ``ae_reduction``: ``1 - ae_learned_common / ae_baseline`` (target: >= 0.30);
- ``sign_learned``, ``sign_baseline``: share with ``p . n > 0`` (common targets);
  ``sign_learned_all``: the same for the learned flow on all targets;
- ``sign_u_learned_all``: share with ``p . u > 0`` against GT optical flow ``u`` on all
  targets (VecKM_flow's sign-correct rate, method.md section 3: weaker than ``p . n > 0``,
  since every valid normal flow of ``u`` lies in ``u``'s half-plane);
- ``relmag_learned``, ``relmag_baseline``: median ``| |p| - |n| | / |n|`` (common targets);
- ``normerr_learned``, ``normerr_baseline``: median VecKM_flow norm error
  ``| |p| - (p . u) / |p| |`` against GT optical flow ``u``, px/s (common targets);
- ``ae_learned_keep80``: median angular error of the 80 % least uncertain learned flows;
  ``uncertainty_gain``: ``1 - ae_learned_keep80 / ae_learned`` (target: >= 0.25);
- ``sign_learned_keep80``: sign-correct share (``p . n > 0``) of the same 80 % least uncertain
  flows: what a user who drops the most uncertain fifth gets (issue 3's sign-correct target is
  on all targets, ``sign_learned_all``).

The ``overall`` row pools the targets of all presets.

Real recordings without ground truth (:func:`evaluate_flow_real`, ``evseg eval flow-real``):
the label-free warp sharpness (:func:`evseg.metrics.warp_sharpness`: variance of the smoothed
image of events moved along their flow to the window's middle, over that of the unmoved
events) of both estimators over 30 ms windows, every event with its own flow (three 10 ms
slices, each with the context the pipeline gives), on the events where both give a flow;
median over windows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from evseg.metrics import angular_error_deg, norm_error, relative_magnitude_error, warp_sharpness

HELD_OUT_SEED_START = 1000
VALIDATION_SEED_START = 900
"""Seeds 900-999: the training configs' validation scenes (``data.val_seeds``), which
``evseg eval flow --seeds`` may use to compare models without looking at the held-out ones."""

SHIPPED_MODEL_TRAIN_SEEDS = (0, 144)
"""The scene seeds the shipped model was trained on, ``[start, stop)`` of each preset: what
``configs/train/default.yaml``'s ``data.train_seeds`` reads (a test checks they agree)."""


@dataclass(frozen=True)
class FlowEvalConfig:
    """What :func:`evaluate_flow` runs on.

    Attributes:
        presets: simulator presets (empty: all of :func:`evseg.simulator.list_scene_presets`).
        seeds: scene seeds per preset (>= 1000: held out from training, the default;
            900-999: validation).
        duration_us: simulated duration per scene, microseconds.
        slice_us: slice duration, microseconds (the pipeline's 10 ms window).
        context_us: events of this span before a slice are neighbours of its targets too,
            for both estimators (the pipeline's ``flow_context_us``).
        cell_px: target selection cell, px (as ``evseg flow``).
        max_targets_per_slice: uniform subsample per slice (bounds the run time).
        drop_fraction: share of most uncertain learned flows dropped for ``ae_learned_keep80``.
    """

    presets: tuple[str, ...] = ()
    seeds: tuple[int, ...] = (1000, 1001, 1002, 1003)
    duration_us: int = 200_000
    slice_us: int = 10_000
    context_us: int = 20_000
    cell_px: int = 2
    max_targets_per_slice: int = 2000
    drop_fraction: float = 0.2

    def __post_init__(self) -> None:
        bad = [s for s in self.seeds if s < VALIDATION_SEED_START]
        if bad:
            raise ValueError(f"evaluation seeds must be >= {VALIDATION_SEED_START} (validation {VALIDATION_SEED_START}-"
                             f"{HELD_OUT_SEED_START - 1}, held out from {HELD_OUT_SEED_START}; the training configs "
                             f"train on lower seeds), got {bad}")


QUICK = FlowEvalConfig(seeds=(1000,), duration_us=60_000)


@dataclass
class _Collected:
    """Per-target arrays of one preset (learned, baseline, ground truth)."""

    learned: list = field(default_factory=list)  # (T, 2) px/s
    uncertainty: list = field(default_factory=list)  # (T,)
    baseline: list = field(default_factory=list)  # (T, 2) px/s, NaN where rejected
    normal_flow: list = field(default_factory=list)  # (T, 2) px/s
    optical_flow: list = field(default_factory=list)  # (T, 2) px/s

    def arrays(self) -> dict[str, np.ndarray]:
        def cat(v, shape):
            return np.concatenate(v) if v else np.zeros(shape, np.float32)

        return {
            "learned": cat(self.learned, (0, 2)),
            "uncertainty": cat(self.uncertainty, (0,)),
            "baseline": cat(self.baseline, (0, 2)),
            "normal_flow": cat(self.normal_flow, (0, 2)),
            "optical_flow": cat(self.optical_flow, (0, 2)),
        }


def _median(v: np.ndarray) -> float:
    return float(np.median(v)) if len(v) else float("nan")


def flow_accuracy_row(a: dict[str, np.ndarray], drop_fraction: float = 0.2) -> dict:
    """Metrics of one set of targets (see the module docstring for the columns).

    Args:
        a: ``learned``, ``baseline``, ``normal_flow``, ``optical_flow`` (T, 2) px/s and
            ``uncertainty`` (T,); baseline rows are NaN where it rejected the target.
    """
    p, b, n, u = a["learned"], a["baseline"], a["normal_flow"], a["optical_flow"]
    common = np.all(np.isfinite(b), axis=1)
    ae = angular_error_deg(p, n)
    ae_b = angular_error_deg(b[common], n[common])
    keep = np.ones(len(p), bool)
    if len(p):
        # Drop the most uncertain share: keep the flows whose uncertainty ranks below it.
        order = np.argsort(a["uncertainty"], kind="stable")
        keep[:] = False
        keep[order[: int(round((1.0 - drop_fraction) * len(p)))]] = True
    ae_all = _median(ae)
    ae_keep = _median(ae[keep])
    ae_common = _median(ae[common])
    ae_base = _median(ae_b)

    def sign(x, y):
        return float(np.mean(np.sum(x * y, axis=1) > 0)) if len(x) else float("nan")

    return {
        "targets": int(len(p)),
        "baseline_kept": float(np.mean(common)) if len(p) else float("nan"),
        "ae_learned": ae_all,
        "ae_learned_common": ae_common,
        "ae_baseline": ae_base,
        "ae_reduction": 1.0 - ae_common / ae_base if ae_base > 0 else float("nan"),
        "sign_learned": sign(p[common], n[common]),
        "sign_baseline": sign(b[common], n[common]),
        "sign_learned_all": sign(p, n),
        "sign_u_learned_all": sign(p, u),
        "relmag_learned": _median(relative_magnitude_error(p[common], n[common])),
        "relmag_baseline": _median(relative_magnitude_error(b[common], n[common])),
        "normerr_learned": _median(norm_error(p[common], u[common])),
        "normerr_baseline": _median(norm_error(b[common], u[common])),
        "ae_learned_keep80": ae_keep,
        "uncertainty_gain": 1.0 - ae_keep / ae_all if ae_all > 0 else float("nan"),
        "sign_learned_keep80": sign(p[keep], n[keep]),
    }


Estimator = Callable[..., object]
"""``est(events, sensor_size, targets) -> NormalFlow`` (index, nx, ny, uncertainty)."""


def context_before(events: np.ndarray, first: int, t0_us: int, context_us: int) -> np.ndarray:
    """The events with ``t0_us - context_us <= t`` before position ``first`` (a slice's start):
    the neighbours-only context the pipeline gives a window (empty for ``context_us = 0``)."""
    if context_us <= 0:
        return events[first:first]
    return events[int(np.searchsorted(events["t"], t0_us - context_us, side="left")) : first]


def _history_before(est: Estimator, events: np.ndarray, t0_us: int, slice_us: int, context_us: int) -> np.ndarray | None:
    """The events before the context of a slice starting at ``t0_us`` that the estimator's
    slow-edge look wants (as ``evseg flow`` and the pipeline give them), or None when it wants
    none."""
    from evseg.veckm_flow.context import history_span_us

    span = history_span_us(est, slice_us + context_us)
    if span == 0:
        return None
    t_ctx = t0_us - context_us
    a, b = np.searchsorted(events["t"], [t_ctx - span, t_ctx], side="left")
    return events[int(a) : int(b)]


def _flows(
    est: Estimator, events: np.ndarray, sensor_size, targets: np.ndarray, context: np.ndarray | None = None,
    history: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    from evseg.veckm_flow.context import flow_with_context

    res = flow_with_context(est, events, sensor_size, targets, context, history=history)
    if not np.array_equal(np.asarray(res.index), targets):
        raise RuntimeError("estimator returned flows for other events than the targets it was given")
    return np.stack([res.nx, res.ny], axis=1).astype(np.float64), np.asarray(res.uncertainty, np.float64)


def collect_scene(rec, learned: Estimator, baseline: Estimator, cfg: FlowEvalConfig, out: _Collected) -> None:
    """Run both estimators on the slices of one simulated recording; append to ``out``."""
    from evseg.veckm_flow.targets import select_targets

    ev = rec.stream.events
    sensor = rec.stream.sensor_size
    nf_all = np.asarray(rec.normal_flow, np.float64)
    of_all = np.asarray(rec.flow, np.float64)
    t = ev["t"]
    if len(ev) == 0:
        return
    for k, t0 in enumerate(range(int(t[0]), int(t[-1]) + 1, cfg.slice_us)):
        a, b = np.searchsorted(t, [t0, t0 + cfg.slice_us])
        if b - a < 2:
            continue
        e, nf, of = ev[a:b], nf_all[a:b], of_all[a:b]
        idx = select_targets(e, sensor, cell_px=cfg.cell_px)
        ok = np.all(np.isfinite(nf[idx]), axis=1) & (np.linalg.norm(np.nan_to_num(nf[idx]), axis=1) > 0)
        idx = idx[ok]
        if len(idx) > cfg.max_targets_per_slice:
            rng = np.random.default_rng([int(t0), k])
            idx = np.sort(rng.choice(idx, cfg.max_targets_per_slice, replace=False))
        if len(idx) == 0:
            continue
        context = context_before(ev, int(a), t0, cfg.context_us)
        history = _history_before(learned, ev, t0, cfg.slice_us, cfg.context_us)
        p, unc = _flows(learned, e, sensor, idx, context, history)
        bflow, _ = _flows(baseline, e, sensor, idx, context)
        out.learned.append(p)
        out.uncertainty.append(unc)
        out.baseline.append(bflow)
        out.normal_flow.append(nf[idx])
        out.optical_flow.append(of[idx])


def evaluate_estimators(learned: Estimator, baseline: Estimator, cfg: FlowEvalConfig) -> list[dict]:
    """Rows per preset and an ``overall`` row (pooled targets) for two estimators."""
    from evseg.simulator import list_scene_presets, load_scene_preset, simulate

    presets = list(cfg.presets) or list(list_scene_presets())
    rows, pooled = [], _Collected()
    for preset in presets:
        col = _Collected()
        for seed in cfg.seeds:
            rec = simulate(load_scene_preset(preset), seed=seed, duration_us=cfg.duration_us)
            collect_scene(rec, learned, baseline, cfg, col)
        rows.append({"preset": preset, **flow_accuracy_row(col.arrays(), cfg.drop_fraction)})
        for name in ("learned", "uncertainty", "baseline", "normal_flow", "optical_flow"):
            getattr(pooled, name).extend(getattr(col, name))
    rows.append({"preset": "overall", **flow_accuracy_row(pooled.arrays(), cfg.drop_fraction)})
    return rows


def _estimators(model_path: str | Path | None, mirrors: int = 1):
    from evseg.veckm_flow.baseline import PlaneFitNormalFlow
    from evseg.veckm_flow.inference import OnnxNormalFlow

    return OnnxNormalFlow(model_path, mirrors=mirrors), PlaneFitNormalFlow()


def evaluate_flow(quick: bool = False, model_path: str | Path | None = None, mirrors: int = 1,
                  seeds=None, presets=None) -> list[dict]:
    """``evseg eval flow``: learned (shipped model by default; ``mirrors``: its mirror looks,
    ``evseg flow --mirrors``) vs plane fit on held-out scenes; ``seeds`` / ``presets``: other
    scenes (``--seeds 900-903``: the training configs' validation scenes)."""
    from dataclasses import replace

    from evseg.segmentation.evaluate import check_presets
    from evseg.simulator import list_scene_presets

    cfg = QUICK if quick else FlowEvalConfig()
    if seeds is not None:
        cfg = replace(cfg, seeds=tuple(int(s) for s in seeds))
    if presets is not None:
        cfg = replace(cfg, presets=tuple(check_presets(presets, list_scene_presets(), "evseg eval flow")))
    learned, baseline = _estimators(model_path, mirrors)
    return evaluate_estimators(learned, baseline, cfg)


# --------------------------------------------------------------------------- real recordings

REAL_RECORDINGS = (
    "ecd_poster/poster_translation.npz",
    "dvs128_single_motion/building.mat",
    "dvs128_single_motion/stripes.mat",
    "eed_what_is_background/events_t_us_x_y_on.npy",
)
"""Recordings under the shared data folder (``EVSEG_SHARED_DATA`` or ``../shared/data``)."""


def shared_data_dir() -> Path:
    """The folder of the shared real recordings: ``EVSEG_SHARED_DATA``, else ``../shared/data``
    beside the repository (a pip install has no such neighbour: set the variable)."""
    import os

    env = os.environ.get("EVSEG_SHARED_DATA")
    if env:
        return Path(env)
    return (Path(__file__).resolve().parents[1] / ".." / "shared" / "data").resolve()


def missing_shared_data_message(root: Path) -> str:
    """The error for a shared data folder that is not there."""
    return (f"real recordings not found at {root}: set EVSEG_SHARED_DATA to the folder that holds them "
            f"({', '.join(sorted({r.split('/')[0] for r in REAL_RECORDINGS}))}, ...; by default ../shared/data "
            "beside a repository checkout)")


def recording_slices(events: np.ndarray, slice_us: int, max_slices: int) -> list[tuple[int, int]]:
    """``(start, stop)`` event positions of up to ``max_slices`` back-to-back slices, spread
    evenly over the recording (every k-th slice)."""
    t = events["t"]
    if len(t) == 0:
        return []
    starts = np.arange(int(t[0]), int(t[-1]) + 1, slice_us)
    bounds = [tuple(int(v) for v in np.searchsorted(t, [s, s + slice_us])) for s in starts]
    bounds = [b for b in bounds if b[1] - b[0] >= 100]  # too few events to judge sharpness
    if len(bounds) > max_slices:
        pick = np.linspace(0, len(bounds) - 1, max_slices).round().astype(int)
        bounds = [bounds[i] for i in pick]
    return bounds


def sharpness_of_window(
    events: np.ndarray, t0_us: int, sensor_size, learned: Estimator, baseline: Estimator,
    slice_us: int = 10_000, n_slices: int = 3, context_us: int = FlowEvalConfig.context_us,
) -> tuple[float, float, int]:
    """Warp sharpness of learned and baseline flow over ``n_slices`` back-to-back slices of
    ``slice_us`` from ``t0_us`` (us), and the number of events
    both estimate. Each slice's events all get a flow, with ``context_us`` of events before
    the slice as neighbours (and the history the learned flow's slow-edge look needs), as in
    the pipeline; the window's events are then warped to its middle."""
    t = events["t"]
    learned_parts, baseline_parts = [], []
    for k in range(n_slices):
        s0 = t0_us + k * slice_us
        a, b = (int(v) for v in np.searchsorted(t, [s0, s0 + slice_us]))
        e = events[a:b]
        if len(e) == 0:
            continue
        targets = np.arange(len(e))
        context = context_before(events, a, s0, context_us)
        history = _history_before(learned, events, s0, slice_us, context_us)
        learned_parts.append(_flows(learned, e, sensor_size, targets, context, history)[0])
        baseline_parts.append(_flows(baseline, e, sensor_size, targets, context)[0])
    if not learned_parts:
        return float("nan"), float("nan"), 0
    p, b = np.concatenate(learned_parts), np.concatenate(baseline_parts)
    first, stop = (int(v) for v in np.searchsorted(t, [t0_us, t0_us + n_slices * slice_us]))
    e = events[first:stop]  # the slices' events, back to back
    ok = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(b), axis=1)
    x, y, te = e["x"][ok], e["y"][ok], e["t"][ok]
    shape = (sensor_size[1], sensor_size[0])
    t_ref = t0_us + 0.5 * n_slices * slice_us
    return (warp_sharpness(x, y, te, p[ok], shape, t_ref), warp_sharpness(x, y, te, b[ok], shape, t_ref),
            int(ok.sum()))


def evaluate_estimators_real(
    learned: Estimator, baseline: Estimator, root: Path, slice_us: int = 10_000, n_slices: int = 3,
    max_windows: int = 20, context_us: int = FlowEvalConfig.context_us,
) -> list[dict]:
    """Rows per real recording: median warp sharpness of both estimators over up to
    ``max_windows`` windows of ``n_slices`` x ``slice_us`` spread over it
    (:func:`sharpness_of_window`)."""
    from evseg.io import read_events

    rows = []
    for rel in REAL_RECORDINGS:
        path = root / rel
        if not path.is_file():
            continue
        stream = read_events(path)
        ls, bs, n = [], [], 0
        for a, _ in recording_slices(stream.events, n_slices * slice_us, max_windows):
            t0 = int(stream.events["t"][a])
            sl, sb, k = sharpness_of_window(stream.events, t0, stream.sensor_size, learned, baseline,
                                            slice_us, n_slices, context_us)
            if np.isfinite(sl) and np.isfinite(sb):
                ls.append(sl)
                bs.append(sb)
                n += k
        rows.append({
            "recording": rel,
            "windows": len(ls),
            "events": n,
            "sharpness_learned": _median(np.array(ls)),
            "sharpness_baseline": _median(np.array(bs)),
            "learned_sharper_share": float(np.mean(np.array(ls) >= np.array(bs))) if ls else float("nan"),
        })
    return rows


def evaluate_flow_real(quick: bool = False, model_path: str | Path | None = None, mirrors: int = 1) -> list[dict]:
    """``evseg eval flow-real``: label-free warp sharpness on the shared real recordings
    (``mirrors``: the learned flow's mirror looks)."""
    from evseg.errors import EvsegError

    root = shared_data_dir()
    if not root.is_dir():
        raise EvsegError(missing_shared_data_message(root))
    learned, baseline = _estimators(model_path, mirrors)
    return evaluate_estimators_real(learned, baseline, root, max_windows=5 if quick else 20)


# --------------------------------------------------------------------------- pictures


def flow_colors(flow_px_s: np.ndarray, max_px_s: float) -> np.ndarray:
    """Colour-wheel BGR uint8 (T, 3): hue = direction (x right, y down), value = speed
    (saturating at ``max_px_s``)."""
    import cv2

    ang = (np.degrees(np.arctan2(flow_px_s[:, 1], flow_px_s[:, 0])) % 360.0) / 2.0  # OpenCV hue 0..180
    mag = np.clip(np.linalg.norm(flow_px_s, axis=1) / max(max_px_s, 1e-9), 0, 1)
    hsv = np.stack([ang, np.full_like(ang, 255), 80 + 175 * mag], axis=1).astype(np.uint8)
    return cv2.cvtColor(hsv[None], cv2.COLOR_HSV2BGR)[0]


def color_wheel(size: int) -> np.ndarray:
    """A BGR legend of the colour wheel, ``(size, size, 3)`` (black outside the disc)."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    c = (size - 1) / 2.0
    f = np.stack([(xx - c).ravel(), (yy - c).ravel()], axis=1)
    img = flow_colors(f, c).reshape(size, size, 3)
    img[np.hypot(xx - c, yy - c) > c] = 0
    return img


def flow_picture(events: np.ndarray, sensor_size, flows: dict[str, np.ndarray], scale: int = 2) -> np.ndarray:
    """Side-by-side colour-wheel images of several flows of the same target events.

    Args:
        events: the target events (T,) of one slice.
        flows: name -> (T, 2) px/s (NaN rows are not drawn).
        scale: integer upscaling of each panel (small sensors).

    Returns:
        BGR uint8 image: one panel per flow with its name and a colour-wheel legend.
    """
    import cv2

    w, h = sensor_size
    finite = [f[np.all(np.isfinite(f), axis=1)] for f in flows.values()]
    speeds = np.concatenate([np.linalg.norm(f, axis=1) for f in finite]) if finite else np.zeros(0)
    vmax = float(np.percentile(speeds, 95)) if len(speeds) else 1.0
    panels = []
    for name, f in flows.items():
        img = np.zeros((h, w, 3), np.uint8)
        ok = np.all(np.isfinite(f), axis=1)
        img[events["y"][ok], events["x"][ok]] = flow_colors(f[ok], vmax)
        img = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
        legend = color_wheel(max(24, 12 * scale))
        img[: legend.shape[0], -legend.shape[1]:] = legend
        cv2.putText(img, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(img)
    sep = np.full((h * scale, 4, 3), 255, np.uint8)
    out = panels[0]
    for p in panels[1:]:
        out = np.concatenate([out, sep, p], axis=1)
    return out


def save_real_pictures(
    out_dir: str | Path, model_path: str | Path | None = None, slice_us: int = 10_000,
    context_us: int = FlowEvalConfig.context_us,
) -> list[Path]:
    """Write ``flow_<recording>.png`` per shared real recording (learned | plane fit) into
    ``out_dir``, from the middle slice of each recording (with ``context_us`` of events before
    it as neighbours, as the pipeline). Returns the paths written."""
    import cv2

    from evseg.io import read_events
    from evseg.veckm_flow.targets import select_targets

    learned, baseline = _estimators(model_path)
    root = shared_data_dir()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for rel in REAL_RECORDINGS:
        path = root / rel
        if not path.is_file():
            continue
        stream = read_events(path)
        bounds = recording_slices(stream.events, slice_us, 10**9)
        if not bounds:
            continue
        a, b = bounds[len(bounds) // 2]
        e = stream.events[a:b]
        context = context_before(stream.events, a, int(e["t"][0]), context_us)
        history = _history_before(learned, stream.events, int(e["t"][0]), slice_us, context_us)
        idx = select_targets(e, stream.sensor_size, cell_px=1)
        p, _ = _flows(learned, e, stream.sensor_size, idx, context, history)
        q, _ = _flows(baseline, e, stream.sensor_size, idx, context)
        scale = 3 if max(stream.sensor_size) <= 128 else 2
        img = flow_picture(e[idx], stream.sensor_size, {"learned": p, "plane fit": q}, scale=scale)
        name = f"flow_{Path(rel).parent.name}_{Path(rel).stem}.png"
        cv2.imwrite(str(out_dir / name), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        written.append(out_dir / name)
    return written
