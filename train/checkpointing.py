"""``last.ckpt`` that holds the last step, and the check of a checkpoint to resume from.

Lightning 2.6's ``ModelCheckpoint(save_last=True)`` rewrites ``last.ckpt`` only at steps where
it also saves a top-k checkpoint: when the monitored validation error does not improve at
the end of a run (or the run ends between validations), ``last.ckpt`` keeps an earlier step,
and exporting or resuming from it silently loses the final steps.
"""

from __future__ import annotations

from pathlib import Path

from lightning.pytorch.callbacks import Callback, ModelCheckpoint

from evseg.errors import ConfigError

LIGHTNING_CKPT_KEYWORDS = ("last", "best", "hpc")
"""``--ckpt_path`` values Lightning resolves itself (no file name); ``registry...`` too."""


class FinalLastCheckpoint(Callback):
    """At the end of training, write the final state over each ``ModelCheckpoint``'s
    ``last.ckpt`` (those with ``save_last``). A ``ModelCheckpoint`` that never saved one
    writes its own at that moment, so it is left to do so (its file would otherwise get
    a version suffix)."""

    def on_train_end(self, trainer, pl_module) -> None:
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and cb.last_model_path:
                # Collective in distributed runs (every rank calls it; rank 0 writes). The
                # callback's own setting, given explicitly: Lightning logs a notice otherwise.
                trainer.save_checkpoint(cb.last_model_path, weights_only=bool(cb.save_weights_only))


def check_resume_checkpoint(ckpt_path, max_steps: int | None = None) -> None:
    """Refuse a ``--ckpt_path`` that cannot resume this run, before anything is built.

    Args:
        ckpt_path: the option's value; None (no resume) and Lightning's keywords
            (:data:`LIGHTNING_CKPT_KEYWORDS`, ``registry...``) pass unchecked.
        max_steps: the run's ``trainer.max_steps`` (None or <= 0: not a step-limited run). A
            checkpoint whose one-cycle learning rate was planned for another number of steps
            is refused (resuming would fail deep in the schedule).

    Raises:
        ConfigError: the file is missing, is a folder, is not a checkpoint torch can read, or
            was planned for another ``max_steps``; the message names ``--ckpt_path`` and the file.
    """
    if ckpt_path is None or str(ckpt_path) in LIGHTNING_CKPT_KEYWORDS or str(ckpt_path).startswith("registry"):
        return
    path = Path(ckpt_path)
    if not path.exists():
        raise ConfigError(f"--ckpt_path {path}: file not found")
    if not path.is_file():
        raise ConfigError(f"--ckpt_path {path}: is a folder; give a checkpoint file (e.g. .../checkpoints/last.ckpt)")
    import torch

    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same user error
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"--ckpt_path {path}: not a Lightning checkpoint torch can read ({first[:200]})") from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "global_step" not in ckpt:
        raise ConfigError(f"--ckpt_path {path}: not a Lightning training checkpoint (no 'state_dict' and "
                          "'global_step'); resume from a .ckpt that evseg train wrote")
    planned = [s.get("total_steps") for s in ckpt.get("lr_schedulers", []) if isinstance(s, dict)]
    if max_steps is not None and int(max_steps) > 0 and planned and planned[0] is not None \
            and int(planned[0]) != int(max_steps):
        raise ConfigError(
            f"--ckpt_path {path}: the checkpoint's run was planned for {int(planned[0])} steps (its one-cycle "
            f"learning rate ends there), this one for {int(max_steps)}; resume it with --trainer.max_steps "
            f"{int(planned[0])}, or start a new run to train longer")
