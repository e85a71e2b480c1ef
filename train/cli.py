"""LightningCLI for the normal-flow head: ``python -m evseg.train fit --config configs/train/default.yaml``.

Standard LightningCLI subcommands (``fit``, ``validate``) and options (``--trainer.max_steps``,
``--trainer.devices 4 --trainer.strategy ddp``, ``--seed_everything``, ``--print_config``). The
encoder settings are given once, as ``model.encoding``, and linked to the datamodule, so the
features the head is trained on and the checkpoint's ``encoding`` hyper-parameters can never
disagree. LightningCLI writes the effective config (``config.yaml``) into the run's log
folder next to the checkpoints and the CSV metrics; ``last.ckpt`` there holds the final step
(:class:`~evseg.train.checkpointing.FinalLastCheckpoint`).
"""

from __future__ import annotations


from lightning.pytorch.cli import LightningCLI

from evseg.train.checkpointing import FinalLastCheckpoint
from evseg.train.data import NormalFlowDataModule
from evseg.train.module import NormalFlowModule


class NormalFlowCLI(LightningCLI):
    """LightningCLI with the encoder config shared by model and data."""

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("model.encoding", "data.encoding")
        # Always on, whatever the config's callbacks: last.ckpt holds the last step.
        parser.add_lightning_class_args(FinalLastCheckpoint, "final_last_checkpoint")


def main(args: list[str] | None = None) -> NormalFlowCLI:
    """Run the CLI on ``args`` (default: ``sys.argv[1:]``); returns it (trainer, model, data)."""
    return NormalFlowCLI(
        NormalFlowModule,
        NormalFlowDataModule,
        args=args,
        # A fixed default seed: runs are reproducible unless the config says otherwise.
        seed_everything_default=0,
        save_config_kwargs={"overwrite": True},
        parser_kwargs={"parser_mode": "yaml"},
    )
