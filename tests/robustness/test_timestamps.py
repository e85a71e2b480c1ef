"""Timestamps and coordinates users' converters get wrong, through `evseg segment`.

Each case either segments with defined labels (10 s gap, equal timestamps, duplicate flow rows)
or stops with one line naming the file, the field and the event (wrap-around, negative time,
NaN/inf, coordinates off the sensor, no sensor size); never labels computed on wrong data.
The readers' own checks are tested in tests/io; here the whole command is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evseg.cli import main
from evseg.io import write_npz
from evseg.events import EventStream
from evseg.results import load_result

from robust_helpers import random_events

SIZE = (32, 24)


def _translation_flow_file(path: Path, n: int, index: np.ndarray | None = None) -> Path:
    """Flow of one translation (100, -50) px/s on random edge directions for events ``index``."""
    index = np.arange(n) if index is None else index
    a = np.random.default_rng(0).uniform(0, np.pi, len(index))
    s = np.cos(a) * 100 - np.sin(a) * 50
    np.savez(path, index=index, nx=(s * np.cos(a)).astype(np.float32), ny=(s * np.sin(a)).astype(np.float32))
    return path


def _segment(capsys, rec: Path, out: Path, *extra: str) -> tuple[int, list[str]]:
    capsys.readouterr()
    rc = main(["segment", str(rec), "--out", str(out), "--no-progress", *extra])
    return rc, capsys.readouterr().err.strip().splitlines()


def test_ten_second_gap_gives_empty_windows_and_all_labels(tmp_path, capsys):
    a = random_events(400, SIZE, seed=1)
    b = random_events(400, SIZE, t0_us=int(a["t"][-1]) + 10_000_000, seed=2)
    ev = np.concatenate([a, b])
    rec = write_npz(EventStream(ev, SIZE), tmp_path / "gap.npz")
    flow = _translation_flow_file(tmp_path / "flow.npz", len(ev))
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow", str(flow))
    assert rc == 0, err
    r = load_result(tmp_path / "r.npz")
    n_windows = (int(ev["t"][-1]) - int(ev["t"][0])) // 10_000 + 1
    assert len(r.window_t0_us) == n_windows > 1000  # the gap is kept as empty windows
    assert np.all(np.diff(r.window_t0_us) == 10_000)
    assert len(r.label) == len(ev) and (r.label == 0).all()  # one translation: background


def test_all_events_at_one_timestamp(tmp_path, capsys):
    ev = random_events(500, SIZE, seed=3)
    ev["t"] = 123_456
    rec = write_npz(EventStream(ev, SIZE), tmp_path / "same_t.npz")
    flow = _translation_flow_file(tmp_path / "flow.npz", len(ev), np.arange(len(ev)))
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow", str(flow))
    assert rc == 0, err
    r = load_result(tmp_path / "r.npz")
    assert r.window_t0_us.tolist() == [123_456] and len(r.label) == len(ev)
    assert set(np.unique(r.label).tolist()) <= {-1, 0}


def test_duplicate_flow_rows_are_refused_before_work(tmp_path, capsys):
    # Two flows for one event: which one counts would be arbitrary, so the file is refused.
    ev = random_events(500, SIZE, seed=3)
    rec = write_npz(EventStream(ev, SIZE), tmp_path / "rec.npz")
    index = np.sort(np.concatenate([np.arange(len(ev)), np.arange(0, len(ev), 7)]))  # some rows twice
    flow = _translation_flow_file(tmp_path / "flow.npz", len(ev), index)
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow", str(flow))
    assert rc == 2
    assert f"{flow}: key 'index' holds event 0 more than once (72 repeated rows)" in err[0]
    assert not (tmp_path / "r.npz").exists()


def _bad_file(tmp_path: Path, case: str) -> tuple[Path, list[str]]:
    """A recording broken in one way and the texts its error line must contain."""
    ev = random_events(600, SIZE, span_us=30_000, seed=4)
    if case == "wrap-around":
        # A 32-bit microsecond counter overflowing after event 300.
        ev["t"][:300] += 2**32 - 40_000
        ev["t"][300:] -= ev["t"][300] - 5
        p = tmp_path / "wrap.npy"
        np.save(p, ev)
        return p, [str(p), "not sorted", "event 300"]
    if case == "time goes back":
        ev["t"][450] = ev["t"][449] - 1
        p = tmp_path / "back.npy"
        np.save(p, ev)
        return p, [str(p), "not sorted", "event 450"]
    if case == "negative time":
        ev["t"] -= ev["t"][10] + 1
        p = tmp_path / "neg.npy"
        np.save(p, ev)
        return p, [str(p), "negative timestamp", "event 0"]
    if case == "NaN time (text)":
        p = tmp_path / "nan.txt"
        p.write_text("32 24\n0.000001 1 2 1\n0.000002 3 4 0\nnan 3 4 0\n0.000004 1 1 1\n")
        return p, [str(p), "line 4", "field 't'", "nan"]
    if case == "inf x (float npy)":
        f = np.zeros(3, dtype=[("t", "f8"), ("x", "f4"), ("y", "f4"), ("p", "i1")])
        f["t"], f["x"], f["y"] = [0, 1e-6, 2e-6], [1, np.inf, 2], [1, 1, 1]
        p = tmp_path / "inf.npy"
        np.save(p, f)
        return p, [str(p), "field 'x'", "inf", "event 1"]
    if case == "x off the sensor":
        ev["x"][77] = SIZE[0]
        p = tmp_path / "off.npy"
        np.save(p, ev)
        return p, [str(p), "field 'x' = 32", "event 77", "outside the sensor 32x24"]
    raise AssertionError(case)


@pytest.mark.parametrize("case", ["wrap-around", "time goes back", "negative time", "NaN time (text)",
                                  "inf x (float npy)", "x off the sensor"])
def test_broken_time_or_coordinates_stop_with_one_line(case, tmp_path, capsys):
    rec, texts = _bad_file(tmp_path, case)
    out = tmp_path / "out" / "r.npz"
    rc, err = _segment(capsys, rec, out, "--flow-method", "planefit", "--sensor-size", "32x24")
    assert rc == 2 and len(err) == 1, err
    for text in texts:
        assert text in err[0], (text, err[0])
    if out.exists():  # windows before the broken event were processed: kept, flagged partial
        r = load_result(out)
        assert r.partial and len(r.window_t0_us) >= 1 and len(r.label) == r.n_events_processed


def test_wrap_around_after_some_windows_keeps_them_as_partial(tmp_path, capsys, monkeypatch):
    """Chunks of 500 events: the wrap at event 2000 is found in the 5th chunk, after the windows
    of the first 2000 events were segmented; those are kept (partial), nothing after them."""
    import functools

    import evseg.io

    monkeypatch.setattr(evseg.io, "open_recording", functools.partial(evseg.io.open_recording, chunk_events=500))
    ev = random_events(3000, SIZE, span_us=60_000, seed=5)
    ev["t"][2000:] -= ev["t"][2000] - 3  # the counter wraps after 2000 events (~40 ms)
    rec = tmp_path / "wrap.npy"
    np.save(rec, ev)
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow-method", "planefit", "--sensor-size", "32x24")
    assert rc == 2 and len(err) == 1 and "event 2000" in err[0], err
    r = load_result(tmp_path / "r.npz")
    assert r.partial and len(r.window_t0_us) >= 2
    assert 0 < r.n_events_processed <= 2000 and len(r.label) == r.n_events_processed
    assert r.window_t1_us[-1] <= ev["t"][1999] + 1  # no window reaches into the wrapped part


def test_sensor_size_absent(tmp_path, capsys):
    """No sensor size in the file: the events' grid (max + 1), said in the summary, as `evseg
    flow` does; --sensor-size overrides."""
    ev = random_events(300, SIZE, seed=6)
    rec = tmp_path / "nosize.npy"
    np.save(rec, ev)
    out = tmp_path / "r.npz"
    capsys.readouterr()
    rc = main(["segment", str(rec), "--out", str(out), "--no-progress", "--flow-method", "planefit"])
    size = (int(ev["x"].max()) + 1, int(ev["y"].max()) + 1)
    assert rc == 0 and f"sensor size {size[0]}x{size[1]} inferred from the events" in capsys.readouterr().out
    assert load_result(out).sensor_size == size and len(load_result(out).label) == len(ev)
    rc, err = _segment(capsys, rec, out, "--flow-method", "planefit", "--sensor-size", "32x24")
    assert rc == 0, err
    assert load_result(out).sensor_size == (32, 24) and len(load_result(out).label) == len(ev)


def test_unsorted_time_hint_is_an_option_of_segment(tmp_path, capsys):
    rec, _ = _bad_file(tmp_path, "time goes back")
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow-method", "planefit", "--sensor-size", "32x24")
    assert rc == 2 and "--sort" in err[0]
    rc, err = _segment(capsys, rec, tmp_path / "r.npz", "--flow-method", "planefit", "--sensor-size", "32x24",
                       "--sort")
    assert rc == 0, err
