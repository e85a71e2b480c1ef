"""`evseg simulate` and `evseg bench sim` end to end (small sensors, short durations)."""

import numpy as np
import pytest

from evseg.cli import main
from evseg.simulator import load_recording


def test_simulate_writes_a_loadable_recording_and_a_preview(tmp_path, capsys):
    # --sensor-size as the other commands name it (--sensor works too, below).
    out, png = tmp_path / "sim.npz", tmp_path / "preview.png"
    rc = main(["simulate", "--preset", "evimo_like", "--sensor-size", "96x72", "--duration", "0.02",
               "--seed", "3", "--out", str(out), "--preview", str(png)])
    assert rc == 0
    rec = load_recording(out)
    assert rec.stream.sensor_size == (96, 72) and rec.seed == 3 and rec.duration_us == 20_000
    assert png.stat().st_size > 1000
    text = capsys.readouterr().out
    assert f"{len(rec):,} events" in text and "object" in text


def test_simulate_from_a_config_file(tmp_path):
    cfg = tmp_path / "scene.yaml"
    cfg.write_text("name: mine\nsensor: {width: 40, height: 30}\nbackground: {texture: {family: checker}, "
                   "motion: {speed_px_s: 100}}\n")
    out = tmp_path / "a.npz"
    assert main(["simulate", "--config", str(cfg), "--duration", "0.01", "--out", str(out), "--quiet"]) == 0
    rec = load_recording(out)
    assert rec.config.name == "mine" and len(rec) > 0 and np.all(rec.label <= 0)


@pytest.mark.parametrize("args, message", [
    (["--preset", "nope"], "unknown scene preset 'nope'"),
    (["--sensor", "12by3"], "--sensor must be WIDTHxHEIGHT"),
    (["--duration", "0"], "--duration must be positive"),
    (["--duration", "1e-7"], "--duration must be at least 1 us (1e-6 s), got 1e-07 s"),  # was reported as "0 us"
])
def test_user_errors_exit_2_with_one_line(tmp_path, capsys, args, message):
    rc = main(["simulate", *args, "--out", str(tmp_path / "x.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1


def test_bad_config_key_exits_2(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("sensor: {widht: 3}\n")
    assert main(["simulate", "--config", str(cfg), "--out", str(tmp_path / "x.npz")]) == 2
    assert "'sensor.widht'" in capsys.readouterr().err


def test_list_presets(capsys):
    assert main(["simulate", "--list"]) == 0
    out = capsys.readouterr().out
    for name in ("eed_like", "evimo_like", "driving_like", "ego_only"):
        assert name in out


def test_bench_quick_rows_name_their_input_size():
    from evseg.simulator.bench import benchmark

    rows = benchmark(repeats=1, quick=True)
    assert rows and set(rows[0]) >= {"preset", "sensor", "sim_s", "events", "rate_Mev_s", "wall_s"}
    assert rows[0]["events"] > 0 and rows[0]["wall_s"] > 0
