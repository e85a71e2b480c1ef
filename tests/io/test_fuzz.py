"""A corpus of broken files for every format: truncations, flipped bytes, garbage.

Each broken file must either read as a valid recording (some damage is undetectable, e.g. a
flipped bit in an x coordinate) or fail with an :class:`EvsegError` naming the file, never
with another exception (a numpy IndexError, a struct.error, a library's own error type).
The corpus is generated deterministically (fixed seed) from small valid files.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.io

from evfiles import dat_bytes, es_bytes, evt2_bytes, evt3_bytes, sample_events, text_lines, write_bag
from evseg.errors import EvsegError
from evseg.events import EventStream, validate_events
from evseg.io import read_events, write_h5, write_npz

N_FLIPS = 12


def _valid_file(tmp_path, fmt: str, shared) -> tuple[bytes, str]:
    ev = sample_events(60, seed=7)
    stream = EventStream(ev, (64, 48), t_offset_us=10**15)
    src = tmp_path / f"src.{fmt}"
    if fmt == "txt":
        return text_lines(ev).encode(), ".txt"
    if fmt == "csv":
        return ("t,x,y,p\n" + "".join(f"{e['t']},{e['x']},{e['y']},{int(e['p'] > 0)}\n" for e in ev)).encode(), ".csv"
    if fmt == "npy":
        np.save(src.with_suffix(".npy"), ev)
        return src.with_suffix(".npy").read_bytes(), ".npy"
    if fmt == "npz":
        return write_npz(stream, src.with_suffix(".npz")).read_bytes(), ".npz"
    if fmt == "mat":
        m = np.stack([ev["x"], ev["y"], ev["p"], ev["t"]], axis=1).astype(np.int32)
        scipy.io.savemat(src.with_suffix(".mat"), {"events": m})
        return src.with_suffix(".mat").read_bytes(), ".mat"
    if fmt == "h5":
        return write_h5(stream, src.with_suffix(".h5")).read_bytes(), ".h5"
    if fmt == "bag":
        write_bag(src.with_suffix(".bag"), {"/dvs/events": [ev[:30], ev[30:]]})
        return src.with_suffix(".bag").read_bytes(), ".bag"
    if fmt == "evt2":
        return evt2_bytes(ev), ".raw"
    if fmt == "evt3":
        return evt3_bytes(ev), ".raw"
    if fmt == "es":
        return es_bytes(ev), ".es"
    if fmt == "dat":
        return dat_bytes(ev), ".dat"
    if fmt == "aedat4":
        if shared is None:
            pytest.skip("no AEDAT4 writer; the corpus needs the shared real file")
        return (shared / "davis346_aedat4_fixtures" / "shiba24_sample.aedat4").read_bytes(), ".aedat4"
    raise AssertionError(fmt)


def corpus(data: bytes, seed: int) -> list[tuple[str, bytes]]:
    """Broken variants of ``data``: (description, bytes)."""
    rng = np.random.default_rng(seed)
    n = len(data)
    out = [("empty", b"")]
    for frac in (0.01, 0.1, 0.3, 0.5, 0.9):
        out.append((f"truncated to {int(frac * n)} bytes", data[: int(frac * n)]))
    out.append(("last byte cut", data[:-1]))
    for _ in range(N_FLIPS):
        i = int(rng.integers(0, n))
        b = bytearray(data)
        b[i] ^= 1 << int(rng.integers(0, 8))
        out.append((f"bit flipped at byte {i}", bytes(b)))
    for _ in range(3):
        i = int(rng.integers(0, n))
        b = bytearray(data)
        k = min(64, n - i)
        b[i : i + k] = rng.integers(0, 256, k, dtype=np.uint8).tobytes()
        out.append((f"64 garbage bytes at {i}", bytes(b)))
    out.append(("all garbage", rng.integers(0, 256, max(n // 4, 16), dtype=np.uint8).tobytes()))
    out.append(("magic then garbage", data[:16] + rng.integers(0, 256, 200, dtype=np.uint8).tobytes()))
    out.append(("valid twice", data + data))
    return out


FORMATS = ["txt", "csv", "npy", "npz", "mat", "h5", "bag", "evt2", "evt3", "es", "dat", "aedat4"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_broken_files_fail_cleanly(tmp_path, fmt, request):
    shared = None
    if fmt == "aedat4":
        shared = request.getfixturevalue("shared_data")
    data, suffix = _valid_file(tmp_path, fmt, shared)
    outcomes = {"read": 0, "error": 0}
    for k, (what, blob) in enumerate(corpus(data, seed=FORMATS.index(fmt))):
        p = tmp_path / f"broken{k}{suffix}"
        p.write_bytes(blob)
        try:
            s = read_events(p, sensor_size=None)
        except EvsegError as exc:
            assert str(p) in str(exc), (what, str(exc))
            assert "\n" not in str(exc).strip(), (what, str(exc))
            outcomes["error"] += 1
            continue
        except Exception as exc:  # pragma: no cover - the failure this test exists to catch
            pytest.fail(f"{fmt}, {what}: {type(exc).__name__}: {exc}")
        validate_events(s.events, s.sensor_size)  # whatever was read obeys the event model
        outcomes["read"] += 1
    assert outcomes["error"] >= 3  # at least empty, all-garbage and a truncation are detected


def test_misnamed_files_of_every_other_format(tmp_path, request):
    """Each valid file renamed to each other format's extension: refused with a clear message."""
    files = {f: _valid_file(tmp_path, f, None) for f in FORMATS if f != "aedat4"}
    for fmt, (data, _) in files.items():
        for other, (_, suffix) in files.items():
            # .txt, .csv and .dat all name text files (.dat also Prophesee DAT, told apart by content).
            if suffix == files[fmt][1] or (fmt in ("txt", "csv") and suffix in (".txt", ".csv", ".dat")):
                continue
            p = tmp_path / f"{fmt}_as{suffix}"
            p.write_bytes(data)
            try:
                read_events(p)
            except EvsegError as exc:
                assert str(p) in str(exc)
            except Exception as exc:  # pragma: no cover
                pytest.fail(f"{fmt} named {suffix}: {type(exc).__name__}: {exc}")
            else:
                pytest.fail(f"{fmt} named {suffix} was read without complaint")


from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_HEADERS = {
    ".raw2": b"% evt 2.0\n% geometry 64x48\n",
    ".raw3": b"% evt 3.0\n% geometry 64x48\n",
    ".es": b"Event Stream" + bytes([2, 0, 0, 1, 64, 0, 48, 0]),
}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(sorted(_HEADERS)), body=st.binary(max_size=400))
def test_random_binary_payloads(tmp_path, kind, body):
    """Any bytes after a valid header: a valid recording or an EvsegError, nothing else."""
    p = tmp_path / ("x.raw" if kind.startswith(".raw") else "x.es")
    p.write_bytes(_HEADERS[kind] + body)
    try:
        s = read_events(p)
    except EvsegError:
        return
    validate_events(s.events, s.sensor_size)


_token = st.one_of(
    st.integers(-5, 70).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", "x", "1e309", "0x10", "--", "1,2", "#"]),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lines=st.lists(st.lists(_token, min_size=0, max_size=5).map(" ".join), max_size=8),
       sep=st.sampled_from([" ", ",", "\t"]))
def test_random_text_lines(tmp_path, lines, sep):
    p = tmp_path / "x.txt"
    p.write_text("\n".join(line.replace(" ", sep) for line in lines))
    try:
        s = read_events(p, sensor_size=(64, 48))
    except EvsegError:
        return
    validate_events(s.events, s.sensor_size)
