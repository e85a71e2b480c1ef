"""Determinism: the same input and configuration give identical labels, run after run.

Covers the CLI end to end with the plane-fit flow, the simulator (events and ground-truth normal
flow), both flow estimators, and the pipeline fed the same recording in different chunkings
(the streaming reader's chunk size must not change any label).
"""

from __future__ import annotations

import numpy as np
import pytest

from evseg.cli import main
from evseg.events import EventStream
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
from evseg.results import load_result


def test_cli_planefit_twice_gives_identical_results(tmp_path, sim_files):
    rec, recording, _ = sim_files
    outs = [tmp_path / f"r{k}.npz" for k in range(2)]
    for out in outs:
        assert main(["segment", str(recording), "--flow-method", "planefit", "--out", str(out), "--masks",
                     "--no-progress"]) == 0
    a, b = (load_result(p) for p in outs)
    assert len(a.label) == len(rec.stream) and not a.partial
    assert (a.label >= 0).any()  # not trivially all unassigned
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_array_equal(a.window_t0_us, b.window_t0_us)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    np.testing.assert_array_equal(a.masks, b.masks)
    assert a.config == b.config


def test_cli_shipped_learned_flow_twice_gives_identical_labels(tmp_path, sim_files):
    from evseg.veckm_flow.inference import DEFAULT_MODEL

    if not DEFAULT_MODEL.is_file():
        pytest.skip(f"no shipped model at {DEFAULT_MODEL}")
    rec, recording, _ = sim_files
    outs = [tmp_path / f"r{k}.npz" for k in range(3)]
    for out, threads in zip(outs, (["--threads", "1"], [], [])):  # default threads: all cores
        assert main(["segment", str(recording), "--out", str(out), "--no-progress", *threads]) == 0
    a, b, c = (load_result(p) for p in outs)
    assert len(a.label) == len(rec.stream) and (a.label >= 0).any()
    for other in (b, c):  # the thread count does not change any label
        np.testing.assert_array_equal(a.label, other.label)
        np.testing.assert_array_equal(a.boxes, other.boxes)


def test_simulator_and_flow_estimators_are_deterministic(random_onnx):
    from evseg.simulator import load_scene_preset, simulate
    from evseg.veckm_flow import OnnxNormalFlow, PlaneFitNormalFlow, select_targets

    scene = load_scene_preset("eed_like").with_sensor_size(96, 72)
    r1, r2 = (simulate(scene, seed=3, duration_us=15_000) for _ in range(2))
    assert len(r1.stream) > 500
    np.testing.assert_array_equal(r1.stream.events, r2.stream.events)
    np.testing.assert_array_equal(r1.label, r2.label)
    np.testing.assert_array_equal(r1.normal_flow, r2.normal_flow)  # NaN where undefined, equal too
    ev, size = r1.stream.events, r1.stream.sensor_size
    targets = select_targets(ev, size, cell_px=2)
    for make in (PlaneFitNormalFlow, lambda: OnnxNormalFlow(random_onnx, threads=1)):
        f1, f2 = make()(ev, size, targets), make()(ev, size, targets)
        np.testing.assert_array_equal(f1.index, f2.index)
        np.testing.assert_array_equal(f1.nx, f2.nx)
        np.testing.assert_array_equal(f1.ny, f2.ny)


def _labels(rec, chunks, flow) -> list[np.ndarray]:
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
    return [(r.t0_us, r.labels, r.boxes) for r in pipe.run(chunks, precomputed_flow=flow)]


def test_chunking_of_the_input_does_not_change_labels(sim_files):
    """Whole array, chunks of 1000 and uneven chunks (incl. a 1-event chunk): same labels."""
    from evseg.pipeline import load_flow_file

    rec, _, flow_path = sim_files
    ev = rec.stream.events
    flow = load_flow_file(flow_path, n_events=len(ev))
    whole = _labels(rec, EventStream(ev, rec.stream.sensor_size), flow)
    cuts = [0, 1, 2, 777, 3001, 3002, 6500, len(ev)]
    for chunks in ([ev[i : i + 1000] for i in range(0, len(ev), 1000)],
                   [ev[a:b] for a, b in zip(cuts[:-1], cuts[1:])]):
        other = _labels(rec, chunks, flow)
        assert len(other) == len(whole)
        for (t0a, la, ba), (t0b, lb, bb) in zip(whole, other):
            assert t0a == t0b and ba == bb
            np.testing.assert_array_equal(la, lb)
