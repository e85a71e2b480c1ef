"""`evseg eval live`: what dropping windows on a live source costs in accuracy.

The held-out simulated scenes of ``evseg eval pipeline`` (seeds 1000-1007, 300 ms, 10 ms
windows) are replayed at the sensor's pace (:func:`evseg.live.replay`) through
:func:`evseg.live.run_live` with a 20 ms lag bound, and the windows it segmented are scored as
``evseg eval pipeline`` scores every window (:func:`evseg.pipeline_eval.score_result`). Beside
them, the same windows segmented offline as ``evseg eval pipeline`` segments them (every window
before them segmented too, so motion prediction and tracks never see a gap) and all windows
offline (``evseg eval pipeline``'s pooled rows). The live rows depend on the
machine's speed (which windows are dropped is decided by the clock), so two runs can differ
slightly; the offline rows are deterministic.
"""

from __future__ import annotations

from evseg.metrics import summarize
from evseg.pipeline_eval import (
    SEGMENTATION_PRESET,
    SEGMENTATION_PRESET_ORDER,
    evaluate_recording,
    score_result,
    summary_row,
)


def evaluate_live(quick: bool = False, speed: float = 1.0, max_lag_us: int = 20_000, seeds=None,
                  presets=None, worker: str = "process") -> list[dict]:
    """Pooled rows per preset and over the scenes with objects: live (the windows segmented),
    offline on the same windows, offline on all windows; with the share of windows segmented
    live. ``worker``: the pipeline's (``"process"``, as ``evseg segment --realtime`` on a long
    recording; ``"none"`` for one window after the other)."""
    from evseg.live import replay, run_live
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
    from evseg.segmentation import load_segmentation_config
    from evseg.segmentation.evaluate import check_presets
    from evseg.simulator import load_scene_preset, simulate

    presets = check_presets(presets, list(SEGMENTATION_PRESET_ORDER), "evaluate_live")
    if seeds is None:
        seeds = range(1000, 1002) if quick else range(1000, 1008)
    duration_us = 100_000 if quick else 300_000
    overlap = {"overlap": False} if worker == "none" else {"worker": worker}
    pooled: dict[tuple[str, str], list] = {}
    for preset in presets:
        seg = load_segmentation_config(SEGMENTATION_PRESET[preset])
        cfg = PipelineConfig(segmentation=seg, **overlap)
        pipe = None
        try:
            for seed in seeds:
                rec = simulate(load_scene_preset(preset), seed=seed, duration_us=duration_us)
                # as `evseg eval pipeline` runs it (the worker thread), so its rows are the same
                offline = evaluate_recording(rec, PipelineConfig(segmentation=seg)).scores
                if pipe is None:
                    pipe = MotionSegmentationPipeline(cfg, sensor_size=rec.stream.sensor_size)
                    pipe.warm_up()
                pipe.reset()
                live = list(run_live(pipe, replay([rec.stream.events], speed=speed), max_lag_us=max_lag_us))
                pooled.setdefault((preset, "live"), []).extend(score_result(rec, r.window) for r in live)
                pooled.setdefault((preset, "same"), []).extend(offline[r.window.index] for r in live)
                pooled.setdefault((preset, "all"), []).extend(offline)
        finally:
            if pipe is not None:
                pipe.close()
    names = {"live": "live, windows segmented", "same": "offline, the same windows", "all": "offline, all windows"}
    rows = []
    groups = [(p, [p]) for p in presets] + [("scenes with objects", [p for p in presets if p != "ego_only"])]
    for name, members in groups:
        if not members:
            continue
        # windows segmented live / all windows
        done, total = (sum(len(pooled[(p, kind)]) for p in members) for kind in ("live", "all"))
        for kind in ("live", "same", "all"):
            row = summary_row(f"**{name}**, {names[kind]}",
                              summarize([s for p in members for s in pooled[(p, kind)]]), float("nan"), float("nan"))
            row = {k: v for k, v in row.items() if k not in ("flow median AE deg", "ms/window")}
            rows.append({**row, "windows segmented live %": 100 * done / total})
    return rows
