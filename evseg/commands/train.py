"""Train the normal-flow head on simulated scenes (LightningCLI underneath).

Everything from --config on is handed to LightningCLI unchanged, so every Lightning option
works: ``evseg train --config configs/train/default.yaml --trainer.max_steps 2000
--trainer.accelerator gpu --trainer.devices 2 --trainer.strategy ddp``. The run folder
(``runs/<config>/normal_flow/version_N``, set by the config's logger:
``--trainer.logger.init_args.save_dir DIR`` moves it) receives the effective config,
checkpoints (``last.ckpt``: the final step) and CSV metrics. A run resumes from a checkpoint
with ``--ckpt_path FILE`` and the same ``--trainer.max_steps``.
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
        help="training config (configs/train/default.yaml, quick.yaml); must come last: "
        "the options after it go to LightningCLI",
    )


def run(args: argparse.Namespace) -> int:
    if not args.config:
        raise ConfigError("--config needs a YAML file")
    config, rest = args.config[0], args.config[1:]
    if not Path(config).is_file():
        raise ConfigError(f"--config: file not found: {config}")
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    from evseg.train.cli import main

    import warnings

    try:
        with warnings.catch_warnings():
            # The arguments are sys.argv's own, handed over on purpose: Lightning's warning
            # against giving both would only confuse.
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            main([args.subcommand, "--config", config, *rest])
    except MisconfigurationException as exc:
        # Lightning's word for a setting this machine or run cannot honour (e.g. an
        # accelerator it does not have): the user's to change, not a bug in evseg.
        raise ConfigError(f"{config}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    return 0
