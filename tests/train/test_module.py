"""The LightningModule: losses per target kind, training steps on CPU, the checkpoint format."""

from __future__ import annotations

import math

import torch

from evseg.train.module import NormalFlowModule
from evseg.veckm_flow.encoding import EncodingConfig


def _batch(n: int = 8, kind: str = "nf") -> dict:
    g = torch.Generator().manual_seed(0)
    flow = torch.randn(n, 2, generator=g) * 200.0  # px/s
    nan = torch.full((n, 2), float("nan"))
    return {
        "features": torch.randn(n, 65, generator=g),
        "normal_flow": flow if kind == "nf" else nan,
        "optical_flow": flow if kind == "of" else nan,
    }


def test_hyper_parameters_follow_the_checkpoint_format():
    m = NormalFlowModule(encoding={"d": 16}, head={"hidden": 32, "layers": 1})
    assert m.hparams.encoding == EncodingConfig(d=16).to_dict()
    assert m.hparams.head == {"hidden": 32, "layers": 1}
    assert all(k.startswith("head.") for k in m.state_dict())
    assert m(torch.zeros(4, 33)).shape == (4, 3)


def test_head_sizes_from_the_command_line_are_ints_and_bad_ones_are_named():
    """`--model.head.hidden 128` reaches the module as the string '128'."""
    import pytest

    from evseg.errors import ConfigError

    m = NormalFlowModule(head={"hidden": "128", "layers": 2})
    assert m.hparams.head == {"hidden": 128, "layers": 2} and m.head.hidden == 128
    for bad, field in (({"hidden": "wide"}, "hidden"), ({"layers": 0}, "layers"), ({"hidden": 1.5}, "hidden"),
                       ({"depth": 2}, "depth")):
        with pytest.raises(ConfigError, match=field):
            NormalFlowModule(head=bad)


def test_loss_kind_follows_the_available_ground_truth():
    m = NormalFlowModule(head={"hidden": 16, "layers": 1})
    nf = m._losses(_batch(kind="nf"))
    assert nf["nf"] > 0 and nf["of"] == 0 and len(nf["angular_error_deg"]) == 8
    of = m._losses(_batch(kind="of"))
    assert of["of"] != 0 and of["nf"] == 0 and len(of["angular_error_deg"]) == 0
    mixed = {k: torch.cat([_batch(kind="nf")[k], _batch(kind="of")[k]]) for k in _batch()}
    parts = m._losses(mixed)
    # flow loss = mean over rows of the per-kind losses (equal counts: the average of both)
    expected = 0.5 * (parts["nf"] + parts["of"]) + m.hparams.uncertainty_weight * parts["nll"]
    torch.testing.assert_close(parts["loss"], expected)
    parts["loss"].backward()
    assert all(torch.isfinite(p.grad).all() for p in m.parameters())


def test_optimiser_steps_reduce_the_normal_flow_loss():
    torch.manual_seed(0)
    m = NormalFlowModule(head={"hidden": 32, "layers": 2}, lr=1e-2)
    batch = _batch(64)
    opt = torch.optim.Adam(m.parameters(), lr=1e-2)
    first = m._losses(batch)["nf"].item()
    for _ in range(200):
        opt.zero_grad()
        m._losses(batch)["loss"].backward()
        opt.step()
    last = m._losses(batch)["nf"].item()
    assert math.isfinite(last) and last < 0.5 * first  # 64 random rows: an MLP memorises them


def test_magnitude_weights_favour_rare_speeds():
    from evseg.veckm_flow.losses import magnitude_weights

    gt = torch.cat([torch.full((99, 2), 10.0), torch.full((1, 2), 1000.0)])  # one fast target
    w = magnitude_weights(gt, 1.0)
    assert torch.allclose(w.mean(), torch.tensor(1.0)) and w[-1] > 5 * w[0]
    assert torch.allclose(magnitude_weights(gt, 0.0), torch.ones(100))
    assert torch.allclose(magnitude_weights(torch.ones(5, 2), 1.0), torch.ones(5))  # one speed
    m = NormalFlowModule(magnitude_balance=0.5)
    assert m.hparams.magnitude_balance == 0.5 and torch.isfinite(m._losses(_batch())["loss"])


def test_uncertainty_target_chooses_the_error_the_uncertainty_learns():
    """'angle': the angular error (rad); 'relative_error': |p - n| / |n|. The NLL is
    err * exp(-log u) + log u with that error, row by row."""
    import pytest

    from evseg.veckm_flow import losses as L

    batch = _batch(16)
    for target in ("angle", "relative_error"):
        torch.manual_seed(0)
        m = NormalFlowModule(head={"hidden": 16, "layers": 1}, uncertainty_target=target)
        out = m(batch["features"])
        pred, log_u = out[:, :2], out[:, 2]
        gt = batch["normal_flow"] / m.flow_unit_px_s
        if target == "angle":
            err = L.angular_error(pred, gt)
        else:
            err = (pred - gt).norm(dim=1) / gt.norm(dim=1)
        torch.testing.assert_close(m._losses(batch)["nll"], (err * torch.exp(-log_u) + log_u).mean())
        assert m.hparams.uncertainty_target == target
    with pytest.raises(ValueError, match="uncertainty_target must be one of angle, relative_error"):
        NormalFlowModule(uncertainty_target="epe")


def test_object_weight_weighs_object_targets_in_the_normal_flow_loss():
    """object_weight w: the normal-flow loss is the weighted mean with weight w on object
    targets and 1 elsewhere; 1 (default) or rows without `is_object` give the plain mean."""
    import pytest

    from evseg.veckm_flow import losses as L

    batch = _batch(16)
    batch["is_object"] = (torch.arange(16) < 4).float()
    torch.manual_seed(0)
    m = NormalFlowModule(head={"hidden": 16, "layers": 1}, object_weight=5.0)
    per = L.normal_flow_loss(m(batch["features"])[:, :2], batch["normal_flow"] / m.flow_unit_px_s)
    expected = (5.0 * per[:4].sum() + per[4:].sum()) / (5.0 * 4 + 12)
    torch.testing.assert_close(m._losses(batch)["nf"], expected)
    plain = {k: v for k, v in batch.items() if k != "is_object"}
    torch.testing.assert_close(m._losses(plain)["nf"], per.mean())
    m.hparams.object_weight = 1.0
    torch.testing.assert_close(m._losses(batch)["nf"], per.mean())
    with pytest.raises(ValueError, match="object_weight must be > 0"):
        NormalFlowModule(object_weight=0.0)


def test_flow_target_optical_trains_every_row_with_optical_flow_by_veckm_flow_s_loss():
    """flow_target 'optical': rows with both ground truths (simulated) take VecKM_flow's
    optical-flow loss, not the normal-flow loss, with the object weight applied alike; the
    angular error against the normal flow is still reported for every such row."""
    import pytest

    from evseg.errors import ConfigError
    from evseg.veckm_flow import losses as L

    g = torch.Generator().manual_seed(1)
    batch = _batch(16)
    batch["optical_flow"] = batch["normal_flow"] + torch.randn(16, 2, generator=g) * 50.0  # both known
    batch["is_object"] = (torch.arange(16) < 4).float()
    torch.manual_seed(0)
    m = NormalFlowModule(head={"hidden": 16, "layers": 1}, object_weight=3.0, flow_target="optical")
    pred = m(batch["features"])[:, :2]
    per = L.veckm_optical_flow_loss(pred, batch["optical_flow"] / m.flow_unit_px_s)
    parts = m._losses(batch)
    torch.testing.assert_close(parts["of"], (3.0 * per[:4].sum() + per[4:].sum()) / (3.0 * 4 + 12))
    assert parts["nf"] == 0 and len(parts["angular_error_deg"]) == 16
    # the default learns the normal flow where both are known
    m.hparams.flow_target = "normal"
    parts = m._losses(batch)
    assert parts["of"] == 0 and parts["nf"] > 0
    # rows with normal flow only still take the normal-flow loss under 'optical'
    m.hparams.flow_target = "optical"
    nf_only = _batch(16)
    parts = m._losses(nf_only)
    assert parts["nf"] > 0 and parts["of"] == 0
    with pytest.raises(ConfigError, match="flow_target must be one of normal, optical"):
        NormalFlowModule(flow_target="full")


def test_magnitude_weight_scales_only_the_log_magnitude_term():
    """magnitude_weight w: per target (1 - cos) + w (log(eps + |p|) - log(eps + |n|))^2; 1
    (default) is the plain loss."""
    import pytest

    from evseg.veckm_flow import losses as L

    pred = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    gt = torch.tensor([[2.0, 0.0], [0.0, 2.0]])  # same directions: only the magnitude differs
    logmag = math.log(L.EPS + 1.0) - math.log(L.EPS + 2.0)
    torch.testing.assert_close(L.normal_flow_loss(pred, gt, magnitude_weight=3.0),
                               torch.tensor([3.0 * logmag**2, 0.0]))
    turned = torch.tensor([[0.0, 2.0]])  # a right angle, equal magnitudes: only the direction term
    torch.testing.assert_close(L.normal_flow_loss(turned, gt[:1], magnitude_weight=3.0), torch.tensor([1.0]))
    batch = _batch(16)
    torch.manual_seed(0)
    m = NormalFlowModule(head={"hidden": 16, "layers": 1}, magnitude_weight=2.5)
    p = m(batch["features"])[:, :2]
    expected = L.normal_flow_loss(p, batch["normal_flow"] / m.flow_unit_px_s, magnitude_weight=2.5).mean()
    torch.testing.assert_close(m._losses(batch)["nf"], expected)
    assert m.hparams.magnitude_weight == 2.5
    with pytest.raises(ValueError, match="magnitude_weight must be > 0"):
        NormalFlowModule(magnitude_weight=0.0)


def test_object_weight_uncertainty_weighs_the_uncertainty_nll_alike():
    """object_weight_uncertainty: the uncertainty NLL is the object-weighted mean too (default:
    the plain mean over every target)."""
    from evseg.veckm_flow import losses as L

    batch = _batch(16)
    batch["is_object"] = (torch.arange(16) < 4).float()
    for weighted in (False, True):
        torch.manual_seed(0)
        m = NormalFlowModule(head={"hidden": 16, "layers": 1}, object_weight=3.0, object_weight_uncertainty=weighted)
        out = m(batch["features"])
        nf = batch["normal_flow"] / m.flow_unit_px_s
        nll = L.uncertainty_nll(out[:, 2], L.angular_error(out[:, :2], nf))
        expected = (3.0 * nll[:4].sum() + nll[4:].sum()) / (3.0 * 4 + 12) if weighted else nll.mean()
        torch.testing.assert_close(m._losses(batch)["nll"], expected)


def test_the_learning_rate_schedule_works_for_any_number_of_steps():
    # OneCycleLR divides by its warm-up length - 1: 10 steps at 10 % warm-up was a
    # ZeroDivisionError; short runs (evseg train --trainer.max_steps N) must all work.
    from types import SimpleNamespace

    for total in (1, 2, 3, 4, 5, 10, 11, 16_000):
        m = NormalFlowModule(encoding={"d": 16}, head={"hidden": 8, "layers": 1})
        m._trainer = SimpleNamespace(estimated_stepping_batches=total)
        out = m.configure_optimizers()
        opt = out["optimizer"] if isinstance(out, dict) else out
        lrs = []
        for _ in range(total):
            lrs.append(opt.param_groups[0]["lr"])
            opt.step()
            if isinstance(out, dict):
                out["lr_scheduler"]["scheduler"].step()
        assert all(math.isfinite(v) and v > 0 for v in lrs), (total, lrs)
        if total >= 4:
            assert math.isclose(max(lrs), m.hparams.lr, rel_tol=1e-6), total  # the warm-up reaches the peak
