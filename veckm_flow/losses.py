"""Losses for the normal-flow head (torch). All flows in head units (see :mod:`.model`).

- :func:`normal_flow_loss`: against ground-truth *normal* flow (the simulator gives it):
  ``(1 - cos angle) + (log(eps + |p|) - log(eps + |n|))^2``.
- :func:`veckm_optical_flow_loss`: VecKM_flow's loss against ground-truth *optical* flow ``u``
  (method.md section 3): pulls ``p`` onto the circle of diameter ``u`` (all normal flows
  consistent with ``u``): ``-cos angle(p - u/2, u) + (log(eps + |u|/2) - log(eps + |p - u/2|))^2``.
- :func:`uncertainty_nll`: Laplace negative log-likelihood that makes ``u = exp(log_u)`` the
  expected angular error (rad): ``err / u + log u``, with ``err`` detached.
"""

from __future__ import annotations

import torch

EPS = 0.01  # head units (3 px/s with the default encoding): below it magnitudes count as ~equal


def angular_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Angle between ``pred`` and ``gt`` (both (T, 2)), radians in [0, pi], shape (T,)."""
    cross = pred[:, 0] * gt[:, 1] - pred[:, 1] * gt[:, 0]
    dot = (pred * gt).sum(dim=1)
    return torch.atan2(cross.abs(), dot)


def normal_flow_loss(pred: torch.Tensor, gt: torch.Tensor, eps: float = EPS,
                     magnitude_weight: float = 1.0) -> torch.Tensor:
    """Per-target loss (T,) against ground-truth normal flow: direction + ``magnitude_weight``
    x log magnitude."""
    cos = torch.nn.functional.cosine_similarity(pred, gt, dim=1, eps=1e-8)
    logmag = torch.log(eps + pred.norm(dim=1)) - torch.log(eps + gt.norm(dim=1))
    return (1.0 - cos) + magnitude_weight * logmag.square()


def veckm_optical_flow_loss(pred: torch.Tensor, u: torch.Tensor, eps: float = 0.1) -> torch.Tensor:
    """Per-target loss (T,) against ground-truth optical flow ``u`` (VecKM_flow's form)."""
    half = 0.5 * u
    r = pred - half
    cos = torch.nn.functional.cosine_similarity(r, u, dim=1, eps=1e-8)
    return -cos + (torch.log(eps + half.norm(dim=1)) - torch.log(eps + r.norm(dim=1))).square()


def optical_flow_error(pred: torch.Tensor, u: torch.Tensor, eps: float = 0.1) -> torch.Tensor:
    """Distance (T,) of ``pred`` from the circle of normal flows consistent with ``u``:
    ``|log((eps + |pred - u/2|) / (eps + |u|/2))|`` (dimensionless). With optical-flow targets
    the true gradient direction is unknown, so there is no angular error; pass this as ``err``
    to :func:`uncertainty_nll` (the uncertainty then estimates this error, not an angle)."""
    r = (pred - 0.5 * u).norm(dim=1)
    return (torch.log(eps + r) - torch.log(eps + 0.5 * u.norm(dim=1))).abs()


def magnitude_weights(gt: torch.Tensor, balance: float, bins: int = 12, cap: float = 10.0) -> torch.Tensor:
    """Per-target weights (T,) ``p(log |gt|)^-balance`` from the histogram of log speed of the
    batch, normalised to mean 1 and capped at ``cap`` (then renormalised): rare speeds weigh
    more. Detached (a function of the targets only)."""
    with torch.no_grad():
        logm = torch.log(gt.norm(dim=1).clamp_min(1e-6))
        lo, hi = float(logm.min()), float(logm.max())
        if hi - lo < 1e-9:
            return torch.ones_like(logm)
        idx = ((logm - lo) / (hi - lo) * bins).long().clamp(0, bins - 1)
        freq = torch.bincount(idx, minlength=bins).to(logm.dtype) / len(logm)
        w = freq[idx].pow(-float(balance))
        w = w / w.mean()
        w = w.clamp(max=cap)
        return w / w.mean()


def uncertainty_nll(log_u: torch.Tensor, err: torch.Tensor) -> torch.Tensor:
    """Per-target Laplace NLL (T,): minimised by ``exp(log_u) = E[err]``; ``err`` is detached."""
    return err.detach() * torch.exp(-log_u) + log_u
