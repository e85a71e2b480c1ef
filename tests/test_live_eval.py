import pytest

from evseg.live_eval import evaluate_live
from evseg.pipeline_eval import evaluate_pipeline


def test_live_evaluation_scores_the_windows_it_segmented_beside_the_offline_run():
    """`evseg eval live`: three pooled rows per preset; the offline row over all windows is
    `evseg eval pipeline`'s for the same scene (deterministic), the live rows cover the windows
    segmented live, which are the share the last column gives."""
    rows = evaluate_live(quick=True, seeds=[1000], presets=["eed_like"], worker="none")
    assert [r["scene"] for r in rows] == [
        "**eed_like**, live, windows segmented", "**eed_like**, offline, the same windows",
        "**eed_like**, offline, all windows", "**scenes with objects**, live, windows segmented",
        "**scenes with objects**, offline, the same windows", "**scenes with objects**, offline, all windows"]
    live, same, every = rows[:3]
    offline = evaluate_pipeline(quick=True, seeds=[1000], presets=["eed_like"])[0]
    assert every["windows"] == offline["windows"] == 10
    assert every["detection rate %"] == offline["detection rate %"]
    assert every["mean IoU"] == offline["mean IoU"]
    assert 1 <= live["windows"] == same["windows"] <= 10
    assert live["windows segmented live %"] == pytest.approx(100 * live["windows"] / 10)


def test_live_evaluation_rejects_unknown_presets():
    from evseg.errors import EvsegError

    with pytest.raises(EvsegError, match="evaluate_live"):
        evaluate_live(quick=True, presets=["moon_like"])
