"""The normal-flow head (torch) and its checkpoint format.

:class:`FlowHead` maps the VecKM-style features of :func:`~evseg.veckm_flow.encode_targets`
``(T, F)`` (``F = levels (2 d + 1)``) to ``(T, 3)``: normal flow ``(nx, ny)`` in head units (``xy_scale_px`` px per
``t_scale_us`` us; :func:`~evseg.veckm_flow.head_output_to_flow` converts to px/s) and
``log u``, the log of the predicted angular error in radians.

Training (see :mod:`evseg.veckm_flow.losses`): with ground-truth normal flow ``n`` in head
units (:func:`~evseg.veckm_flow.flow_to_head_units`),
``loss = normal_flow_loss(out[:, :2], n) + w * uncertainty_nll(out[:, 2], angular_error(out[:, :2], n))``;
with ground-truth optical flow ``u`` use :func:`~evseg.veckm_flow.losses.veckm_optical_flow_loss`
and :func:`~evseg.veckm_flow.losses.optical_flow_error` as the error for the NLL. The angular error passed to the
NLL is detached, so the uncertainty output learns the expected error without pushing the flow.
The head is rotation-equivariant only through training (random in-plane rotation augmentation).

Checkpoint format read by :func:`load_head_checkpoint` (a ``torch.save`` / Lightning file)::

    {"hyper_parameters": {"encoding": EncodingConfig.to_dict(), "head": FlowHead kwargs},
     "state_dict": {"head.<param>": tensor, ...}}

i.e. a Lightning ``.ckpt`` of a LightningModule that calls ``save_hyperparameters()`` with
arguments ``encoding`` (dict) and ``head`` (dict) and holds the head as attribute ``head``.
The same dict without the ``hyper_parameters`` level (``{"encoding", "head", "state_dict"}``)
and/or without the ``head.`` prefix is accepted too (:func:`save_head_checkpoint` writes it).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from evseg.errors import ModelError
from evseg.veckm_flow.encoding import EncodingConfig


class FlowHead(nn.Module):
    """MLP ``(T, F) -> (T, 3)``: ``[nx, ny]`` in head units and ``log u`` (u: angular error, rad).

    Args:
        in_features: ``F = levels (2 d + 1)`` of the encoding.
        hidden: width of the hidden layers.
        layers: number of hidden layers (>= 1), ReLU after each.

    Size: 64 x 2 (8.6 k parameters) costs ~2.2 ms per 10,000 targets on one core with
    onnxruntime, 128 x 2 (25 k) ~7 ms; in short trainings on simulated scenes 128 was ~1.3 deg
    better. The default keeps encoding + network within the 1 M flows/s budget on 2 cores.
    """

    def __init__(self, in_features: int, hidden: int = 64, layers: int = 2) -> None:
        super().__init__()
        if layers < 1 or hidden < 1 or in_features < 1:
            raise ValueError(f"FlowHead needs positive sizes, got in={in_features} hidden={hidden} layers={layers}")
        self.in_features = int(in_features)
        self.hidden = int(hidden)
        self.layers = int(layers)
        mods: list[nn.Module] = []
        width = self.in_features
        for _ in range(self.layers):
            mods += [nn.Linear(width, self.hidden), nn.ReLU()]
            width = self.hidden
        self.body = nn.Sequential(*mods)
        self.out = nn.Linear(width, 3)

    def kwargs(self) -> dict:
        """Constructor arguments (what a checkpoint stores under ``head``)."""
        return {"in_features": self.in_features, "hidden": self.hidden, "layers": self.layers}

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        """``feats`` float32 (T, F) -> float32 (T, 3)."""
        return self.out(self.body(feats))


def build_head(cfg: EncodingConfig, seed: int = 0, **kwargs) -> FlowHead:
    """A freshly initialised head for ``cfg`` (deterministic for ``seed``)."""
    gen_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    try:
        return FlowHead(in_features=cfg.n_features, **kwargs)
    finally:
        torch.random.set_rng_state(gen_state)  # do not disturb the caller's global RNG


def save_head_checkpoint(path: str | Path, head: FlowHead, cfg: EncodingConfig) -> None:
    """Write the plain checkpoint form (see module docstring), atomically."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"encoding": cfg.to_dict(), "head": head.kwargs(), "state_dict": head.state_dict()}, tmp)
    tmp.replace(path)


def load_head_checkpoint(path: str | Path) -> tuple[FlowHead, EncodingConfig]:
    """Load a head and its encoding from a Lightning ``.ckpt`` or the plain form.

    Checkpoints are pickles: load only files you trust. Raises :class:`ModelError` naming the
    file and the missing field.
    """
    path = Path(path)
    if not path.is_file():
        raise ModelError(f"{path}: checkpoint not found")
    try:
        doc = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # corrupt or not a torch file
        raise ModelError(f"{path}: not a readable torch checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(doc, dict):
        raise ModelError(f"{path}: expected a checkpoint dict, got {type(doc).__name__}")
    hp = doc.get("hyper_parameters", doc)
    for key in ("encoding", "head"):
        if key not in hp:
            raise ModelError(f"{path}: missing field '{key}' (in 'hyper_parameters' or at the top level)")
    if "state_dict" not in doc:
        raise ModelError(f"{path}: missing field 'state_dict'")
    enc = hp["encoding"]
    cfg = enc if isinstance(enc, EncodingConfig) else EncodingConfig.from_dict(dict(enc))
    head_kw = dict(hp["head"])
    head_kw.setdefault("in_features", cfg.n_features)
    if head_kw["in_features"] != cfg.n_features:
        raise ModelError(
            f"{path}: field 'head.in_features' = {head_kw['in_features']} does not match the "
            f"encoding's levels (2 d + 1) = {cfg.n_features}"
        )
    head = FlowHead(**head_kw)
    sd = doc["state_dict"]
    if any(k.startswith("head.") for k in sd):
        sd = {k[len("head."):]: v for k, v in sd.items() if k.startswith("head.")}
    try:
        head.load_state_dict(sd)
    except RuntimeError as exc:
        raise ModelError(f"{path}: field 'state_dict' does not fit FlowHead({head_kw}): {exc}") from None
    head.eval()
    return head, cfg
