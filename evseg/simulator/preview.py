"""A picture of one window of a simulated recording: events, ground-truth labels, flows."""

from __future__ import annotations

import numpy as np

from evseg import visualize as vis
from evseg.simulator.recording import SimulatedRecording


def busiest_window(rec: SimulatedRecording, window_us: int) -> int:
    """Start (us) of the window of ``window_us`` with the most object events (the most events if
    there is no object), among back-to-back windows."""
    t = rec.events["t"]
    if len(t) == 0:
        return 0
    starts = np.arange(0, max(1, rec.duration_us - window_us + 1), max(1, window_us // 2))
    weight = (rec.label > 0) if rec.object_ids else np.ones(len(t), bool)
    cum = np.concatenate([[0], np.cumsum(weight)])
    counts = cum[np.searchsorted(t, starts + window_us)] - cum[np.searchsorted(t, starts)]
    return int(starts[int(np.argmax(counts))])


PANELS = ("events", "labels", "normal_flow", "flow")


def preview_image(
    rec: SimulatedRecording,
    t0_us: int | None = None,
    window_us: int = 10_000,
    scale: int = 0,
    panels: tuple[str, ...] = PANELS,
) -> np.ndarray:
    """uint8 RGB panel row for the window ``[t0_us, t0_us + window_us)``: events (red ON / blue
    OFF), ground-truth labels (grey background, colours per object, object mask outlines at the
    window's mid-time), normal flow and optical flow (colour wheel legend at the right, rim =
    the 95th percentile of the window's optical-flow speed), in the order of ``panels`` (a
    subset of :data:`PANELS`). ``t0_us=None`` picks the busiest window; ``scale=0`` enlarges
    small sensors to about 350 px wide."""
    if t0_us is None:
        t0_us = busiest_window(rec, window_us)
    t = rec.events["t"]
    sl = slice(int(np.searchsorted(t, t0_us)), int(np.searchsorted(t, t0_us + window_us)))
    ev = rec.events[sl]
    size = rec.stream.sensor_size
    if scale <= 0:
        scale = max(1, int(round(350 / size[0])))
    speeds = np.hypot(rec.flow[sl, 0], rec.flow[sl, 1])
    speeds = speeds[np.isfinite(speeds)]
    vmax = float(np.percentile(speeds, 95)) if len(speeds) else 1.0
    vmax = float(f"{max(vmax, 1.0):.2g}")
    truth = rec.window_truth(t0_us, t0_us + window_us)
    labels = vis.labels_to_image(ev["x"], ev["y"], rec.label[sl], size)
    palette = vis.label_palette(max(1, max(rec.object_ids, default=0)))
    for oid, m in zip(truth.object_ids, truth.masks):
        labels = vis.mask_outline(labels, m, tuple(int(c) for c in palette[oid - 1] // 2))
    ms = window_us / 1000
    make = {
        "events": lambda: vis.titled(vis.events_to_image(ev["x"], ev["y"], ev["p"], size), f"events {ms:g} ms (ON red, OFF blue)", scale),
        "labels": lambda: vis.titled(labels, "GT labels (grey = background)", scale),
        "normal_flow": lambda: vis.titled(vis.flow_events_to_image(ev["x"], ev["y"], rec.normal_flow[sl], size, vmax), "GT normal flow", scale),
        "flow": lambda: vis.titled(vis.flow_events_to_image(ev["x"], ev["y"], rec.flow[sl], size, vmax), "GT optical flow", scale),
    }
    unknown = [p for p in panels if p not in make]
    if unknown:
        raise ValueError(f"unknown preview panel {unknown[0]!r} (known: {', '.join(PANELS)})")
    images = [make[p]() for p in panels]
    if any(p in ("normal_flow", "flow") for p in panels):
        images.append(vis.titled(vis.color_wheel_legend(96, vmax), "flow colours", 1))
    return vis.hstack_padded(images)


def docs_figure(scenes: tuple[tuple[str, int], ...] = (("evimo_like", 5), ("eed_like", 0)), duration_us: int = 100_000) -> np.ndarray:
    """The README's figure: one row per ``(preset, seed)`` with the busiest 10 ms window's
    events, ground-truth labels and normal flow. uint8 RGB."""
    from evseg.simulator.engine import simulate
    from evseg.simulator.presets import load_scene_preset

    rows = [
        preview_image(simulate(load_scene_preset(name), seed=seed, duration_us=duration_us), scale=1,
                      panels=("events", "labels", "normal_flow"))
        for name, seed in scenes
    ]
    return vis.vstack_padded(rows, gap=8)


if __name__ == "__main__":  # python -m evseg.simulator.preview docs/simulated_window.png
    import sys

    vis.save_rgb(sys.argv[1] if len(sys.argv) > 1 else "simulated_window.png", docs_figure())
