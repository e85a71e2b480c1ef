"""Convert a recording in any supported format to evseg's .npz or DSEC-style .h5.

Streams chunk by chunk (bounded memory; --sort loads everything), writes atomically (a
temporary file renamed at the end, so OUT is never half-written) and losslessly: reading OUT
gives the same events, sensor size, time offset and calibration.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from evseg.errors import EvsegError

HELP = "convert a recording (any supported format) to evseg .npz or DSEC-style .h5"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from evseg.io.registry import FORMATS

    p.add_argument("input", type=Path, help="event file (any supported format)")
    p.add_argument("output", type=Path, help="output file (.npz or .h5)")
    p.add_argument("--format", choices=list(FORMATS), default=None,
                   help="read the input as this format instead of detecting it")
    p.add_argument("--to", choices=["npz", "h5"], default=None,
                   help="output format; None: from the output's extension")
    p.add_argument("--topic", default=None, help="ROS bag topic of the event messages (default: the only one)")
    p.add_argument("--sensor-size", default=None, metavar="WxH",
                   help="sensor size in px, e.g. 346x260 (overrides the input's)")
    p.add_argument("--time-unit", choices=["s", "ms", "us", "ns"], default=None,
                   help="text/csv, .npy and .npz only: unit of the time column (default: its name's suffix, e.g. t_ns; "
                        "else for text s if any of the first 1,000 times has a decimal point or exponent, else us; for "
                        "arrays s when floating point, us when integer)")
    p.add_argument("--sort", action="store_true",
                   help="accept unsorted timestamps and sort them (loads the whole recording)")


def output_format(path: Path, to: str | None) -> str:
    """``"npz"`` or ``"h5"`` from ``--to`` or the output's extension."""
    if to is not None:
        return to
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return "npz"
    if suffix in (".h5", ".hdf5"):
        return "h5"
    raise EvsegError(f"{path}: cannot tell the output format from extension '{suffix}'; use --to npz|h5")


def run(args: argparse.Namespace) -> int:
    from evseg.io import open_recording, parse_sensor_size
    from evseg.io.hdf5 import write_h5_chunks
    from evseg.io.numpy_files import write_npz_chunks

    to = output_format(args.output, args.to)
    if args.output.resolve() == args.input.resolve():
        raise EvsegError(f"{args.output}: output is the input file; choose another name")
    size = parse_sensor_size(args.sensor_size) if args.sensor_size else None
    with open_recording(args.input, format=args.format, topic=args.topic,
                        sensor_size=size, sort=args.sort, time_unit=args.time_unit) as rec:
        counted = [0]

        def chunks():
            for c in rec.chunks():
                counted[0] += len(c)
                yield c

        def meta():
            if rec.sensor_size is None:
                raise EvsegError(f"{args.input}: no events and no sensor size; pass --sensor-size WxH")
            cal = rec.calibration
            if cal is not None and tuple(cal.sensor_size) != tuple(rec.sensor_size):
                from dataclasses import replace

                cal = replace(cal, sensor_size=rec.sensor_size)
            return rec.sensor_size, rec.t_offset_us, cal

        write = write_npz_chunks if to == "npz" else write_h5_chunks
        write(chunks(), args.output, meta)
        print(
            f"wrote {args.output} ({to}): {counted[0]:,} events, sensor "
            f"{rec.sensor_size[0]}x{rec.sensor_size[1]} px ({rec.sensor_size_source}), "
            f"t_offset {rec.t_offset_us} us"
        )
    return 0
