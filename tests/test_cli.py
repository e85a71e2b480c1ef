import subprocess
import sys
from pathlib import Path

import pytest

from evseg.cli import main


def test_help_lists_subcommands(capsys):
    assert main([]) == 2
    out = capsys.readouterr().out
    assert "bench" in out and "eval" in out


def test_every_command_has_a_help_page(capsys):
    # argparse formats each option's help only when asked; a stray % in one crashed --help.
    from evseg.cli import _command_modules, build_parser

    build_parser()
    for name in _command_modules():
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0, name
        assert f"usage: evseg {name}" in capsys.readouterr().out


def test_user_error_is_one_line_and_exit_2(capsys):
    assert main(["bench", "seg", "--repeats", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["evseg bench: error: --repeats must be at least 1, got 0"]


def test_console_script_help_is_fast_and_torch_free(tmp_path):
    code = "import sys; from evseg.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    assert out.stdout.strip() == "False"


def test_commands_make_openmp_wait_passively_except_torch_training(monkeypatch):
    """OMP_WAIT_POLICY=PASSIVE for the inference commands (spinning OpenMP threads of the
    encoder slow the network right after it), never over the user's own setting, and not for
    train/export, where torch's CPU steps are faster with OpenMP's default."""
    import os

    from evseg.cli import _openmp_waits_passively

    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    _openmp_waits_passively("train")
    assert "OMP_WAIT_POLICY" not in os.environ
    _openmp_waits_passively("segment")
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    _openmp_waits_passively("bench")
    assert os.environ["OMP_WAIT_POLICY"] == "ACTIVE"


def test_bench_and_eval_tables_name_the_machine_and_its_speed(tmp_path, capsys):
    """Every table's first line says the machine, the threads and a speed reference (the
    median time of a fixed workload), so timings from different days can be compared."""
    import re

    from evseg.commands.bench import emit_table, speed_reference_ms

    ref = speed_reference_ms(repeats=1)
    assert 0 < ref < 10_000
    emit_table([{"input": "x", "total ms": 1.5}], tmp_path / "t.md")
    first = (tmp_path / "t.md").read_text().splitlines()[0]
    assert first.startswith("machine: ") and "cores" in first and "OMP_NUM_THREADS=" in first
    assert re.search(r"speed reference \d+\.\d ms", first)
    # the builds that decide floating-point results, so runs of other days can be told apart
    assert re.search(r"numpy \d+\.\d+", first) and re.search(r"onnxruntime \d+\.\d+", first)
    assert capsys.readouterr().out.splitlines()[0] == first


def test_model_option_only_where_a_learned_flow_runs(capsys):
    assert main(["eval", "seg", "--model", "m.onnx"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["evseg eval: error: --model applies to flow, flow-real, pipeline, flow-errors, not to 'seg'"]


@pytest.fixture
def fake_evaluations(monkeypatch):
    """The evaluation functions of `evseg eval` flow, flow-real, pipeline, pipeline-real and
    static replaced by fakes that record their options in the returned dict (target -> options)."""
    import evseg.pipeline_eval as pipeline_eval
    import evseg.pipeline_real as pipeline_real
    import evseg.train.evaluate as evaluate

    seen = {}

    def fake(name):
        def run(quick, **options):
            seen[name] = options
            return [{"scene": "all", "detection rate %": 1.0}]
        return run

    monkeypatch.setattr(evaluate, "evaluate_flow", fake("flow"))
    monkeypatch.setattr(evaluate, "evaluate_flow_real", fake("flow-real"))
    monkeypatch.setattr(pipeline_eval, "evaluate_pipeline_and_oracle", fake("pipeline"))
    monkeypatch.setattr(pipeline_real, "evaluate_pipeline_real", fake("pipeline-real"))
    monkeypatch.setattr(pipeline_eval, "evaluate_static_camera", fake("static"))
    return seen


def test_slow_edges_option_reaches_the_pipeline_evaluations(fake_evaluations, tmp_path, capsys):
    """`evseg eval pipeline|pipeline-real|static --slow-edges` runs the pipeline with the slow-edge
    look; other targets refuse the option with one line."""
    seen = fake_evaluations
    for target in ("pipeline", "pipeline-real", "static"):
        assert main(["eval", target, "--quick", "--slow-edges", "--out", str(tmp_path / "t.md")]) == 0
        assert seen[target] == {"slow_edges": True}
    assert main(["eval", "pipeline", "--quick", "--out", str(tmp_path / "t.md")]) == 0
    assert seen["pipeline"] == {}
    capsys.readouterr()
    assert main(["eval", "flow", "--slow-edges"]) == 2
    assert capsys.readouterr().err.strip() == (
        "evseg eval: error: --slow-edges applies to pipeline, pipeline-real, static, not to 'flow' "
        "(evseg eval flow measures the estimator with the look already)")


def test_mirrors_option_reaches_the_flow_evaluations(fake_evaluations, tmp_path, capsys):
    """`evseg eval flow|flow-real|pipeline|pipeline-real|static --mirrors N` evaluates with the
    learned flow's N mirror looks; `seg` (ground-truth flow) refuses the option with one line,
    and counts other than 1, 2, 4, 8 are refused."""
    seen = fake_evaluations
    for target in ("flow", "flow-real", "pipeline", "pipeline-real", "static"):
        assert main(["eval", target, "--quick", "--mirrors", "4", "--out", str(tmp_path / "t.md")]) == 0
        assert seen[target] == {"mirrors": 4}
    assert main(["eval", "flow", "--quick", "--out", str(tmp_path / "t.md")]) == 0
    assert seen["flow"] == {}
    capsys.readouterr()
    assert main(["eval", "seg", "--mirrors", "2"]) == 2
    assert capsys.readouterr().err.strip() == (
        "evseg eval: error: --mirrors applies to flow, flow-real, pipeline, pipeline-real, static, not to 'seg' "
        "(it evaluates ground-truth flow)")
    with pytest.raises(SystemExit):
        main(["eval", "flow", "--mirrors", "3"])
    assert "invalid choice: 3" in capsys.readouterr().err


def test_tracked_mirrors_option_reaches_the_pipeline_evaluations(fake_evaluations, tmp_path, capsys):
    """`evseg eval pipeline|pipeline-real|static --tracked-mirrors N` runs the pipeline with N
    looks in the tracked boxes; the flow targets, which have no tracks, refuse it."""
    seen = fake_evaluations
    for target in ("pipeline", "pipeline-real", "static"):
        assert main(["eval", target, "--quick", "--tracked-mirrors", "8", "--out", str(tmp_path / "t.md")]) == 0
        assert seen[target] == {"tracked_mirrors": 8}
    capsys.readouterr()
    assert main(["eval", "flow", "--tracked-mirrors", "8"]) == 2
    assert capsys.readouterr().err.strip() == (
        "evseg eval: error: --tracked-mirrors applies to pipeline, pipeline-real, static, not to 'flow' "
        "(it has no object tracks)")


def test_model_option_names_a_missing_file_before_the_run(tmp_path, capsys):
    missing = tmp_path / "missing.onnx"
    assert main(["bench", "flow", "--model", str(missing)]) == 2
    assert capsys.readouterr().err.strip() == f"evseg bench: error: {missing}: model file not found"


def test_model_option_reaches_the_evaluation(monkeypatch, tmp_path):
    """`evseg eval flow --model M` evaluates M (the evaluation function gets its path)."""
    import evseg.train.evaluate as evaluate
    from evseg.veckm_flow.inference import DEFAULT_MODEL

    seen = {}

    def fake(quick, model_path=None):
        seen.update(quick=quick, model_path=model_path)
        return [{"preset": "overall", "ae_learned": 1.0}]

    monkeypatch.setattr(evaluate, "evaluate_flow", fake)
    assert main(["eval", "flow", "--quick", "--model", str(DEFAULT_MODEL), "--out", str(tmp_path / "t.md")]) == 0
    assert seen == {"quick": True, "model_path": DEFAULT_MODEL}
    assert "| overall | 1 |" in (tmp_path / "t.md").read_text()


def test_flow_baseline_refuses_learned_flow_options(tmp_path, capsys):
    """`--model`, `--no-fast-edges`, `--no-slow-edges` and `--mirrors` only mean something for the learned flow: with
    `--baseline` they are an error before anything is read or written."""
    for option in (["--model", "m.onnx"], ["--no-fast-edges"], ["--no-slow-edges"], ["--mirrors", "8"]):
        out = tmp_path / "f.npz"
        assert main(["flow", str(tmp_path / "rec.npz"), "--out", str(out), "--baseline", *option]) == 2
        assert capsys.readouterr().err.strip() == (
            f"evseg flow: error: --baseline and {option[0]} exclude each other (both are about the learned flow)")
        assert not out.exists()


def test_seeds_set_and_presets_options_reach_the_simulated_evaluations(fake_evaluations, monkeypatch, tmp_path, capsys):
    """`evseg eval seg|pipeline --seeds 900-902,950 --set FIELD=VALUE` evaluates other scenes
    (validation) with segmentation parameters changed on every preset: the options reach the
    evaluation functions parsed (ranges inclusive, values as YAML)."""
    import evseg.segmentation.evaluate as seg_eval

    seen = fake_evaluations
    monkeypatch.setattr(seg_eval, "evaluate_oracle",
                        lambda quick, **options: seen.__setitem__("seg", options) or [{"scene": "all"}])
    out = str(tmp_path / "t.md")
    for target in ("seg", "pipeline"):
        assert main(["eval", target, "--seeds", "900-902,950", "--set", "lambda_m=60",
                     "--set", "mask_method=hull", "--presets", "driving_like, eed_like", "--out", out]) == 0
        assert seen[target] == {"seeds": [900, 901, 902, 950], "overrides": {"lambda_m": 60, "mask_method": "hull"},
                                "presets": ["driving_like", "eed_like"]}
    # The still-camera evaluation takes seeds and settings (one scene preset, so no --presets);
    # the real recordings take settings (set on each recording's preset).
    assert main(["eval", "static", "--seeds", "900-901", "--set", "uncertainty_angle_gain=0", "--out", out]) == 0
    assert seen["static"] == {"seeds": [900, 901], "overrides": {"uncertainty_angle_gain": 0}}
    assert main(["eval", "pipeline-real", "--set", "lambda_m=60", "--out", out]) == 0
    assert seen["pipeline-real"] == {"overrides": {"lambda_m": 60}}
    # The flow's accuracy on the training configs' validation scenes (a user's own model).
    assert main(["eval", "flow", "--seeds", "900-903", "--presets", "eed_like", "--out", out]) == 0
    assert seen["flow"] == {"seeds": [900, 901, 902, 903], "presets": ["eed_like"]}
    capsys.readouterr()


@pytest.mark.parametrize("argv, message", [
    (["eval", "seg", "--seeds", "900-9x"], "--seeds: '900-9x' is not a seed or a range A-B (e.g. 900-909)"),
    (["eval", "seg", "--seeds", "910-900"], "--seeds: range '910-900' runs backwards"),
    (["eval", "seg", "--seeds", "900,900"], "--seeds: '900,900' must name distinct non-negative seeds"),
    (["eval", "flow-real", "--seeds", "900"], "--seeds applies to seg, pipeline, flow-errors, static, flow, not to "
                                              "'flow-real' (it runs fixed scenes or recordings)"),
    (["eval", "flow", "--seeds", "0-3"], "--seeds: [0, 1, 2, 3] are below 900; the shipped normal-flow model was trained "
                                         "on scene seeds 0-143: use validation seeds (900-999) or the held-out ones (>= 1000, "
                                         "the default)"),
    (["eval", "static", "--seeds", "5"], "--seeds: [5] are below 900; the shipped normal-flow model was trained on scene "
                                         "seeds 0-143: use validation seeds (900-999) or the held-out ones (>= 1000, the default)"),
    (["eval", "pipeline", "--seeds", "40-42"], "--seeds: [40, 41, 42] are below 900; the shipped normal-flow model was "
                                                "trained on scene seeds 0-143: use validation seeds (900-999) or the "
                                                "held-out ones (>= 1000, the default)"),
    # A model of the user's own is not said to be the shipped one.
    (["eval", "flow", "--model", "{model}", "--seeds", "0-3"],
     "--seeds: [0, 1, 2, 3] are below 900; training configs draw their scenes there (data.train_seeds; the shipped "
     "model's: 0-143), so {model} may have been trained on them: use validation seeds (900-999) or the held-out ones "
     "(>= 1000, the default)"),
    # Validation and held-out seeds mixed: the comparison would be tuned on the published tables' scenes.
    (["eval", "flow", "--seeds", "950-1002"],
     "--seeds: mixes held-out seeds ([1000, 1001, 1002], >= 1000) with others; compare settings and models on "
     "validation seeds only (900-999), the held-out ones are for the published tables (the default without --seeds)"),
    (["eval", "seg", "--seeds", "5,1000"],
     "--seeds: mixes held-out seeds ([1000], >= 1000) with others; compare settings and models on validation seeds "
     "only (900-999), the held-out ones are for the published tables (the default without --seeds)"),
    (["eval", "seg", "--set", "lambda_m"], "--set: expected FIELD=VALUE, got 'lambda_m'"),
    (["eval", "seg", "--set", "lambda_m=[1"], "--set: cannot read the value of 'lambda_m=[1'"),
    (["eval", "flow", "--set", "lambda_m=60"], "--set applies to seg, pipeline, flow-errors, static, pipeline-real, not to "
                                                "'flow' (it segments nothing)"),
    (["eval", "static", "--presets", "eed_like"], "--presets applies to seg, pipeline, flow-errors, flow, not to 'static' (it runs "
                                                   "fixed scenes or recordings)"),
    (["eval", "seg", "--quick", "--set", "lambda_m=abc"], "evaluate_oracle: field 'lambda_m' must be float, got 'abc'"),
    (["eval", "seg", "--quick", "--set", "lambda_mm=60"], "evaluate_oracle: unknown segmentation parameter(s) ['lambda_mm']"),
    (["eval", "static", "--quick", "--set", "lambda_mm=60"],
     "evaluate_static_camera: unknown segmentation parameter(s) ['lambda_mm']"),
    (["eval", "pipeline-real", "--quick", "--set", "lambda_mm=60"],
     "evaluate_pipeline_real: unknown segmentation parameter(s) ['lambda_mm']"),
    (["eval", "seg", "--quick", "--presets", "eed"], "evaluate_oracle: unknown or no simulator preset(s) ['eed']; "
                                                      "known: ['eed_like', 'evimo_like', 'driving_like']"),
    (["eval", "pipeline", "--quick", "--presets", ","], "evaluate_pipeline: unknown or no simulator preset(s) []; "
                                                         "known: ['eed_like', 'evimo_like', 'driving_like', 'ego_only']"),
])
def test_bad_seeds_or_settings_are_one_line_errors(argv, message, capsys):
    from evseg.veckm_flow.inference import DEFAULT_MODEL

    argv = [a.format(model=DEFAULT_MODEL) for a in argv]
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == f"evseg eval: error: {message.format(model=DEFAULT_MODEL)}"


def test_eval_bench_and_simulate_check_their_outputs_before_running(tmp_path, capsys):
    # Each would run for seconds to minutes before writing: the output is checked first.
    (tmp_path / "adir").mkdir()
    folder = "--out {d}/adir: is a folder; give a file name inside it"
    cases = [(["eval", "seg", "--quick", "--out", str(tmp_path / "adir")], folder),
             (["bench", "seg", "--quick", "--out", str(tmp_path / "adir")], folder),
             (["simulate", "--preset", "eed_like", "--out", str(tmp_path / "sim.txt"), "--quiet"],
              "--out {d}/sim.txt: the file must end in .npz"),
             (["simulate", "--preset", "eed_like", "--out", str(tmp_path / "s.npz"), "--preview",
               str(tmp_path / "p.jpg"), "--quiet"], "--preview {d}/p.jpg: the file must end in .png")]
    for argv, message in cases:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message.format(d=tmp_path) in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir"]


def test_an_evaluation_of_another_model_names_it_in_its_table(fake_evaluations, tmp_path, capsys):
    shipped = Path(__file__).resolve().parents[1] / "veckm_flow" / "weights" / "normal_flow.onnx"
    model = tmp_path / "mine.onnx"
    model.write_bytes(shipped.read_bytes())
    assert main(["eval", "flow", "--quick", "--model", str(model), "--out", str(tmp_path / "t.md")]) == 0
    assert f"normal-flow model: {model}" in (tmp_path / "t.md").read_text()
    assert main(["eval", "flow", "--quick", "--out", str(tmp_path / "t.md")]) == 0
    assert "normal-flow model" not in (tmp_path / "t.md").read_text()  # the shipped one: no line


def test_evaluate_flow_runs_the_scenes_asked_for():
    from evseg.errors import ConfigError
    from evseg.train.evaluate import evaluate_flow

    rows = evaluate_flow(quick=True, seeds=[900], presets=["eed_like"])
    assert [r["preset"] for r in rows] == ["eed_like", "overall"]
    with pytest.raises(ConfigError, match="evseg eval flow: unknown or no simulator preset"):
        evaluate_flow(quick=True, presets=["nope"])


def test_a_training_checkpoint_given_as_model_says_to_export_it(tmp_path, capsys):
    ckpt = tmp_path / "last.ckpt"
    ckpt.write_bytes(b"PK\x03\x04 not an onnx model")
    assert main(["flow", str(tmp_path / "x.npz"), "--model", str(ckpt), "--out", str(tmp_path / "f.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"a training checkpoint? export it first: evseg export {ckpt} --out model.onnx" in err[0]


def test_debug_before_the_command_shows_the_traceback(tmp_path, capsys):
    bad = tmp_path / "bad.txt"
    bad.write_text("not an event\n")
    for argv in (["--debug", "info", str(bad)], ["info", "--debug", str(bad)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "Traceback (most recent call last)" in err and "evseg info: error:" in err, argv
    assert main(["info", str(bad)]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_a_missing_optional_dependency_names_the_extra_to_install(capsys, monkeypatch, tmp_path):
    """Without the 'formats' extra an HDF5 file is a one-line error with the pip command, not
    an "internal error ... please report it"."""
    import builtins

    real_import = builtins.__import__

    def without_h5py(name, *args, **kwargs):
        if name.split(".")[0] in ("h5py", "hdf5plugin"):
            raise ModuleNotFoundError(f"No module named '{name}'", name=name)
        return real_import(name, *args, **kwargs)

    for module in ("h5py", "hdf5plugin", "evseg.io.hdf5"):
        monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setattr(builtins, "__import__", without_h5py)
    (tmp_path / "x.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(200))  # the magic bytes, then nothing
    assert main(["info", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evseg info: error: this needs ") and \
        err[0].endswith("part of the optional 'formats' dependencies: pip install \"evseg[formats]\""), err
