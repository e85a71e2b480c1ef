"""VecKM-style local event encoding in O(N) events: a per-pixel complex field and box sums.

Each target event i is encoded by the sum over the events j of the same slice that lie in the
``(2k+1) x (2k+1)`` pixel window around it (``k = window_px``, clipped at the sensor border)::

    G_i = sum_j exp(i A^T (p_j - p_i)),   p = (x / xy_scale_px, y / xy_scale_px, t / t_scale_us)

with ``A`` a fixed random ``(3, d)`` matrix, entries ``N(0, 1) * alpha`` drawn from
``numpy.random.default_rng(seed)`` (rows: x, y, t; with ``polarity=True`` a fourth coordinate
``p = +1/-1`` and row). Because ``p_j - p_i`` is relative, the sum
factorises into ``exp(-i A^T p_i) * sum_j exp(i A^T p_j)``: the second factor is a box sum of the
per-pixel complex field ``F(x, y) = sum_{j at (x, y)} exp(i A^T p_j)`` (method.md section 3).
The events are counting-sorted by pixel (O(N)); one pass down the pixel grid then slides a box
along each row (a pixel's field value is computed from its events when it enters the box) and
adds the row-box sum at a target's column to that target's window sum for each of its
``2k+1`` window rows, in order; rows no target's window reaches are skipped. So a target
costs O(k d) and the whole encoding O(N d + W H d + T k d): linear in events, no N x N
adjacency, no H x W x d buffer (compiled loops in :mod:`evseg.veckm_flow._kernels`).

Precision: float32 (complex64). Each window sum is a fresh sum of ``2k+1`` row-box sums
(each bounded by the events of a ``2k+1`` pixel wide strip), so float32 rounding stays far
below one event's contribution.

Time: ``t`` enters only through differences; internally it is taken relative to the slice's
first event (integer microseconds, exact) and the per-event phase ``exp(i a_t t / t_scale_us)``
is the product of two small exact tables (high and low 10 bits of the microsecond offset), so no
per-event transcendental function is evaluated.

Coordinates: without a calibration, ``x, y`` are raw integer pixels. With one, the *positions*
``(x, y)`` in ``p`` are the undistorted pixel coordinates of each event's pixel (OpenCV,
``P = K``, so still in px), while the *neighbourhood* stays the raw-pixel window: no binning of
non-integer coordinates is needed because each pixel's spatial phase is looked up from a
per-pixel table. Without a calibration that table is never stored: the phase of raw pixel
``(x, y)`` is the product of a column factor ``exp(i a_x x / s)`` and a row factor
``exp(i a_y y / s)`` (:class:`SpatialPhase`), so a 1280x720 sensor needs two small tables instead
of ~0.5 GB of per-pixel tables (d = 32; more while building them, ~3.5 s). The network then sees undistorted local geometry, and its output (normal flow
in undistorted px/s) is mapped back to the sensor grid by :func:`undistorted_to_sensor_flow`.

Features (``encode_targets``): float32 ``(T, 2 d + 1)``: real parts, imaginary parts of ``G_i``
rescaled to norm ``sqrt(d)`` (as VecKM does), then ``log(1 + n_i)`` with ``n_i`` the number of
events in the window (the rescaling discards the count, which tells dense texture from a lone
event). With ``pyramid_levels`` L > 1 the features of the L levels follow one another
(``(T, L (2 d + 1))``, see :class:`EncodingConfig`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from functools import lru_cache
from typing import TYPE_CHECKING, Sequence

import numpy as np

from evseg.errors import ConfigError, EventDataError

if TYPE_CHECKING:  # pragma: no cover
    from evseg.calibration import Calibration

# Split of a microsecond offset into high and low parts for the exact two-table time phase.
_LO_BITS = 10
_LO_SIZE = 1 << _LO_BITS
# Width (px) of the column blocks of the grid pass that threads share.
_BLOCK_COLUMNS = 96
# Longest time span of a slice the encoder takes (us, ~17.9 min): the kernels keep times since
# the slice's start as int32 (see _kernels.pixel_lists). Window plus context must fit in it.
MAX_SLICE_SPAN_US = (1 << 30) - 1


@dataclass(frozen=True)
class EncodingConfig:
    """Constants of the VecKM-style encoding (stored with every exported model).

    Attributes:
        d: number of complex features per pyramid level (the head sees ``2 d + 1`` real inputs
            per level).
        window_px: half-width ``k`` of the square neighbourhood window, px (window ``2k+1``).
        alpha: standard deviation of the random matrix entries (kernel sharpness: the
            encoding's spatial resolution is about ``xy_scale_px / alpha`` px and its temporal
            resolution about ``t_scale_us / alpha`` us).
        xy_scale_px: spatial normalisation, px (coordinates enter as ``x / xy_scale_px``).
        t_scale_us: temporal normalisation, microseconds (times enter as ``t / t_scale_us``).
        seed: seed of ``numpy.random.default_rng`` that draws the random matrix.
        polarity: add the polarity (+1/-1) as a fourth coordinate (a fourth row of ``A``), so
            that the encoding tells same-polarity from opposite-polarity neighbours (VecKM
            itself ignores polarity). Costs nothing at run time. Off by default so that
            configs and checkpoints written before this field existed keep their meaning;
            recommended on for new models (see below).
        t_octaves: spread of temporal resolutions: the time entry of feature j is multiplied
            by ``2 ** (o_j * t_octaves)`` with ``o_j`` uniform in [0, 1] (drawn from a second
            stream of the seed, so 0 leaves the matrix exactly as before). With a 10 ms time
            scale and alpha 2 the temporal resolution is ~5 ms, coarse for an edge crossing
            a pixel in 2-3 ms (a 400 px/s ball): 2 octaves reach down to ~1.3 ms while half the
            features keep the coarse scales that slow edges need. Negative values spread
            towards coarser resolutions instead (for long contexts and slow edges).
        pyramid_levels: number of spatial scales. Level ``l`` encodes the events binned into
            ``2^l x 2^l`` pixel cells with the same window and scale counted in cells: a window
            ``2^l`` times wider (``(2k+1) 2^l`` px) at ``2^l`` times coarser resolution, with a
            random matrix of its own. The features of all levels are concatenated (``F =
            levels (2 d + 1)``). A coarse level sees the edge's surroundings (is the edge part
            of a longer line, which way does the structure around it move) that a 7x7 window
            misses. Each level costs about as much as level 0 (every event's phase is summed
            again; the smaller grid saves little): 1.75x the shipped model's time per flow
            with two levels. 1 (the default) is the plain single-scale encoding.

    Defaults: chosen on simulated scenes (evimo_like, eed_like, ego_only; 20 ms slices, cell
    targets, same short training each): a 7x7 window with alpha 2 and 10 ms time scale gave a
    median angular error of 25 deg against 29 deg for 9x9 and 39-48 deg for 17x17 windows
    (alpha 2-4); d = 16 instead of 32 cost 7 deg; ``polarity=True`` gained 2 deg (22.5 vs
    24.4) and 2 points of sign-correct rate. Textured scenes favour small windows: a large
    window mixes edges of different orientation.
    """

    d: int = 32
    window_px: int = 3
    alpha: float = 2.0
    xy_scale_px: float = 3.0
    t_scale_us: float = 10000.0
    seed: int = 0
    polarity: bool = False
    t_octaves: float = 0.0
    pyramid_levels: int = 1

    def __post_init__(self) -> None:
        for name in ("d", "window_px", "seed", "pyramid_levels"):
            v = getattr(self, name)
            if int(v) != v or (v < 0 if name == "seed" else v < 1):
                raise ConfigError(f"EncodingConfig: field '{name}' must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        for name in ("alpha", "xy_scale_px", "t_scale_us"):
            v = float(getattr(self, name))
            if not np.isfinite(v) or v <= 0:
                raise ConfigError(f"EncodingConfig: field '{name}' must be a positive number, got {v!r}")
            object.__setattr__(self, name, v)
        if not isinstance(self.polarity, (bool, np.bool_)):
            raise ConfigError(f"EncodingConfig: field 'polarity' must be true or false, got {self.polarity!r}")
        object.__setattr__(self, "polarity", bool(self.polarity))
        t_oct = float(self.t_octaves)
        if not np.isfinite(t_oct) or not -8 <= t_oct <= 8:
            raise ConfigError(f"EncodingConfig: field 't_octaves' must be in [-8, 8], got {self.t_octaves!r}")
        object.__setattr__(self, "t_octaves", t_oct)
        if self.pyramid_levels > 6:
            raise ConfigError(f"EncodingConfig: field 'pyramid_levels' must be in [1, 6], got {self.pyramid_levels!r}")

    @property
    def n_coords(self) -> int:
        """Rows of the random matrix: x, y, t (and polarity)."""
        return 4 if self.polarity else 3

    @property
    def n_features(self) -> int:
        """Width ``F = levels (2 d + 1)`` of :func:`encode_targets`'s output."""
        return self.pyramid_levels * (2 * self.d + 1)

    @property
    def matrix_shape(self) -> tuple[int, int]:
        """Shape of :func:`encoding_matrix`: ``(n_coords, levels d)``, one block of ``d``
        columns per pyramid level."""
        return (self.n_coords, self.pyramid_levels * self.d)

    def level(self) -> "EncodingConfig":
        """The single-scale config that encodes one pyramid level (its own cells as pixels)."""
        return replace(self, pyramid_levels=1)

    @property
    def flow_unit_px_s(self) -> float:
        """px/s of one head output unit: ``xy_scale_px`` px per ``t_scale_us`` us."""
        return self.xy_scale_px / (self.t_scale_us * 1e-6)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: dict) -> "EncodingConfig":
        """Build from a dict (YAML, checkpoint hyper-parameters, ONNX metadata); unknown keys
        raise :class:`ConfigError`."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(doc) - known)
        if unknown:
            raise ConfigError(f"EncodingConfig: unknown field(s) {unknown}; known: {sorted(known)}")
        return cls(**doc)


def encoding_matrix(cfg: EncodingConfig) -> np.ndarray:
    """The fixed random matrix ``A``: float64 ``(3, d)``, rows (x, y, t), entries N(0,1)*alpha;
    ``(4, d)`` with a polarity row when ``cfg.polarity`` (the first three rows are the same);
    the time row scaled per feature by ``2 ** (o_j * t_octaves)`` (see :class:`EncodingConfig`).
    With ``pyramid_levels`` L > 1: ``(3 or 4, L d)``, columns ``l d : (l + 1) d`` for level
    ``l``; level 0's block is the single-scale matrix, the others are drawn from streams
    ``[seed, 2, l]`` (and ``[seed, 3, l]`` for their octaves)."""
    blocks = []
    for level in range(cfg.pyramid_levels):
        stream = cfg.seed if level == 0 else [cfg.seed, 2, level]
        A = np.random.default_rng(stream).standard_normal((cfg.n_coords, cfg.d)) * cfg.alpha
        if cfg.t_octaves > 0:
            octave = np.random.default_rng([cfg.seed, 1] if level == 0 else [cfg.seed, 3, level]).uniform(0.0, 1.0, cfg.d)
            A[2] *= 2.0 ** (octave * cfg.t_octaves)
        blocks.append(A)
    return np.concatenate(blocks, axis=1)


@lru_cache(maxsize=8)
def _spatial_phase_raw(cfg: EncodingConfig, width: int, height: int) -> np.ndarray:
    """``exp(i (a_x x + a_y y) / xy_scale_px)`` per raw pixel: complex64 ``(H, W, d)``."""
    A = encoding_matrix(cfg.level())
    px = np.exp(1j * np.outer(np.arange(width), A[0]) / cfg.xy_scale_px)
    py = np.exp(1j * np.outer(np.arange(height), A[1]) / cfg.xy_scale_px)
    return (py[:, None, :] * px[None, :, :]).astype(np.complex64)


def spatial_phase(
    cfg: EncodingConfig,
    sensor_size: tuple[int, int],
    calibration: "Calibration | None" = None,
    matrix: np.ndarray | None = None,
) -> np.ndarray:
    """Per-pixel spatial phase ``exp(i (a_x x + a_y y) / xy_scale_px)``: complex64 ``(H, W, d)``.

    ``(x, y)`` are raw pixels, or the pixel's undistorted coordinates (px) with a calibration.
    One pyramid level: ``matrix`` is a ``(3 or 4, d)`` block (default: level 0's); the
    other levels' tables come from :func:`pyramid_phases`.
    The raw table is cached per (config, sensor size); cache the calibrated one yourself
    (:class:`~evseg.veckm_flow.inference.OnnxNormalFlow` does).
    """
    width, height = int(sensor_size[0]), int(sensor_size[1])
    if calibration is None and matrix is None:
        return _spatial_phase_raw(cfg, width, height)
    A = encoding_matrix(cfg.level()) if matrix is None else _check_matrix(matrix, cfg.level())
    if calibration is None:
        yu, xu = np.mgrid[0:height, 0:width].astype(np.float64)
    else:
        _check_calibration(calibration, sensor_size)
        xu, yu = calibration.undistortion_map(normalized=False)
    return _phase_table(xu, yu, A, cfg.xy_scale_px)


def _phase_table(xu: np.ndarray, yu: np.ndarray, A: np.ndarray, xy_scale_px: float) -> np.ndarray:
    """``exp(i (a_x xu + a_y yu) / xy_scale_px)`` per grid cell: complex64 ``(H, W, d)``."""
    phase = (xu.astype(np.float64)[..., None] * A[0] + yu.astype(np.float64)[..., None] * A[1])
    return np.exp(1j * phase / xy_scale_px).astype(np.complex64)


def level_sensor_size(sensor_size: tuple[int, int], level: int) -> tuple[int, int]:
    """``(width, height)`` in cells of pyramid level ``level`` (``2^level`` px cells, the
    last row and column of cells possibly partial)."""
    f = 1 << int(level)
    return (-(-int(sensor_size[0]) // f), -(-int(sensor_size[1]) // f))


def _cell_positions(calibration: "Calibration", level: int) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted position of each cell of pyramid level ``level``, in cells: the mean
    undistorted position (px) of its pixels divided by the cell size (border cells repeat
    the edge pixels)."""
    xu, yu = calibration.undistortion_map(normalized=False)
    if level == 0:
        return xu, yu
    f = 1 << level
    wc, hc = level_sensor_size(calibration.sensor_size, level)
    out = []
    for m in (xu, yu):
        m = np.pad(m.astype(np.float64), ((0, hc * f - m.shape[0]), (0, wc * f - m.shape[1])), mode="edge")
        out.append(m.reshape(hc, f, wc, f).mean(axis=(1, 3)) / f)
    return out[0], out[1]


@dataclass(frozen=True, eq=False)
class SpatialPhase:
    """Per-pixel spatial phase in factored, planar float32 form (what the kernels read).

    The phase of pixel ``(x, y)`` is ``rows[y, x or 0] * cols[x, 0]`` (complex product; index
    ``[..., 0, :]`` real, ``[..., 1, :]`` imaginary parts):

    * separable (raw pixels): ``rows`` ``(H, 1, 2, d)`` = ``exp(i a_y y / s)``, ``cols``
      ``(W, 1, 2, d)`` = ``exp(i a_x x / s)``;
    * full (undistorted positions, or a user-supplied table): ``rows`` ``(H, W, 2, d)`` holds
      every pixel's phase and ``cols`` is all ones.
    """

    rows: np.ndarray
    cols: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(H, W, d)``, the shape of the equivalent :func:`spatial_phase` table."""
        return (self.rows.shape[0], self.cols.shape[0], self.rows.shape[3])


def spatial_phase_factors(
    cfg: EncodingConfig,
    sensor_size: tuple[int, int],
    calibration: "Calibration | None" = None,
    matrix: np.ndarray | None = None,
) -> SpatialPhase:
    """:func:`spatial_phase` as :class:`SpatialPhase`: separable (two small tables) for raw
    pixels, a full planar table with a calibration. Raw-pixel factors are cached per
    (config, sensor size, matrix)."""
    width, height = int(sensor_size[0]), int(sensor_size[1])
    if calibration is None:
        key = None if matrix is None else _check_matrix(matrix, cfg.level()).tobytes()
        return _separable_phase(cfg, width, height, key)
    return _full_phase(spatial_phase(cfg, sensor_size, calibration, matrix))


def _full_phase(table: np.ndarray) -> SpatialPhase:
    """A complex ``(H, W, d)`` phase table as :class:`SpatialPhase` (``cols`` all ones)."""
    ones = np.zeros((table.shape[1], 1, 2, table.shape[2]), np.float32)
    ones[:, :, 0, :] = 1.0
    return SpatialPhase(rows=_planar(table), cols=ones)


@lru_cache(maxsize=8)
def _separable_phase(cfg: EncodingConfig, width: int, height: int, matrix_bytes: bytes | None) -> SpatialPhase:
    A = encoding_matrix(cfg.level()) if matrix_bytes is None else np.frombuffer(matrix_bytes).reshape(cfg.n_coords, cfg.d)
    px = np.exp(1j * np.outer(np.arange(width), A[0]) / cfg.xy_scale_px)
    py = np.exp(1j * np.outer(np.arange(height), A[1]) / cfg.xy_scale_px)
    return SpatialPhase(rows=_planar(py[:, None, :]), cols=_planar(px[:, None, :]))


def pyramid_phases(
    cfg: EncodingConfig,
    sensor_size: tuple[int, int],
    calibration: "Calibration | None" = None,
    matrix: np.ndarray | None = None,
) -> tuple[SpatialPhase, ...]:
    """:func:`spatial_phase_factors` of every pyramid level, level 0 first.

    Level ``l``'s table is over its ``2^l`` px cells (:func:`level_sensor_size`) with its block
    of the matrix; with a calibration a cell's position is the mean undistorted position of
    its pixels, in cells. ``matrix``: the whole ``(3 or 4, levels d)`` matrix (default
    :func:`encoding_matrix`).
    """
    A = encoding_matrix(cfg) if matrix is None else _check_matrix(matrix, cfg)
    if calibration is not None:
        _check_calibration(calibration, sensor_size)
    single = cfg.level()
    out = []
    for level in range(cfg.pyramid_levels):
        block = np.ascontiguousarray(A[:, level * cfg.d:(level + 1) * cfg.d])
        size = level_sensor_size(sensor_size, level)
        if calibration is None:
            out.append(spatial_phase_factors(single, size, None, block))
        else:
            xu, yu = _cell_positions(calibration, level)
            out.append(_full_phase(_phase_table(xu, yu, block, cfg.xy_scale_px)))
    return tuple(out)


def _check_calibration(calibration: "Calibration", sensor_size: tuple[int, int]) -> None:
    if tuple(calibration.sensor_size) != (int(sensor_size[0]), int(sensor_size[1])):
        raise EventDataError(
            f"calibration is for a {calibration.sensor_size[0]}x{calibration.sensor_size[1]} sensor, "
            f"the events are from a {sensor_size[0]}x{sensor_size[1]} sensor"
        )


def _check_matrix(matrix: np.ndarray, cfg: EncodingConfig) -> np.ndarray:
    """The matrix of ``cfg`` as float64, of shape ``cfg.matrix_shape`` (pass ``cfg.level()``
    for one pyramid level's ``(3 or 4, d)`` block)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != cfg.matrix_shape:
        raise ConfigError(f"encoding matrix has shape {matrix.shape}, expected {cfg.matrix_shape}")
    return matrix


def time_phase_tables(
    cfg: EncodingConfig, span_us: int, matrix: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Exact factorisation of ``exp(i a_t dt / t_scale_us)`` for integer ``0 <= dt <= span_us``.

    Returns complex64 tables ``hi`` ``(span_us >> 10) + 1, d)`` and ``lo`` ``(P, 1024, d)`` with
    ``exp(i a_t dt / t_scale_us) = hi[dt >> 10] * lo[0, dt & 1023]``. With ``cfg.polarity``,
    ``P = 2`` and ``lo[q]`` also carries the polarity phase ``exp(i a_p p)`` with
    ``p = -1`` for ``q = 0`` and ``+1`` for ``q = 1``; otherwise ``P = 1``. One pyramid level:
    ``matrix`` is a ``(3 or 4, d)`` block (default: level 0's).
    """
    A = encoding_matrix(cfg.level()) if matrix is None else _check_matrix(matrix, cfg.level())
    a_t = A[2] / cfg.t_scale_us
    n_hi = (int(span_us) >> _LO_BITS) + 1
    hi = np.exp(1j * np.outer(np.arange(n_hi, dtype=np.float64) * _LO_SIZE, a_t))
    lo = np.exp(1j * np.outer(np.arange(_LO_SIZE, dtype=np.float64), a_t))
    if cfg.polarity:
        lo = np.stack([lo * np.exp(-1j * A[3]), lo * np.exp(1j * A[3])])
    else:
        lo = lo[None]
    return hi.astype(np.complex64), lo.astype(np.complex64)


def _validate_targets(targets: np.ndarray, n_events: int) -> np.ndarray:
    targets = np.asarray(targets)
    if targets.ndim != 1 or not (np.issubdtype(targets.dtype, np.integer) or len(targets) == 0):
        raise EventDataError(f"targets must be a 1-D integer array of event positions, got {targets.dtype} {targets.shape}")
    targets = targets.astype(np.int64, copy=False)
    if len(targets) and (targets.min() < 0 or targets.max() >= n_events):
        bad = int(targets[(targets < 0) | (targets >= n_events)][0])
        raise EventDataError(f"targets: position {bad} is outside the {n_events} events of the slice")
    return targets


def encode_targets(
    events: np.ndarray,
    targets: np.ndarray,
    sensor_size: tuple[int, int],
    cfg: EncodingConfig,
    calibration: "Calibration | None" = None,
    phase_xy: "np.ndarray | SpatialPhase | tuple | None" = None,
    matrix: np.ndarray | None = None,
) -> np.ndarray:
    """VecKM-style features of the target events of one slice.

    Args:
        events: the slice, :data:`~evseg.events.EVENT_DTYPE` ``(N,)``, sorted by ``t`` (us);
            every event is a potential neighbour.
        targets: int ``(T,)`` positions in ``events`` of the events to encode.
        sensor_size: ``(width, height)`` px.
        cfg: encoding constants.
        calibration: optional; positions then are undistorted pixel coordinates (module doc).
        phase_xy: optional precomputed spatial phases (saves their cost): :func:`pyramid_phases`
            (one per level), or for a single-level encoding one :func:`spatial_phase`
            ``(H, W, d)`` or :func:`spatial_phase_factors` (the factors are cheaper).
        matrix: optional ``cfg.matrix_shape`` random matrix overriding :func:`encoding_matrix`
            (an ONNX model stores its own, so it does not depend on numpy's generator staying
            the same).

    Returns:
        float32 ``(T, levels (2 d + 1))``: per pyramid level ``[Re G, Im G]`` rescaled to norm
        ``sqrt(d)``, ``log(1 + n)``.
    """
    A = encoding_matrix(cfg) if matrix is None else _check_matrix(matrix, cfg)
    return _encode_looks(events, targets, sensor_size, cfg, (A,), calibration, (phase_xy,))[0]


def encode_targets_looks(
    events: np.ndarray,
    targets: np.ndarray,
    sensor_size: tuple[int, int],
    cfg: EncodingConfig,
    matrices: "Sequence[np.ndarray]",
    calibration: "Calibration | None" = None,
    phases: "Sequence[tuple[SpatialPhase, ...] | None] | None" = None,
) -> np.ndarray:
    """:func:`encode_targets` of the same targets with several random matrices at once, such
    as the mirror images of :mod:`evseg.veckm_flow.mirrors`.

    The matrices must share every row but x and y (time and polarity): a pixel's sum over its
    events, most of the encoding's work, is then the same in every look and computed once;
    only the spatial phases differ. The result equals stacking :func:`encode_targets` with
    each matrix, bit for bit.

    Args:
        matrices: L ``cfg.matrix_shape`` matrices.
        phases: optional, per matrix, its :func:`pyramid_phases` (saves their cost).
        Other arguments: as :func:`encode_targets`.

    Returns:
        float32 ``(L, T, levels (2 d + 1))``, look ``l`` encoded with ``matrices[l]``.

    Example:
        >>> from evseg.events import make_events
        >>> from evseg.veckm_flow.mirrors import mirrored_encoding_matrix
        >>> ev = make_events([1, 2, 2], [1, 1, 2], [0, 500, 900], [1, -1, 1])
        >>> cfg = EncodingConfig(d=4, window_px=1, polarity=True)
        >>> A = encoding_matrix(cfg)
        >>> looks = encode_targets_looks(ev, np.array([2]), (4, 4), cfg, [A, mirrored_encoding_matrix(A, 5)])
        >>> looks.shape
        (2, 1, 9)
        >>> bool(np.array_equal(looks[1], encode_targets(ev, np.array([2]), (4, 4), cfg,
        ...                                              matrix=mirrored_encoding_matrix(A, 5))))
        True
    """
    mats = tuple(_check_matrix(m, cfg) for m in matrices)
    if not mats:
        raise ConfigError("encode_targets_looks needs at least one matrix")
    if any(not np.array_equal(m[2:], mats[0][2:]) for m in mats[1:]):
        raise ConfigError("the looks' encoding matrices must share their time (and polarity) rows; "
                          "only rows x and y may differ")
    if phases is not None and len(phases) != len(mats):
        raise EventDataError(f"phases holds {len(phases)} look(s) for {len(mats)} matrices")
    return _encode_looks(events, targets, sensor_size, cfg, mats, calibration,
                         tuple(phases) if phases is not None else (None,) * len(mats))


def _encode_looks(events, targets, sensor_size, cfg: EncodingConfig, matrices: tuple, calibration,
                  phase_xy: tuple) -> np.ndarray:
    """Features ``(L, T, F)`` of the targets under each (checked) matrix; ``phase_xy`` per
    matrix as :func:`encode_targets` takes it (or None)."""
    from evseg.veckm_flow import _kernels

    targets = _validate_targets(targets, len(events))
    width, height = int(sensor_size[0]), int(sensor_size[1])
    phases = [_level_phases(ph, cfg, sensor_size, calibration, A) for ph, A in zip(phase_xy, matrices)]
    if len(targets) == 0:
        return np.zeros((len(matrices), 0, cfg.n_features), np.float32)
    x, y, t, p = events["x"], events["y"], events["t"], events["p"]  # views, read in place
    max_x, max_y, t0, t1 = _kernels.slice_extent(x, y, t)
    if max_x >= width or max_y >= height:
        raise EventDataError(f"events lie outside the {width}x{height} sensor")
    if int(t1) - int(t0) > MAX_SLICE_SPAN_US:
        raise EventDataError(
            f"the slice spans {(int(t1) - int(t0)) / 1e6:.0f} s; the encoder takes slices of at most "
            f"{MAX_SLICE_SPAN_US / 1e6:.0f} s (it encodes a neighbourhood of milliseconds)")
    single = cfg.level()
    out = []
    for level in range(cfg.pyramid_levels):
        block = matrices[0][:, level * cfg.d:(level + 1) * cfg.d]  # its time rows are every look's
        # A coarse level is the same encoding of the events binned into 2^level px cells.
        xl, yl = (x, y) if level == 0 else (x >> level, y >> level)
        w, h = level_sensor_size(sensor_size, level)
        out.append(_encode_level(xl, yl, t, p, t0, int(t1) - int(t0), targets, (w, h), single,
                                 tuple(ph[level] for ph in phases), block))
    return out[0] if len(out) == 1 else np.concatenate(out, axis=2)


def _level_phases(phase_xy, cfg: EncodingConfig, sensor_size, calibration, matrix) -> tuple[SpatialPhase, ...]:
    """The spatial phases of every level: the caller's (checked) or :func:`pyramid_phases`."""
    if phase_xy is None:
        return pyramid_phases(cfg, sensor_size, calibration, matrix)
    given = tuple(phase_xy) if isinstance(phase_xy, (tuple, list)) else (phase_xy,)
    if len(given) != cfg.pyramid_levels:
        raise EventDataError(f"phase_xy holds {len(given)} level(s), the encoding has {cfg.pyramid_levels} "
                             "(pass pyramid_phases(...))")
    out = []
    for level, ph in enumerate(given):
        w, h = level_sensor_size(sensor_size, level)
        if ph.shape != (h, w, cfg.d):
            raise EventDataError(f"phase_xy has shape {ph.shape}, expected {(h, w, cfg.d)}"
                                 + (f" at pyramid level {level}" if cfg.pyramid_levels > 1 else ""))
        out.append(ph if isinstance(ph, SpatialPhase) else _planar_phase(ph))
    return tuple(out)


def _encode_level(x, y, t, p, t0, span_us: int, targets: np.ndarray, size: tuple[int, int],
                  cfg: EncodingConfig, phases: tuple[SpatialPhase, ...], matrix: np.ndarray) -> np.ndarray:
    """Features ``(L, T, 2 d + 1)`` of one pyramid level in L looks: ``x, y`` in the level's
    cells, ``size`` its grid, ``cfg`` single-level, ``phases`` each look's spatial phase,
    ``matrix`` a ``(3 or 4, d)`` block with the looks' common time rows."""
    from evseg.veckm_flow import _kernels

    width, height = size
    # Times enter as integer us since the slice's first event (t0): exact.
    hi, lo = _planar_time_tables(cfg, span_us, matrix)
    # Column blocks of a fixed width, not one per thread: each block restarts its sliding
    # float32 sums, so a thread-dependent split would make the features (and every label
    # downstream) depend on the thread count. Each block re-reads 2 k + 1 columns per row
    # (7 % more pixel evaluations for the shipped 3 px window).
    nblk = max(1, -(-width // _BLOCK_COLUMNS))
    start, sdt, spol, row_used = _kernels.pixel_lists(x, y, t, p, t0, cfg.polarity, width, height)
    # Targets grouped by the column block that owns them, in row order within a block (the
    # order in which the pass completes their windows); ``order`` maps back.
    order, tx, ty, tdt, tpol, blk_start = _kernels.order_targets(
        targets, x, y, t, p, t0, cfg.polarity, width, height, nblk)
    # The kernel indexes the looks' tables as one tuple, which must be of one array type
    # (a caller's SpatialPhase may hold strided or float64 arrays; no copy when it does not).
    rows = tuple(np.ascontiguousarray(ph.rows, np.float32) for ph in phases)
    cols = tuple(np.ascontiguousarray(ph.cols, np.float32) for ph in phases)
    return _kernels.window_features(
        start, sdt, spol, hi, lo, _LO_BITS, row_used, rows, cols, cfg.window_px, nblk,
        tx, ty, tdt, tpol, order, blk_start,
    )


_TIME_TABLES: dict = {}
_PLANAR_PHASE: dict = {}


def _planar(a: np.ndarray) -> np.ndarray:
    """complex (..., d) -> float32 (..., 2, d): real and imaginary planes (see _kernels)."""
    return np.ascontiguousarray(np.stack([a.real, a.imag], axis=-2), dtype=np.float32)



def _planar_time_tables(cfg: EncodingConfig, span_us: int, matrix: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Planar :func:`time_phase_tables`, cached per (config, matrix) and grown in steps of
    ~65 ms of span (building them costs ~0.5 ms, a twentieth of a slice's encoding)."""
    key = (cfg, None if matrix is None else np.asarray(matrix, np.float64).tobytes())
    hit = _TIME_TABLES.get(key)
    if hit is None or len(hit[0]) <= (span_us >> _LO_BITS):
        span = ((span_us >> 16) + 1) << 16
        if len(_TIME_TABLES) > 4:
            _TIME_TABLES.clear()
        hit = _TIME_TABLES[key] = tuple(_planar(a) for a in time_phase_tables(cfg, span, matrix))
    return hit


def _planar_phase(phase_xy: np.ndarray) -> SpatialPhase:
    """A full :func:`spatial_phase` table as :class:`SpatialPhase`, cached by identity (callers
    reuse their table, and converting one costs about as much as encoding a slice)."""
    key = id(phase_xy)
    hit = _PLANAR_PHASE.get(key)
    if hit is None or hit[0] is not phase_xy:
        _PLANAR_PHASE.clear()
        hit = _PLANAR_PHASE[key] = (phase_xy, _full_phase(phase_xy))
    return hit[1]


def encode_targets_reference(
    events: np.ndarray,
    targets: np.ndarray,
    sensor_size: tuple[int, int],
    cfg: EncodingConfig,
    calibration: "Calibration | None" = None,
) -> np.ndarray:
    """Direct O(T x window) evaluation of the same features in float64 (slow; for tests).

    Same arguments and output as :func:`encode_targets`.
    """
    targets = _validate_targets(targets, len(events))
    A_all = encoding_matrix(cfg)
    k = cfg.window_px
    t = (events["t"] - events["t"].min()).astype(np.float64)
    out = np.zeros((len(targets), cfg.n_features), np.float64)
    width = 2 * cfg.d + 1
    for level in range(cfg.pyramid_levels):
        A = A_all[:, level * cfg.d:(level + 1) * cfg.d]
        x = events["x"].astype(np.int64) >> level
        y = events["y"].astype(np.int64) >> level
        if calibration is not None:
            xu, yu = _cell_positions(calibration, level)
            px, py = xu[y, x].astype(np.float64), yu[y, x].astype(np.float64)
        else:
            px, py = x.astype(np.float64), y.astype(np.float64)
        cols = [px / cfg.xy_scale_px, py / cfg.xy_scale_px, t / cfg.t_scale_us]
        if cfg.polarity:
            cols.append(np.where(events["p"] > 0, 1.0, -1.0))
        P = np.stack(cols, axis=1)
        o = level * width
        for r, i in enumerate(targets):
            nb = (np.abs(x - x[i]) <= k) & (np.abs(y - y[i]) <= k)
            G = np.exp(1j * (P[nb] - P[i]) @ A).sum(axis=0)
            G = G * np.sqrt(cfg.d) / max(np.linalg.norm(G), 1e-12)
            out[r, o:o + cfg.d], out[r, o + cfg.d:o + 2 * cfg.d] = G.real, G.imag
            out[r, o + width - 1] = np.log1p(nb.sum())
    return out.astype(np.float32)


def undistorted_to_sensor_flow(
    nx: np.ndarray, ny: np.ndarray, x: np.ndarray, y: np.ndarray, calibration: "Calibration"
) -> tuple[np.ndarray, np.ndarray]:
    """Map normal flow in undistorted px/s at raw pixels ``(x, y)`` to sensor-grid px/s.

    Normal flow is ``n = g / |g|^2`` with ``g`` the time-surface gradient (s/px). ``g`` is a
    covector: with ``M = d(undistorted)/d(raw)`` (finite differences of the undistortion map),
    ``g_raw = M^T g_und``. Exact for the local linearisation of the distortion.

    Args:
        nx, ny: float ``(T,)`` normal flow, undistorted px/s.
        x, y: int ``(T,)`` raw pixel column, row of each flow.

    Returns:
        ``(nx, ny)`` float32 ``(T,)`` in px/s of the raw sensor grid.
    """
    xu, yu = calibration.undistortion_map(normalized=False)
    # np.gradient: axis 0 = rows (y), axis 1 = columns (x); one-sided at the border.
    dxu_dy, dxu_dx = np.gradient(xu.astype(np.float64))
    dyu_dy, dyu_dx = np.gradient(yu.astype(np.float64))
    x = np.asarray(x, np.int64)
    y = np.asarray(y, np.int64)
    nx = np.asarray(nx, np.float64)
    ny = np.asarray(ny, np.float64)
    m2 = nx * nx + ny * ny
    with np.errstate(divide="ignore", invalid="ignore"):
        gx, gy = nx / m2, ny / m2
        grx = dxu_dx[y, x] * gx + dyu_dx[y, x] * gy
        gry = dxu_dy[y, x] * gx + dyu_dy[y, x] * gy
        g2 = grx * grx + gry * gry
        return (grx / g2).astype(np.float32), (gry / g2).astype(np.float32)
