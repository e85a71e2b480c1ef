"""Simulate an event camera watching a layered scene, with per-event ground truth.

Writes one .npz: events (x, y, t us, p), per-event label (-1 noise, 0 background, k object),
optical flow and normal flow (px/s), and the scene config + seed that reproduce the recording
(object masks and boxes are re-rendered from them by evseg.simulator.load_recording).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

from evseg.errors import ConfigError

HELP = "simulate events with ground truth (labels, optical/normal flow, masks) from a scene preset"


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument("--preset", default="evimo_like", help="scene preset (configs/scenes/NAME.yaml); see --list")
    src.add_argument("--config", type=Path, help="scene YAML file (layout of configs/scenes/*.yaml)")
    p.add_argument("--list", action="store_true", help="list the scene presets and exit")
    p.add_argument("--seed", type=int, default=0, help="random seed (the recording is deterministic in it)")
    p.add_argument("--duration", type=float, default=0.2, help="duration in seconds")
    p.add_argument("--sensor", "--sensor-size", dest="sensor", default=None, help="override the sensor size, WIDTHxHEIGHT in px (e.g. 640x480)")
    p.add_argument("--out", type=Path, default=Path("sim.npz"), help="output .npz")
    p.add_argument("--preview", type=Path, default=None,
                   help="also write a PNG of the busiest 10 ms window: events, GT labels, normal and optical flow")
    p.add_argument("--quiet", action="store_true", help="no progress bar or summary")


def parse_sensor(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) == 0 or int(m.group(2)) == 0:
        raise ConfigError(f"--sensor must be WIDTHxHEIGHT in px, e.g. 346x260; got {text!r}")
    return int(m.group(1)), int(m.group(2))


def run(args: argparse.Namespace) -> int:
    from evseg.simulator import list_scene_presets, load_scene_file, load_scene_preset, save_recording, simulate
    from evseg.simulator.scene import scene_to_dict

    if args.list:
        for name in list_scene_presets():
            cfg = load_scene_preset(name)
            print(f"{name:14s} {cfg.sensor.width}x{cfg.sensor.height}  {cfg.description}")
        return 0
    if not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError(f"--duration must be positive seconds, got {args.duration}")
    if round(args.duration * 1e6) < 1:
        raise ConfigError(f"--duration must be at least 1 us (1e-6 s), got {args.duration:g} s")
    from evseg.io.output_paths import check_output_path

    check_output_path(args.out, "--out", (".npz",), [("the scene config (--config)", args.config)])
    if args.preview is not None:
        check_output_path(args.preview, "--preview", (".png",), [("the scene config (--config)", args.config)])
    cfg = load_scene_file(args.config) if args.config else load_scene_preset(args.preset)
    if args.sensor:
        cfg = cfg.with_sensor_size(*parse_sensor(args.sensor))
    duration_us = int(round(args.duration * 1e6))

    progress = None
    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=0, unit="step", desc=f"simulate {cfg.name}", leave=False, file=sys.stderr,
                   disable=None)  # disable=None: no bar when stderr is not a terminal

        def progress(done: int, total: int) -> None:
            if bar.total != total:
                bar.total = total
            bar.update(done - bar.n)

    try:
        rec = simulate(cfg, seed=args.seed, duration_us=duration_us, progress=progress)
    finally:
        if bar is not None:
            bar.close()
    save_recording(rec, args.out)
    if args.preview is not None:
        from evseg.simulator.preview import preview_image
        from evseg.visualize import save_rgb

        save_rgb(args.preview, preview_image(rec))
    if not args.quiet:
        s = rec.summary()
        print(
            f"{args.out}: {s['events']:,} events in {s['duration_s']:g} s ({s['rate_ev_s'] / 1e6:.2f} M ev/s) "
            f"on {s['sensor']}, scene {cfg.name!r} seed {args.seed}, {s['objects']} object(s); "
            f"events: {100 * s['share_background']:.1f} % background, {100 * s['share_objects']:.1f} % objects, "
            f"{100 * s['share_noise']:.1f} % noise"
        )
        if args.preview is not None:
            print(f"{args.preview}: preview (events | GT labels | GT normal flow | GT optical flow)")
        if args.config:
            print("effective config: " + json.dumps(scene_to_dict(cfg)))  # whole: a cut JSON cannot be reused
    return 0
