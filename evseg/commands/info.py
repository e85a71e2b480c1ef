"""Summarise a recording: format, sensor size, event count, duration, rate, polarity balance.

Reads the file once in chunks (constant memory). The format is detected from the file's magic
bytes and extension; --format overrides. Unsorted timestamps are an error unless --sort is
given (which loads the whole recording to sort it).
"""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "summary of a recording: format, sensor size, duration, event count, rate, polarity"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from evseg.io.registry import FORMATS

    p.add_argument("recording", type=Path, help="event file (any supported format)")
    p.add_argument("--format", choices=list(FORMATS), default=None,
                   help="read as this format instead of detecting it")
    p.add_argument("--topic", default=None, help="ROS bag topic of the event messages (default: the only one)")
    p.add_argument("--sensor-size", default=None, metavar="WxH",
                   help="sensor size in px, e.g. 346x260 (overrides the file's)")
    p.add_argument("--time-unit", choices=["s", "ms", "us", "ns"], default=None,
                   help="text/csv, .npy and .npz only: unit of the time column (default: its name's suffix, e.g. t_ns; "
                        "else for text s if any of the first 1,000 times has a decimal point or exponent, else us; for "
                        "arrays s when floating point, us when integer)")
    p.add_argument("--sort", action="store_true",
                   help="accept unsorted timestamps and sort them (loads the whole recording)")


def format_summary(path: Path, s) -> str:
    """Human-readable lines for a :class:`evseg.io.summary.RecordingSummary`."""
    how = {"file": "from the file", "user": "given", "inferred": "inferred as max+1", "calibration": "from the calibration"}
    size = (f"{s.sensor_size[0]}x{s.sensor_size[1]} px ({how[s.sensor_size_source]})"
            if s.sensor_size else "unknown")
    lines = [
        f"file:         {path}",
        f"format:       {s.format}",
    ]
    if s.topic is not None:
        lines.append(f"topic:        {s.topic} ({s.message_type})")
    lines += [
        f"sensor size:  {size}",
        f"events:       {s.n_events:,}",
    ]
    if s.n_events:
        lines += [
            f"time range:   {s.t_first_us:,} .. {s.t_last_us:,} us (relative to t_offset)",
            f"t_offset:     {s.t_offset_us:,} us",
            f"duration:     {s.duration_us / 1e3:,.3f} ms",
            f"event rate:   {s.rate_ev_s / 1e6:,.3f} Mev/s",
            f"polarity:     {100 * s.on_fraction:.1f} % ON, {100 * (1 - s.on_fraction):.1f} % OFF",
            f"x, y range:   {s.x_range[0]}..{s.x_range[1]}, {s.y_range[0]}..{s.y_range[1]} px",
        ]
    else:
        lines.append(f"t_offset:     {s.t_offset_us:,} us")
    where = "camera_info beside the topic" if s.topic is not None else "file"
    if s.calibration_problem is not None:
        lines.append(f"calibration:  unusable: {s.calibration_problem}")
    else:
        lines.append(f"calibration:  {f'K, D in {where}' if s.has_calibration else 'none'}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from evseg.io import open_recording, parse_sensor_size
    from evseg.io.summary import summarize

    size = parse_sensor_size(args.sensor_size) if args.sensor_size else None
    with open_recording(args.recording, format=args.format, topic=args.topic,
                        sensor_size=size, sort=args.sort, time_unit=args.time_unit) as rec:
        summary = summarize(rec)
    print(format_summary(args.recording, summary))
    return 0
