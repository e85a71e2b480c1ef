"""Pictures of segmentation results: events coloured by object id, with boxes and ids.

All functions return uint8 **BGR** images (OpenCV's order) of shape (height, width, 3), so they
can go straight to ``cv2.imwrite`` or a ``cv2.VideoWriter``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from evseg.checks import is_whole
from evseg.errors import EvsegError

BACKGROUND_BGR = (150, 150, 150)
UNASSIGNED_BGR = (60, 60, 60)


def object_color(object_id: int) -> tuple[int, int, int]:
    """A distinct, stable BGR colour per object id (golden-angle hue steps); the same colour,
    in RGB order, as row ``object_id - 1`` of :func:`evseg.visualize.label_palette`."""
    import cv2

    hue = int((object_id * 0.618033988749895 % 1.0) * 180)
    hsv = np.array([[[hue, 230, 255]]], dtype=np.uint8)
    b, g, r = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0]
    return int(b), int(g), int(r)


def auto_scale(height_px: int, target_px: int = 480) -> int:
    """The smallest integer upscaling that makes a picture of ``height_px`` rows at least
    ``target_px`` high (at least 1).

    >>> auto_scale(260), auto_scale(128), auto_scale(720)
    (2, 4, 1)
    """
    return max(1, -(-int(target_px) // max(int(height_px), 1)))


def label_overlay(
    events: np.ndarray,
    labels: np.ndarray,
    boxes: dict[int, tuple[int, int, int, int]],
    sensor_size: tuple[int, int],
    scale: int | None = None,
    title: str | None = None,
) -> np.ndarray:
    """Events of one window drawn on black, coloured by label, with object boxes and ids.

    Args:
        events: :data:`~evseg.events.EVENT_DTYPE` array of the window.
        labels: per event: -1 unassigned (dark grey), 0 background (grey), k >= 1 object k.
        boxes: object id -> (x0, y0, x1, y1) inclusive px.
        sensor_size: (width, height) px.
        scale: integer upscaling of the picture (boxes and text stay crisp); None: the
            smallest that makes it at least 480 px high (2 for 346x260, 4 for 128x128, 1 from
            480 px on), so that the text stays legible on small and large sensors alike.
    """
    import cv2

    from evseg.events import checked_sensor_size, first_off_sensor, validate_events

    w, h = checked_sensor_size(sensor_size)
    validate_events(events, None, source="label_overlay events", check_sorted=False)
    labels = np.asarray(labels)
    if labels.shape != (len(events),):
        raise EvsegError(f"label_overlay: labels has shape {labels.shape}, expected one per event ({len(events)},)")
    off = first_off_sensor(events, (w, h))
    if off is not None:
        raise EvsegError(f"label_overlay: {off} is outside the {w}x{h} sensor (sensor_size is (width, height))")
    if not isinstance(boxes, dict):
        raise EvsegError(f"label_overlay: boxes must map object id -> (x0, y0, x1, y1), got {type(boxes).__name__}")
    boxes = {oid: tuple(int(round(v)) for v in box) for oid, box in boxes.items()}
    if scale is None:
        scale = auto_scale(h)
    if not is_whole(scale) or scale < 1:
        raise EvsegError(f"label_overlay: scale must be a whole number >= 1, got {scale!r}")
    scale = int(scale)
    img = np.zeros((h, w, 3), dtype=np.uint8)
    for lab in np.unique(labels):
        sel = labels == lab
        color = UNASSIGNED_BGR if lab < 0 else BACKGROUND_BGR if lab == 0 else object_color(int(lab))
        img[events["y"][sel], events["x"][sel]] = color
    if scale != 1:
        img = cv2.resize(img, (w * scale, h * scale), interpolation=cv2.INTER_NEAREST)
    for oid, (x0, y0, x1, y1) in sorted(boxes.items()):
        c = object_color(int(oid))
        cv2.rectangle(img, (x0 * scale, y0 * scale), ((x1 + 1) * scale - 1, (y1 + 1) * scale - 1), c, 1)
        # Above the box, or inside it at the top where the title would cover it.
        y_text = y0 * scale - 3 if y0 * scale - 3 >= (22 if title else 10) else (y0 + 1) * scale + 12
        cv2.putText(img, f"#{oid}", (x0 * scale + 1, y_text), cv2.FONT_HERSHEY_SIMPLEX, 0.4, c, 1, cv2.LINE_AA)
    if title:
        cv2.putText(img, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
    return img


MAX_VIDEO_FPS = 65535
"""The highest frame rate an mp4 holds: its time base is 1 / fps with a 16-bit denominator."""

FRAME_NAME = re.compile(r"\d{6}\.png")
"""Names of the numbered frames :class:`VideoSink` writes (``000000.png``, ...)."""


class VideoSink:
    """Write BGR frames to an mp4 (OpenCV ``mp4v``) and/or numbered PNGs in a folder.

    The video is written to a temporary name and renamed on :meth:`close`, so an interrupted
    run never leaves a truncated file under the requested name; leaving a ``with`` block on an
    error keeps the frames written so far (a partial video), and an error of the video itself
    then yields to the one in flight. Numbered frames of an earlier run in ``frames_dir`` are
    removed when the first frame of this one is written (``stale_frames_removed`` counts them),
    so the folder never mixes two runs; other files there are left alone.
    """

    def __init__(self, video: Path | None = None, frames_dir: Path | None = None, fps: float = 25.0):
        self.video = Path(video) if video is not None else None
        self.frames_dir = Path(frames_dir) if frames_dir is not None else None
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and 0 < fps <= MAX_VIDEO_FPS):
            raise EvsegError(f"the video's frame rate must be a positive number of frames per second up to "
                             f"{MAX_VIDEO_FPS} (the mp4 time base), got {fps}")
        self.fps = float(fps)
        self._writer = None
        self._tmp: Path | None = None
        self._n = 0
        self._size: tuple[int, int] | None = None  # (height, width) of the first frame
        self.stale_frames_removed = 0
        if self.video is not None and self.video.suffix.lower() != ".mp4":
            # OpenCV picks the container from the suffix and, for one it cannot write with
            # mp4v, may write nothing without saying so.
            raise EvsegError(f"{self.video}: the video must be an .mp4 file")
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)

    def add(self, frame: np.ndarray) -> None:
        import cv2

        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
            # OpenCV's writer drops such frames with a warning on stderr only.
            raise EvsegError(f"{self.video or self.frames_dir}: frame {self._n} must be uint8 (height, width, 3) BGR, "
                             f"got {frame.dtype} {frame.shape}")
        if self._size is None:
            self._size = frame.shape[:2]
        elif frame.shape[:2] != self._size:
            raise EvsegError(f"{self.video or self.frames_dir}: frame {self._n} is {frame.shape[1]}x{frame.shape[0]}, "
                             f"the first was {self._size[1]}x{self._size[0]}; a video has one frame size")
        if self.video is not None:
            if self._writer is None:
                self.video.parent.mkdir(parents=True, exist_ok=True)
                self._tmp = self.video.with_name(f".{self.video.stem}.partial{self.video.suffix}")
                h, w = frame.shape[:2]
                self._writer = cv2.VideoWriter(str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
                if not self._writer.isOpened():
                    raise EvsegError(f"{self.video}: OpenCV cannot open an mp4 writer here")
            self._writer.write(frame)
        if self.frames_dir is not None:
            if self._n == 0:
                self._remove_stale_frames()
            name = self.frames_dir / f"{self._n:06d}.png"
            if not cv2.imwrite(str(name), frame):
                raise EvsegError(f"{name}: OpenCV could not write the frame")
        self._n += 1

    @property
    def n_frames(self) -> int:
        """Frames added so far."""
        return self._n

    def _remove_stale_frames(self) -> None:
        for old in self.frames_dir.iterdir():
            if FRAME_NAME.fullmatch(old.name) and old.is_file():
                old.unlink()
                self.stale_frames_removed += 1

    def close(self) -> None:
        """Finish the video: rename it to its requested name."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            if not self._tmp.is_file():
                raise EvsegError(f"{self.video}: OpenCV wrote no video (is the mp4v codec available?)")
            self._tmp.replace(self.video)

    def abort(self) -> None:
        """Discard the unfinished video (a video already at the requested name stays)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoSink":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is None:
            self.close()
            return
        try:
            self.close()  # an interrupted run keeps the frames it wrote, as its partial result
        except EvsegError:
            self.abort()  # the error in flight is the one to report, not a second one from here
