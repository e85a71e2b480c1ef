"""Persistent object identities across windows (beyond the paper, which relabels per window).

The segmentation numbers IMOs 1..K afresh in every window. To give users stable ids, each
tracked object's box is moved to the next window (by the caller, with the object's motion
model) and matched one to one to the new IMO boxes by IoU (Hungarian; tracks found in more
than one window first, then the others). A matched IMO keeps the track's id; an unmatched IMO starts a new id; a track unmatched for ``max_missed``
windows is dropped. Each track counts the windows it was found in (``hits``), so a caller can
report an object only once it has been seen more than once (SORT's ``min_hits``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

Box = tuple[int, int, int, int]


def box_iou(a: Box, b: Box) -> float:
    """IoU of two inclusive pixel boxes (x0, y0, x1, y1).

    >>> box_iou((0, 0, 9, 9), (5, 0, 14, 9))
    0.3333333333333333
    """
    ix = min(a[2], b[2]) - max(a[0], b[0]) + 1
    iy = min(a[3], b[3]) - max(a[1], b[1]) + 1
    if ix <= 0 or iy <= 0:
        return 0.0
    inter = ix * iy
    area = lambda r: (r[2] - r[0] + 1) * (r[3] - r[1] + 1)  # noqa: E731
    return inter / (area(a) + area(b) - inter)


def shift_box(box: Box, dx: float, dy: float, sensor_size: tuple[int, int] | None = None) -> Box:
    """Move a box by (dx, dy) px, rounding to pixels and clipping to the sensor if given."""
    x0, y0, x1, y1 = (int(round(v)) for v in (box[0] + dx, box[1] + dy, box[2] + dx, box[3] + dy))
    if sensor_size is not None:
        w, h = sensor_size
        x0, x1 = max(0, min(x0, w - 1)), max(0, min(x1, w - 1))
        y0, y1 = max(0, min(y0, h - 1)), max(0, min(y1, h - 1))
    return x0, y0, x1, y1


@dataclass
class ObjectTracker:
    """Assign stable ids to per-window IMO labels.

    Attributes:
        min_iou: smallest IoU between a predicted track box and a new box to keep the id.
        max_missed: windows a track survives without a match.
        hits: id -> number of windows in which the track was found (matched or new).
    """

    min_iou: float = 0.1
    max_missed: int = 2
    next_id: int = 1
    tracks: dict[int, Box] = field(default_factory=dict)  # id -> box predicted for this window
    missed: dict[int, int] = field(default_factory=dict)
    hits: dict[int, int] = field(default_factory=dict)

    def update(self, boxes: dict[int, Box]) -> dict[int, int]:
        """Match this window's IMO boxes (label -> box) to tracks; return label -> object id.

        Labels are processed in sorted order so that new ids are deterministic.
        """
        from scipy.optimize import linear_sum_assignment

        labels = sorted(boxes)
        track_ids = sorted(self.tracks)
        mapping: dict[int, int] = {}
        # Tracks found in more than one window are matched first, then the others to what is
        # left (the confirmed / tentative order of ByteTrack and DeepSORT): an object seen as
        # two pieces for one window must not hand its id to the piece that started a track.
        for tier in ([t for t in track_ids if self.hits.get(t, 0) >= 2],
                     [t for t in track_ids if self.hits.get(t, 0) < 2]):
            free = [l for l in labels if l not in mapping]
            if not free or not tier:
                continue
            iou = np.array([[box_iou(boxes[l], self.tracks[t]) for t in tier] for l in free])
            rows, cols = linear_sum_assignment(-iou)
            for r, c in zip(rows, cols):
                if iou[r, c] >= self.min_iou:
                    mapping[free[r]] = tier[c]
        for l in labels:
            if l not in mapping:
                mapping[l] = self.next_id
                self.next_id += 1
        matched = set(mapping.values())
        for t in track_ids:
            if t not in matched:
                self.missed[t] = self.missed.get(t, 0) + 1
                if self.missed[t] > self.max_missed:
                    self.tracks.pop(t)
                    self.missed.pop(t)
                    self.hits.pop(t, None)
        for l, oid in mapping.items():
            self.tracks[oid] = boxes[l]
            self.missed[oid] = 0
            self.hits[oid] = self.hits.get(oid, 0) + 1
        return mapping

    def predict(self, displacement: dict[int, tuple[float, float]], sensor_size: tuple[int, int] | None = None) -> None:
        """Move tracked boxes by their expected displacement (px) until the next window."""
        for oid, (dx, dy) in displacement.items():
            if oid in self.tracks:
                self.tracks[oid] = shift_box(self.tracks[oid], dx, dy, sensor_size)
