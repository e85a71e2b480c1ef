"""Train the normal-flow head on simulated scenes (LightningCLI underneath).

Everything from --config on is handed to LightningCLI unchanged, so every Lightning option
works: ``evseg train --config configs/train/default.yaml --trainer.max_steps 2000
--trainer.accelerator gpu --trainer.devices 2 --trainer.strategy ddp``. The run folder
(``runs/<config>/normal_flow/version_N``, set by the config's logger:
``--trainer.logger.init_args.save_dir DIR`` moves it) receives the effective config,
checkpoints (``last.ckpt``: the final step) and CSV metrics. A run resumes from a checkpoint
with ``--ckpt_path FILE`` and the same ``--trainer.max_steps``, into a new version_N folder
(not bit-identical to an uninterrupted run: Lightning's dataloader is not resumable).
Every --config file, --ckpt_path and the data settings are checked before anything is built.
Equivalent to ``python -m evseg.train fit --config ...``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg.errors import ConfigError

HELP = "train the normal-flow network (LightningCLI; options after --config pass through)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--subcommand",
        choices=["fit", "validate"],
        default="fit",
        help="LightningCLI subcommand",
    )
    # REMAINDER on an option swallows everything after it, Lightning's dotted options too,
    # which argparse would otherwise reject as unknown.
    p.add_argument(
        "--config",
        nargs=argparse.REMAINDER,
        required=True,
        metavar="CONFIG.yaml [LIGHTNING OPTIONS]",
        help="training config: a YAML file or the name of a shipped one (default, quick, ...: configs/train/ of "
        "the repository, installed with evseg); must come last: "
        "the options after it go to LightningCLI (evseg train --config FILE --help lists them)",
    )


def run(args: argparse.Namespace) -> int:
    if not args.config:
        raise ConfigError("--config needs a YAML file")
    config = resolve_training_config(args.config[0])
    rest, more = _resolve_more_configs(args.config[1:])
    for path in [config, *more]:
        check_training_config(path)
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from evseg.train.cli import main

    import warnings

    try:
        with warnings.catch_warnings():
            # The arguments are sys.argv's own, handed over on purpose: Lightning's warning
            # against giving both would only confuse.
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            main([args.subcommand, "--config", config, *rest], prog="evseg train")
    except MisconfigurationException as exc:
        # Lightning's word for a setting this machine or run cannot honour (e.g. an
        # accelerator it does not have): the user's to change, not a bug in evseg.
        raise ConfigError(lightning_setting_problem(str(exc))) from None
    return 0


def shipped_training_configs() -> dict[str, Path]:
    """The training configs installed with evseg (``configs/train`` of the repository), by
    name: ``{"default": .../default.yaml, "quick": ..., ...}``."""
    import evseg.configs

    folder = Path(evseg.configs.__file__).parent / "train"
    return {p.stem: p for p in sorted(folder.glob("*.yaml"))}


def resolve_training_config(value: str) -> str:
    """``value`` when it is a file; else the shipped training config it names: ``quick``,
    ``quick.yaml`` or the README's ``configs/train/quick.yaml`` run outside the repository
    (a pip install has no ``configs/`` folder). Anything else is returned as it is, for
    :func:`check_training_config` to report.

    >>> Path(resolve_training_config("quick")).name
    'quick.yaml'
    """
    path = Path(value)
    if path.exists():
        return value
    stem = path.name[:-len(".yaml")] if path.name.endswith(".yaml") else path.name
    shipped = shipped_training_configs()
    if stem in shipped and path.parent in (Path("."), Path("configs/train")):
        return str(shipped[stem])
    return value


def _resolve_more_configs(rest: list[str]) -> tuple[list[str], list[str]]:
    """``rest`` (the options handed to LightningCLI) with the files of further ``--config FILE``
    / ``--config=FILE`` / ``-c FILE`` options resolved as the first one, and those files."""
    out, files = list(rest), []
    for i, arg in enumerate(out):
        if arg in ("--config", "-c") and i + 1 < len(out):
            out[i + 1] = resolve_training_config(out[i + 1])
            files.append(out[i + 1])
        elif arg.startswith("--config="):
            files.append(resolve_training_config(arg.split("=", 1)[1]))
            out[i] = "--config=" + files[-1]
    return out, files


def check_training_config(path: str) -> None:
    """Raise :class:`ConfigError` naming ``--config`` and ``path`` unless it is a readable YAML
    file holding a mapping (LightningCLI would otherwise fail with a decoding traceback, e.g. on
    a ``.npz`` given by mistake)."""
    import yaml

    from evseg.errors import yaml_problem

    p = Path(path)
    if not p.is_file():
        names = ", ".join(shipped_training_configs())
        raise ConfigError(f"--config: file not found: {path} (the shipped configs, by name: {names})")
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"--config {path}: not a text file (a training config is YAML, e.g. "
                          "configs/train/default.yaml)") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"--config {path}: {yaml_problem(exc)}") from None
    except OSError as exc:
        raise ConfigError(f"--config {path}: cannot read ({exc.strerror or type(exc).__name__})") from None
    if not isinstance(doc, dict):
        raise ConfigError(f"--config {path}: a training config is a YAML mapping (trainer:, model:, data:), "
                          f"got {type(doc).__name__}")


def lightning_setting_problem(message: str) -> str:
    """One line for a Lightning ``MisconfigurationException``: a trainer setting this machine
    or run cannot honour. The settings come from the config files and the command line alike,
    so no file is blamed; an accelerator the machine lacks gets the option that works.

    >>> lightning_setting_problem("No supported gpu backend found!")
    'this machine has no such accelerator (No supported gpu backend found!); train on the CPU with --trainer.accelerator cpu'
    """
    first = message.splitlines()[0].strip() if message.strip() else "Lightning refused the trainer settings"
    low = first.lower()
    if "backend found" in low or "not available" in low or "can not run on your system" in low:
        return (f"this machine has no such accelerator ({first}); train on the CPU with "
                "--trainer.accelerator cpu")
    return f"trainer settings (config or command line): {first}"
