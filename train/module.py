"""LightningModule of the normal-flow head: losses, metrics, optimiser.

The module owns one :class:`evseg.veckm_flow.FlowHead` as ``self.head`` (so checkpoint keys are
``head.*``) and saves ``encoding`` (the :class:`~evseg.veckm_flow.EncodingConfig` fields) and
``head`` (the head's constructor arguments) as hyper-parameters: the checkpoint format
:func:`evseg.veckm_flow.load_head_checkpoint` reads.

Batches come from :class:`evseg.train.data.NormalFlowDataModule`: ``features`` (B, F) float32,
``normal_flow`` and ``optical_flow`` (B, 2) float32 px/s with NaN where unknown. Each row is
trained with the normal-flow loss when its GT normal flow is known (simulated data), otherwise
with VecKM_flow's loss against its GT optical flow (users' real recordings); with
``flow_target="optical"`` every row with GT optical flow takes VecKM_flow's loss, as VecKM_flow
itself is trained. The uncertainty output is trained with a negative log-likelihood of the
realised error: the angular error (radians) on normal-flow rows.
"""

from __future__ import annotations

import math

import lightning.pytorch as pl
import torch

from evseg.errors import ConfigError
from evseg.veckm_flow.encoding import EncodingConfig
from evseg.veckm_flow.model import FlowHead
from evseg.veckm_flow import losses as L


UNCERTAINTY_TARGETS = ("angle", "relative_error")
FLOW_TARGETS = ("normal", "optical")


class NormalFlowModule(pl.LightningModule):
    """Train a :class:`~evseg.veckm_flow.FlowHead` on precomputed encoder features.

    Args:
        encoding: the :class:`~evseg.veckm_flow.EncodingConfig` (also used by the data), or a
            dict of its fields (a checkpoint's hyper-parameters). Typed as the dataclass so
            that LightningCLI parses each field with its type (``--model.encoding.d 16``,
            ``--model.encoding.polarity false``) and merges a later ``--config`` that sets a
            few fields with the earlier ones, instead of replacing the whole encoding.
        head: keyword arguments of :class:`~evseg.veckm_flow.FlowHead` besides the input width
            (which follows from ``encoding``).
        lr: peak learning rate (AdamW, one-cycle schedule over the run's steps).
        weight_decay: AdamW weight decay.
        uncertainty_weight: weight of the uncertainty NLL in the total loss.
        optical_flow_weight: weight of VecKM_flow's optical-flow loss (rows without GT normal
            flow) relative to the normal-flow loss.
        magnitude_balance: 0 = every target weighs alike in the normal-flow loss; b > 0 weighs
            each target by ``p(log |n|)^-b`` (the batch's histogram of log speed, 12 bins,
            weights normalised to mean 1, capped at 10): fast edges are ~1 % of the targets
            (a small fast object), and without weighting the head shrinks their magnitude
            towards the common speeds.
        uncertainty_target: what the uncertainty output predicts where GT normal flow is
            known: ``"angle"`` (the angular error, rad; the shipped model) or
            ``"relative_error"`` (|p - n| / |n|, dimensionless: the angular error and the
            magnitude error together, which is what the segmentation's residual scale
            |n| * uncertainty stands for).
        object_weight: weight of a target on an independently moving object (ground-truth
            label >= 1, simulated data) in the normal-flow loss, relative to a background
            target's 1. Objects are a few % of the targets, yet the segmentation needs their
            flow most: 1 = every target weighs alike (the shipped model). It weighs the
            optical-flow loss alike (real recordings have no labels: every row weighs 1).
        flow_target: which ground truth the flow output learns where both are known
            (simulated data). ``"normal"`` (the shipped model): the normal flow, the optical
            flow only where no normal flow is known. ``"optical"``: VecKM_flow's loss against
            the optical flow on every row that has it, which accepts any flow on the circle of
            normal flows consistent with it (the projection of the optical flow on any
            direction: where a neighbourhood shows texture the head may give the optical flow
            itself, where it shows one edge the normal flow); the segmentation's constraint
            p . u = |p|^2 holds for all of them. The normal-flow metrics are still logged.
        magnitude_weight: weight of the log-magnitude term of the normal-flow loss against its
            direction term (1: the shipped model).
        object_weight_uncertainty: the uncertainty NLL weighs object targets by
            ``object_weight`` too (False: the shipped model; every target alike).
    """

    def __init__(
        self,
        encoding: EncodingConfig = EncodingConfig(),  # noqa: B008 - frozen, never modified
        head: dict | None = None,
        lr: float = 3e-3,
        weight_decay: float = 1e-4,
        uncertainty_weight: float = 0.1,
        optical_flow_weight: float = 1.0,
        magnitude_balance: float = 0.0,
        uncertainty_target: str = "angle",
        object_weight: float = 1.0,
        flow_target: str = "normal",
        magnitude_weight: float = 1.0,
        object_weight_uncertainty: bool = False,
    ):
        super().__init__()
        encoding = encoding_fields(encoding)
        head = _head_arguments(head)
        self.save_hyperparameters({"encoding": encoding, "head": head, "lr": lr,
                                   "weight_decay": weight_decay,
                                   "uncertainty_weight": uncertainty_weight,
                                   "optical_flow_weight": optical_flow_weight,
                                   "magnitude_balance": float(magnitude_balance),
                                   "uncertainty_target": uncertainty_target,
                                   "object_weight": float(object_weight),
                                   "flow_target": flow_target,
                                   "magnitude_weight": float(magnitude_weight),
                                   "object_weight_uncertainty": bool(object_weight_uncertainty)})
        if not object_weight > 0:
            raise ConfigError(f"model.object_weight must be > 0, got {object_weight}")
        if not magnitude_weight > 0:
            raise ConfigError(f"model.magnitude_weight must be > 0, got {magnitude_weight}")
        if flow_target not in FLOW_TARGETS:
            raise ConfigError(f"model.flow_target must be one of {', '.join(FLOW_TARGETS)}, got {flow_target!r}")
        if uncertainty_target not in UNCERTAINTY_TARGETS:
            raise ConfigError(f"model.uncertainty_target must be one of {', '.join(UNCERTAINTY_TARGETS)}, "
                             f"got {uncertainty_target!r}")
        self.encoding_config = EncodingConfig.from_dict(encoding)
        self.head = FlowHead(in_features=self.encoding_config.n_features, **head)
        self.flow_unit_px_s = float(self.encoding_config.flow_unit_px_s)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """(B, F) features -> (B, 3) head output (flow in head units, log uncertainty)."""
        return self.head(features)

    # ------------------------------------------------------------------ loss

    def _losses(self, batch: dict) -> dict[str, torch.Tensor]:
        out = self(batch["features"])
        pred = out[:, :2]
        log_u = out[:, 2]
        nf = batch["normal_flow"] / self.flow_unit_px_s
        of = batch["optical_flow"] / self.flow_unit_px_s
        known_nf = torch.isfinite(nf).all(dim=1)
        known_of = torch.isfinite(of).all(dim=1)
        if self.hparams.get("flow_target", "normal") == "optical":
            has_nf, has_of = known_nf & ~known_of, known_of
        else:
            has_nf, has_of = known_nf, known_of & ~known_nf
        zero = out.sum() * 0.0  # keeps every parameter in the graph (DDP needs it)
        parts = {"nf": zero, "of": zero, "nll": zero}
        # Error label of the uncertainty output: the angular error (rad) where GT normal flow
        # is known; VecKM_flow's distance from the circle of consistent normal flows where only
        # optical flow is (the gradient direction, hence an angle, is unknown there).
        err = torch.zeros_like(log_u)
        ae = L.angular_error(pred, torch.nan_to_num(nf))
        if has_nf.any():
            per_target = L.normal_flow_loss(pred[has_nf], nf[has_nf],
                                            magnitude_weight=float(self.hparams.get("magnitude_weight", 1.0)))
            balance = float(self.hparams.get("magnitude_balance", 0.0))
            if balance > 0:
                per_target = per_target * L.magnitude_weights(nf[has_nf], balance)
            parts["nf"] = self._object_weighted_mean(per_target, batch, has_nf)
            if self.hparams.get("uncertainty_target", "angle") == "relative_error":
                gt = torch.nan_to_num(nf)
                rel = (pred - gt).norm(dim=1) / gt.norm(dim=1).clamp_min(1e-6)
                err = torch.where(has_nf, rel, err)
            else:
                err = torch.where(has_nf, ae, err)
        if has_of.any():
            per_target = L.veckm_optical_flow_loss(pred[has_of], of[has_of])
            parts["of"] = self._object_weighted_mean(per_target, batch, has_of)
            err = torch.where(has_of, L.optical_flow_error(pred, torch.nan_to_num(of)), err)
        known = has_nf | has_of
        if known.any():
            # uncertainty_nll detaches the error: the uncertainty learns it, the flow is not
            # pulled by it.
            nll = L.uncertainty_nll(log_u[known], err[known])
            if self.hparams.get("object_weight_uncertainty", False):
                parts["nll"] = self._object_weighted_mean(nll, batch, known)
            else:
                parts["nll"] = nll.mean()
        n_nf, n_of = has_nf.sum(), has_of.sum()
        flow_loss = (n_nf * parts["nf"] + self.hparams.optical_flow_weight * n_of * parts["of"]) / known.sum().clamp(min=1)
        parts["loss"] = flow_loss + self.hparams.uncertainty_weight * parts["nll"]
        # Reported against the normal flow wherever it is known, whichever loss trained the row.
        parts["angular_error_deg"] = torch.rad2deg(ae[known_nf]).detach()
        parts["sign_ok"] = ((pred[known_nf] * nf[known_nf]).sum(dim=1) > 0).float().detach()
        return parts

    def _object_weighted_mean(self, per_target: torch.Tensor, batch: dict, rows: torch.Tensor) -> torch.Tensor:
        """Mean of ``per_target`` (the loss of the ``rows`` of the batch), targets on objects
        weighing ``object_weight`` and the others 1; the plain mean without ``is_object``."""
        w_obj = float(self.hparams.get("object_weight", 1.0))
        if w_obj == 1.0 or "is_object" not in batch:
            return per_target.mean()
        w = 1.0 + (w_obj - 1.0) * batch["is_object"][rows]
        return (w * per_target).sum() / w.sum()

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        parts = self._losses(batch)
        bs = len(batch["features"])
        self.log("train/loss", parts["loss"], prog_bar=True, batch_size=bs)
        self.log_dict({f"train/{k}": parts[k] for k in ("nf", "of", "nll")}, batch_size=bs)
        return parts["loss"]

    def on_validation_epoch_start(self) -> None:
        self._val_err: list[torch.Tensor] = []
        self._val_sign: list[torch.Tensor] = []

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        parts = self._losses(batch)
        self.log("val/loss", parts["loss"], prog_bar=True, sync_dist=True, batch_size=len(batch["features"]))
        self._val_err.append(parts["angular_error_deg"])
        self._val_sign.append(parts["sign_ok"])

    def on_validation_epoch_end(self) -> None:
        # Per-process median and rate, averaged over processes: gathering rows of unequal
        # length across DDP ranks is not portable, and the shards are large enough that the
        # per-rank median is the global one to within noise.
        if self._val_err:
            err = torch.cat(self._val_err)
            if err.numel():
                self.log("val/median_ae_deg", err.median(), prog_bar=True, sync_dist=True)
        if self._val_sign:
            sign = torch.cat(self._val_sign)
            if sign.numel():
                self.log("val/sign_correct", sign.mean(), sync_dist=True)

    # ------------------------------------------------------------------ optimiser

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Resuming (``--ckpt_path``) a run with another length would fail deep in the
        one-cycle schedule (its total step count is restored with it): say so first."""
        from evseg.errors import ConfigError

        trainer = self._trainer
        planned = [s.get("total_steps") for s in checkpoint.get("lr_schedulers", []) if isinstance(s, dict)]
        if trainer is None or not planned or planned[0] is None or trainer.state.fn != "fit":
            return
        now = trainer.max_steps
        if now is not None and now > 0 and int(now) != int(planned[0]):
            raise ConfigError(
                f"--ckpt_path: the checkpoint's run was planned for {int(planned[0])} steps (its one-cycle "
                f"learning rate ends there), this one for {int(now)}; resume it with --trainer.max_steps "
                f"{int(planned[0])}, or start a new run to train longer")

    def configure_optimizers(self):
        opt = torch.optim.AdamW(self.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        total = self.trainer.estimated_stepping_batches
        if not math.isfinite(total) or total < 4:
            return opt  # too short for the one-cycle schedule's two phases: a constant rate
        # 10 % warm-up, but at least 2 steps: OneCycleLR divides by the warm-up's length - 1.
        pct_start = max(0.1, 2.0 / int(total))
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=self.hparams.lr, total_steps=int(total),
                                                    pct_start=pct_start)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}


def encoding_fields(encoding) -> dict:
    """Every :class:`~evseg.veckm_flow.EncodingConfig` field of ``encoding`` (an
    ``EncodingConfig``, a dict of some of its fields, a parsed config group with ``as_dict``,
    or None: the defaults) as a plain dict; an unknown field or a bad value is a
    :class:`~evseg.errors.ConfigError` naming it."""
    if isinstance(encoding, EncodingConfig):
        return encoding.to_dict()
    if hasattr(encoding, "as_dict"):  # jsonargparse's Namespace (a linked config group)
        encoding = encoding.as_dict()
    return EncodingConfig.from_dict(dict(encoding or {})).to_dict()


def _head_arguments(head: dict | None) -> dict:
    """The head's size arguments as ints. Values set on the command line
    (``--model.head.hidden 128``) arrive as strings; anything else is a ConfigError naming
    the field."""
    from evseg.errors import ConfigError

    out = {}
    for key, value in dict(head or {}).items():
        if key not in ("hidden", "layers"):
            raise ConfigError(f"model.head: unknown field '{key}'; known: hidden, layers")
        try:
            number = int(str(value).strip())
        except ValueError:
            number = None
        if number is None or number < 1 or isinstance(value, bool) or (isinstance(value, float) and value != number):
            raise ConfigError(f"model.head.{key} must be a positive integer, got {value!r}")
        out[key] = number
    return out
