"""Output paths checked before any work (evseg.io.output_paths)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from evseg.errors import ConfigError
from evseg.io.output_paths import check_output_folder, check_output_path


def test_a_writable_new_file_passes_and_leaves_nothing_behind(tmp_path):
    check_output_path(tmp_path / "new" / "deeper" / "r.npz", "--out", (".npz",))
    assert list(tmp_path.iterdir()) == []  # no folder created, the probe removed


@pytest.mark.parametrize("name, message", [("r.txt", "must end in .npz"), ("r", "must end in .npz"),
                                           ("R.NPZ", None)])
def test_the_extension(tmp_path, name, message):
    if message is None:
        check_output_path(tmp_path / name, "--out", (".npz",))
        return
    with pytest.raises(ConfigError, match=rf"--out {tmp_path / name}: the file must end in \.npz"):
        check_output_path(tmp_path / name, "--out", (".npz",))


def test_a_folder_is_refused(tmp_path):
    (tmp_path / "adir.npz").mkdir()
    with pytest.raises(ConfigError, match="is a folder; give a file name inside it"):
        check_output_path(tmp_path / "adir.npz", "--out", (".npz",))


def test_an_input_is_refused_under_any_name(tmp_path):
    rec = tmp_path / "rec.npz"
    rec.write_bytes(b"events")
    other_name = tmp_path / "link.npz"
    os.symlink(rec, other_name)
    for path in (rec, other_name, tmp_path / "." / "rec.npz"):
        with pytest.raises(ConfigError, match="is the recording, which the run reads; choose another name"):
            check_output_path(path, "--out", (".npz",), [("the recording", rec)])
    assert rec.read_bytes() == b"events"
    check_output_path(tmp_path / "other.npz", "--out", (".npz",), [("the recording", rec), ("the flow", None)])


def test_a_file_in_the_folder_path_is_refused(tmp_path):
    (tmp_path / "sim.npz").write_bytes(b"x")
    with pytest.raises(ConfigError, match=r"sim\.npz is a file, not a folder"):
        check_output_path(tmp_path / "sim.npz" / "deeper" / "r.npz", "--out", (".npz",))
    with pytest.raises(ConfigError, match="--frames .*sim.npz: is a file, not a folder"):
        check_output_folder(tmp_path / "sim.npz", "--frames")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs /proc, a folder that refuses new files")
def test_a_folder_that_refuses_files():
    # /proc refuses new files even to root, for whom os.access says yes everywhere.
    with pytest.raises(ConfigError, match=r"--out /proc/r\.npz: cannot write in /proc"):
        check_output_path(Path("/proc/r.npz"), "--out", (".npz",))
