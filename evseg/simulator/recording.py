"""A simulated recording: events with per-event ground truth, and masks/boxes on demand."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from evseg.events import EventStream
from evseg.simulator import ground_truth
from evseg.simulator.render import SceneInstance, sample_scene
from evseg.simulator.scene import SceneConfig


@dataclass(frozen=True)
class WindowTruth:
    """Ground truth of one time window ``[t0_us, t1_us)``, taken at its mid-time ``t_us``.

    Attributes:
        object_ids: ids in the order of ``masks``.
        masks: bool (K, H, W) object masks at ``t_us``.
        boxes: id -> inclusive box ``(x0, y0, x1, y1)``, visible objects only.
    """

    t0_us: int
    t1_us: int
    t_us: int
    object_ids: list[int]
    masks: np.ndarray
    boxes: dict[int, tuple[int, int, int, int]]


@dataclass
class SimulatedRecording:
    """Events of a simulated scene with their ground truth.

    Attributes:
        stream: the events (sorted by t, time base 0 = start of the simulation, sensor size of
            the scene).
        label: int16 (N,) -1 noise / hot pixel, 0 background (incl. foreground occluders),
            k >= 1 object k.
        flow: float32 (N, 2) optical flow in px/s at each event (x = column, y = row down);
            NaN for noise events (they are not caused by motion).
        normal_flow: float32 (N, 2) normal flow in px/s (optical flow projected on the log
            intensity gradient); NaN for noise events and where the gradient vanishes.
        object_ids: ids of all objects of the scene (also those never visible), ascending =
            back to front.
        config, seed, duration_us: what reproduces the recording exactly.
        ground_truth_version: the simulator's ground-truth rule the labels and flows follow
            (:data:`evseg.simulator.ground_truth.GROUND_TRUTH_VERSION` when simulated now; a
            loaded file keeps the version it was written with).

    See :mod:`evseg.simulator.ground_truth` for how labels, flows and masks are defined.
    """

    stream: EventStream
    label: np.ndarray
    flow: np.ndarray
    normal_flow: np.ndarray
    object_ids: list[int]
    config: SceneConfig
    seed: int
    duration_us: int
    _scene: SceneInstance | None = field(default=None, repr=False, compare=False)
    ground_truth_version: int = ground_truth.GROUND_TRUTH_VERSION

    def __len__(self) -> int:
        return len(self.stream)

    @property
    def events(self) -> np.ndarray:
        return self.stream.events

    @property
    def scene(self) -> SceneInstance:
        """The concrete scene (re-drawn from config + seed + duration when loaded from disk)."""
        if self._scene is None:
            self._scene = sample_scene(self.config, self.seed, self.duration_us)
        return self._scene

    def object_masks(self, t_us: float) -> np.ndarray:
        """bool (K, H, W) visible silhouettes of the objects at ``t_us``, order =
        :attr:`object_ids`. An object counts as covering a pixel when it covers at least half of
        it after occlusion by objects in front of it; a net (foreground occluder) in front does
        **not** cut holes (the mask is the silhouette region, as evaluation needs). An object
        outside the frame has an empty mask."""
        return ground_truth.object_masks(self.scene, t_us)

    def object_boxes(self, t_us: float) -> dict[int, tuple[int, int, int, int]]:
        """id -> inclusive pixel box ``(x0, y0, x1, y1)`` of each visible object at ``t_us``."""
        return ground_truth.object_boxes(self.scene, t_us)

    def window_truth(self, t0_us: int, t1_us: int) -> WindowTruth:
        """Masks and boxes for the window ``[t0_us, t1_us)``, taken at its mid-time (an object
        moving 500 px/s shifts 2.5 px in half of a 10 ms window, so use short windows for
        fast objects)."""
        t_mid = (int(t0_us) + int(t1_us)) // 2
        masks = self.object_masks(t_mid)
        boxes = {}
        for oid, m in zip(self.object_ids, masks):
            b = ground_truth.mask_box(m)
            if b is not None:
                boxes[oid] = b
        return WindowTruth(int(t0_us), int(t1_us), t_mid, list(self.object_ids), masks, boxes)

    def summary(self) -> dict:
        """Counts for humans: events, rate, share per label, objects."""
        n = len(self.stream)
        dur_s = self.duration_us * 1e-6
        return {
            "events": n,
            "duration_s": dur_s,
            "rate_ev_s": n / dur_s if dur_s > 0 else 0.0,
            "sensor": f"{self.stream.width}x{self.stream.height}",
            "objects": len(self.object_ids),
            "share_background": float(np.mean(self.label == 0)) if n else 0.0,
            "share_objects": float(np.mean(self.label > 0)) if n else 0.0,
            "share_noise": float(np.mean(self.label < 0)) if n else 0.0,
        }
