"""Event-camera simulator with ground truth: the project's only source of labelled data.

>>> from evseg.simulator import load_scene_preset, simulate
>>> rec = simulate(load_scene_preset("ego_only").with_sensor_size(64, 48), seed=0, duration_us=5_000)
>>> rec.label.dtype.name, rec.flow.shape[1]
('int16', 2)

Layered 2D scenes (textured background under camera ego-motion, independently moving textured
objects, optional occluders such as a net) are rendered at sub-steps of at most half a pixel of
motion; pixels fire on log-intensity threshold crossings with interpolated timestamps,
threshold mismatch, refractory period, background-activity noise and hot pixels. Every event
carries its label, optical flow and normal flow (:mod:`evseg.simulator.ground_truth`);
object masks and boxes are available at any time.
"""

from evseg.simulator.engine import simulate
from evseg.simulator.io import load_recording, save_recording
from evseg.simulator.presets import list_scene_presets, load_scene_preset
from evseg.simulator.recording import SimulatedRecording, WindowTruth
from evseg.simulator.scene import (
    SENSOR_PRESETS,
    BackgroundConfig,
    ForegroundConfig,
    LightingConfig,
    MotionConfig,
    ObjectConfig,
    SceneConfig,
    SensorConfig,
    TextureConfig,
    load_scene_file,
    scene_from_dict,
    scene_to_dict,
)

__all__ = [
    "SENSOR_PRESETS",
    "BackgroundConfig",
    "ForegroundConfig",
    "LightingConfig",
    "MotionConfig",
    "ObjectConfig",
    "SceneConfig",
    "SensorConfig",
    "SimulatedRecording",
    "TextureConfig",
    "WindowTruth",
    "list_scene_presets",
    "load_recording",
    "load_scene_file",
    "load_scene_preset",
    "save_recording",
    "scene_from_dict",
    "scene_to_dict",
    "simulate",
]
