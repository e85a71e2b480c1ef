"""`evseg eval flow-errors`: which error of the learned normal flow costs detection.

Each simulated scene is segmented once as the pipeline runs (learned flow), keeping every
window's learned flows with their uncertainty; then the same targets are segmented again
(``flow="precomputed"``) with flows that mix the learned estimate and the simulator's ground
truth, so that each row changes one thing:

- ``learned, fed back``: the learned flows themselves, all of them (feeding them back gives the
  pipeline's own result: a check of the comparison);
- ``ground truth``: the ground-truth normal flow, no uncertainty;
- ``ground truth + learned uncertainty``: what the uncertainty's widening of the residual scale
  costs on its own;
- ``true direction, learned speed`` and ``learned direction, true speed``: which half of the
  flow's error matters;
- ``exact optical flow``: the simulator's optical flow on the same targets (each optical flow is
  a normal flow along its own direction), no uncertainty.

Targets without ground truth are left out of the other fed-back rows alike. Rows are pooled per
preset (detection, IoU, windows with a false object, as ``evseg eval pipeline``).
"""

from __future__ import annotations

import numpy as np

from evseg.metrics import summarize
from evseg.pipeline_eval import SEGMENTATION_PRESET, score_result, summary_row

FLOW_VARIANTS = ("learned", "learned, fed back", "ground truth", "ground truth + learned uncertainty",
                 "true direction, learned speed", "learned direction, true speed", "exact optical flow")


def learned_flows(pipe, rec) -> tuple[list, dict[str, np.ndarray]]:
    """Run ``pipe`` (learned or plane-fit flow, no overlap) over ``rec``: its window results and
    every window's flows as one flow dict (``index`` into the recording, ``nx``, ``ny`` px/s,
    ``uncertainty``)."""
    flows = []
    estimate = pipe._flow_fn

    def keep(events, *args, **kwargs):
        flow = estimate(events, *args, **kwargs)
        flows.append(flow)
        return flow

    pipe._flow_fn = keep
    try:
        results = list(pipe.run(rec.stream))
    finally:
        pipe._flow_fn = estimate
    parts = [(r.first_event + f.index, f.nx, f.ny, f.uncertainty) for r, f in zip(results, flows)]
    index, nx, ny, unc = (np.concatenate(a) for a in zip(*parts)) if parts else (np.empty(0),) * 4
    return results, {"index": index.astype(np.int64), "nx": nx, "ny": ny, "uncertainty": unc}


def flow_variants(rec, learned: dict[str, np.ndarray]) -> dict[str, dict[str, np.ndarray]]:
    """The fed-back flows of :data:`FLOW_VARIANTS` (all but ``learned``): the learned flows as
    they are, and the others on the learned flow's targets that have a ground-truth normal and
    optical flow."""
    gt_n, gt_o = rec.normal_flow[learned["index"]], rec.flow[learned["index"]]
    ln = np.stack([learned["nx"], learned["ny"]], -1).astype(np.float64)
    ls, gs = np.hypot(*ln.T), np.hypot(*gt_n.T)
    ok = np.isfinite(gt_n[:, 0]) & np.isfinite(gt_o[:, 0]) & np.isfinite(ls) & (gs > 0) & (ls > 0)
    ln, gn, go, ls, gs = ln[ok], gt_n[ok], gt_o[ok], ls[ok], gs[ok]
    unc = learned["uncertainty"][ok]
    flows = {
        "ground truth": (gn, None),
        "ground truth + learned uncertainty": (gn, unc),
        "true direction, learned speed": (gn / gs[:, None] * ls[:, None], unc),
        "learned direction, true speed": (ln / ls[:, None] * gs[:, None], unc),
        "exact optical flow": (go, None),
    }
    out = {"learned, fed back": dict(learned)}
    for name, (f, u) in flows.items():
        d = {"index": learned["index"][ok], "nx": f[:, 0].astype(np.float32), "ny": f[:, 1].astype(np.float32)}
        if u is not None:
            d["uncertainty"] = u
        out[name] = d
    return out


def evaluate_flow_errors(quick: bool = False, seeds=None, presets=None, overrides: dict | None = None,
                         model_path: str | None = None) -> list[dict]:
    """One row per preset and variant (:data:`FLOW_VARIANTS`), pooled over ``seeds`` (default:
    the held-out 1000-1007, 300 ms each; quick: 1000-1001, 100 ms). ``presets``: simulator
    presets with objects (default EED-like, EVIMO-like, driving-like). ``overrides``:
    :class:`~evseg.segmentation.SegmentationConfig` fields set on every preset."""
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
    from evseg.segmentation import SegmentationConfig, load_segmentation_config
    from evseg.segmentation.config import with_overrides
    from evseg.segmentation.evaluate import check_presets
    from evseg.simulator import load_scene_preset, simulate

    with_overrides(SegmentationConfig(), overrides, "evaluate_flow_errors")  # bad keys fail before any work
    presets = check_presets(presets, ["eed_like", "evimo_like", "driving_like"], "evaluate_flow_errors")
    if seeds is None:
        seeds = range(1000, 1002) if quick else range(1000, 1008)
    duration_us = 100_000 if quick else 300_000
    rows = []
    for preset in presets:
        seg = with_overrides(load_segmentation_config(SEGMENTATION_PRESET[preset]), overrides, "evaluate_flow_errors")
        scores: dict[str, list] = {v: [] for v in FLOW_VARIANTS}
        for seed in seeds:
            rec = simulate(load_scene_preset(preset), seed=seed, duration_us=duration_us)
            sensor = rec.stream.sensor_size
            pipe = MotionSegmentationPipeline(PipelineConfig(segmentation=seg, overlap=False, model_path=model_path),
                                              sensor_size=sensor)
            results, learned = learned_flows(pipe, rec)
            scores["learned"] += [score_result(rec, r) for r in results]
            for name, flow in flow_variants(rec, learned).items():
                fed = MotionSegmentationPipeline(PipelineConfig(flow="precomputed", segmentation=seg, overlap=False),
                                                 sensor_size=sensor)
                scores[name] += [score_result(rec, r) for r in fed.run(rec.stream, precomputed_flow=flow)]
        for name in FLOW_VARIANTS:
            row = summary_row(f"{preset}, {name}", summarize(scores[name]), float("nan"), float("nan"))
            rows.append({k: v for k, v in row.items() if k not in ("flow median AE deg", "ms/window")})
    return rows
