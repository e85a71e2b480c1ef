"""``last.ckpt`` that holds the last step.

Lightning 2.6's ``ModelCheckpoint(save_last=True)`` rewrites ``last.ckpt`` only at steps where
it also saves a top-k checkpoint: when the monitored validation error does not improve at
the end of a run (or the run ends between validations), ``last.ckpt`` keeps an earlier step,
and exporting or resuming from it silently loses the final steps.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import Callback, ModelCheckpoint


class FinalLastCheckpoint(Callback):
    """At the end of training, write the final state over each ``ModelCheckpoint``'s
    ``last.ckpt`` (those with ``save_last``). A ``ModelCheckpoint`` that never saved one
    writes its own at that moment, so it is left to do so (its file would otherwise get
    a version suffix)."""

    def on_train_end(self, trainer, pl_module) -> None:
        for cb in trainer.checkpoint_callbacks:
            if isinstance(cb, ModelCheckpoint) and cb.save_last and cb.last_model_path:
                # Collective in distributed runs (every rank calls it; rank 0 writes).
                trainer.save_checkpoint(cb.last_model_path)
