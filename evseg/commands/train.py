"""Train the normal-flow head on simulated scenes (LightningCLI underneath).

Everything from --config on is handed to LightningCLI unchanged, so every Lightning option
works: ``evseg train --config configs/train/default.yaml --trainer.max_steps 2000
--trainer.accelerator gpu --trainer.devices 2 --trainer.strategy ddp``. The run folder
(default ``runs/<name>/version_N``) receives the effective config, checkpoints and CSV metrics.
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
    from evseg.train.cli import main

    main([args.subcommand, "--config", config, *rest])
    return 0
