"""Oracle evaluation helpers (the full evaluation runs through `evseg eval seg`)."""

import numpy as np

from evseg.segmentation.evaluate import add_outliers, evaluate_scene, own_events_detected


def test_add_outliers_replaces_the_requested_share_deterministically():
    rng = np.random.default_rng(0)
    nx, ny = rng.normal(0, 100, 1000), rng.normal(0, 100, 1000)
    nx[:100] = np.nan  # flow-less events stay flow-less
    ox, oy = add_outliers(nx, ny, 0.3, seed=5)
    changed = (ox != nx) | (oy != ny)
    assert np.all(np.isnan(ox[:100]))
    assert changed[100:].sum() == 270  # 30 % of the 900 finite flows
    ox2, _ = add_outliers(nx, ny, 0.3, seed=5)
    np.testing.assert_array_equal(ox, ox2)
    assert not np.shares_memory(ox, nx)


def test_evaluate_scene_runs_on_a_short_simulated_scene():
    row = evaluate_scene("evimo_like", 1000, 20_000)
    assert row["windows"] == 2
    assert 0.0 <= row["mean_iou"] <= 1.0
    assert row["nodes"] > 100
    assert row["detection_ceiling"] == 1.0  # every object's events span its box here


def test_own_events_detected_needs_the_events_to_span_the_truth_box():
    """A car whose events cover the top 45 % of its 10 x 20 px box fails the criterion (IoU
    0.45); events at its four corners pass (the box they span is the truth box)."""
    truth = (0, 0, 9, 19)
    assert not own_events_detected(np.array([0, 9]), np.array([0, 8]), truth, (30, 30))
    assert own_events_detected(np.array([0, 9, 0, 9]), np.array([0, 0, 19, 19]), truth, (30, 30))


def test_evaluate_oracle_takes_other_seeds_and_setting_overrides():
    import pytest

    from evseg.errors import ConfigError
    from evseg.segmentation.evaluate import evaluate_oracle

    rows = evaluate_oracle(quick=True, seeds=[900], overrides={"contrast_min_weight": 1.0})
    scenes = [r for r in rows if "pooled" not in str(r["preset"])]
    assert [r["seed"] for r in scenes] == [900, 900, 900]  # one scene per preset
    with pytest.raises(ConfigError, match="lamda_p"):
        evaluate_oracle(quick=True, seeds=[900], overrides={"lamda_p": 1.0})


def test_oracle_evaluation_of_a_preset_subset():
    """evaluate_oracle(presets=[...]) runs only those presets (`evseg eval seg --presets`): one
    scene row, its preset's pooled row and the ALL row, which pools the same windows."""
    from evseg.segmentation.evaluate import evaluate_oracle

    rows = evaluate_oracle(quick=True, presets=["eed_like"])
    assert [r["preset"] for r in rows] == ["eed_like", "eed_like (pooled)", "ALL (pooled)"]
    assert rows[1]["detection_rate"] == rows[2]["detection_rate"] == rows[0]["detection_rate"]
