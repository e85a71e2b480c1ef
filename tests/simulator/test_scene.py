"""Scene configs: YAML presets load into the dataclasses; bad keys and values are reported."""

import dataclasses

import pytest

from evseg.errors import ConfigError
from evseg.simulator import list_scene_presets, load_scene_preset, scene_from_dict, scene_to_dict, simulate
from evseg.simulator.scene import SENSOR_PRESETS, ObjectConfig, SceneConfig, SensorConfig, load_scene_file

REQUIRED = {"eed_like", "evimo_like", "driving_like", "ego_only"}


def test_required_presets_exist_with_their_sensors():
    assert REQUIRED <= set(list_scene_presets())
    sizes = {n: (load_scene_preset(n).sensor.width, load_scene_preset(n).sensor.height) for n in REQUIRED}
    assert sizes["eed_like"] == (240, 180)
    assert sizes["evimo_like"] == sizes["ego_only"] == (346, 260)
    assert sizes["driving_like"][0] >= 640
    assert set(sizes.values()) <= set(SENSOR_PRESETS.values())
    assert load_scene_preset("ego_only").objects == ()
    eed = load_scene_preset("eed_like")
    assert eed.foreground and eed.foreground[0].texture.family == ("grid",)


@pytest.mark.parametrize("name", sorted(REQUIRED | {"eed_lowlight"}))
def test_every_preset_simulates_on_a_small_sensor(name):
    rec = simulate(load_scene_preset(name).with_sensor_size(48, 36), seed=0, duration_us=3_000)
    assert rec.stream.sensor_size == (48, 36)
    assert rec.config.name == name


def test_dict_round_trip_is_lossless():
    for name in list_scene_presets():
        cfg = load_scene_preset(name)
        assert scene_from_dict(scene_to_dict(cfg)) == cfg


def test_unknown_key_names_key_and_file(tmp_path):
    path = tmp_path / "scene.yaml"
    path.write_text("name: x\nsensor:\n  widht: 100\n")
    with pytest.raises(ConfigError, match=r"scene\.yaml.*'sensor\.widht'"):
        load_scene_file(path)
    path.write_text("objects:\n  - count: [1, 2]\n    colour: red\n")
    with pytest.raises(ConfigError, match=r"'objects\[0\]\.colour'"):
        load_scene_file(path)


@pytest.mark.parametrize("text, fragment", [
    ("sensor: {width: many}", "'sensor.width' must be an integer"),
    ("background: {texture: {family: marble}}", "unknown texture family 'marble'"),
    ("objects: [{shape: [cube]}]", "unknown shape 'cube'"),
    ("background: {motion: {speed_px_s: [300, 100]}}", "lo <= hi"),
    ("objects: [{count: [3, 1]}]", "'objects[0].count'"),
    ("- just\n- a list", "must be a mapping"),
    ("sensor: {c_pos: 0}", "thresholds"),
    # these ran: a numpy broadcast error, a run that never ends, log of negative light, and
    # silently empty or mislabelled recordings
    ("gradient_sigma_px: -1", "'gradient_sigma_px' must be >= 0 px"),
    ("max_step_us: 0.001", "'max_step_us' must be >= 1 us"),
    ("lighting: {gain: -0.5}", "'lighting.gain' must be positive"),
    ("lighting: {flicker_amplitude: 2}", "'lighting.flicker_amplitude' must be in [0, 1)"),
    ("label_coverage: 0", "'label_coverage' must be in (0, 1]"),
    ("mask_coverage: 5", "'mask_coverage' must be in (0, 1]"),
    ("background: {texture: {scale_px: 0}}", "'background.texture.scale_px' must be positive"),
    ("background: {texture: {mean: [-1, 0.5]}}", "'background.texture.mean' must lie in [0, 1]"),
    ("foreground: [{probability: 2}]", "'foreground[0].probability' must be in [0, 1]"),
    ("objects: [{min_log_contrast: -1}]", "'objects[0].min_log_contrast' must be >= 0"),
    ("sensor: {c_pos: 1e9}", "must be a number, got '1e9' (YAML 1.1 reads a number like 1e9 as text"),
])
def test_bad_values_raise_config_error(tmp_path, text, fragment):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_scene_file(path)
    assert fragment in str(info.value) and "bad.yaml" in str(info.value)


def test_scalars_and_single_names_are_accepted_for_ranges_and_lists():
    cfg = scene_from_dict({"background": {"texture": {"family": "wood", "scale_px": 12}}})
    assert cfg.background.texture.family == ("wood",)
    assert cfg.background.texture.scale_px == (12.0, 12.0)


def test_unknown_preset_and_unreadable_file():
    with pytest.raises(ConfigError, match="unknown scene preset 'nope'.*evimo_like"):
        load_scene_preset("nope")
    with pytest.raises(ConfigError, match="cannot read"):
        load_scene_file("/nonexistent/scene.yaml")


def test_with_sensor_size_keeps_everything_else():
    cfg = load_scene_preset("evimo_like")
    small = cfg.with_sensor_size(100, 80)
    assert (small.sensor.width, small.sensor.height) == (100, 80)
    assert dataclasses.replace(small, sensor=cfg.sensor) == cfg
    assert isinstance(cfg.objects[0], ObjectConfig) and isinstance(cfg, SceneConfig)


@pytest.mark.parametrize("make, message", [
    (lambda: SceneConfig(sensor=SensorConfig(width=-5)),
     "SensorConfig: 'width' and height must be positive, got -5x260"),
    (lambda: ObjectConfig(count=(3, 1)), "ObjectConfig: 'count' must be a range 0 <= lo <= hi, got [3, 1]"),
    (lambda: ObjectConfig(aspect=(0.5, 2.0)), "ObjectConfig: 'aspect' must lie in (0, 1]"),
])
def test_the_python_api_refuses_what_a_yaml_file_is_refused_for(make, message):
    with pytest.raises(ConfigError) as info:
        make()
    assert message in str(info.value)


def test_refractory_and_speed_ranges_are_checked_when_made():
    from evseg.simulator.scene import MotionConfig

    with pytest.raises(ConfigError, match="SensorConfig: 'refractory_us' must be >= 0, got -1"):
        SensorConfig(refractory_us=-1)
    with pytest.raises(ConfigError, match=r"MotionConfig: 'speed_px_s' range must have lo <= hi, got \[5, 1\]"):
        MotionConfig(speed_px_s=(5, 1))


@pytest.mark.parametrize("seed", [1.5, "1", True, -1])
def test_simulate_refuses_a_seed_it_would_change(seed):
    with pytest.raises(ConfigError, match="seed must be"):
        simulate(load_scene_preset("evimo_like"), seed=seed, duration_us=1000)


def test_nan_in_any_number_is_refused():
    with pytest.raises(ConfigError, match="'sensor.c_pos' must be finite, got nan"):
        scene_from_dict({"sensor": {"c_pos": float("nan")}})


def test_simulate_takes_a_preset_name():
    a = simulate("ego_only", seed=3, duration_us=2_000)
    b = simulate(load_scene_preset("ego_only"), seed=3, duration_us=2_000)
    assert len(a) == len(b) and (a.stream.events == b.stream.events).all()
    with pytest.raises(ConfigError, match="simulate needs a SceneConfig or a preset name, got int"):
        simulate(3)
