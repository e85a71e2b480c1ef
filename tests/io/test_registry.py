"""Format detection: magic bytes, extensions, contradictions, empty and unknown files."""

from __future__ import annotations

import numpy as np
import pytest

from evfiles import es_bytes, evt2_bytes, sample_events
from evseg.errors import FormatError
from evseg.io import FORMATS, detect_format, format_names, read_events


def test_every_format_has_a_reader_module():
    import importlib

    for spec in FORMATS.values():
        assert hasattr(importlib.import_module(f"evseg.io.{spec.module}"), "open_source")
    assert format_names() == ["text", "npy", "npz", "mat", "h5", "rosbag", "rosbag2", "aedat4", "evt2", "evt3", "es",
                              "dat"]


def test_detection_by_magic_ignores_unknown_extension(tmp_path):
    p = tmp_path / "recording.bin"
    p.write_bytes(es_bytes(sample_events(5)))
    assert detect_format(p) == "es"
    np.save(tmp_path / "a.npy", np.zeros((2, 4)))
    (tmp_path / "a.npy").rename(tmp_path / "a.dat2")
    assert detect_format(tmp_path / "a.dat2") == "npy"


def test_misleading_extension_is_refused_and_format_overrides(tmp_path):
    p = tmp_path / "events.npz"
    p.write_bytes(evt2_bytes(sample_events(5)))
    with pytest.raises(FormatError, match=r"events.npz: the extension '.npz' says npz but the content .* is evt2; pass --format evt2"):
        detect_format(p)
    assert len(read_events(p, format="evt2")) == 5


def test_bad_magic_for_binary_extension(tmp_path):
    p = tmp_path / "x.h5"
    p.write_bytes(b"hello world, not hdf5")
    with pytest.raises(FormatError, match=r"x.h5: not a valid h5 file: bad magic bytes at offset 0"):
        detect_format(p)


def test_empty_missing_directory_and_garbage(tmp_path):
    (tmp_path / "e.raw").write_bytes(b"")
    with pytest.raises(FormatError, match=r"e.raw: empty file \(0 bytes\)"):
        read_events(tmp_path / "e.raw")
    with pytest.raises(FormatError, match=r"empty file"):
        read_events(tmp_path / "e.raw", format="evt3")
    with pytest.raises(FormatError, match="nope.es: file not found"):
        read_events(tmp_path / "nope.es")
    with pytest.raises(FormatError, match="is a directory"):
        read_events(tmp_path)
    g = tmp_path / "g.xyz"
    g.write_bytes(bytes(range(256)))
    with pytest.raises(FormatError, match=r"g.xyz: unknown format .* supported: text, npy"):
        read_events(g)
    with pytest.raises(FormatError, match="unknown format 'foo'"):
        read_events(g, format="foo")


def test_raw_without_encoding_line(tmp_path):
    p = tmp_path / "a.raw"
    p.write_bytes(b"% date 2020\n" + bytes(8))
    with pytest.raises(FormatError, match="no header line names its encoding.*--format evt2 or evt3"):
        detect_format(p)


def test_raw_header_cut_short_says_so(tmp_path):
    p = tmp_path / "cut.raw"
    p.write_bytes(b"% camera_integrator_name Prophesee\n% evt 3.0\n% format EVT3;he")
    p.write_bytes(p.read_bytes()[:20])
    with pytest.raises(FormatError, match=r"cut.raw: the evt2/evt3 header is cut short or damaged \(20 bytes"):
        detect_format(p)
