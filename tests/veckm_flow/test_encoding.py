import numpy as np
import pytest

from evseg.calibration import Calibration
from evseg.errors import ConfigError, EventDataError
from evseg.veckm_flow import EncodingConfig, encode_targets, encoding_matrix
from evseg.veckm_flow.encoding import encode_targets_reference, time_phase_tables, undistorted_to_sensor_flow

# The fast path accumulates in complex64 while the reference is float64; features have
# magnitude ~1 (norm sqrt(d)), so 1e-4 is ~1000 float32 ulps, far below any effect on the head.
ATOL = 1e-4


@pytest.mark.parametrize("k,n", [(1, 500), (3, 2000), (8, 4000)])
def test_fast_encoding_matches_direct_window_sum(k, n, make_slice):
    cfg = EncodingConfig(d=8, window_px=k, seed=1)
    ev = make_slice(n, (40, 30), seed=k)
    targets = np.arange(0, n, 7)
    fast = encode_targets(ev, targets, (40, 30), cfg)
    ref = encode_targets_reference(ev, targets, (40, 30), cfg)
    assert fast.shape == (len(targets), cfg.n_features) and fast.dtype == np.float32
    np.testing.assert_allclose(fast, ref, atol=ATOL)


def test_windows_across_column_blocks_and_sensor_edges_match_direct_sum(make_slice):
    # 250 px wide: three column blocks of the grid pass (96 px blocks), so windows straddle
    # block boundaries; every pixel of the first and last rows and of the block-boundary
    # columns is a target, so windows cut by the top and bottom edges are covered too.
    from evseg.veckm_flow.encoding import _BLOCK_COLUMNS

    w, h = 250, 16
    assert w > 2 * _BLOCK_COLUMNS
    cfg = EncodingConfig(d=8, window_px=3, seed=2)
    ev = make_slice(6000, (w, h), seed=5)
    x, y = ev["x"].astype(int), ev["y"].astype(int)
    edge_cols = {0, w - 1} | {c * w // 3 + o for c in (1, 2) for o in (-1, 0, 1)}
    targets = np.flatnonzero((y == 0) | (y == h - 1) | np.isin(x, sorted(edge_cols)))
    assert len(targets) > 200
    fast = encode_targets(ev, targets, (w, h), cfg)
    ref = encode_targets_reference(ev, targets, (w, h), cfg)
    np.testing.assert_allclose(fast, ref, atol=ATOL)



def test_sparse_targets_skip_rows_and_blocks_and_still_match_direct_sum(make_slice):
    # The pass adds a row's box sums only to the windows that hold the row, skips rows no
    # window reaches and blocks without targets: a few targets in a few rows of one block,
    # with windows overlapping (same and neighbouring rows), at the top and bottom edges
    # and many rows apart, must still get their exact window sums.
    w, h = 250, 60
    cfg = EncodingConfig(d=8, window_px=3, seed=4)
    ev = make_slice(8000, (w, h), seed=7)
    x, y = ev["x"].astype(int), ev["y"].astype(int)
    left = x < 90  # the first column block only
    picks = []
    for row in (0, 1, 4, 30, 31, 33, 58, 59):
        picks += list(np.flatnonzero(left & (y == row))[:3])
    targets = np.array(sorted(picks))
    assert len(targets) >= 20 and len(np.unique(y[targets])) == 8
    fast = encode_targets(ev, targets, (w, h), cfg)
    np.testing.assert_allclose(fast, encode_targets_reference(ev, targets, (w, h), cfg), atol=ATOL)

def test_features_have_vecKM_norm_and_count(make_slice):
    cfg = EncodingConfig(d=16, window_px=2)
    ev = make_slice(300, (20, 10))
    f = encode_targets(ev, np.arange(300), (20, 10), cfg)
    np.testing.assert_allclose(np.linalg.norm(f[:, :32], axis=1), 4.0, rtol=1e-5)  # sqrt(16)
    # Event 0's window: all events within 2 px in x and y (itself included).
    x, y = ev["x"].astype(int), ev["y"].astype(int)
    n0 = np.sum((abs(x - x[0]) <= 2) & (abs(y - y[0]) <= 2))
    assert f[0, -1] == pytest.approx(np.log1p(n0), rel=1e-6)


def test_encoding_is_translation_invariant_in_space_and_time(make_slice):
    cfg = EncodingConfig(d=16, window_px=3)
    ev = make_slice(400, (20, 20), seed=5)
    shifted = ev.copy()
    shifted["x"] += 7
    shifted["y"] += 11
    shifted["t"] += 123_457
    targets = np.flatnonzero((ev["x"] >= 4) & (ev["x"] < 16) & (ev["y"] >= 4) & (ev["y"] < 16))
    a = encode_targets(ev, targets, (40, 40), cfg)
    b = encode_targets(shifted, targets, (40, 40), cfg)
    np.testing.assert_allclose(a, b, atol=ATOL)


def test_time_tables_are_exact_factorisation():
    cfg = EncodingConfig(d=4, polarity=False)
    hi, lo = time_phase_tables(cfg, 50_000)
    dt = np.array([0, 1, 1023, 1024, 37_777, 50_000])
    a_t = encoding_matrix(cfg)[2] / cfg.t_scale_us
    expect = np.exp(1j * np.outer(dt, a_t))
    np.testing.assert_allclose(hi[dt >> 10] * lo[0, dt & 1023], expect, atol=1e-6)  # complex64 rounding


def test_does_not_mutate_input_and_is_deterministic(make_slice):
    cfg = EncodingConfig(d=8, window_px=2)
    ev = make_slice(500, (30, 20))
    before = ev.copy()
    a = encode_targets(ev, np.arange(0, 500, 3), (30, 20), cfg)
    b = encode_targets(ev, np.arange(0, 500, 3), (30, 20), cfg)
    np.testing.assert_array_equal(ev, before)
    np.testing.assert_array_equal(a, b)


def test_features_do_not_depend_on_the_thread_count(make_slice):
    """The grid pass splits the sensor into column blocks of a fixed width: with blocks per
    thread, 1 and 2 threads summed in another float32 order and labels could change."""
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has a single thread here")
    cfg = EncodingConfig(d=8, window_px=3)
    ev = make_slice(4000, (346, 60))
    targets = np.arange(0, 4000, 2)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = encode_targets(ev, targets, (346, 60), cfg)
        numba.set_num_threads(2)
        two = encode_targets(ev, targets, (346, 60), cfg)
    finally:
        numba.set_num_threads(before)
    np.testing.assert_array_equal(one, two)


def test_matrix_is_seeded():
    a = encoding_matrix(EncodingConfig(d=8, seed=0, alpha=2.0))
    b = encoding_matrix(EncodingConfig(d=8, seed=0, alpha=2.0))
    c = encoding_matrix(EncodingConfig(d=8, seed=1, alpha=2.0))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (3, 8) and not np.allclose(a, c)


def test_time_octaves_spread_only_the_time_row():
    """t_octaves scales the time entries by 2**(o t_octaves), o in [0, 1], and nothing else;
    0 gives exactly the old matrix (models exported before the field keep their meaning)."""
    base = encoding_matrix(EncodingConfig(d=64, seed=4, polarity=True))
    spread = encoding_matrix(EncodingConfig(d=64, seed=4, polarity=True, t_octaves=2.0))
    np.testing.assert_array_equal(base[[0, 1, 3]], spread[[0, 1, 3]])
    ratio = spread[2] / base[2]
    assert ratio.min() >= 1.0 and ratio.max() <= 4.0 and ratio.max() > 3.0 and ratio.min() < 1.2
    np.testing.assert_array_equal(encoding_matrix(EncodingConfig(d=64, seed=4, polarity=True, t_octaves=0.0)), base)
    with pytest.raises(ConfigError, match="t_octaves"):
        EncodingConfig(t_octaves=-9)


def test_fast_encoding_with_time_octaves_matches_direct_window_sum(make_slice):
    cfg = EncodingConfig(d=8, window_px=3, seed=2, t_octaves=3.0, polarity=True)
    ev = make_slice(2000, (40, 30), seed=5)
    targets = np.arange(0, 2000, 7)
    np.testing.assert_allclose(encode_targets(ev, targets, (40, 30), cfg),
                               encode_targets_reference(ev, targets, (40, 30), cfg), atol=ATOL)


def test_config_validation_and_roundtrip():
    cfg = EncodingConfig(d=24, window_px=5, alpha=3.0, xy_scale_px=8.0, t_scale_us=2000.0, seed=7)
    assert EncodingConfig.from_dict(cfg.to_dict()) == cfg
    assert cfg.flow_unit_px_s == pytest.approx(8.0 / 0.002)
    with pytest.raises(ConfigError, match="window_px"):
        EncodingConfig(window_px=0)
    with pytest.raises(ConfigError, match="unknown"):
        EncodingConfig.from_dict({"d": 8, "radius": 3})


def test_bad_targets_and_events_raise(make_slice):
    cfg = EncodingConfig(d=4, window_px=1)
    ev = make_slice(10, (8, 8))
    with pytest.raises(EventDataError, match="position 10"):
        encode_targets(ev, np.array([10]), (8, 8), cfg)
    with pytest.raises(EventDataError, match="outside"):
        encode_targets(ev, np.array([0]), (4, 4), cfg)
    assert encode_targets(ev, np.zeros(0, np.int64), (8, 8), cfg).shape == (0, 9)
    long = ev.copy()
    long["t"][-1] = long["t"][0] + (1 << 30)  # 17.9 min after the first event
    with pytest.raises(EventDataError, match="the slice spans 1074 s"):
        encode_targets(long, np.array([0]), (8, 8), cfg)
    long["t"][-1] -= 1  # the longest span taken
    assert encode_targets(long, np.array([0]), (8, 8), cfg).shape == (1, 9)


def test_calibrated_encoding_matches_reference_with_undistorted_positions(make_slice):
    K = np.array([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]])
    cal = Calibration(K, np.array([-0.3, 0.1, 0.001, -0.001]), (40, 30))
    cfg = EncodingConfig(d=8, window_px=3)
    ev = make_slice(1500, (40, 30), seed=2)
    targets = np.arange(0, 1500, 11)
    fast = encode_targets(ev, targets, (40, 30), cfg, calibration=cal)
    ref = encode_targets_reference(ev, targets, (40, 30), cfg, calibration=cal)
    np.testing.assert_allclose(fast, ref, atol=ATOL)
    assert not np.allclose(fast, encode_targets(ev, targets, (40, 30), cfg), atol=1e-2)


def test_undistorted_to_sensor_flow_identity_and_scaling():
    # No distortion: undistorted == raw pixels, flow unchanged.
    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    cal = Calibration(K, np.zeros(4), (40, 30))
    nx, ny = undistorted_to_sensor_flow(np.array([100.0, -30.0]), np.array([0.0, 40.0]), np.array([5, 20]), np.array([5, 10]), cal)
    np.testing.assert_allclose(nx, [100.0, -30.0], rtol=1e-4)  # float32 undistortion map
    np.testing.assert_allclose(ny, [0.0, 40.0], atol=1e-3)


def test_polarity_coordinate_matches_reference_and_matters(make_slice):
    cfg = EncodingConfig(d=8, window_px=3, polarity=True)
    ev = make_slice(2000, (40, 30), seed=6)
    targets = np.arange(0, 2000, 13)
    fast = encode_targets(ev, targets, (40, 30), cfg)
    np.testing.assert_allclose(fast, encode_targets_reference(ev, targets, (40, 30), cfg), atol=ATOL)
    plain = encode_targets(ev, targets, (40, 30), EncodingConfig(d=8, window_px=3, polarity=False))
    assert not np.allclose(fast, plain, atol=1e-2)
    # The polarity row is appended: x, y, t rows are those of the plain encoding.
    np.testing.assert_array_equal(encoding_matrix(cfg)[:3], encoding_matrix(EncodingConfig(d=8, window_px=3, polarity=False)))


def test_separable_phase_factors_equal_the_full_table(make_slice):
    # Raw pixels: the phase is stored as a row and a column factor (H + W rows of d, not
    # H x W); their product is the full table, and a caller's full table gives the same features.
    from evseg.veckm_flow.encoding import spatial_phase, spatial_phase_factors

    cfg = EncodingConfig(d=8, window_px=2, seed=3)
    f = spatial_phase_factors(cfg, (40, 30))
    assert f.rows.shape == (30, 1, 2, 8) and f.cols.shape == (40, 1, 2, 8) and f.shape == (30, 40, 8)
    rows = f.rows[:, :, 0] + 1j * f.rows[:, :, 1]  # (H, 1, d)
    cols = f.cols[:, 0, 0] + 1j * f.cols[:, 0, 1]  # (W, d)
    np.testing.assert_allclose(rows * cols[None], spatial_phase(cfg, (40, 30)), atol=1e-6)
    ev = make_slice(800, (40, 30), seed=9)
    targets = np.arange(0, 800, 5)
    factored = encode_targets(ev, targets, (40, 30), cfg, phase_xy=f)
    full = encode_targets(ev, targets, (40, 30), cfg, phase_xy=spatial_phase(cfg, (40, 30)))
    np.testing.assert_allclose(factored, full, atol=ATOL)


def test_phase_table_of_the_wrong_shape_is_refused(make_slice):
    from evseg.veckm_flow.encoding import spatial_phase_factors

    cfg = EncodingConfig(d=8, window_px=2)
    ev = make_slice(100, (40, 30))
    with pytest.raises(EventDataError, match="phase_xy has shape"):
        encode_targets(ev, np.arange(10), (40, 30), cfg, phase_xy=spatial_phase_factors(cfg, (30, 40)))


_FRESH_OR_CACHED = """
import sys
import numpy as np
from evseg.veckm_flow import EncodingConfig, encode_targets
from evseg.veckm_flow.encoding import spatial_phase
from evseg.veckm_flow.bench import SENSOR, synthetic_slice

cfg = EncodingConfig(polarity=True)  # the shipped model's width (d = 32)
ev = synthetic_slice(30_000, seed=3)
targets = np.arange(0, len(ev), 3)
raw = encode_targets(ev, targets, SENSOR, cfg)
full = encode_targets(ev, targets, SENSOR, cfg, phase_xy=spatial_phase(cfg, SENSOR))
np.save(sys.argv[1], np.concatenate([raw, full]))
"""


def test_features_are_the_same_compiled_fresh_and_loaded_from_numba_cache(tmp_path):
    # The first run after an install compiles the encoder's kernels; every later run loads
    # them from numba's cache. Both must give the same bits, or the first run's labels differ
    # (fastmath's fused multiply-add did: ~1e-6 in the features).
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba_cache"))
    outs = []
    for run in ("fresh", "cached"):
        out = tmp_path / f"{run}.npy"
        subprocess.run([sys.executable, "-c", _FRESH_OR_CACHED, str(out)], env=env, check=True, timeout=300,
                       cwd=tmp_path)  # not the repository root, whose ./evseg would shadow an installed one
        outs.append(np.load(out))
        if run == "fresh":  # otherwise the second run would compile afresh too and prove nothing
            assert list((tmp_path / "numba_cache").rglob("*window_features*.nbi"))
    assert outs[0].shape == (20_000, 65)
    np.testing.assert_array_equal(outs[0], outs[1])


@pytest.mark.parametrize("width,height", [(40, 30), (346, 260), (1000, 7)])
def test_targets_are_ordered_by_column_block_then_row_stably(width, height):
    # The box pass completes windows block by block, row by row; the compiled counting sort
    # must give the plain numpy rule's permutation (stable: duplicates keep input order).
    from evseg.events import EVENT_DTYPE
    from evseg.veckm_flow import _kernels
    from evseg.veckm_flow.encoding import _BLOCK_COLUMNS

    rng = np.random.default_rng(width)
    ev = np.zeros(3000, EVENT_DTYPE)
    ev["x"] = rng.integers(0, width, len(ev))
    ev["y"] = rng.integers(0, height, len(ev))
    ev["t"] = np.sort(rng.integers(5_000, 50_000, len(ev)))
    ev["p"] = rng.choice([-1, 1], len(ev))
    targets = rng.integers(0, len(ev), 1500)  # with repeats
    nblk = max(1, -(-width // _BLOCK_COLUMNS))
    order, tx, ty, tdt, tpol, blk_start = _kernels.order_targets(
        targets, ev["x"], ev["y"], ev["t"], ev["p"], 4_000, True, width, height, nblk)
    x, y = ev["x"][targets].astype(np.int64), ev["y"][targets].astype(np.int64)
    blk = np.searchsorted(np.arange(nblk + 1) * width // nblk, x, side="right") - 1
    expect = np.argsort(blk * height + y, kind="stable")
    np.testing.assert_array_equal(order, expect)
    np.testing.assert_array_equal(tx, x[expect])
    np.testing.assert_array_equal(ty, y[expect])
    np.testing.assert_array_equal(tdt, ev["t"][targets][expect] - 4_000)
    np.testing.assert_array_equal(tpol, (ev["p"][targets][expect] > 0).astype(np.int8))
    np.testing.assert_array_equal(blk_start, np.searchsorted(blk[expect], np.arange(nblk + 1)))


# ----------------------------------------------------------------- pyramid levels


@pytest.mark.parametrize("size", [(40, 30), (41, 29)])  # even, and odd (partial border cells)
def test_pyramid_encoding_matches_direct_window_sums_per_level(size, make_slice):
    cfg = EncodingConfig(d=8, window_px=2, seed=3, polarity=True, pyramid_levels=3)
    ev = make_slice(2500, size, seed=4)
    targets = np.arange(0, 2500, 9)
    fast = encode_targets(ev, targets, size, cfg)
    assert fast.shape == (len(targets), 3 * 17) and cfg.n_features == 51
    np.testing.assert_allclose(fast, encode_targets_reference(ev, targets, size, cfg), atol=ATOL)


def test_pyramid_level_one_is_the_encoding_of_events_binned_into_2px_cells(make_slice):
    from evseg.veckm_flow.encoding import level_sensor_size

    cfg = EncodingConfig(d=8, window_px=3, seed=5, polarity=True, pyramid_levels=2)
    single = EncodingConfig(d=8, window_px=3, seed=5, polarity=True)
    ev = make_slice(2000, (41, 30), seed=6)
    targets = np.arange(0, 2000, 5)
    both = encode_targets(ev, targets, (41, 30), cfg)
    # Level 0 is exactly the single-scale encoding (same matrix block, same kernel).
    np.testing.assert_array_equal(encoding_matrix(cfg)[:, :8], encoding_matrix(single))
    np.testing.assert_array_equal(both[:, :17], encode_targets(ev, targets, (41, 30), single))
    # Level 1: the same encoding, with level 1's matrix block, of the events at x // 2, y // 2.
    binned = ev.copy()
    binned["x"] //= 2
    binned["y"] //= 2
    assert level_sensor_size((41, 30), 1) == (21, 15)
    level1 = encode_targets(binned, targets, (21, 15), single, matrix=encoding_matrix(cfg)[:, 8:])
    np.testing.assert_array_equal(both[:, 17:], level1)
    # A window of 7 cells of 2 px sees more events than one of 7 px.
    assert np.all(both[:, 33] >= both[:, 16]) and np.any(both[:, 33] > both[:, 16])


def test_pyramid_matrix_blocks_are_seeded_and_distinct():
    a = encoding_matrix(EncodingConfig(d=8, seed=0, pyramid_levels=3))
    assert a.shape == (3, 24) == EncodingConfig(d=8, pyramid_levels=3).matrix_shape
    np.testing.assert_array_equal(a, encoding_matrix(EncodingConfig(d=8, seed=0, pyramid_levels=3)))
    assert not np.allclose(a[:, :8], a[:, 8:16]) and not np.allclose(a[:, 8:16], a[:, 16:])
    assert not np.allclose(a[:, 8:], encoding_matrix(EncodingConfig(d=8, seed=1, pyramid_levels=3))[:, 8:])


def test_calibrated_pyramid_encoding_matches_reference(make_slice):
    K = np.array([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]])
    cal = Calibration(K, np.array([-0.3, 0.1, 0.001, -0.001]), (40, 30))
    cfg = EncodingConfig(d=8, window_px=2, pyramid_levels=2)
    ev = make_slice(1500, (40, 30), seed=2)
    targets = np.arange(0, 1500, 11)
    fast = encode_targets(ev, targets, (40, 30), cfg, calibration=cal)
    np.testing.assert_allclose(fast, encode_targets_reference(ev, targets, (40, 30), cfg, calibration=cal), atol=ATOL)
    assert not np.allclose(fast[:, 17:], encode_targets(ev, targets, (40, 30), cfg)[:, 17:], atol=1e-2)


def test_pyramid_config_and_phase_arguments_are_checked(make_slice):
    from evseg.veckm_flow.encoding import pyramid_phases, spatial_phase_factors

    for bad in (0, 7, 1.5):
        with pytest.raises(ConfigError, match="pyramid_levels"):
            EncodingConfig(pyramid_levels=bad)
    cfg = EncodingConfig(d=8, pyramid_levels=2)
    assert EncodingConfig.from_dict(cfg.to_dict()) == cfg
    ev = make_slice(200, (40, 30))
    with pytest.raises(EventDataError, match="1 level"):
        encode_targets(ev, np.arange(10), (40, 30), cfg, phase_xy=spatial_phase_factors(cfg, (40, 30)))
    with pytest.raises(ConfigError, match=r"expected \(3, 16\)"):
        encode_targets(ev, np.arange(10), (40, 30), cfg, matrix=encoding_matrix(EncodingConfig(d=8)))
    phases = pyramid_phases(cfg, (40, 30))
    assert [p.shape for p in phases] == [(30, 40, 8), (15, 20, 8)]
    np.testing.assert_array_equal(encode_targets(ev, np.arange(10), (40, 30), cfg, phase_xy=phases),
                                  encode_targets(ev, np.arange(10), (40, 30), cfg))


@pytest.mark.parametrize("calibrated,levels", [(False, 1), (True, 1), (False, 2)])
def test_looks_encoded_together_equal_each_look_alone_bit_for_bit(make_slice, calibrated, levels):
    # The mirror looks share each pixel's sum over its events; sharing it must not change a bit
    # of any look's features (raw pixels, undistorted positions, a pyramid).
    from evseg.veckm_flow.encoding import encode_targets_looks
    from evseg.veckm_flow.mirrors import mirrored_encoding_matrix

    cfg = EncodingConfig(d=8, window_px=3, polarity=True, pyramid_levels=levels)
    ev = make_slice(3000, (40, 30), seed=4)
    targets = np.arange(0, 3000, 7)
    cal = None
    if calibrated:
        K = np.array([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]])
        cal = Calibration(K, np.array([-0.3, 0.1, 0.001, -0.001]), (40, 30))
    mats = [mirrored_encoding_matrix(encoding_matrix(cfg), k) for k in range(8)]
    together = encode_targets_looks(ev, targets, (40, 30), cfg, mats, calibration=cal)
    assert together.shape == (8, len(targets), cfg.n_features) and together.dtype == np.float32
    for k, m in enumerate(mats):
        np.testing.assert_array_equal(together[k], encode_targets(ev, targets, (40, 30), cfg, cal, matrix=m))
    assert not np.allclose(together[0], together[5], atol=1e-2)  # the looks are not one look copied


def test_looks_must_differ_only_in_their_spatial_rows(make_slice):
    from evseg.veckm_flow.encoding import encode_targets_looks

    cfg = EncodingConfig(d=8, window_px=3, polarity=True)
    ev = make_slice(500, (40, 30), seed=1)
    a = encoding_matrix(cfg)
    for row in (2, 3):  # time, polarity
        b = a.copy()
        b[row] *= 2.0
        with pytest.raises(ConfigError, match="time .and polarity. rows"):
            encode_targets_looks(ev, np.arange(5), (40, 30), cfg, [a, b])
    with pytest.raises(ConfigError, match="at least one matrix"):
        encode_targets_looks(ev, np.arange(5), (40, 30), cfg, [])
    with pytest.raises(ConfigError, match="shape"):
        encode_targets_looks(ev, np.arange(5), (40, 30), cfg, [a, a[:3]])
    assert encode_targets_looks(ev, np.zeros(0, np.int64), (40, 30), cfg, [a, a]).shape == (2, 0, 17)


def test_looks_take_callers_phase_tables_of_any_layout(make_slice):
    # A caller's SpatialPhase may hold strided arrays; the looks' tables are made uniform
    # (the kernel reads them as one tuple) without changing the features.
    from evseg.veckm_flow.encoding import SpatialPhase, encode_targets_looks, spatial_phase_factors

    cfg = EncodingConfig(d=8, window_px=3, polarity=True)
    ev = make_slice(800, (40, 30), seed=3)
    targets = np.arange(0, 800, 9)
    f = spatial_phase_factors(cfg, (40, 30))
    strided = SpatialPhase(rows=np.repeat(f.rows, 2, axis=0)[::2], cols=f.cols)
    assert not strided.rows.flags.c_contiguous
    a = encoding_matrix(cfg)
    out = encode_targets_looks(ev, targets, (40, 30), cfg, [a, a], phases=[(f,), (strided,)])
    ref = encode_targets(ev, targets, (40, 30), cfg)
    np.testing.assert_array_equal(out[0], ref)
    np.testing.assert_array_equal(out[1], ref)
