"""An error or Ctrl-C in the middle of `evseg segment` leaves a readable, partial result.

The failure is injected after N windows by wrapping MotionSegmentationPipeline.process (in
process for exceptions and KeyboardInterrupt; in a child process for a real SIGINT). The
result must load, be flagged ``partial``, hold the windows done and, for the events they
cover, exactly the labels of an uninterrupted run.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from evseg.cli import main
from evseg.errors import FormatError
from evseg.pipeline import MotionSegmentationPipeline
from evseg.results import load_result

N_DONE = 2  # windows that complete before the failure


@pytest.fixture(scope="module")
def full_run(sim_files, tmp_path_factory):
    """The uninterrupted result (precomputed flow: deterministic and fast)."""
    _, recording, flow = sim_files
    out = tmp_path_factory.mktemp("full") / "full.npz"
    assert main(["segment", str(recording), "--flow", str(flow), "--out", str(out), "--no-progress"]) == 0
    return load_result(out)


def _fail_after(monkeypatch, n: int, exc: BaseException) -> None:
    original = MotionSegmentationPipeline.process

    def process(self, window, flow=None, context=None):
        if window.index == n:
            raise exc
        return original(self, window, flow, context)

    monkeypatch.setattr(MotionSegmentationPipeline, "process", process)


def _check_partial(out, full, n_windows: int, t_us: np.ndarray) -> None:
    """``out`` holds exactly the first ``n_windows`` windows of ``full`` (event times ``t_us``)."""
    r = load_result(out)
    assert r.partial
    assert len(r.window_t0_us) == n_windows
    np.testing.assert_array_equal(r.window_t0_us, full.window_t0_us[:n_windows])
    # Events of the windows done carry their labels; the writer stops there (label is as long
    # as the events processed when the recording's length is unknown to the streaming writer).
    done = r.n_events_processed
    assert 0 < done < len(full.label) and len(r.label) == done
    np.testing.assert_array_equal(r.label, full.label[:done])
    t0 = full.window_t0_us[n_windows]
    assert done == int(np.searchsorted(t_us, t0))  # exactly the events before window N
    np.testing.assert_array_equal(r.boxes, full.boxes[full.boxes[:, 0] < n_windows])


@pytest.mark.parametrize("exc, rc", [(RuntimeError("boom"), 1), (KeyboardInterrupt(), 130),
                                     (FormatError("flow.npz: broken at row 7"), 2)])
def test_failure_mid_run_leaves_partial_result(exc, rc, monkeypatch, tmp_path, capsys, sim_files, full_run):
    _, recording, flow = sim_files
    _fail_after(monkeypatch, N_DONE, exc)
    out = tmp_path / "r.npz"
    assert main(["segment", str(recording), "--flow", str(flow), "--out", str(out), "--no-progress"]) == rc
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    _check_partial(out, full_run, N_DONE, sim_files[0].stream.events["t"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.npz"]  # temporary label file removed


def test_failure_before_the_first_window_writes_nothing(monkeypatch, tmp_path, sim_files):
    """Nothing processed, nothing to keep: no empty result, an existing result untouched."""
    _, recording, flow = sim_files
    _fail_after(monkeypatch, 0, KeyboardInterrupt())
    out = tmp_path / "r.npz"
    assert main(["segment", str(recording), "--flow", str(flow), "--out", str(out), "--no-progress"]) == 130
    assert not out.exists() and list(tmp_path.iterdir()) == []
    out.write_bytes(b"an earlier result")
    assert main(["segment", str(recording), "--flow", str(flow), "--out", str(out), "--no-progress"]) == 130
    assert out.read_bytes() == b"an earlier result" and list(tmp_path.iterdir()) == [out]


def test_partial_result_replaces_an_older_result_atomically(monkeypatch, tmp_path, sim_files, full_run):
    """The old file is replaced only by a complete npz (rename), never truncated in place."""
    _, recording, flow = sim_files
    out = tmp_path / "r.npz"
    out.write_bytes(b"old")
    _fail_after(monkeypatch, N_DONE, KeyboardInterrupt())
    assert main(["segment", str(recording), "--flow", str(flow), "--out", str(out), "--no-progress"]) == 130
    _check_partial(out, full_run, N_DONE, sim_files[0].stream.events["t"])


CHILD = textwrap.dedent("""
    import signal, sys, time
    # A shell starts background jobs ('cmd &', as CI runners may) with SIGINT ignored, and
    # Python then installs no KeyboardInterrupt handler; restore it so that the test sees
    # what a terminal's Ctrl-C does.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import evseg.pipeline as p
    original = p.MotionSegmentationPipeline.process
    def process(self, window, flow=None, context=None):
        if window.index == {n}:
            print("ready", flush=True)
            time.sleep(60)  # Ctrl-C arrives here
        return original(self, window, flow, context)
    p.MotionSegmentationPipeline.process = process
    from evseg.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def test_real_sigint_to_a_running_segment(tmp_path, sim_files, full_run):
    _, recording, flow = sim_files
    out = tmp_path / "r.npz"
    cmd = [sys.executable, "-c", CHILD.format(n=N_DONE), "segment", str(recording), "--flow", str(flow),
           "--out", str(out), "--no-progress"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            cwd=tmp_path)  # not the repository root, whose ./evseg would shadow an installed one
    try:
        assert proc.stdout.readline().strip() == "ready"
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert err.strip().splitlines() == ["evseg segment: interrupted"]
    _check_partial(out, full_run, N_DONE, sim_files[0].stream.events["t"])
