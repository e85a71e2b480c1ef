"""The normal-flow result and the conversion of head outputs to px/s (no torch here).

Head output convention (shared by the torch head, the ONNX model and the trainer):
``out`` is ``(T, 3)`` float: ``out[:, 0:2]`` is the normal flow ``(nx, ny)`` in head units of
``xy_scale_px`` px per ``t_scale_us`` us (see :attr:`EncodingConfig.flow_unit_px_s`), x = column,
y = row; ``out[:, 2]`` is ``log u`` with ``u`` the predicted angular error of that flow in
radians (trained with :func:`evseg.veckm_flow.losses.uncertainty_nll`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from evseg.veckm_flow.encoding import EncodingConfig

# exp(log u) is clipped to this range (rad): keeps one wild output from producing inf.
_LOG_U_RANGE = (-12.0, 4.0)


@dataclass(frozen=True)
class NormalFlow:
    """Normal flow of the target events of a slice or recording.

    Attributes:
        index: int64 ``(T,)`` position of each target in the input events.
        nx, ny: float32 ``(T,)`` normal flow, px/s of the sensor grid (x = column, y = row);
            NaN where an estimator rejects a target (the plane-fit baseline does).
        uncertainty: float32 ``(T,)``, larger = less certain; for both estimators it is an
            angular error estimate in radians (inf where rejected).
    """

    index: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    uncertainty: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    @property
    def valid(self) -> np.ndarray:
        """bool ``(T,)``: finite flow."""
        return np.isfinite(self.nx) & np.isfinite(self.ny)

    def shifted(self, offset: int) -> "NormalFlow":
        """Same flows with ``index + offset`` (slice positions to recording positions)."""
        return NormalFlow(self.index + np.int64(offset), self.nx, self.ny, self.uncertainty)

    @staticmethod
    def concatenate(parts: "list[NormalFlow]") -> "NormalFlow":
        if not parts:
            return NormalFlow(np.zeros(0, np.int64), *(np.zeros(0, np.float32) for _ in range(3)))
        return NormalFlow(*(np.concatenate([getattr(p, k) for p in parts]) for k in ("index", "nx", "ny", "uncertainty")))


def head_output_to_flow(out, cfg: EncodingConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Head output ``(T, 3)`` (numpy or torch) -> ``(nx_px_s, ny_px_s, uncertainty)`` float32.

    Flow in px/s of the encoding's coordinates (raw pixels, or undistorted pixels with a
    calibration); uncertainty = predicted angular error in radians.
    """
    if hasattr(out, "detach"):  # a torch tensor: convert without importing torch here
        out = out.detach().cpu().numpy()
    out = np.asarray(out, dtype=np.float32)
    if out.ndim != 2 or out.shape[1] != 3:
        raise ValueError(f"head output must have shape (T, 3), got {out.shape}")
    s = np.float32(cfg.flow_unit_px_s)
    unc = np.exp(np.clip(out[:, 2], *_LOG_U_RANGE)).astype(np.float32)
    return out[:, 0] * s, out[:, 1] * s, unc


def flow_to_head_units(n_px_s: np.ndarray, cfg: EncodingConfig) -> np.ndarray:
    """Normal flow in px/s (any shape) -> head units (training targets)."""
    return np.asarray(n_px_s, dtype=np.float32) / np.float32(cfg.flow_unit_px_s)
