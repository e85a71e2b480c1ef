"""Normal flow with onnxruntime on CPU: encoder rebuilt from the ONNX file, no torch.

The ONNX file (written by :func:`evseg.export.export_onnx`) holds the head, one input
``features`` float32 ``(T, levels (2 d + 1))`` (T dynamic) and one output ``head_out`` float32 ``(T, 3)``
(see :mod:`evseg.veckm_flow.result` for its units), and in its metadata (``metadata_props``):

- ``evseg.format``: ``"evseg-normal-flow/1"``
- ``evseg.encoding``: JSON of :class:`~evseg.veckm_flow.EncodingConfig`
- ``evseg.matrix``: JSON ``(3, levels d)`` list of the random matrix (rows x, y, t; a fourth
  row, polarity, when the encoding uses it; one block of ``d`` columns per pyramid level)
- ``evseg.flow_unit_px_s``: px/s of one head output unit (a check, derived from the encoding)
- ``evseg.head``: JSON of the head's constructor arguments (informative)
"""

from __future__ import annotations

import copy
import json
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from evseg.errors import ModelError
from evseg.events import validate_events
from evseg.veckm_flow.encoding import (
    EncodingConfig,
    SpatialPhase,
    _validate_targets,
    encode_targets_looks,
    pyramid_phases,
    undistorted_to_sensor_flow,
)
from evseg.veckm_flow.fast_edges import FastEdges, combine, gate_weights, stretched_start
from evseg.veckm_flow.mirrors import combine_looks, mirror_looks, mirrored_encoding_matrix, unmirror_flow
from evseg.veckm_flow.result import NormalFlow, head_output_to_flow
from evseg.veckm_flow.slow_edges import SlowEdges, combine_directions, compressed_start, gate

if TYPE_CHECKING:  # pragma: no cover
    from evseg.calibration import Calibration

FORMAT = "evseg-normal-flow/1"
DEFAULT_MODEL = Path(__file__).resolve().parent / "weights" / "normal_flow.onnx"
PREDICT_ROWS = 16_384
"""Most rows per onnxruntime call: 80,000 rows (8 mirror looks at 10,000 targets) took 33 ms in
one call and 24-25 ms in runs of 4,096-16,384 (32,768: 31 ms; the hidden layers' activations
then outgrow the core's cache), with the same outputs."""


def read_model_metadata(path: str | Path) -> tuple[EncodingConfig, np.ndarray, dict]:
    """``(cfg, matrix (3 or 4, d) float64, all metadata)`` of an exported model (ModelError if not one)."""
    path = Path(path)
    meta = dict(_session(path, threads=1).get_modelmeta().custom_metadata_map)
    cfg, matrix = _parse_metadata(path, meta)
    return cfg, matrix, meta


def _parse_metadata(path: Path, meta: dict) -> tuple[EncodingConfig, np.ndarray]:
    if meta.get("evseg.format") != FORMAT:
        raise ModelError(f"{path}: metadata 'evseg.format' is {meta.get('evseg.format')!r}, expected {FORMAT!r} (not an evseg normal-flow model?)")
    for key in ("evseg.encoding", "evseg.matrix", "evseg.flow_unit_px_s"):
        if key not in meta:
            raise ModelError(f"{path}: metadata field '{key}' is missing")
    try:
        cfg = EncodingConfig.from_dict(json.loads(meta["evseg.encoding"]))
        matrix = np.asarray(json.loads(meta["evseg.matrix"]), dtype=np.float64)
        unit = float(meta["evseg.flow_unit_px_s"])
    except (ValueError, TypeError) as exc:
        raise ModelError(f"{path}: metadata field is malformed: {exc}") from None
    if matrix.shape != cfg.matrix_shape:
        raise ModelError(f"{path}: metadata 'evseg.matrix' has shape {matrix.shape}, expected {cfg.matrix_shape}")
    if not np.isclose(unit, cfg.flow_unit_px_s, rtol=1e-9):
        raise ModelError(f"{path}: metadata 'evseg.flow_unit_px_s' = {unit} disagrees with the encoding ({cfg.flow_unit_px_s})")
    return cfg, matrix


def _session(path: Path, threads: int | None):
    import onnxruntime as ort

    if not path.is_file():
        raise ModelError(f"{path}: model file not found")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 0 if threads is None else int(threads)  # 0 = onnxruntime's default
    opts.inter_op_num_threads = 1
    # No busy-waiting after a run: the encoder's numba threads run right after on the same cores.
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    try:
        return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for corrupt files
        hint = ""
        if path.suffix.lower() in (".ckpt", ".pt", ".pth"):
            hint = f"; a training checkpoint? export it first: evseg export {path} --out model.onnx"
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise ModelError(f"{path}: onnxruntime cannot load the model ({type(exc).__name__}: {first}){hint}") from None


class OnnxNormalFlow:
    """Learned normal flow: VecKM-style encoding (numpy/numba) + head (onnxruntime, CPU).

    Args:
        model_path: an exported ``.onnx`` (default: the model shipped in
            ``evseg/veckm_flow/weights/normal_flow.onnx``).
        threads: threads of the network (onnxruntime intra-op) and of the encoder (numba),
            None: all cores. On a machine shared with other busy processes, 1 can be faster:
            the encoder's parallel loops wait for their slowest thread.
        fast_edges: the time-stretched second look at targets whose flow is fast
            (:mod:`evseg.veckm_flow.fast_edges`; on by default), None for the head's first
            look alone.
        slow_edges: the time-compressed second look over a longer slice at targets whose flow
            is slow (:mod:`evseg.veckm_flow.slow_edges`); it runs only when a call passes the
            events before the slice (``history``), None never.
        mirrors: how many mirror images of the slice the network looks at, 1, 2, 4 or 8
            (:mod:`evseg.veckm_flow.mirrors`): their flows are averaged; 8 looks cost about 5x
            the time of one (they share the encoding's per-event work). 1 (default): the
            slice as it is.

    Call: ``est(events, sensor_size, targets=None, calibration=None, history=None) -> NormalFlow``.
    """

    def __init__(self, model_path: str | Path | None = None, threads: int | None = None,
                 fast_edges: FastEdges | None = FastEdges(), slow_edges: SlowEdges | None = SlowEdges(),
                 mirrors: int = 1) -> None:
        path = Path(model_path) if model_path is not None else DEFAULT_MODEL
        if model_path is None and not path.is_file():
            raise ModelError(f"{path}: no shipped default model in this build; pass a model_path (evseg export)")
        self.model_path = path
        from evseg.checks import is_int

        if threads is not None and (not is_int(threads) or threads < 1):
            from evseg.errors import ConfigError

            raise ConfigError(f"OnnxNormalFlow: threads must be an integer >= 1 or None (all cores), got {threads!r}")
        self.threads = None if threads is None else int(threads)
        self.session = _session(path, self.threads)
        meta = self.session.get_modelmeta().custom_metadata_map
        self.cfg, self.matrix = _parse_metadata(path, meta)
        self.metadata = dict(meta)
        self._input = self.session.get_inputs()[0].name
        if fast_edges is not None and not isinstance(fast_edges, FastEdges):
            raise ModelError(f"fast_edges must be a FastEdges or None, got {type(fast_edges).__name__}")
        self.fast_edges = fast_edges
        if slow_edges is not None and not isinstance(slow_edges, SlowEdges):
            raise ModelError(f"slow_edges must be a SlowEdges or None, got {type(slow_edges).__name__}")
        self.slow_edges = slow_edges
        self.looks = mirror_looks(mirrors)
        self.mirrors = int(mirrors)
        self._phase_cache: dict = {}
        self.last_timing_s: dict[str, float] = {}

    def with_mirrors(self, mirrors: int) -> "OnnxNormalFlow":
        """This estimator with ``mirrors`` mirror looks instead (1, 2, 4 or 8), sharing its model
        session, second looks and cached phase tables (no second copy of the model)."""
        looks = mirror_looks(mirrors)
        other = copy.copy(self)
        other.looks, other.mirrors, other.last_timing_s = looks, int(mirrors), {}
        return other

    def _phase(self, sensor_size: tuple[int, int], calibration: "Calibration | None",
               matrix: np.ndarray) -> tuple[SpatialPhase, ...]:
        where = (int(sensor_size[0]), int(sensor_size[1]), id(calibration))
        key = (*where, matrix.tobytes())
        if key not in self._phase_cache:
            if any(k[:3] != where for k in self._phase_cache):
                self._phase_cache.clear()  # one sensor / calibration at a time (a table per mirror look)
            # Keep a reference to the calibration so that its id stays unique while cached.
            self._phase_cache[key] = (pyramid_phases(self.cfg, sensor_size, calibration, matrix), calibration)
        return self._phase_cache[key][0]

    def encode(self, events: np.ndarray, sensor_size, targets: np.ndarray, calibration=None,
               cfg: EncodingConfig | None = None, matrix: np.ndarray | None = None) -> np.ndarray:
        """Features float32 ``(T, levels (2 d + 1))`` of the targets (see :func:`encode_targets`);
        ``cfg``: another time scale of the model's encoding (the second looks), default its own;
        ``matrix``: another random matrix (a mirror look's), default the model's."""
        return self.encode_looks(events, sensor_size, targets, calibration, cfg,
                                 (self.matrix if matrix is None else matrix,))[0]

    def encode_looks(self, events: np.ndarray, sensor_size, targets: np.ndarray, calibration=None,
                     cfg: EncodingConfig | None = None, matrices=None) -> np.ndarray:
        """Features float32 ``(L, T, levels (2 d + 1))`` of the targets with each of the
        ``matrices`` (default: the model's alone), which must differ only in their x and y rows
        (mirror looks; :func:`~evseg.veckm_flow.encoding.encode_targets_looks`, which computes
        the work they share once)."""
        import numba

        cfg = self.cfg if cfg is None else cfg
        matrices = (self.matrix,) if matrices is None else tuple(matrices)
        phases = tuple(self._phase(sensor_size, calibration, m) for m in matrices)
        if self.threads is None:
            return encode_targets_looks(events, targets, sensor_size, cfg, matrices, calibration, phases)
        before = numba.get_num_threads()
        numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))
        try:
            return encode_targets_looks(events, targets, sensor_size, cfg, matrices, calibration, phases)
        finally:
            numba.set_num_threads(before)

    def predict(self, feats: np.ndarray) -> np.ndarray:
        """Raw head output float32 ``(T, 3)`` for features ``(T, F)``, in runs of at most
        :data:`PREDICT_ROWS` rows (each row's output does not depend on the others)."""
        if len(feats) == 0:
            return np.zeros((0, 3), np.float32)
        feats = np.ascontiguousarray(feats, dtype=np.float32)
        if len(feats) <= PREDICT_ROWS:
            return self.session.run(None, {self._input: feats})[0]
        return np.concatenate([self.session.run(None, {self._input: feats[i:i + PREDICT_ROWS]})[0]
                               for i in range(0, len(feats), PREDICT_ROWS)])

    def __call__(
        self,
        events: np.ndarray,
        sensor_size: tuple[int, int],
        targets: np.ndarray | None = None,
        calibration: "Calibration | None" = None,
        history: np.ndarray | None = None,
    ) -> NormalFlow:
        """Normal flow (px/s of the sensor grid) of ``targets`` (default: every event) of the
        slice ``events``; every event of the slice is a potential neighbour.

        ``history``: events before the slice (sorted, none later than its first event), seen
        only by the slow-edge look, which spans ``slow_edges.compress`` times the slice's time
        span (:meth:`SlowEdges.history_us` of history is enough; with less it sees less).
        Without it there is no slow-edge look.

        ``last_timing_s`` then holds the seconds spent in ``encode`` and ``network`` (the
        second looks' shares included) and ``fast_edges`` / ``slow_edges`` (their shares alone),
        summed over the mirror looks."""
        validate_events(events, sensor_size, source="normal flow input")
        if history is not None:
            validate_events(history, sensor_size, source="normal flow history")
            if len(history) and len(events) and int(history["t"][-1]) > int(events["t"][0]):
                raise ValueError("history events must come before the slice's events "
                                 f"(last history t {int(history['t'][-1])} us > first slice t {int(events['t'][0])} us)")
        if targets is None:
            targets = np.arange(len(events), dtype=np.int64)
        targets = _validate_targets(targets, len(events))
        timing = {"encode": 0.0, "network": 0.0, "fast_edges": 0.0, "slow_edges": 0.0}
        matrices = tuple(mirrored_encoding_matrix(self.matrix, k) if k else self.matrix for k in self.looks)
        looks = [(*unmirror_flow(nx, ny, k), unc) if k else (nx, ny, unc)
                 for k, (nx, ny, unc) in zip(self.looks, self._looks(events, sensor_size, targets, calibration,
                                                                     history, matrices, timing))]
        nx, ny, unc = looks[0] if len(looks) == 1 else combine_looks(looks)
        self.last_timing_s = timing
        if calibration is not None:
            nx, ny = undistorted_to_sensor_flow(nx, ny, events["x"][targets], events["y"][targets], calibration)
        return NormalFlow(targets, nx, ny, unc)

    def _looks(self, events, sensor_size, targets, calibration, history, matrices, timing):
        """Per encoding matrix (mirror look), ``(nx, ny, uncertainty)`` (px/s, rad; undistorted
        px with a calibration) of the first look and the second looks where their gates open,
        all looks computed together; adds its seconds to ``timing``."""
        first = self._encode_and_predict(events, sensor_size, targets, calibration, self.cfg, matrices, timing)
        if self.fast_edges is not None and len(targets):
            first = self._fast_edges(events, sensor_size, targets, calibration, first, matrices, timing)
        if self.slow_edges is not None and history is not None and len(history) and len(targets):
            first = self._slow_edges(events, history, sensor_size, targets, calibration, first, matrices, timing)
        return first

    def _fast_edges(self, events, sensor_size, targets, calibration, looks, matrices, timing):
        """Each look's ``(nx, ny, uncertainty)`` with the time-stretched second look mixed in
        where its gate opens (:mod:`evseg.veckm_flow.fast_edges`). The stretched slice is the
        last ``1 / stretch`` of the slice for the gated targets in it, and the whole slice for
        those before it (a target must lie in its slice): a rule of each target's own
        position, so that a target's flow never depends on the other targets asked for. The
        looks' targets of one start are computed together, so each look's result is the one
        it gets alone. Adds its seconds to ``timing``."""
        fe = self.fast_edges
        t0 = time.perf_counter()
        speeds = [np.hypot(lk[0], lk[1]) / self.cfg.flow_unit_px_s for lk in looks]
        gated = [np.flatnonzero(v > fe.speed_from) for v in speeds]
        base = stretched_start(events["t"], fe.stretch, fe.min_keep_us)
        jobs: dict[int, dict[int, np.ndarray]] = {}  # slice start -> look -> its gated targets there
        for i, g in enumerate(gated):
            early = targets[g] < base
            for start, sel in ((0, g[early]), (base, g[~early])):
                if len(sel):
                    jobs.setdefault(start, {})[i] = sel
        cfg = replace(self.cfg, t_scale_us=self.cfg.t_scale_us / fe.stretch)
        for start in sorted(jobs):
            group = sorted(jobs[start])
            union = np.unique(np.concatenate([jobs[start][i] for i in group]))
            seconds = self._encode_and_predict(events[start:], sensor_size, targets[union] - start,
                                               calibration, cfg, tuple(matrices[i] for i in group), timing)
            for i, second in zip(group, seconds):
                g = jobs[start][i]
                at = np.searchsorted(union, g)
                mixed = combine(tuple(a[g] for a in looks[i]), tuple(a[at] for a in second),
                                gate_weights(speeds[i][g], fe.speed_from, fe.speed_full))
                for a, b in zip(looks[i], mixed):  # the looks' arrays are this call's own
                    a[g] = b
        timing["fast_edges"] += time.perf_counter() - t0
        return looks

    def _slow_edges(self, events, history, sensor_size, targets, calibration, looks, matrices, timing):
        """Each look's ``(nx, ny, uncertainty)`` so far with the direction of the
        time-compressed look over the longer slice (``history`` + ``events``) mixed in where
        its gate opens (:mod:`evseg.veckm_flow.slow_edges`); computed together for every look
        (the longer slice does not depend on the gate), at the targets any look gates. Adds
        its seconds to ``timing``."""
        se = self.slow_edges
        t0 = time.perf_counter()
        weights = [gate(np.hypot(lk[0], lk[1]) / self.cfg.flow_unit_px_s, se.speed_full, se.speed_to) for lk in looks]
        gated = [np.flatnonzero(w > 0) for w in weights]
        union = np.unique(np.concatenate(gated))
        if len(union):
            cfg = replace(self.cfg, t_scale_us=self.cfg.t_scale_us * se.compress)
            older = history[compressed_start(history["t"], events["t"], se.compress):]
            slice_ = np.concatenate([older, events]) if len(older) else events
            seconds = self._encode_and_predict(slice_, sensor_size, targets[union] + len(older), calibration,
                                               cfg, matrices, timing)
            for lk, w, g, second in zip(looks, weights, gated, seconds):
                at = np.searchsorted(union, g)
                old, new = tuple(a[g] for a in lk), tuple(a[at] for a in second)
                # Direction only: the speed stays the first look's (slow_edges docstring).
                mixed = combine_directions(old, new, w[g])
                if se.uncertainty == "combined":
                    mixed = (*mixed, combine(old, new, w[g])[2])
                for a, b in zip(lk, mixed):  # the looks' arrays are this call's own
                    a[g] = b
        timing["slow_edges"] += time.perf_counter() - t0
        return looks

    def _encode_and_predict(self, events, sensor_size, targets, calibration, cfg: EncodingConfig, matrices, timing):
        """Per matrix, ``(nx, ny, uncertainty)`` (px/s, rad) of ``targets`` with the encoding
        ``cfg`` (the model's or another time scale of it); adds its encoding and network
        seconds to ``timing``."""
        t0 = time.perf_counter()
        feats = self.encode_looks(events, sensor_size, targets, calibration, cfg, matrices)
        t1 = time.perf_counter()
        out = self.predict(feats.reshape(-1, feats.shape[-1])).reshape(len(feats), -1, 3)
        timing["encode"] += t1 - t0
        timing["network"] += time.perf_counter() - t1
        return [head_output_to_flow(o, cfg) for o in out]  # px/s, whatever the time scale
