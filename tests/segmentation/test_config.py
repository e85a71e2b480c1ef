"""SegmentationConfig validation and YAML presets."""

import pytest

from evseg.errors import ConfigError
from evseg.segmentation import SegmentationConfig, load_segmentation_config
from evseg.segmentation.config import preset_names, with_overrides


def test_presets_load():
    assert set(preset_names()) >= {"eed_like", "evimo_like", "outdoor_like"}
    for name in preset_names():
        cfg = load_segmentation_config(name)
        assert isinstance(cfg, SegmentationConfig)
    assert load_segmentation_config("outdoor_like").cell_px == 4.0  # the YAML overrides the default 3
    eed = load_segmentation_config("eed_like")
    assert (eed.n_sampled_normal, eed.tracked_label_cost) == (2, 0.75)
    assert SegmentationConfig().n_sampled_normal == 0


def test_unknown_key_names_file_and_field(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("cell_px: 3\nlamda_m: 5\n")
    with pytest.raises(ConfigError, match="lamda_m") as exc:
        load_segmentation_config(p)
    assert "bad.yaml" in str(exc.value)


def test_wrong_types_and_values(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("lambda_p: fast\n")
    with pytest.raises(ConfigError, match="lambda_p"):
        load_segmentation_config(p)
    p.write_text("robust_loss: tukey\n")
    with pytest.raises(ConfigError, match="robust_loss"):
        load_segmentation_config(p)
    p.write_text("origin_px: [1, 2]\nmax_rounds: 5\nlambda_m: 7\n")
    cfg = load_segmentation_config(p)
    assert cfg.origin_px == (1.0, 2.0) and cfg.max_rounds == 5 and cfg.lambda_m == 7.0
    with pytest.raises(ConfigError):
        SegmentationConfig(max_rounds=0)
    with pytest.raises(ConfigError, match="cell_rule"):
        SegmentationConfig(cell_rule="latest")
    with pytest.raises(ConfigError, match="tracked_label_cost"):
        SegmentationConfig(tracked_label_cost=-0.5)
    for bad in (0.0, 1.5):
        with pytest.raises(ConfigError, match="contrast_min_weight must be in \\(0, 1\\]"):
            SegmentationConfig(contrast_min_weight=bad)
    for field in ("occlusion_gap_px", "n_sampled_normal", "contrast_max_noise"):
        with pytest.raises(ConfigError, match=field):
            SegmentationConfig(**{field: -1})
    with pytest.raises(ConfigError, match=r"nope: no such file, and no segmentation preset of that name; presets: "):
        load_segmentation_config("nope")


def test_load_takes_what_the_pipeline_takes_and_files_without_an_extension(tmp_path, monkeypatch):
    assert load_segmentation_config({"lambda_m": 40.0}).lambda_m == 40.0
    assert load_segmentation_config(None) == SegmentationConfig()
    cfg = SegmentationConfig(lambda_m=30.0)
    assert load_segmentation_config(cfg) is cfg
    (tmp_path / "myconf").write_text("lambda_m: 50.0\n")
    assert load_segmentation_config(tmp_path / "myconf").lambda_m == 50.0
    with pytest.raises(ConfigError, match=r": a folder, and no segmentation preset of that name"):
        load_segmentation_config(tmp_path)
    (tmp_path / "d.yaml").mkdir()
    with pytest.raises(ConfigError, match=r"d.yaml: is a folder, not a segmentation config file"):
        load_segmentation_config(tmp_path / "d.yaml")
    from evseg.segmentation.config import _PRESET_DIR

    monkeypatch.chdir(tmp_path)
    (tmp_path / "eed_like").mkdir()  # a folder of that name does not hide the preset
    assert load_segmentation_config("eed_like") == load_segmentation_config(_PRESET_DIR / "eed_like.yaml")


def test_node_budget_values(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("max_nodes: 12000\n")
    assert load_segmentation_config(p).max_nodes == 12_000
    p.write_text("max_nodes: null\n")
    assert load_segmentation_config(p).max_nodes is None
    for bad in ("0", "-5", "2.5", "many", "true"):
        p.write_text(f"max_nodes: {bad}\n")
        with pytest.raises(ConfigError, match="max_nodes"):
            load_segmentation_config(p)
    with pytest.raises(ConfigError, match="max_nodes"):
        SegmentationConfig(max_nodes=0)


def test_static_camera_settings(tmp_path):
    cfg = load_segmentation_config("static_camera")
    assert cfg.static_camera is True and cfg.min_cell_events == 3
    assert SegmentationConfig().static_camera is False and SegmentationConfig().min_cell_events == 1
    p = tmp_path / "c.yaml"
    p.write_text("static_camera: yes please\n")
    with pytest.raises(ConfigError, match="static_camera"):
        load_segmentation_config(p)
    with pytest.raises(ConfigError, match="min_cell_events"):
        SegmentationConfig(min_cell_events=0)
    with pytest.raises(ConfigError, match="still_px_s"):
        SegmentationConfig(still_px_s=0.0)


def test_overrides_are_checked_like_yaml_fields():
    """with_overrides (evaluate_oracle / evaluate_pipeline overrides, `evseg eval --set`) keeps
    the preset's other fields, turns an int into a float field's float, and names the caller
    and the field for an unknown name, a wrong type or a value the config refuses."""
    base = load_segmentation_config("eed_like")
    cfg = with_overrides(base, {"lambda_m": 60, "mask_method": "dilate"}, "here")
    assert cfg.lambda_m == 60.0 and isinstance(cfg.lambda_m, float) and cfg.mask_method == "dilate"
    assert cfg.cell_px == base.cell_px and cfg.tracked_label_cost == base.tracked_label_cost
    assert with_overrides(base, None, "here") is base
    with pytest.raises(ConfigError, match=r"^here: unknown segmentation parameter\(s\) \['lamda_m'\]$"):
        with_overrides(base, {"lamda_m": 60}, "here")
    with pytest.raises(ConfigError, match=r"^here: field 'lambda_m' must be float, got 'abc'$"):
        with_overrides(base, {"lambda_m": "abc"}, "here")
    with pytest.raises(ConfigError, match=r"^here: SegmentationConfig.lambda_m must be >= 0, got -1.0$"):
        with_overrides(base, {"lambda_m": -1}, "here")


def test_angular_uncertainty_gain_is_set_where_it_was_validated():
    """uncertainty_angle_gain is on by default, in eed_like and in evimo_like (at its
    uncertainty_gain), off in outdoor_like and static_camera (it cost detection there), and
    never < 0."""
    assert SegmentationConfig().uncertainty_angle_gain == 1.0
    assert load_segmentation_config("outdoor_like").uncertainty_angle_gain == 0.0
    assert load_segmentation_config("static_camera").uncertainty_angle_gain == 0.0
    assert load_segmentation_config("eed_like").uncertainty_angle_gain == 1.0
    evimo = load_segmentation_config("evimo_like")
    assert evimo.uncertainty_angle_gain == evimo.uncertainty_gain == 1.25
    with pytest.raises(ConfigError, match=r"uncertainty_angle_gain must be >= 0, got -0.5"):
        SegmentationConfig(uncertainty_angle_gain=-0.5)


@pytest.mark.parametrize("field, value", [("lambda_m", float("nan")), ("truncation", float("nan")),
                                          ("residual_scale_noise", float("inf")), ("cell_px", float("-inf"))])
def test_numbers_must_be_finite(field, value):
    # NaN passes every range check (all comparisons are False) and then poisons the energy.
    with pytest.raises(ConfigError, match=rf"SegmentationConfig.{field} must be a finite number, got {value}"):
        SegmentationConfig(**{field: value})
    with pytest.raises(ConfigError, match=r"origin_px must be finite"):
        SegmentationConfig(origin_px=(float("nan"), 0.0))
    assert SegmentationConfig(max_uncertainty=float("inf")).max_uncertainty == float("inf")  # a limit: no limit


@pytest.mark.parametrize("kwargs, message", [
    (dict(lambda_m="80"), "SegmentationConfig.lambda_m must be a float, got '80'"),
    (dict(max_rounds=2.5), "SegmentationConfig.max_rounds must be an int, got 2.5"),
    (dict(static_camera="false"), "SegmentationConfig.static_camera must be a bool, got 'false'"),
    (dict(node_window_us=-5), "SegmentationConfig.node_window_us must be > 0 (us) or None"),
    (dict(max_uncertainty=-1.0), "SegmentationConfig.max_uncertainty must be > 0 or None (keep every flow), got -1.0"),
    (dict(max_object_parts=0), "SegmentationConfig.max_object_parts must be >= 1, got 0"),
    (dict(n_sampled_with_prediction=-3), "SegmentationConfig.n_sampled_with_prediction must be >= 0, got -3"),
    (dict(min_object_nodes=-1), "SegmentationConfig.min_object_nodes must be >= 0, got -1"),
    (dict(prediction_margin_px=-50.0), "SegmentationConfig.prediction_margin_px must be >= 0, got -50.0"),
    (dict(origin_px=(1, 2, 3)), "SegmentationConfig.origin_px must be [column, row] in px"),
])
def test_values_of_the_wrong_type_are_refused_when_made(kwargs, message):
    # They failed later inside range() or a comparison, or ("false") switched the option on.
    import re

    with pytest.raises(ConfigError, match=re.escape(message)):
        SegmentationConfig(**kwargs)


def test_numpy_numbers_are_numbers():
    import numpy as np

    from evseg.segmentation.config import config_from_dict

    cfg = SegmentationConfig(lambda_m=np.float32(80), max_rounds=np.int64(3))
    assert cfg.lambda_m == 80.0 and type(cfg.lambda_m) is float and cfg.max_rounds == 3
    assert config_from_dict({"lambda_m": np.float32(40)}).lambda_m == 40.0
    with pytest.raises(ConfigError, match="must be a finite number"):
        SegmentationConfig(lambda_m=np.float32("nan"))


def test_a_window_of_nodes_is_a_whole_number_and_survives_a_stored_config():
    """node_window_us is a count of microseconds: it stays an int, so the config a result file
    stores (yaml of the dataclass) loads again; it was kept as 8000.0, which the loader then
    refused as 'must be int'."""
    import dataclasses

    import yaml

    from evseg.segmentation.config import config_from_dict

    cfg = SegmentationConfig(node_window_us=8000)
    assert cfg.node_window_us == 8000 and type(cfg.node_window_us) is int
    back = config_from_dict(yaml.safe_load(yaml.safe_dump(dataclasses.asdict(cfg))))
    assert back == cfg
    assert config_from_dict({"node_window_us": 8000.0}).node_window_us == 8000
    with pytest.raises(ConfigError, match=r"SegmentationConfig.node_window_us must be an int, got 8000.5"):
        SegmentationConfig(node_window_us=8000.5)
    with pytest.raises(ConfigError, match=r"field 'lambda_m' must be float, got '1e2' \(YAML 1.1 reads a number like "
                                          r"1e2 as text: write 1.0e2 or 100.0\)"):
        config_from_dict({"lambda_m": "1e2"})
