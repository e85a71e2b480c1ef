"""``evseg bench flow``: normal flows per second, the encoding/network split, and the scaling
with the number of events per slice (time must grow linearly).

Medians over the repeats, plus the best run (``best_*``): on a machine shared with other busy
processes the encoder's parallel loops wait for descheduled threads, which the median shows
and the best run mostly does not.

Input: synthetic slices of translating edges (:mod:`evseg.veckm_flow.synthetic`) at 346x260,
20 ms, subsampled to the asked number of events. Their edges all move at 200-2,000 px/s, so the
fast-edge look (:mod:`evseg.veckm_flow.fast_edges`) runs for nearly every target: the rows
with it are the worst case, and the headline slice is also timed without it (the head's first
look alone, the network's own throughput). The slow-edge look (:mod:`evseg.veckm_flow.slow_edges`)
needs the events before a slice and slow edges: two more rows time it on a slice of slow edges
(20-80 px/s, 30 ms: the pipeline's window plus context) with the 30 ms before it as history,
with and without the look, and one more the same slice with 8 mirror looks (``evseg flow
--mirrors 8``, :mod:`evseg.veckm_flow.mirrors`). The learned model is the shipped one when
present, otherwise a randomly initialised head of the default size (same cost; the rows say so).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from evseg.veckm_flow.synthetic import translating_edges
from evseg.veckm_flow.targets import select_targets

SENSOR = (346, 260)
SLICE_US = 20_000


SLOW_SPEED_PX_S = (20.0, 80.0)
SLOW_SLICE_US = 30_000


def synthetic_slice(n_events: int, seed: int = 0, duration_us: int = SLICE_US,
                    speed_px_s: tuple[float, float] = (200.0, 2000.0)) -> np.ndarray:
    """Exactly ``n_events`` events of a ``duration_us`` slice at 346x260 (sorted), from
    translating edges at ``speed_px_s``."""
    per_crossing = 2 if n_events <= 150_000 else 6
    # events per edge ~ length (100 px) x travel (px) x per_crossing
    travel = np.sqrt(speed_px_s[0] * speed_px_s[1]) * duration_us * 1e-6
    n_edges = max(10, int(n_events / (100 * max(travel, 1.0) * per_crossing)) + 10)
    ev = translating_edges(SENSOR, n_edges=n_edges, duration_us=duration_us, speed_px_s=speed_px_s,
                           events_per_crossing=per_crossing, seed=seed).events
    if len(ev) < n_events:  # too few: add edges of another seed (rare)
        extra = synthetic_slice(n_events - len(ev), seed + 1, duration_us, speed_px_s)
        ev = np.sort(np.concatenate([ev, extra]), order="t", kind="stable")
    rng = np.random.default_rng(seed)
    keep = np.sort(rng.choice(len(ev), size=n_events, replace=False))
    return ev[keep]


def _estimator(model_path: str | Path | None = None):
    """(estimator, label): ``model_path``, else the shipped model, else a random-weights head
    of the default size."""
    from evseg.veckm_flow.inference import DEFAULT_MODEL, OnnxNormalFlow

    if model_path is not None:
        return OnnxNormalFlow(model_path), f"model {Path(model_path).name}"
    if DEFAULT_MODEL.is_file():
        return OnnxNormalFlow(), "shipped model"
    from evseg.export import export_onnx
    from evseg.veckm_flow import EncodingConfig, build_head

    cfg = EncodingConfig(polarity=True)  # the recommended encoding; same cost either way
    path = Path(tempfile.mkdtemp(prefix="evseg-bench-")) / "random_head.onnx"
    head = build_head(cfg)
    export_onnx(head, cfg, path)
    return OnnxNormalFlow(path), f"random weights, hidden {head.hidden}x{head.layers} (no shipped model)"


def _time_learned(est, ev, targets, repeats: int, history: np.ndarray | None = None) -> tuple[float, ...]:
    """Medians (s) of encode, network, fast-edge share, slow-edge share, total; best total."""
    est(ev, SENSOR, targets, history=history)  # warm-up: compiled kernels, onnxruntime arenas
    enc, net, fast, slow, tot = [], [], [], [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        est(ev, SENSOR, targets, history=history)
        tot.append(time.perf_counter() - t0)
        enc.append(est.last_timing_s["encode"])
        net.append(est.last_timing_s["network"])
        fast.append(est.last_timing_s["fast_edges"])
        slow.append(est.last_timing_s["slow_edges"])
    return (float(np.median(enc)), float(np.median(net)), float(np.median(fast)), float(np.median(slow)),
            float(np.median(tot)), float(np.min(tot)))


def slow_slice(n_events: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(history, slice, targets)``: ``n_events`` events of a 30 ms slice of slow edges
    (20-80 px/s) with the 30 ms before it as history (about as many events), and 10 k target
    events drawn among the slice's last 10 ms (the pipeline's window)."""
    ev = synthetic_slice(int(2.2 * n_events), seed, 2 * SLOW_SLICE_US, SLOW_SPEED_PX_S)
    cut = int(np.searchsorted(ev["t"], SLOW_SLICE_US))
    # Thin both halves alike (the same event density) so that the slice holds exactly n_events.
    rng = np.random.default_rng(seed)
    keep = rng.random(len(ev)) < n_events / (len(ev) - cut)  # the history's share
    keep[cut:] = False
    keep[cut + rng.choice(len(ev) - cut, n_events, replace=False)] = True  # exactly n in the slice
    history, sl = ev[:cut][keep[:cut]], ev[cut:][keep[cut:]]
    w0 = int(np.searchsorted(sl["t"], 2 * SLOW_SLICE_US - 10_000))
    n_targets = min(10_000, len(sl) - w0)  # events, not cells: slow edges fire few pixels per 10 ms
    targets = w0 + np.sort(rng.choice(len(sl) - w0, n_targets, replace=False))
    return history, sl, targets


def benchmark(repeats: int, quick: bool, model_path: str | Path | None = None) -> list[dict]:
    """Rows per slice size for the learned flow (``model_path``, default the shipped model),
    then the plane-fit baseline on the 100 k-event slice."""
    import numba

    from evseg.veckm_flow.baseline import PlaneFitNormalFlow

    from evseg.veckm_flow.inference import OnnxNormalFlow

    est, label = _estimator(model_path)
    first_look = OnnxNormalFlow(est.model_path, fast_edges=None)
    mirrored = OnnxNormalFlow(est.model_path, mirrors=8)
    threads = f"numba {numba.get_num_threads()}, ort default"
    rows = []
    sizes = [10_000, 100_000] if quick else [10_000, 30_000, 100_000, 300_000, 1_000_000]
    # (events, estimator, label, slow-edge slice, its history given)
    runs = [(n, est, "", False, False) for n in sizes]
    runs.insert(sizes.index(100_000) + 1, (100_000, first_look, ", first look only", False, False))
    runs += [(100_000, est, ", slow edges, no history: no slow look", True, False),
             (100_000, est, ", slow edges + 30 ms history: slow look", True, True),
             (100_000, mirrored, ", slow edges + 30 ms history, 8 mirror looks", True, True)]
    for n, e, variant, slow_edges, with_history in runs:
        history = None
        if slow_edges:
            hist, ev, targets = slow_slice(n)
            history = hist if with_history else None
        else:
            ev = synthetic_slice(n)
            targets = select_targets(ev, SENSOR, cell_px=1, max_targets=10_000)
        enc, net, fast, slow, tot, best = _time_learned(e, ev, targets, repeats, history)
        rows.append({
            "method": "learned (" + label + variant + ")", "events": n, "targets": len(targets),
            "history_events": 0 if history is None else len(history), "mirrors": e.mirrors,
            "encode_ms": enc * 1e3, "network_ms": net * 1e3, "fast_edges_ms": fast * 1e3,
            "slow_edges_ms": slow * 1e3, "total_ms": tot * 1e3,
            "flows_per_s": len(targets) / tot, "ns_per_event": tot / n * 1e9,
            "best_total_ms": best * 1e3, "best_flows_per_s": len(targets) / best, "threads": threads,
        })
    # The classical baseline on the headline input, for comparison.
    ev = synthetic_slice(100_000)
    targets = select_targets(ev, SENSOR, cell_px=1, max_targets=10_000)
    base = PlaneFitNormalFlow()
    base(ev, SENSOR, targets)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        base(ev, SENSOR, targets)
        ts.append(time.perf_counter() - t0)
    tot, best = float(np.median(ts)), float(np.min(ts))
    rows.append({
        "method": "plane-fit baseline", "events": 100_000, "targets": len(targets), "history_events": 0,
        "mirrors": 1,
        "encode_ms": float("nan"), "network_ms": float("nan"), "fast_edges_ms": float("nan"),
        "slow_edges_ms": float("nan"), "total_ms": tot * 1e3, "flows_per_s": len(targets) / tot,
        "ns_per_event": tot / 100_000 * 1e9, "best_total_ms": best * 1e3,
        "best_flows_per_s": len(targets) / best, "threads": "numpy",
    })
    return rows
