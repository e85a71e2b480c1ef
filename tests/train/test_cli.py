"""LightningCLI end to end on CPU: a few steps, run folder contents, `evseg train`, DDP on 2 processes."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from evseg.cli import main as evseg_main
from evseg.veckm_flow.model import load_head_checkpoint

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


def test_evseg_train_passes_options_through(tmp_path, edge_recording):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rc = evseg_main(["train", "--config", str(QUICK), *_tiny_args(tmp_path, edge_recording),
                         "--trainer.max_steps", "2"])
    assert rc == 0
    # evseg hands LightningCLI the command line on purpose: no warning against doing so.
    assert not [w for w in caught if "LightningCLI's args parameter" in str(w.message)]
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
        if name == "time_scale_30ms.yaml":
            assert printed["model"]["encoding"]["t_scale_us"] == 30000.0
            assert printed["trainer"]["max_steps"] == 16000  # the rest is default.yaml's
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
    cli = main(["fit", "--config", str(QUICK), *args])
    assert cli.trainer.global_step == 7
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
    assert rc == 2 and len(err) == 1 and str(QUICK) in err[0] and "gpu" in err[0].lower(), err
