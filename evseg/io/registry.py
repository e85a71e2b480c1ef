"""Format registry: which reader opens a file, from its magic bytes and suffix.

Detection reads the first bytes of the file. A known magic number decides the format; the
suffix is only used for formats without one (text) and to catch files whose content
contradicts their extension (e.g. an HDF5 file named ``.npz``): those are refused with a
message naming both, unless the caller names the format explicitly (``format=`` /
``--format``), which skips detection. A directory is a ROS2 bag when it holds
``metadata.yaml`` (format ``rosbag2``), and refused otherwise.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path

from evseg.errors import FormatError


@dataclass(frozen=True)
class FormatSpec:
    """One supported format.

    Attributes:
        name: registry name (``--format`` value).
        module: ``evseg.io`` module whose ``open_source(path, **options)`` reads it.
        suffixes: file name endings that suggest this format (lower case, with dot).
        magic: leading bytes that identify the format (``b""``: none).
        description: one line for ``--help`` and the README.
    """

    name: str
    module: str
    suffixes: tuple[str, ...]
    magic: bytes
    description: str


MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
"""A ROS2 bag's storage files: MCAP, or SQLite (``.db3``; any SQLite file is taken for one)."""

FORMATS: dict[str, FormatSpec] = {
    s.name: s
    for s in [
        FormatSpec("text", "text", (".txt", ".csv", ".dat"), b"",
                   "text 't x y p' (t seconds, optional 'width height' first line) or csv"),
        FormatSpec("npy", "numpy_files", (".npy",), b"\x93NUMPY",
                   "numpy .npy: structured events or N x 4 [t, x, y, p]"),
        FormatSpec("npz", "numpy_files", (".npz",), b"PK\x03\x04",
                   "numpy .npz: 'events' array or x/y/t/p columns (+ K, D calibration)"),
        FormatSpec("mat", "matlab", (".mat",), b"MATLAB 5.0 MAT-file",
                   "MATLAB v5 .mat, variable 'events' N x 4 [x, y, p, t_us]"),
        FormatSpec("h5", "hdf5", (".h5", ".hdf5", ".hdf"), b"\x89HDF\r\n\x1a\n",
                   "DSEC-style HDF5: events/{x,y,t,p}, t_offset, ms_to_idx"),
        FormatSpec("rosbag", "rosbag", (".bag",), b"#ROSBAG V2.0\n",
                   "ROS1 bag of dvs_msgs or prophesee_event_msgs EventArray or event_camera_msgs "
                   "EventPacket messages (no ROS needed)"),
        FormatSpec("rosbag2", "rosbag", (".db3", ".mcap"), MCAP_MAGIC,
                   "ROS2 bag (directory with metadata.yaml, or its .db3 / .mcap file), same messages"),
        FormatSpec("aedat4", "aedat4", (".aedat4",), b"#!AER-DAT4.0",
                   "iniVation AEDAT4 (event packets; frames and IMU are skipped)"),
        FormatSpec("evt2", "prophesee", (".raw",), b"%",
                   "Prophesee .raw EVT 2.0"),
        FormatSpec("evt3", "prophesee", (".raw",), b"%",
                   "Prophesee .raw EVT 3.0"),
        FormatSpec("es", "eventstream", (".es",), b"Event Stream",
                   "Event Stream v2 .es, type DVS"),
        FormatSpec("dat", "prophesee_dat", (".dat",), b"%",
                   "Prophesee .dat of CD events (Gen1 / 1 Mpx automotive datasets, Metavision export)"),
    ]
}
"""Supported formats by registry name."""

_SNIFF_BYTES = 4096


def format_names() -> list[str]:
    """Registry names of all supported formats."""
    return list(FORMATS)


def _by_magic(head: bytes) -> str | None:
    if head.startswith(SQLITE_MAGIC):
        return "rosbag2"
    for spec in FORMATS.values():
        if spec.magic and spec.magic != b"%" and head.startswith(spec.magic):
            return spec.name
    if head.startswith(b"%"):
        from evseg.io.prophesee import sniff_raw_format

        return sniff_raw_format(head)
    return None


def _looks_like_text(head: bytes) -> bool:
    try:
        text = head.decode("ascii")
    except UnicodeDecodeError:
        return False
    return all(c.isprintable() or c in "\r\n\t" for c in text)


def detect_format(path: str | Path) -> str:
    """Registry name of the format of ``path`` (see module docstring).

    Raises :class:`FormatError` for missing or empty files, unknown content, and content that
    contradicts the extension.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(_SNIFF_BYTES)
    except FileNotFoundError:
        raise FormatError(f"{path}: file not found") from None
    except IsADirectoryError:
        if (path / "metadata.yaml").is_file():
            return "rosbag2"
        raise FormatError(f"{path}: is a directory, not a recording file (a ROS2 bag directory "
                          "holds metadata.yaml)") from None
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror})") from None
    if not head:
        raise FormatError(f"{path}: empty file (0 bytes), no events to read")
    suffix = path.suffix.lower()
    by_suffix = [s.name for s in FORMATS.values() if suffix in s.suffixes]
    by_magic = _by_magic(head)
    if by_magic == "raw (no encoding in header)" and suffix == ".dat":
        by_magic = "dat"  # a DAT header without its (mandatory) 'Data file containing' line
    elif by_magic == "raw (no encoding in header)" and by_suffix == ["text"] and _looks_like_text(head):
        by_magic = None  # a text file whose first line is a '%' comment, not a Prophesee header
    if by_magic == "raw (no encoding in header)":
        raise FormatError(
            f"{path}: starts with a '%' header like a Prophesee .raw file, but no header line names its "
            "encoding ('% evt 2.0', '% format EVT3;...'); pass --format evt2 or evt3 (format=...)"
        )
    if by_magic is not None and by_magic not in FORMATS:
        raise FormatError(
            f"{path}: Prophesee .raw header names encoding '{by_magic}', which evseg does not read "
            "(supported: evt2, evt3; pass --format evt2 or evt3 if the header is wrong)"
        )
    if by_magic is not None:
        if by_suffix and by_magic not in by_suffix:
            raise FormatError(
                f"{path}: the extension '{suffix}' says {'/'.join(by_suffix)} but the content "
                f"(magic bytes at offset 0) is {by_magic}; pass --format {by_magic} "
                "(format=...) to read it as such"
            )
        return by_magic
    if "text" in by_suffix and (by_suffix == ["text"] or _looks_like_text(head)):
        return "text"  # no magic: the text reader reports bad content with its line number
    if by_suffix:
        spec = next((FORMATS[n] for n in by_suffix if FORMATS[n].magic), FORMATS[by_suffix[0]])
        expected = [SQLITE_MAGIC, MCAP_MAGIC] if spec.name == "rosbag2" else [spec.magic]
        if any(m and head.startswith(m) for m in expected):
            raise FormatError(f"{path}: the {'/'.join(by_suffix)} header is cut short or damaged "
                              f"({path.stat().st_size} bytes in the file)")
        raise FormatError(
            f"{path}: not a valid {'/'.join(by_suffix)} file: bad magic bytes at offset 0 "
            f"(expected {' or '.join(repr(m) for m in expected)}, got {head[:len(expected[0]) or 8]!r})"
        )
    if _looks_like_text(head):
        return "text"
    raise FormatError(
        f"{path}: unknown format (magic bytes {head[:8]!r} at offset 0, extension '{suffix}'); "
        f"supported: {', '.join(FORMATS)}"
    )


def open_source(path: Path, format: str, **options):
    """Open ``path`` with the reader of ``format`` (no detection)."""
    if format not in FORMATS:
        raise FormatError(f"{path}: unknown format '{format}'; supported: {', '.join(FORMATS)}")
    if not path.exists():
        raise FormatError(f"{path}: file not found")
    if path.is_dir():
        if format != "rosbag2":
            raise FormatError(f"{path}: is a directory, not a recording file (only a ROS2 bag, format "
                              "rosbag2, is a directory)")
    elif path.stat().st_size == 0:
        raise FormatError(f"{path}: empty file (0 bytes), no events to read")
    spec = FORMATS[format]
    module = importlib.import_module(f"evseg.io.{spec.module}")
    return module.open_source(path, format=format, **options)
