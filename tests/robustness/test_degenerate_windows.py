"""Degenerate windows through MotionSegmentationPipeline: every one gets a defined result.

Defined result = one int16 label per event of the window in {-1 unassigned, 0 background} or an
object id that has a box inside the sensor, and the pipeline keeps going (the next, normal
window is segmented as if nothing happened). Each case runs with hand-built precomputed flow,
the plane-fit baseline and the learned flow (a random-weights ONNX head, and the shipped model).
"""

from __future__ import annotations

import numpy as np
import pytest

from evseg.events import EVENT_DTYPE, EventStream
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
from evseg.segmentation import SegmentationConfig

from robust_helpers import random_events

SIZE = (32, 24)
WINDOW_US = 10_000


def _check(res, sensor_size=SIZE) -> None:
    """The contract of a WindowResult, whatever the input."""
    assert res.labels.dtype == np.int16 and len(res.labels) == len(res.events)
    assert set(np.unique(res.labels).tolist()) <= {-1, 0} | set(res.boxes)
    w, h = sensor_size
    for oid, (x0, y0, x1, y1) in res.boxes.items():
        assert oid >= 1 and 0 <= x0 <= x1 < w and 0 <= y0 <= y1 < h
    for oid, m in res.masks.items():
        assert oid in res.boxes and m.shape == (h, w) and m.dtype == bool
    assert len(res.flow_index) == len(res.flow) and np.isfinite(res.flow).all()


def _pipeline(flow: str, random_onnx, seg: SegmentationConfig | None = None) -> MotionSegmentationPipeline:
    """``flow``: precomputed, planefit, learned (random-weights head) or shipped (the default model)."""
    if flow == "shipped":
        from evseg.veckm_flow.inference import DEFAULT_MODEL

        if not DEFAULT_MODEL.is_file():
            pytest.skip(f"no shipped model at {DEFAULT_MODEL}")
    cfg = PipelineConfig(flow="learned" if flow == "shipped" else flow, window_us=WINDOW_US, segmentation=seg,
                         model_path=str(random_onnx) if flow == "learned" else None, threads=1)
    return MotionSegmentationPipeline(cfg, sensor_size=SIZE)


def _translation_flow(ev: np.ndarray, u: float, v: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Normal flow of a translation (u, v) px/s on random edge directions: n = (u.g) g."""
    a = np.random.default_rng(seed).uniform(0, np.pi, len(ev))
    g = np.stack([np.cos(a), np.sin(a)], axis=1)
    s = g[:, 0] * u + g[:, 1] * v
    return (s * g[:, 0]).astype(np.float32), (s * g[:, 1]).astype(np.float32)


def _run(pipe, events: np.ndarray, nx=None, ny=None) -> list:
    """All windows of ``events``; flow given for every event when nx, ny are."""
    flow = None
    if nx is not None:
        flow = {"index": np.arange(len(events)), "nx": np.asarray(nx, np.float32), "ny": np.asarray(ny, np.float32)}
    return list(pipe.run(EventStream(events, SIZE), precomputed_flow=flow))


def _degenerate(case: str) -> np.ndarray:
    """One window (10 ms from t = 0) of a degenerate kind."""
    rng = np.random.default_rng(len(case))
    if case.startswith("n="):
        ev = random_events(int(case[2:]), SIZE, seed=7)
        ev["t"] -= ev["t"][:1]  # windows start at the first event: make that t = 0
        return ev
    n = 200
    ev = random_events(n, SIZE, seed=8)
    if case == "one pixel":
        ev["x"], ev["y"] = 5, 7
    elif case == "one row":
        ev["y"] = 11
    elif case == "one column":
        ev["x"] = 3
    elif case == "diagonal":
        ev["y"] = ev["x"] % SIZE[1]
        ev["x"] = ev["y"]
    elif case == "same timestamp":
        ev["t"] = 4_321
    elif case == "two pixels":
        ev["x"] = np.where(rng.random(n) < 0.5, 2, 30)
        ev["y"] = 12
    else:
        raise AssertionError(case)
    ev["t"] -= ev["t"][0]
    return ev


CASES = ["n=0", "n=1", "n=2", "n=3", "one pixel", "one row", "one column", "diagonal", "same timestamp", "two pixels"]


def _with_normal_window_after(ev: np.ndarray) -> np.ndarray:
    """``ev`` (window 0), then a normal 400-event window 1 (10-20 ms), then one event at 20 ms
    (which closes window 1 and forms a one-event window 2)."""
    normal = random_events(400, SIZE, t0_us=WINDOW_US, seed=9)
    tail = random_events(1, SIZE, t0_us=2 * WINDOW_US, span_us=1, seed=10)
    return np.concatenate([ev, normal, tail])


@pytest.mark.parametrize("flow", ["precomputed", "planefit", "learned", "shipped"])
@pytest.mark.parametrize("case", CASES)
def test_degenerate_window_gives_defined_labels_and_pipeline_goes_on(case, flow, random_onnx):
    ev = _with_normal_window_after(_degenerate(case))
    pipe = _pipeline(flow, random_onnx)
    nx = ny = None
    if flow == "precomputed":
        nx, ny = _translation_flow(ev, 120.0, -40.0)
    results = _run(pipe, ev, nx, ny)
    n0 = len(_degenerate(case))
    if n0 == 0:
        # No events before the normal window: windows start at its first event (empty windows
        # are covered by test_empty_windows_in_a_gap_are_yielded_with_no_labels).
        assert len(results) in (1, 2) and len(results[0].events) >= 400
    else:
        assert len(results) == 3 and len(results[0].events) == n0 and len(results[1].events) == 400
    for r in results:
        _check(r)
    assert sum(len(r.events) for r in results) == len(ev)
    if 0 < n0 < SegmentationConfig().min_object_nodes:
        # Fewer flows than an object needs: nothing can be an object.
        assert results[0].boxes == {} and set(results[0].labels.tolist()) <= {-1, 0}
    if flow == "precomputed":
        # One translation everywhere: the scene has no independently moving object.
        assert all(r.boxes == {} for r in results)
        normal = results[0] if n0 == 0 else results[1]
        assert (normal.labels == 0).all()  # the 400-event window: all background


@pytest.mark.parametrize("flow", ["precomputed", "planefit"])
def test_empty_windows_in_a_gap_are_yielded_with_no_labels(flow, random_onnx):
    """A 55 ms gap: the empty windows come out (fixed window times) with zero events."""
    a = random_events(300, SIZE, seed=1)
    b = random_events(300, SIZE, t0_us=65_000, seed=2)
    ev = np.concatenate([a, b])
    nx, ny = _translation_flow(ev, 50.0, 50.0) if flow == "precomputed" else (None, None)
    results = _run(_pipeline(flow, random_onnx), ev, nx, ny)
    t0 = int(a["t"][0])
    assert [r.t0_us for r in results] == [t0 + k * WINDOW_US for k in range(len(results))]
    empty = [r for r in results if len(r.events) == 0]
    assert len(empty) >= 4
    for r in results:
        _check(r)
    for r in empty:
        assert r.boxes == {} and r.masks == {} and len(r.labels) == 0


def test_burst_of_ten_times_the_rate_is_segmented(random_onnx):
    """Window 1 holds 10x the events of windows 0 and 2 (a flicker burst): all labelled."""
    parts = [random_events(n, SIZE, t0_us=k * WINDOW_US, seed=k) for k, n in enumerate([300, 3000, 300])]
    ev = np.concatenate(parts)
    ev["t"][0] = 0  # windows start at the first event
    for flow in ("precomputed", "planefit"):
        nx, ny = _translation_flow(ev, -80.0, 30.0) if flow == "precomputed" else (None, None)
        results = _run(_pipeline(flow, random_onnx), ev, nx, ny)
        assert [len(r.events) for r in results[:3]] == [300, 3000, 300]
        for r in results:
            _check(r)
        if flow == "precomputed":
            assert all((r.labels == 0).all() and r.boxes == {} for r in results)


def test_static_scene_with_noise_only_has_no_objects(random_onnx):
    """No motion at all: flows are zero (or absent) everywhere -> nothing is an object."""
    ev = random_events(500, SIZE, seed=3)
    zeros = np.zeros(len(ev), np.float32)
    (r,) = _run(_pipeline("precomputed", random_onnx), ev, zeros, zeros)
    _check(r)
    # Zero normal flow carries no direction: no node, every event unassigned.
    assert r.boxes == {} and (r.labels == -1).all() and len(r.flow_index) == 0


def test_nan_and_inf_flows_are_dropped_not_propagated(random_onnx):
    ev = random_events(300, SIZE, seed=4)
    nx, ny = _translation_flow(ev, 100.0, 0.0)
    nx[::3] = np.nan
    ny[1::3] = np.inf
    (r,) = _run(_pipeline("precomputed", random_onnx), ev, nx, ny)
    _check(r)
    assert len(r.flow_index) == np.isfinite(nx * ny).sum()  # the finite (and non-zero) flows only
    assert (r.labels == 0).all()  # one translation: background, NaN flows did not spread


def _patch_flows(ev: np.ndarray, centres, velocities, radius_px: float, seed: int):
    """Normal flow of rigid patches: each disc translates with its own velocity, rest static."""
    nx = np.zeros(len(ev), np.float32)
    ny = np.zeros(len(ev), np.float32)
    bx, by = _translation_flow(ev, 30.0, 0.0, seed=seed)  # the background pans slowly
    nx[:], ny[:] = bx, by
    for k, ((cx, cy), (u, v)) in enumerate(zip(centres, velocities)):
        inside = np.hypot(ev["x"] - cx, ev["y"] - cy) <= radius_px
        fx, fy = _translation_flow(ev[inside], u, v, seed=seed + k + 1)
        nx[inside], ny[inside] = fx, fy
    return nx, ny


def test_more_objects_than_candidate_models():
    """Six patches with six different motions, but fast sampling may draw only 2 candidates:
    a defined labelling (background / some objects / unassigned), never a crash."""
    size = (96, 64)
    ev = random_events(6000, size, seed=5)
    centres = [(15, 15), (48, 15), (80, 15), (15, 48), (48, 48), (80, 48)]
    velocities = [(400, 0), (-400, 0), (0, 400), (0, -400), (300, 300), (-300, 300)]
    nx, ny = _patch_flows(ev, centres, velocities, 9.0, seed=11)
    seg = SegmentationConfig(n_sampled=2, n_sampled_with_prediction=1)
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed", segmentation=seg), sensor_size=size)
    flow = {"index": np.arange(len(ev)), "nx": nx, "ny": ny}
    (r,) = list(pipe.run(EventStream(ev, size), precomputed_flow=flow))
    _check(r, size)
    # Fast sampling drew at most 2 candidates; the solver may add more (e.g. from regions it
    # cannot explain), the result is defined either way.
    assert len(r.boxes) <= 6


def test_object_ids_survive_a_degenerate_window(random_onnx):
    """A moving patch, then a window with 2 events, then the patch again: the tracker and the
    motion prediction take the near-empty window in their stride and the object keeps its id."""
    size = (64, 48)
    wins = []
    for k in range(4):
        ev = random_events(2 if k == 2 else 3000, size, t0_us=k * WINDOW_US, seed=20 + k)
        wins.append(ev)
    ev = np.concatenate(wins)
    ev["t"][0] = 0  # windows start at the first event
    nx, ny = _patch_flows(ev, [(32, 24)], [(500, 0)], 14.0, seed=3)
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=size)
    results = list(pipe.run(EventStream(ev, size), precomputed_flow={"index": np.arange(len(ev)), "nx": nx, "ny": ny}))
    assert [len(r.events) for r in results] == [3000, 3000, 2, 3000]
    for r in results:
        _check(r, size)
    assert results[2].boxes == {}
    assert len(results[0].boxes) == 1
    # The track survives one window without a match (ObjectTracker.max_missed = 2): same id.
    assert list(results[3].boxes) == list(results[0].boxes)
