"""Where results go: `evseg segment` and `evseg flow` refuse outputs that cannot be written or
would replace an input before any work, keep the result when the video fails, and give labels
and flow indices in file order when --sort reorders the events."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from evseg.cli import main
from evseg.errors import EvsegError
from evseg.results import load_result


def _run(capsys, *argv: str) -> tuple[int, list[str]]:
    capsys.readouterr()
    rc = main([*argv, "--no-progress"])
    return rc, capsys.readouterr().err.strip().splitlines()


@pytest.fixture()
def recording(tmp_path, sim_files):
    """A private copy of the simulated recording (so a test that fails may overwrite it)."""
    _, sim, flow = sim_files
    rec, fl = tmp_path / "rec.npz", tmp_path / "flow.npz"
    rec.write_bytes(sim.read_bytes())
    fl.write_bytes(flow.read_bytes())
    return rec, fl


@pytest.mark.parametrize("command", ["segment", "flow"])
def test_the_output_may_not_be_the_recording(command, recording, capsys):
    rec, _ = recording
    before = rec.read_bytes()
    rc, err = _run(capsys, command, str(rec), "--out", str(rec))
    assert rc == 2 and len(err) == 1, err
    assert f"--out {rec}: is the recording, which the run reads; choose another name" in err[0]
    assert rec.read_bytes() == before


def test_the_output_may_not_be_the_flow_file(recording, capsys):
    rec, flow = recording
    before = flow.read_bytes()
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(flow))
    assert rc == 2 and "is the flow file (--flow)" in err[0], err
    assert flow.read_bytes() == before


@pytest.mark.parametrize("extra, message", [
    (["--video", "vid.gif"], "--video {d}/vid.gif: the file must end in .mp4"),
    (["--video", "vid"], "--video {d}/vid: the file must end in .mp4"),
    (["--out-is-a-folder"], "--out {d}/adir.npz: is a folder"),
    (["--frames", "rec.npz"], "--frames {d}/rec.npz: is a file, not a folder"),
    (["--out-below-a-file"], "--out {d}/rec.npz/r.npz: {d}/rec.npz is a file, not a folder"),
    (["--frames", "r.npz"], "--out and --frames are both {d}/r.npz: give each output its own name"),
])
def test_unusable_outputs_fail_before_any_work(extra, message, recording, tmp_path, capsys):
    rec, _ = recording
    out = tmp_path / "r.npz"
    if extra == ["--out-is-a-folder"]:
        out = tmp_path / "adir.npz"
        out.mkdir()
        extra = []
    elif extra == ["--out-below-a-file"]:
        out = rec / "r.npz"
        extra = []
    else:
        extra = [extra[0], str(tmp_path / extra[1])]
    before = sorted(p.name for p in tmp_path.iterdir())
    rc, err = _run(capsys, "segment", str(rec), "--out", str(out), "--flow-method", "planefit", *extra)
    assert rc == 2 and len(err) == 1, err
    assert message.format(d=tmp_path) in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written, no temporary left


def test_a_video_that_fails_at_the_end_keeps_the_result(recording, tmp_path, capsys, monkeypatch):
    from evseg.overlay import VideoSink

    def fail(self):
        raise EvsegError(f"{self.video}: OpenCV wrote no video")

    monkeypatch.setattr(VideoSink, "close", fail)
    rec, flow = recording
    out = tmp_path / "r.npz"
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(out),
                   "--video", str(tmp_path / "v.mp4"))
    assert rc == 2 and "OpenCV wrote no video" in err[-1], err
    r = load_result(out)
    assert not r.partial and len(r.window_t0_us) == 4  # every window of the 40 ms recording


def test_video_frame_rate_is_the_users_choice(recording, tmp_path, capsys):
    import cv2

    rec, flow = recording
    video = tmp_path / "v.mp4"
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r.npz"),
                   "--video", str(video), "--fps", "10")
    assert rc == 0, err
    cap = cv2.VideoCapture(str(video))
    fps, n = cap.get(cv2.CAP_PROP_FPS), int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    cap.release()
    assert fps == pytest.approx(10.0) and n == 4  # one frame per window of the 40 ms recording


@pytest.mark.parametrize("extra, message", [
    (["--fps", "10"], "--fps sets the frame rate of --video: give --video too"),
    (["--fps", "0", "--video", "v.mp4"], "--fps must be a positive number up to 65535 (the mp4 time base), got 0"),
    (["--fps", "nan", "--video", "v.mp4"], "--fps must be a positive number up to 65535 (the mp4 time base), got nan"),
    (["--fps", "70000", "--video", "v.mp4"], "--fps must be a positive number up to 65535 (the mp4 time base), "
                                             "got 70000"),
])
@pytest.mark.parametrize("command", ["segment", "flow"])
def test_bad_frame_rates_are_one_line_errors(command, extra, message, recording, tmp_path, capsys):
    rec, _ = recording
    extra = [str(tmp_path / a) if a.endswith(".mp4") else a for a in extra]
    rc, err = _run(capsys, command, str(rec), "--out", str(tmp_path / "r.npz"), *extra)
    assert rc == 2 and len(err) == 1 and message in err[0], err
    assert not (tmp_path / "r.npz").exists()


@pytest.fixture()
def unsorted(tmp_path, sim_files):
    """The simulated recording with a block of 1,000 events reversed in time, as .npy files
    with the simulator's normal flow as flow files: (unsorted file, its flow, its stable
    time-sorted copy, that copy's flow, order: file position of each sorted event)."""
    from evseg.io import read_events

    sim, path, _ = sim_files
    ev = read_events(path).events.copy()
    source = np.arange(len(ev))  # event of the simulation at each file position
    source[2000:3000] = source[2000:3000][::-1]
    ev = ev[source]
    order = np.argsort(ev["t"], kind="stable")
    assert (order != np.arange(len(ev))).sum() > 900
    files = {}
    for name, at in (("unsorted", source), ("sorted", source[order])):
        np.save(tmp_path / f"{name}.npy", ev if name == "unsorted" else ev[order])
        ok = np.flatnonzero(np.isfinite(sim.normal_flow[at, 0]))
        np.savez(tmp_path / f"{name}_flow.npz", index=ok, nx=sim.normal_flow[at[ok], 0],
                 ny=sim.normal_flow[at[ok], 1])
        files[name] = (tmp_path / f"{name}.npy", tmp_path / f"{name}_flow.npz")
    return (*files["unsorted"], *files["sorted"], order)


def test_sort_gives_labels_in_file_order(unsorted, tmp_path, capsys):
    bad, bad_flow, good, good_flow, order = unsorted
    size = ["--sensor-size", "128x96"]
    assert _run(capsys, "segment", str(bad), "--sort", "--flow", str(bad_flow),
                "--out", str(tmp_path / "a.npz"), *size)[0] == 0
    assert _run(capsys, "segment", str(good), "--flow", str(good_flow), "--out", str(tmp_path / "b.npz"), *size)[0] == 0
    a, b = load_result(tmp_path / "a.npz").label, load_result(tmp_path / "b.npz").label
    assert len(np.unique(b)) >= 3  # background and objects: a reordering would show
    np.testing.assert_array_equal(a[order], b)


def test_flow_with_sort_writes_file_positions(unsorted, tmp_path, capsys):
    bad, _, good, _, order = unsorted
    size = ["--sensor-size", "128x96", "--baseline"]
    assert _run(capsys, "flow", str(bad), "--sort", "--out", str(tmp_path / "fa.npz"), *size)[0] == 0
    assert _run(capsys, "flow", str(good), "--out", str(tmp_path / "fb.npz"), *size)[0] == 0
    fa, fb = np.load(tmp_path / "fa.npz"), np.load(tmp_path / "fb.npz")
    assert len(fb["index"]) > 1000
    back = np.argsort(order[fb["index"]], kind="stable")
    np.testing.assert_array_equal(fa["index"], order[fb["index"]][back])
    np.testing.assert_array_equal(fa["nx"], fb["nx"][back])


def test_flow_of_another_sensor_is_refused(recording, tmp_path, capsys):
    rec, flow = recording
    with np.load(flow) as z:
        arrays = dict(z)
    np.savez(tmp_path / "other.npz", **arrays, sensor_size=np.array([346, 260]))
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(tmp_path / "other.npz"), "--out", str(tmp_path / "r.npz"))
    assert rc == 2 and len(err) == 1, err
    assert "key 'sensor_size' = [346, 260] but the recording's sensor is 128x96 (flow of another recording?)" in err[0]
    assert not (tmp_path / "r.npz").exists()


@pytest.mark.parametrize("extra, message", [
    (["--mirrors", "8"], "--flow and --mirrors exclude each other"),
    (["--model", "m.onnx"], "--flow and --model exclude each other"),
    (["--flow-method", "planefit"], "--flow and --flow-method exclude each other"),
    (["--flow-context-ms", "40"], "--flow and --flow-context-ms exclude each other"),
    (["--threads", "2"], "--flow and --threads exclude each other"),
    (["--speed", "2"], "--speed sets the replay of --realtime: give --realtime too"),
    (["--max-lag-ms", "5"], "--max-lag-ms sets the replay of --realtime: give --realtime too"),
    (["--threads", "0"], "--threads must be at least 1, got 0"),
    (["--window-ms", "nan"], "--window-ms must be a positive number, got nan"),
    (["--window-ms", "inf"], "--window-ms must be a positive number, got inf"),
])
def test_options_that_would_not_act_are_refused(extra, message, recording, tmp_path, capsys):
    rec, flow = recording
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r.npz"), *extra)
    assert rc == 2 and len(err) == 1 and message in err[0], err


def test_planefit_refuses_the_learned_flows_options(recording, tmp_path, capsys):
    rec, _ = recording
    rc, err = _run(capsys, "segment", str(rec), "--flow-method", "planefit", "--mirrors", "8",
                   "--out", str(tmp_path / "r.npz"))
    assert rc == 2 and "--flow-method planefit and --mirrors exclude each other" in err[0], err


def test_video_and_frames_may_not_share_a_name(recording, tmp_path, capsys):
    rec, flow = recording
    v = tmp_path / "v.mp4"
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r.npz"),
                   "--video", str(v), "--frames", str(v))
    assert rc == 2 and err == [f"evseg segment: error: --video and --frames are both {v}: give each output its "
                               "own name"], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flow.npz", "rec.npz"]


def test_frames_of_an_earlier_run_are_replaced_not_mixed(recording, tmp_path, capsys):
    rec, flow = recording
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(7):  # an earlier, longer run's frames
        (frames / f"{i:06d}.png").write_bytes(b"old")
    (frames / "notes.txt").write_text("mine")
    rc = main(["segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r.npz"), "--frames", str(frames),
               "--no-progress"])
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert sorted(p.name for p in frames.iterdir()) == [f"{i:06d}.png" for i in range(4)] + ["notes.txt"]
    assert all((frames / f"{i:06d}.png").read_bytes() != b"old" for i in range(4))
    assert f"; 4 frames in {frames}, 7 numbered frames of an earlier run removed" in out.out


def test_an_error_during_the_run_is_reported_not_masked_by_the_video(recording, tmp_path, capsys, monkeypatch):
    """An error while segmenting must be the one reported, even when the unfinished video then
    fails to close (before, "OpenCV wrote no video" replaced the real error)."""
    from evseg.overlay import VideoSink
    import evseg.overlay

    def fail_close(self):
        self._writer = None
        raise EvsegError(f"{self.video}: OpenCV wrote no video")

    def boom(*a, **k):
        raise EvsegError("the real problem")

    monkeypatch.setattr(VideoSink, "close", fail_close)
    monkeypatch.setattr(evseg.overlay, "label_overlay", boom)
    rec, flow = recording
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r.npz"),
                   "--video", str(tmp_path / "v.mp4"))
    assert rc == 2 and "the real problem" in err[-1] and "OpenCV" not in err[-1], err


@pytest.mark.parametrize("value", ["nan", "inf", "0", "-5"])
def test_flow_colour_scale_is_checked_before_any_work(value, recording, tmp_path, capsys):
    rec, _ = recording
    rc, err = _run(capsys, "flow", str(rec), "--out", str(tmp_path / "f.npz"), "--video", str(tmp_path / "f.mp4"),
                   "--max-px-s", value)
    assert rc == 2 and len(err) == 1 and "--max-px-s must be a positive number (px/s), got" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["flow.npz", "rec.npz"]  # nothing written or left


def test_set_overrides_a_preset_field_and_the_result_records_it(recording, tmp_path, capsys):
    import yaml

    rec, flow = recording
    out = tmp_path / "r.npz"
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(out), "--config", "eed_like",
                   "--set", "lambda_m=55", "--set", "max_nodes=12000")
    assert rc == 0, err
    seg = yaml.safe_load(load_result(out).config)["segmentation"]
    assert seg["lambda_m"] == 55.0 and seg["max_nodes"] == 12000
    assert seg["n_sampled_normal"] == 2  # the rest is the eed_like preset's
    rc, err = _run(capsys, "segment", str(rec), "--flow", str(flow), "--out", str(out), "--set", "lambda_mm=5")
    assert rc == 2 and err == ["evseg segment: error: --set: unknown segmentation parameter(s) ['lambda_mm']"], err


def test_a_flow_file_of_another_recording_is_flagged(recording, tmp_path, capsys):
    """Same sensor, more events: every row's index is valid, so only the event count that
    `evseg flow` records can tell; the summary says so."""
    from evseg.events import EventStream
    from evseg.io import read_events, write_npz

    rec, _ = recording
    flow = tmp_path / "f.npz"
    rc, err = _run(capsys, "flow", str(rec), "--out", str(flow), "--baseline")
    assert rc == 0, err
    s = read_events(rec)
    later = s.events.copy()
    later["t"] += int(s.events["t"][-1]) + 1000
    longer = write_npz(EventStream(np.concatenate([s.events, later]), s.sensor_size), tmp_path / "longer.npz")
    capsys.readouterr()
    assert main(["segment", str(longer), "--flow", str(flow), "--out", str(tmp_path / "r.npz"), "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert (f"WARNING: {flow} was computed for a recording of {len(s.events)} events, this one has "
            f"{2 * len(s.events)} (flow of another recording?)") in out
    assert main(["segment", str(rec), "--flow", str(flow), "--out", str(tmp_path / "r2.npz"), "--no-progress"]) == 0
    assert "WARNING" not in capsys.readouterr().out
