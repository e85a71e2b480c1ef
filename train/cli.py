"""LightningCLI for the normal-flow head: ``python -m evseg.train fit --config configs/train/default.yaml``.

Standard LightningCLI subcommands (``fit``, ``validate``) and options (``--trainer.max_steps``,
``--trainer.devices 4 --trainer.strategy ddp``, ``--seed_everything``, ``--print_config``). The
encoder settings are given once, as ``model.encoding``, and linked to the datamodule, so the
features the head is trained on and the checkpoint's ``encoding`` hyper-parameters can never
disagree. ``model.encoding`` is a typed group (:class:`~evseg.veckm_flow.EncodingConfig`): each
field can be set on the command line (``--model.encoding.pyramid_levels 2``), and a second
``--config`` that sets a few fields keeps the others. LightningCLI writes the effective config
(``config.yaml``) into the run's log folder next to the checkpoints and the CSV metrics;
``last.ckpt`` there holds the final step
(:class:`~evseg.train.checkpointing.FinalLastCheckpoint`). ``--ckpt_path`` is checked before
anything is built (:func:`~evseg.train.checkpointing.check_resume_checkpoint`).
"""

from __future__ import annotations

import warnings

from lightning.pytorch.cli import LightningCLI

from evseg.train.checkpointing import FinalLastCheckpoint, check_resume_checkpoint
from evseg.train.data import NormalFlowDataModule
from evseg.train.module import NormalFlowModule, encoding_fields

KNOWN_HARMLESS_WARNINGS = (
    # Lightning 2.6's own pytree helper builds torch's deprecated LeafSpec on every batch
    # transfer; nothing evseg can change, and it is printed once per run.
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),
)
"""(message regex, category) of the warnings training silences: known, harmless, not the user's."""


class NormalFlowCLI(LightningCLI):
    """LightningCLI with the encoder config shared by model and data.

    ``subcommand_prog`` maps a subcommand to the program name its usage lines and parse errors
    show (``{"fit": "evseg train"}``); by default LightningCLI's ``<program> fit``.
    """

    def __init__(self, *args, subcommand_prog: dict[str, str] | None = None, **kwargs):
        self.subcommand_prog = dict(subcommand_prog or {})
        super().__init__(*args, **kwargs)

    def add_arguments_to_parser(self, parser) -> None:
        # model.encoding is a typed group (EncodingConfig): the data get its fields as a dict.
        parser.link_arguments("model.encoding", "data.encoding", compute_fn=encoding_fields)
        # Always on, whatever the config's callbacks: last.ckpt holds the last step.
        parser.add_lightning_class_args(FinalLastCheckpoint, "final_last_checkpoint")

    def setup_parser(self, add_subcommands: bool, main_kwargs: dict, subparser_kwargs: dict) -> None:
        super().setup_parser(add_subcommands, main_kwargs, subparser_kwargs)
        for name, prog in self.subcommand_prog.items():
            if name in getattr(self, "_subcommand_parsers", {}):
                self._subcommand_parsers[name].prog = prog

    def parse_arguments(self, parser, args) -> None:
        super().parse_arguments(parser, args)
        # Before LightningCLI reads the checkpoint's hyper-parameters and before any data is
        # built: a wrong --ckpt_path must not surface after minutes of shard building.
        sub = self.config.get("subcommand")
        if sub:
            cfg = self.config[sub]
            max_steps = cfg.get("trainer", {}).get("max_steps") if sub == "fit" else None
            check_resume_checkpoint(cfg.get("ckpt_path"), max_steps)


def main(args: list[str] | None = None, prog: str | None = None) -> NormalFlowCLI:
    """Run the CLI on ``args`` (default: ``sys.argv[1:]``); returns it (trainer, model, data).

    ``prog``: the program name in usage lines and parse errors (``"evseg train"``: ``fit`` is
    its default, ``validate`` is ``evseg train --subcommand validate``); default
    ``python -m evseg.train <subcommand>``.
    """
    if prog is not None:
        subcommand_prog = {"fit": prog, "validate": f"{prog} --subcommand validate"}
        parser_kwargs = {"parser_mode": "yaml", "prog": prog}
    else:
        subcommand_prog = {}
        parser_kwargs = {"parser_mode": "yaml", "prog": "python -m evseg.train"}
    with warnings.catch_warnings():
        for message, category in KNOWN_HARMLESS_WARNINGS:
            warnings.filterwarnings("ignore", message=message, category=category)
        return NormalFlowCLI(
            NormalFlowModule,
            NormalFlowDataModule,
            args=args,
            # A fixed default seed: runs are reproducible unless the config says otherwise.
            seed_everything_default=0,
            save_config_kwargs={"overwrite": True},
            parser_kwargs=parser_kwargs,
            subcommand_prog=subcommand_prog,
        )
