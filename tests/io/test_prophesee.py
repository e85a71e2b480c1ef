"""Prophesee EVT2 / EVT3 decoding: hand-encoded words, wrap-around, real samples."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from evfiles import evt2_bytes, evt3_bytes, sample_events
from evseg.errors import FormatError
from evseg.io import detect_format, open_recording, read_events
from evseg.io.prophesee import geometry_of, read_header


def _write(tmp_path, name, data):
    p = tmp_path / name
    p.write_bytes(data)
    return p


@pytest.mark.parametrize("enc, fmt", [(evt2_bytes, "evt2"), (evt3_bytes, "evt3")])
def test_tiny_round_trip(tmp_path, enc, fmt):
    ev = sample_events(200, seed=1)
    p = _write(tmp_path, "a.raw", enc(ev))
    assert detect_format(p) == fmt
    s = read_events(p)
    assert s.sensor_size == (64, 48)
    np.testing.assert_array_equal(s.events, ev)
    # Chunk boundaries must not change the result (decoder state is carried over).
    small = read_events(p, chunk_events=7)
    np.testing.assert_array_equal(small.events, ev)


def test_evt2_time_high_wraps_to_monotonic_time(tmp_path):
    # EVT2 time is 28 + 6 = 34 bits: events straddling 2**34 us must stay increasing.
    t = 2**34 + np.array([-300, -100, -1, 0, 5, 200])
    ev = sample_events(6)
    ev["t"] = t
    p = _write(tmp_path, "w.raw", evt2_bytes(ev))
    np.testing.assert_array_equal(read_events(p).events["t"], t)
    np.testing.assert_array_equal(read_events(p, chunk_events=2).events["t"], t)


def test_evt3_time_high_wraps_to_monotonic_time(tmp_path):
    # EVT3 time is 12 + 12 = 24 bits (16.8 s): two wraps in a row.
    t = np.array([2**24 - 5000, 2**24 - 1, 2**24, 2**24 + 4096, 2**25 + 7, 2**25 + 9000])
    ev = sample_events(6)
    ev["t"] = t
    p = _write(tmp_path, "w.raw", evt3_bytes(ev))
    np.testing.assert_array_equal(read_events(p).events["t"], t)
    np.testing.assert_array_equal(read_events(p, chunk_events=3).events["t"], t)


def test_evt3_vectors_expand_from_base_x(tmp_path):
    words = [
        0x8000 | 0x001,  # TIME_HIGH 1 -> t = 4096 + low
        0x6000 | 0x010,  # TIME_LOW 16
        0x0000 | 7,  # ADDR_Y 7
        0x3000 | (1 << 11) | 20,  # VECT_BASE_X x=20, ON
        0x4000 | 0b100000000101,  # VECT_12: x = 20, 22, 31; base -> 32
        0x5000 | 0b10000001,  # VECT_8: x = 32, 39; base -> 40
        0x2000 | 5,  # ADDR_X x=5 OFF (single event, does not move the base)
        0x4000 | 0b1,  # VECT_12 again: x = 40
        0xA000 | 0x123,  # EXT_TRIGGER: skipped
        0x6000 | 0x011,  # TIME_LOW 17
        0x3000 | 3,  # VECT_BASE_X x=3, OFF
        0x5000 | 0b11,  # x = 3, 4
    ]
    p = _write(tmp_path, "v.raw", b"% evt 3.0\n% geometry 64x48\n" + struct.pack(f"<{len(words)}H", *words))
    ev = read_events(p).events
    assert ev["x"].tolist() == [20, 22, 31, 32, 39, 5, 40, 3, 4]
    assert ev["y"].tolist() == [7] * 9
    assert ev["p"].tolist() == [1, 1, 1, 1, 1, -1, 1, -1, -1]
    assert ev["t"].tolist() == [4096 + 16] * 7 + [4096 + 17] * 2


def test_header_geometry_variants():
    assert geometry_of({"geometry": "1280x720"}) == (1280, 720)
    assert geometry_of({"format": "EVT3;height=720;width=1280"}) == (1280, 720)
    assert geometry_of({"plugin_name": "hal_plugin_gen3_fx3"}) == (640, 480)
    assert geometry_of({"plugin_name": "something_else"}) is None
    import io

    fields, off = read_header(io.BytesIO(b"% evt 3.0\n% end\n\x01\x02"))
    assert fields == {"evt": "3.0"} and off == len(b"% evt 3.0\n% end\n")


def test_unknown_word_type_names_byte_offset(tmp_path):
    header = b"% evt 2.0\n% geometry 64x48\n"
    words = struct.pack("<3I", 0x8 << 28, (1 << 28) | 5, 0x3 << 28)  # type 0x3 is not EVT2
    p = _write(tmp_path, "bad.raw", header + words)
    with pytest.raises(FormatError, match=rf"evt2: unknown word type 0x3 at byte offset {len(header) + 8}"):
        read_events(p)


def test_truncated_word_is_reported(tmp_path):
    data = evt3_bytes(sample_events(10))
    p = _write(tmp_path, "t.raw", data[:-1])
    with pytest.raises(FormatError, match="truncated: 1 trailing byte"):
        open_recording(p)


def test_header_encoding_contradicts_format(tmp_path):
    p = _write(tmp_path, "a.raw", evt3_bytes(sample_events(5)))
    with pytest.raises(FormatError, match="the header says the encoding is evt3, not evt2"):
        read_events(p, format="evt2")


def test_unsupported_encoding(tmp_path):
    p = _write(tmp_path, "a.raw", b"% evt 2.1\n" + bytes(16))
    with pytest.raises(FormatError, match="encoding 'evt21'"):
        read_events(p)


def test_evt3_real_sample_against_reference(shared_data):
    """x, y, p and order are bit-exact; t differs from expelliarmus by its TIME_LOW rule.

    expelliarmus 1.1 (which wrote the reference) counts every decrease of TIME_LOW as a
    12-bit overflow and adds 4096 us, even when TIME_HIGH carries the increment itself and
    when TIME_LOW steps back a few us (this Gen4.1 file re-sends TIME_LOW rounded down every
    ~1 ms). That inflates the clip from 8.8 ms to 53.9 ms. The test recomputes exactly that
    count from the raw words and checks ``t_ref == t + 4096 * count`` for every event.
    """
    folder = shared_data / "prophesee_evt_samples"
    s = read_events(folder / "evt3_sample.raw")
    ref = np.load(folder / "evt3_sample.npy")
    assert len(s) == len(ref) == 219_596
    assert s.sensor_size == (1280, 720)
    ev = s.events
    np.testing.assert_array_equal(ev["x"], ref["x"])
    np.testing.assert_array_equal(ev["y"], ref["y"])
    np.testing.assert_array_equal(ev["p"], np.where(ref["p"] > 0, 1, -1))
    # Independent recount of expelliarmus' extra overflows, per event, from the raw words.
    with open(folder / "evt3_sample.raw", "rb") as f:
        _, off = read_header(f)
        f.seek(off)
        w = np.frombuffer(f.read(), dtype="<u2")
    typ = w >> 12
    tl_idx = np.flatnonzero(typ == 0x6)
    tl = (w[tl_idx] & 0xFFF).astype(np.int64)
    decreases = np.zeros(len(w), dtype=np.int64)
    decreases[tl_idx[1:]] = tl[1:] < tl[:-1]
    count_at_word = np.cumsum(decreases)
    n_per_word = np.where(typ == 0x2, 1, 0)
    n_per_word[typ == 0x4] = [bin(v).count("1") for v in w[typ == 0x4] & 0xFFF]
    n_per_word[typ == 0x5] = [bin(v).count("1") for v in w[typ == 0x5] & 0xFF]
    count_per_event = np.repeat(count_at_word, n_per_word)
    np.testing.assert_array_equal(ref["t"], ev["t"] + 4096 * count_per_event)
    # Our own time base is monotonic and spans 8.8 ms (TIME_HIGH moves only twice).
    assert np.all(np.diff(ev["t"]) >= 0)
    assert (int(ev["t"][0]), int(ev["t"][-1])) == (11_718_656, 11_727_457)


def test_evt2_real_samples(shared_data):
    # Figures from the folder READMEs (decoded there with expelliarmus).
    s = read_events(shared_data / "prophesee_evt_samples" / "evt2_sample.raw")
    assert len(s) == 539_481 and s.sensor_size == (640, 480)
    assert (int(s.events["x"].min()), int(s.events["x"].max())) == (60, 599)
    assert (int(s.events["y"].min()), int(s.events["y"].max())) == (18, 475)
    sparks = read_events(shared_data / "prophesee_sparks" / "evt2.raw")
    assert len(sparks) == 521_252
    assert (int(sparks.events["t"][0]), int(sparks.events["t"][-1])) == (913_716_224, 913_812_095)
    chunked = np.concatenate(list(open_recording(shared_data / "prophesee_sparks" / "evt2.raw",
                                                 chunk_events=100_000).chunks()))
    np.testing.assert_array_equal(chunked, sparks.events)
