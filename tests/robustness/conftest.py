"""Fixtures of the robustness tests: tiny inputs, a random-weights ONNX model, a short simulation.

The segmentation fits its models with torch; on inputs of a few nodes torch's intra-op thread
pool costs more than the work (index_add_ on 5 rows took 6 ms with 2 threads on a loaded
2-core CI machine, 0.1 ms with one), so these tests run torch single-threaded and restore the
setting afterwards.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

# Make robust_helpers importable from the test modules in any import mode.
_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)


@pytest.fixture(autouse=True)
def _torch_single_thread():
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def random_onnx(tmp_path_factory):
    """A randomly initialised normal-flow head exported to ONNX (small d: fast), its path.

    No trained model is shipped yet; random weights give arbitrary but finite flows, which is
    what the robustness tests need from flow="learned".
    """
    from evseg.export import export_onnx
    from evseg.veckm_flow import EncodingConfig, build_head

    cfg = EncodingConfig(d=16, window_px=4, seed=3)
    head = build_head(cfg, seed=0, hidden=32)
    path = tmp_path_factory.mktemp("onnx") / "random_head.onnx"
    export_onnx(head, cfg, path)
    return path


@pytest.fixture(scope="session")
def sim_files(tmp_path_factory):
    """A 40 ms simulated recording (128x96 px, ~8.6 k events, 3 objects) on disk: (recording, sim.npz, flow.npz).

    flow.npz holds the simulator's per-event normal flow in the ``evseg flow`` schema.
    """
    from evseg.simulator import load_scene_preset, save_recording, simulate

    rec = simulate(load_scene_preset("evimo_like").with_sensor_size(128, 96), seed=5, duration_us=40_000)
    d = tmp_path_factory.mktemp("sim")
    save_recording(rec, d / "sim.npz")
    ok = np.flatnonzero(np.isfinite(rec.normal_flow[:, 0]))
    np.savez(d / "flow.npz", index=ok, nx=rec.normal_flow[ok, 0], ny=rec.normal_flow[ok, 1])
    return rec, d / "sim.npz", d / "flow.npz"
