"""LightningCLI end to end on CPU: a few steps, run folder contents, `evseg train`, DDP on 2 processes."""

from __future__ import annotations

import contextlib
import csv
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from evseg.cli import main as evseg_main
from evseg.train.evaluate import SHIPPED_MODEL_TRAIN_SEEDS
from evseg.veckm_flow.model import load_head_checkpoint

# Imported at collection: Lightning's log handler then binds to the session's stderr, not to
# the stderr of the first test's capsys (closed after that test).
pytest.importorskip("lightning.pytorch", reason="the 'train' extra (pip install -e \".[train]\")")

REPO = Path(__file__).resolve().parents[2]
QUICK = REPO / "configs" / "train" / "quick.yaml"


def _tiny_args(root: Path, recording: Path) -> list[str]:
    """Override quick.yaml: the edge recording as the only data, a few steps, outputs in tmp."""
    return [
        "--data.presets", "[]",
        "--data.real_recordings", f"[{recording}]",
        "--data.real_repeats", "2",
        "--data.slices.slices_per_scene", "3",
        "--data.slices.max_targets_per_slice", "64",
        "--data.batch_size", "32",
        "--data.build_workers", "1",
        "--data.cache_dir", str(root / "cache"),
        "--trainer.max_steps", "6",
        "--trainer.log_every_n_steps", "1",
        "--trainer.accelerator", "cpu",
        "--trainer.default_root_dir", str(root),
        "--trainer.logger.init_args.save_dir", str(root),
        "--model.head", "{hidden: 16, layers: 1}",
    ]


def _run_dir(root: Path) -> Path:
    (d,) = sorted((root / "normal_flow").glob("version_*"))
    return d


def test_fit_writes_config_metrics_and_a_loadable_checkpoint(tmp_path, edge_recording):
    from evseg.train.cli import main

    cli = main(["fit", "--config", str(QUICK), *_tiny_args(tmp_path, edge_recording)])
    assert cli.trainer.global_step == 6
    run = _run_dir(tmp_path)
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    assert cfg["seed_everything"] == 0
    from evseg.veckm_flow.encoding import EncodingConfig

    # linked by the CLI: the data are encoded with the model's encoding
    full = EncodingConfig.from_dict(cfg["model"]["encoding"]).to_dict()
    assert cli.datamodule.encoding == cli.model.hparams.encoding == full
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert any(r.get("train/of") for r in rows)  # the optical-flow loss was used
    head, enc = load_head_checkpoint(run / "checkpoints" / "last.ckpt")
    assert head.hidden == 16 and enc.d == cfg["model"]["encoding"]["d"]


@contextlib.contextmanager
def _lightning_messages():
    """The messages Lightning logs inside the block. Its logger does not propagate to the root
    logger (caplog) when it was imported before any handler existed: listen on it directly."""
    messages: list[str] = []
    listener = logging.Handler(logging.INFO)
    listener.emit = lambda record: messages.append(record.getMessage())
    lightning_log = logging.getLogger("lightning.pytorch")
    lightning_log.addHandler(listener)
    try:
        yield messages
    finally:
        lightning_log.removeHandler(listener)


def test_evseg_train_passes_options_through(tmp_path, edge_recording):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = evseg_main(["train", "--config", str(QUICK), *_tiny_args(tmp_path, edge_recording),
                         "--trainer.max_steps", "2"])
    assert rc == 0
    # evseg hands LightningCLI the command line on purpose: no warning against doing so.
    assert not [w for w in caught if "LightningCLI's args parameter" in str(w.message)]
    # Nor Lightning's pytree helper's deprecation notice, known and harmless, which every run printed.
    assert not [w for w in caught if "LeafSpec" in str(w.message)]
    assert (_run_dir(tmp_path) / "checkpoints" / "last.ckpt").exists()
    assert evseg_main(["train", "--config", str(tmp_path / "missing.yaml")]) == 2


def test_ddp_on_two_cpu_processes(tmp_path, edge_recording):
    # DDP relaunches the command line for each process, so run the CLI as its own program.
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    cmd = [
        sys.executable, "-m", "evseg.train", "fit", "--config", str(QUICK),
        *_tiny_args(tmp_path, edge_recording),
        "--trainer.strategy", "ddp", "--trainer.devices", "2", "--trainer.max_steps", "3",
    ]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "distributed_backend=gloo" in proc.stderr + proc.stdout
    assert "All distributed processes registered" in proc.stderr + proc.stdout
    head, _ = load_head_checkpoint(_run_dir(tmp_path) / "checkpoints" / "last.ckpt")
    assert head.hidden == 16


def test_shipped_configs_parse(tmp_path):
    """Every config in configs/train is a valid LightningCLI config (a typo would only surface at
    training time); one without ``seed_everything`` is an override of default.yaml."""
    folder = REPO / "configs" / "train"
    names = sorted(p.name for p in folder.glob("*.yaml"))
    assert {"default.yaml", "quick.yaml", "time_scale_30ms.yaml"} <= set(names)
    for name in names:
        cfg = folder / name
        standalone = "seed_everything" in yaml.safe_load(cfg.read_text())
        configs = [cfg] if standalone else [folder / "default.yaml", cfg]
        args = [a for c in configs for a in ("--config", str(c))]
        proc = subprocess.run(
            [sys.executable, "-m", "evseg.train", "fit", *args, "--print_config"],
            cwd=tmp_path, capture_output=True, text=True, timeout=120,
        )
        assert proc.returncode == 0, (name, proc.stderr[-2000:])
        printed = yaml.safe_load(proc.stdout)
        assert printed["seed_everything"] == 0, name
        assert printed["model"]["encoding"]["polarity"] is True, name
        if name == "default.yaml":
            # the shipped model's recipe, which `evseg eval --seeds` quotes when it refuses them
            assert tuple(printed["data"]["train_seeds"]) == SHIPPED_MODEL_TRAIN_SEEDS
            assert printed["trainer"]["max_steps"] == 48000
        if name in ("time_scale_30ms.yaml", "d64_t20_h64.yaml", "pyramid_t20.yaml"):
            # tried with default.yaml's recipe of their day, which they pin to stay reproducible
            assert printed["trainer"]["max_steps"] == 16000, name
            assert printed["data"]["train_seeds"] == [0, 48], name
        if name == "time_scale_30ms.yaml":
            assert printed["model"]["encoding"]["t_scale_us"] == 30000.0
        if name == "pyramid_t20.yaml":
            assert printed["model"]["encoding"]["pyramid_levels"] == 2
            assert printed["model"]["encoding"]["t_scale_us"] == 20000.0


def test_last_checkpoint_holds_the_final_step_and_resumes(tmp_path, edge_recording):
    import torch

    from evseg.errors import ConfigError
    from evseg.train.cli import main

    # Validation at step 4 of 7 only: Lightning 2.6 alone leaves last.ckpt at step 4.
    args = [*_tiny_args(tmp_path, edge_recording), "--data.val_seeds", "[900, 901]",
            "--data.presets", "[eed_like]", "--data.train_seeds", "[0, 1]", "--data.duration_us", "40000",
            "--trainer.max_steps", "7", "--trainer.val_check_interval", "4"]
    with _lightning_messages() as messages:
        cli = main(["fit", "--config", str(QUICK), *args])
    assert cli.trainer.global_step == 7
    # The final last.ckpt says how it is saved: no "weights_only was not set" notice.
    assert any("max_steps=7" in m for m in messages) and not [m for m in messages if "weights_only" in m]
    last = _run_dir(tmp_path) / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False)["global_step"] == 7
    # Resuming it with the same length is a no-op run; with another length a one-line error.
    cli = main(["fit", "--config", str(QUICK), *args, "--ckpt_path", str(last)])
    assert cli.trainer.global_step == 7
    with pytest.raises(ConfigError, match=r"planned for 7 steps .* this one for 9; resume it with "
                                          r"--trainer.max_steps 7"):
        main(["fit", "--config", str(QUICK), *args, "--trainer.max_steps", "9", "--ckpt_path", str(last)])


def test_an_accelerator_the_machine_lacks_is_a_user_error(tmp_path, edge_recording, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    rc = evseg_main(["train", "--config", str(QUICK), *_tiny_args(tmp_path, edge_recording),
                     "--trainer.accelerator", "gpu"])
    err = capsys.readouterr().err.strip().splitlines()
    # About the machine, not the config file, with the option that works.
    assert rc == 2 and len(err) == 1 and str(QUICK) not in err[0], err
    assert "this machine has no such accelerator" in err[0] and "--trainer.accelerator cpu" in err[0], err
    assert not (tmp_path / "normal_flow").exists()  # refused before the run folder is made


def _cli_without_run(args: list[str]):
    """Parse and instantiate (model, data, trainer) as `fit` would, without fitting."""
    import warnings

    from evseg.train.cli import NormalFlowCLI
    from evseg.train.data import NormalFlowDataModule
    from evseg.train.module import NormalFlowModule

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        return NormalFlowCLI(NormalFlowModule, NormalFlowDataModule, args=args, run=False,
                             parser_kwargs={"parser_mode": "yaml"})


def test_encoding_fields_are_typed_on_the_command_line_and_merged_from_a_second_config(tmp_path, edge_recording):
    from evseg.veckm_flow.encoding import EncodingConfig

    second = tmp_path / "t30.yaml"
    second.write_text("model:\n  encoding:\n    t_scale_us: 30000.0\n")
    cli = _cli_without_run(["--config", str(QUICK), "--config", str(second), *_tiny_args(tmp_path, edge_recording),
                            "--model.encoding.pyramid_levels", "2", "--model.encoding.d", "16",
                            "--model.encoding.window_px", "2", "--model.encoding.seed", "3"])
    expected = EncodingConfig(d=16, window_px=2, seed=3, pyramid_levels=2, t_scale_us=30000.0,
                              polarity=True).to_dict()  # polarity: quick.yaml's, kept
    assert cli.model.hparams.encoding == cli.datamodule.encoding == expected
    cli = _cli_without_run(["--config", str(QUICK), *_tiny_args(tmp_path, edge_recording),
                            "--model.encoding.polarity", "false"])
    assert cli.model.hparams.encoding["polarity"] is False and cli.datamodule.encoding["polarity"] is False


def test_parse_errors_and_usage_name_evseg_train(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        evseg_main(["train", "--config", str(QUICK), "--trainer.max_stepz", "2"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "tip: For details of accepted options run: evseg train --help" in err and "evseg fit" not in err
    assert err.startswith("usage: evseg train ")
    with pytest.raises(SystemExit):
        evseg_main(["train", "--config", str(QUICK), "--help"])
    assert capsys.readouterr().out.startswith("usage: evseg train ")


@pytest.mark.parametrize("option, message", [
    (["--ckpt_path", "{tmp}/nope.ckpt"], "--ckpt_path {tmp}/nope.ckpt: file not found"),
    (["--ckpt_path", "{tmp}/text.ckpt"], "--ckpt_path {tmp}/text.ckpt: not a Lightning checkpoint torch can read"),
    (["--data.slices.slice_us", "[30000, 10000]"],
     "data.slices.slice_us must be [min, max] whole microseconds with 0 < min <= max, got [30000, 10000]"),
    (["--data.batch_size", "0"], "data.batch_size must be a whole number >= 1, got 0"),
    (["--data.presets", "[nope]"], "data.presets: unknown scene preset(s) ['nope']"),
    (["--data.real_recordings", "[{tmp}/hello.npz]"], "{tmp}/hello.npz: not an .npz file (not a zip archive)"),
])
def test_bad_options_fail_at_once_in_one_line(tmp_path, edge_recording, capsys, option, message):
    (tmp_path / "text.ckpt").write_text("not a checkpoint")
    (tmp_path / "hello.npz").write_text("hello")
    option = [o.format(tmp=tmp_path) for o in option]
    rc = evseg_main(["train", "--config", str(QUICK), *_tiny_args(tmp_path, edge_recording), *option])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith(f"evseg train: error: {message.format(tmp=tmp_path)}"), err
    # Before any data is built and before the run folder is made.
    assert not (tmp_path / "cache").exists() and not (tmp_path / "normal_flow").exists()


def test_a_config_that_is_no_yaml_is_one_line(tmp_path, capsys):
    np_file = tmp_path / "some.npz"
    np_file.write_bytes(b"PK\x03\x04\xff\xfe\x00binary")
    assert evseg_main(["train", "--config", str(np_file)]) == 2
    assert capsys.readouterr().err.strip() == (f"evseg train: error: --config {np_file}: not a text file (a training "
                                               "config is YAML, e.g. configs/train/default.yaml)")
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    assert evseg_main(["train", "--config", str(QUICK), "--config", str(tmp_path / "list.yaml")]) == 2
    assert "list.yaml: a training config is a YAML mapping" in capsys.readouterr().err


def test_shipped_training_configs_are_found_by_name_outside_the_repository(tmp_path, monkeypatch, capsys):
    """A pip install has no configs/ folder: `--config quick` (or the README's
    configs/train/quick.yaml, run elsewhere) means the installed copy."""
    from evseg.commands.train import resolve_training_config

    monkeypatch.chdir(tmp_path)
    for value in ("quick", "quick.yaml", "configs/train/quick.yaml"):
        resolved = Path(resolve_training_config(value))
        assert resolved.is_file() and resolved.read_bytes() == QUICK.read_bytes(), value
    (tmp_path / "quick.yaml").write_text("trainer: {}\n")  # a file of the user's wins
    assert resolve_training_config("quick.yaml") == "quick.yaml"
    assert evseg_main(["train", "--config", "nope"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("evseg train: error: --config: file not found: nope (the shipped configs, by name: ")
    assert "default, " in err and "quick" in err
