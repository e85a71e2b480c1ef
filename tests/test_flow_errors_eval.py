"""`evseg eval flow-errors`: mixing the learned flow with the ground truth on the same targets."""

from types import SimpleNamespace

import numpy as np
import pytest

from evseg.cli import main
from evseg.flow_errors_eval import FLOW_VARIANTS, evaluate_flow_errors, flow_variants


def test_each_variant_changes_one_thing():
    # Target 0: learned (30, 0) px/s for a true normal flow (0, 40) with optical flow (10, 40);
    # target 1 has no ground truth (left out of the mixed rows, kept in the fed-back one).
    rec = SimpleNamespace(normal_flow=np.array([[0.0, 40.0], [np.nan, np.nan]]),
                          flow=np.array([[10.0, 40.0], [np.nan, np.nan]]))
    learned = {"index": np.array([0, 1]), "nx": np.float32([30.0, 5.0]), "ny": np.float32([0.0, 5.0]),
               "uncertainty": np.float32([0.2, 0.3])}
    v = flow_variants(rec, learned)
    assert set(v) == set(FLOW_VARIANTS) - {"learned"}
    np.testing.assert_array_equal(v["learned, fed back"]["index"], [0, 1])
    flow = {name: np.c_[d["nx"], d["ny"]].tolist() for name, d in v.items() if name != "learned, fed back"}
    assert flow == {"ground truth": [[0.0, 40.0]], "ground truth + learned uncertainty": [[0.0, 40.0]],
                    "true direction, learned speed": [[0.0, 30.0]], "learned direction, true speed": [[40.0, 0.0]],
                    "exact optical flow": [[10.0, 40.0]]}
    with_unc = {name for name, d in v.items() if "uncertainty" in d}
    assert with_unc == {"learned, fed back", "ground truth + learned uncertainty", "true direction, learned speed",
                        "learned direction, true speed"}


def test_the_learned_flow_fed_back_gives_the_pipeline_s_own_result():
    rows = {r["scene"]: r for r in evaluate_flow_errors(quick=True, seeds=[1000], presets=["eed_like"])}
    assert [name.split(", ", 1)[1] for name in rows] == list(FLOW_VARIANTS)
    assert rows["eed_like, learned, fed back"] == {**rows["eed_like, learned"], "scene": "eed_like, learned, fed back"}


def test_training_seeds_are_refused(capsys):
    assert main(["eval", "flow-errors", "--seeds", "10-12"]) == 2
    assert "below 900" in capsys.readouterr().err
    with pytest.raises(ValueError, match="ego_only"):
        evaluate_flow_errors(quick=True, presets=["ego_only"])
