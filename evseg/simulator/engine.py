"""The simulation loop: render sub-steps, fire threshold crossings, attach ground truth."""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from evseg.checks import is_whole
from evseg.errors import ConfigError
from evseg.events import EVENT_DTYPE, EventStream
from evseg.simulator.camera import PixelArray, noise_events
from evseg.simulator.ground_truth import layer_flow, log_gradient_at, project_on_gradient
from evseg.simulator.recording import SimulatedRecording
from evseg.simulator.render import Frame, SceneInstance, child_rng, event_layers, render_frame, sample_scene
from evseg.simulator.scene import SceneConfig


def substep_count(scene: SceneInstance, cfg: SceneConfig, duration_us: int) -> int:
    """Number of rendering sub-steps so that no visible point moves more than ``max_step_px``
    per step, no step is longer than ``max_step_us`` and a flicker period has 20 steps."""
    vmax = scene.max_speed_px_s(duration_us * 1e-6)
    by_speed = duration_us * 1e-6 * vmax / cfg.max_step_px
    by_time = duration_us / cfg.max_step_us
    # Flicker changes every pixel's log intensity by up to ~amplitude per 1/(2 pi f): keep 20
    # steps per period so the linear interpolation of the crossing times stays close.
    by_flicker = duration_us * 1e-6 * scene.flicker_hz * 20 if scene.flicker_amplitude > 0 else 0.0
    return max(1, int(np.ceil(max(by_speed, by_time, by_flicker))))


def _smooth_log(frame: Frame, eps: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Log intensity on the sensor (H, W) and the smoothed log image with the frame's margin."""
    log = np.log(frame.intensity + np.float32(eps))
    smooth = cv2.GaussianBlur(log, (0, 0), sigma) if sigma > 0 else log
    m = frame.margin
    return log[m : log.shape[0] - m, m : log.shape[1] - m], smooth


def simulate(
    cfg: SceneConfig | str,
    seed: int = 0,
    duration_us: int = 200_000,
    progress: Callable[[int, int], None] | None = None,
) -> SimulatedRecording:
    """Simulate an event camera watching the scene ``cfg`` for ``duration_us`` microseconds.

    Deterministic in ``(cfg, seed, duration_us)``. ``progress(done, total)`` is called after each
    sub-step (for a progress bar; the core prints nothing).

    Returns:
        A :class:`SimulatedRecording` with events sorted by t (time base 0 = start) and
        per-event label, optical flow and normal flow (see
        :mod:`evseg.simulator.ground_truth`).
    """
    if isinstance(cfg, str):
        from evseg.simulator.presets import load_scene_preset

        cfg = load_scene_preset(cfg)  # a preset name, as the CLI takes it
    if not isinstance(cfg, SceneConfig):
        raise ConfigError(f"simulate needs a SceneConfig or a preset name, got {type(cfg).__name__}")
    for name, value in (("seed", seed), ("duration_us", duration_us)):
        # int(1.5) would silently simulate seed 1 (and record it as 1).
        if not is_whole(value):
            raise ConfigError(f"{name} must be a whole number, got {value!r}")
    seed, duration_us = int(seed), int(duration_us)
    if duration_us <= 0:
        raise ConfigError(f"duration must be positive, got {duration_us} us")
    if seed < 0:
        raise ConfigError(f"seed must be >= 0, got {seed}")
    scene = sample_scene(cfg, seed, duration_us)
    sensor = cfg.sensor
    width = sensor.width
    n_steps = substep_count(scene, cfg, duration_us)
    times_us = np.linspace(0.0, duration_us, n_steps + 1)
    eps, sigma = sensor.log_eps, cfg.gradient_sigma_px
    # Render beyond the sensor so the smoothing and the gradient at border pixels see the scene.
    margin = int(np.ceil(3 * sigma)) + 1

    prev = render_frame(scene, 0.0, margin)
    prev_log, prev_smooth = _smooth_log(prev, eps, sigma)
    pixels = PixelArray(sensor, prev_log, child_rng(seed, "pixels"))
    layer_labels = np.array([ly.label for ly in scene.layers], np.int16)
    chunks: list[tuple[np.ndarray, ...]] = []
    for i in range(1, n_steps + 1):
        t0, t1 = times_us[i - 1], times_us[i]
        cur = render_frame(scene, t1 * 1e-6, margin)
        cur_log, cur_smooth = _smooth_log(cur, eps, sigma)
        cr = pixels.step(prev_log, cur_log, t0, t1)
        if len(cr.pixel):
            x = cr.pixel % width
            y = cr.pixel // width
            # The layer whose motion changed the pixel most during the step (depth order = index).
            layer = event_layers(prev, cur, x + margin, y + margin)
            flow = layer_flow(scene, layer, x, y, cr.t_us * 1e-6)
            grad = log_gradient_at(prev_smooth, x + margin, y + margin) + log_gradient_at(cur_smooth, x + margin, y + margin)
            nflow = project_on_gradient(flow, grad)
            # Compact per-event storage (31 bytes) so long recordings fit in memory.
            chunks.append((x.astype(np.uint16), y.astype(np.uint16), cr.t_us, cr.p, layer_labels[layer],
                           flow.astype(np.float32), nflow.astype(np.float32)))
        prev, prev_log, prev_smooth = cur, cur_log, cur_smooth
        if progress is not None:
            progress(i, n_steps)

    noise = noise_events(sensor, duration_us, child_rng(seed, "noise"))
    nn = len(noise.pixel)
    nan2 = np.full((nn, 2), np.nan, np.float32)
    chunks.append(((noise.pixel % width).astype(np.uint16), (noise.pixel // width).astype(np.uint16),
                   noise.t_us, noise.p, np.full(nn, -1, np.int16), nan2, nan2))

    x, y, t, p, label, flow, nflow = (np.concatenate(c) for c in zip(*chunks))
    t_int = np.minimum(np.rint(t).astype(np.int64), duration_us - 1)
    order = np.argsort(t_int, kind="stable")
    events = np.empty(len(order), EVENT_DTYPE)
    events["x"] = x[order]
    events["y"] = y[order]
    events["t"] = t_int[order]
    events["p"] = p[order]
    return SimulatedRecording(
        stream=EventStream(events, (sensor.width, sensor.height)),
        label=label[order],
        flow=flow[order],
        normal_flow=nflow[order],
        object_ids=scene.object_ids,
        config=cfg,
        seed=int(seed),
        duration_us=duration_us,
        _scene=scene,
    )
