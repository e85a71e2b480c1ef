"""Bounded memory: peak RSS of `evseg segment` streaming long recordings from disk.

A 1 s simulated EVIMO-like tile is repeated
with time offsets into recordings of increasing length, streamed to a DSEC-style HDF5 file
through :func:`evseg.io.hdf5.write_h5_chunks` (bounded memory; never committed, written to a
temporary folder). Each recording is segmented by `evseg segment --flow-method METHOD` in a
child process whose resident memory, with that of its own worker process, is sampled from
``/proc/PID/status`` every 0.2 s; the peak is the higher of the sampled total and the kernel's
``ru_maxrss`` of that child (``os.wait4``). Flat memory = the same peak for
10 s and 10 min, and no growth between the middle and the end of one run.

Two tiles: a small one (128x96 px, thinned to 20 k events/s) for runs of 10 s to 10 min with
either estimator, and the size of issue 5's latency target (346x260 px, about 1 M events/s,
:func:`evseg.pipeline_bench.simulated_stream`) for a 10 min run with the learned flow: the
real-time case, ~0.5 G events and a ~7 GB file (written to a temporary folder, deleted after).
A precomputed flow file (``--flow``) is loaded whole by design, so it is not a streaming case.
``OMP_NUM_THREADS=1`` in the child keeps the numbers comparable on a shared machine.

Run: ``evseg bench memory --repeats 1`` (about an hour on 2 cores, 40 min of it the 1 M
events/s run; ``--quick``: plane-fit flow on 5 s and 20 s of the small tile). Memory does not
vary between runs; one repeat suffices.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SENSOR = (128, 96)
FULL_RATE_EV_S = 1e6
TILE_US = 1_000_000
SAMPLE_S = 0.2


def tile_events(rate_ev_s: float, seed: int = 0) -> np.ndarray:
    """One second of a simulated EVIMO-like scene at ``SENSOR``, thinned to ``rate_ev_s``.

    Returns an EVENT_DTYPE array with ``0 <= t < TILE_US`` (us), sorted.
    """
    from evseg.simulator import load_scene_preset, simulate

    rec = simulate(load_scene_preset("evimo_like").with_sensor_size(*SENSOR), seed=seed, duration_us=TILE_US)
    ev = rec.stream.events
    keep = np.random.default_rng(seed).random(len(ev)) < min(1.0, rate_ev_s / max(len(ev), 1))
    return ev[keep]


def full_size_tile(seed: int = 1100) -> tuple[np.ndarray, tuple[int, int]]:
    """One second of the latency benchmark's stream (EVIMO-like, 346x260, ~1 M events/s) and
    its sensor size (width, height)."""
    from evseg.pipeline_bench import simulated_stream

    rec = simulated_stream(FULL_RATE_EV_S, TILE_US, seed=seed)
    return rec.stream.events, tuple(rec.stream.sensor_size)


def write_long_recording(path: Path, tile: np.ndarray, duration_s: int,
                         sensor: tuple[int, int] = SENSOR) -> int:
    """Write ``duration_s`` copies of the 1 s ``tile`` back to back (HDF5, streamed) on a
    ``sensor`` (width, height); returns the number of events."""
    from evseg.io.hdf5 import write_h5_chunks

    def chunks():
        for k in range(duration_s):
            c = tile.copy()
            c["t"] += k * TILE_US
            yield c

    write_h5_chunks(chunks(), path, lambda: (tuple(sensor), 0, None))
    return len(tile) * duration_s


def _rss_kb(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def _tree_rss_kb(pid: int) -> int | None:
    """Resident memory (kB) of ``pid`` and all its descendants (the pipeline's worker process)."""
    total = _rss_kb(pid)
    if total is None:
        return None
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except (FileNotFoundError, ProcessLookupError):
        return total
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children") as f:
                children = [int(c) for c in f.read().split()]
        except (FileNotFoundError, ProcessLookupError):
            continue
        for child in children:
            total += _tree_rss_kb(child) or 0
    return total


def measure_segment(recording: Path, out: Path, flow_method: str = "planefit") -> dict:
    """Run `evseg segment` on ``recording`` in a child; RSS samples (kB) and its peak."""
    cmd = [sys.executable, "-c", "import sys; from evseg.cli import main; sys.exit(main(sys.argv[1:]))",
           "segment", str(recording), "--out", str(out), "--flow-method", flow_method, "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    samples: list[int] = []
    while True:
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        rss = _tree_rss_kb(proc.pid)
        if rss is not None:
            samples.append(rss)
        time.sleep(SAMPLE_S)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    err = proc.stderr.read().decode(errors="replace")
    proc.stderr.close()
    if proc.returncode != 0:
        raise RuntimeError(f"evseg segment failed ({proc.returncode}): {err.strip()}")
    # The kernel's peak of the main process, or the sampled peak of the process tree (the
    # segment command's worker process included) when that is higher.
    peak_kb = max(int(usage.ru_maxrss), max(samples, default=0))
    return {"wall_s": wall, "peak_kb": peak_kb, "samples_kb": samples}


def _row(flow_method: str, duration_s: int, n_events: int, file_mb: float, m: dict,
         sensor: tuple[int, int] = SENSOR) -> dict:
    s = np.asarray(m["samples_kb"], dtype=np.float64) / 1024
    q = max(1, len(s) // 4)
    # Growth within one run: median RSS of the last quarter minus that of the second quarter
    # (the first quarter holds imports and warm-up).
    growth = float(np.median(s[-q:]) - np.median(s[q : 2 * q])) if len(s) >= 8 else float("nan")
    return {
        "flow": flow_method,
        "sensor": f"{sensor[0]}x{sensor[1]}",
        "recording_s": duration_s,
        "events": n_events,
        "rate_ev_s": round(n_events / duration_s),
        "file_mb": file_mb,
        "wall_s": m["wall_s"],
        "samples": len(s),
        "peak_rss_mb": m["peak_kb"] / 1024,
        "median_rss_mb": float(np.median(s)) if len(s) else float("nan"),
        # Median RSS of each quarter of the run: a leak rises steadily, warm-up only at first.
        "rss_by_quarter_mb": "/".join(f"{np.median(p):.0f}" for p in np.array_split(s, 4) if len(p)),
        "growth_mb": growth,
    }


def benchmark(repeats: int = 1, quick: bool = False, rate_ev_s: float = 20_000,
              cases: tuple[tuple, ...] | None = None) -> list[dict]:
    """Peak RSS of `evseg segment` per case, median over ``repeats`` runs.

    A case is ``(flow method, recording length in s)`` on the small tile (``SENSOR`` at
    ``rate_ev_s``) or ``(flow method, length, "full")`` on the full-size tile
    (:func:`full_size_tile`).
    """
    if cases is None:
        cases = ((("planefit", 5), ("planefit", 20)) if quick else
                 (("planefit", 10), ("planefit", 60), ("planefit", 600), ("learned", 10), ("learned", 60),
                  ("learned", 600, "full")))
    for case in cases:  # all checked before the first (long) run
        if len(case) not in (2, 3) or (len(case) == 3 and case[2] not in ("small", "full")):
            raise ValueError(f"memory benchmark: case {case!r}: expected (flow, seconds) or "
                             "(flow, seconds, 'small' | 'full')")
    tiles: dict[str, tuple[np.ndarray, tuple[int, int]]] = {}
    rows = []
    with tempfile.TemporaryDirectory(prefix="evseg-memory-") as d:
        for case in cases:
            flow_method, duration = case[0], int(case[1])
            kind = case[2] if len(case) > 2 else "small"
            if kind not in tiles:
                tiles[kind] = full_size_tile() if kind == "full" else (tile_events(rate_ev_s), SENSOR)
            tile, sensor = tiles[kind]
            rec = Path(d) / f"long_{duration}s.h5"
            n = write_long_recording(rec, tile, duration, sensor)
            runs = [measure_segment(rec, Path(d) / "result.npz", flow_method) for _ in range(repeats)]
            med = sorted(runs, key=lambda m: m["peak_kb"])[len(runs) // 2]
            rows.append(_row(flow_method, duration, n, rec.stat().st_size / 2**20, med, sensor))
            rec.unlink()
    return rows
