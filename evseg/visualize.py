"""Pictures of events, labels and flow for previews and overlays.

Every function takes numpy arrays and returns a **uint8 (H, W, 3) RGB** image (convert with
``img[..., ::-1]`` before ``cv2.imwrite``, which expects BGR; :func:`save_rgb` does it). Pixel
coordinates follow the event model: x = column, y = row, row 0 at the top. Flow colours: hue =
direction (0 deg = +x / right = red, 90 deg = +y / down, going red -> yellow -> green -> cyan ->
blue -> magenta), value = magnitude relative to ``max_px_s`` (black = still, saturating beyond).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

WHITE = (255, 255, 255)
ON_RGB = (220, 40, 40)
"""Colour of ON (+1) events: red."""
OFF_RGB = (40, 80, 230)
"""Colour of OFF (-1) events: blue."""
NOISE_RGB = (128, 128, 128)
BACKGROUND_RGB = (200, 200, 200)


def label_palette(n: int) -> np.ndarray:
    """uint8 (n, 3) RGB colours for object labels 1..n (golden-angle hues: neighbours differ).

    Row ``k - 1`` is object ``k``'s colour, the same as in the segmentation overlays
    (:func:`evseg.overlay.object_color`, which gives it in BGR order), so an object has one
    colour in every picture.
    """
    ids = np.arange(1, n + 1)
    hue = ((ids * 0.618033988749895 % 1.0) * 180).astype(np.int64)
    hsv = np.stack([hue, np.full(n, 230), np.full(n, 255)], -1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]


def flow_to_rgb(nx: np.ndarray, ny: np.ndarray, max_px_s: float) -> np.ndarray:
    """Colour-code flow vectors (any equal shapes, px/s): uint8 (*shape, 3) RGB.

    Hue = direction of (nx, ny) in image coordinates (y down), value = min(1, |n| / max_px_s),
    full saturation. NaN vectors become black (as a still pixel would)."""
    nx = np.asarray(nx, np.float64)
    ny = np.asarray(ny, np.float64)
    if nx.shape != ny.shape:
        from evseg.errors import EventDataError

        raise EventDataError(f"flow_to_rgb: nx and ny must have one shape, got {nx.shape} and {ny.shape}")
    if not (isinstance(max_px_s, (int, float, np.integer, np.floating)) and np.isfinite(max_px_s) and max_px_s > 0):
        from evseg.errors import ConfigError

        raise ConfigError(f"flow_to_rgb: max_px_s (the speed shown at full brightness) must be a positive number "
                          f"(px/s), got {max_px_s!r}")
    shape = nx.shape
    ang = np.degrees(np.arctan2(ny, nx)) % 360.0
    mag = np.hypot(nx, ny)
    val = np.clip(np.nan_to_num(mag / max(max_px_s, 1e-12)), 0, 1)
    hsv = np.stack([np.nan_to_num(ang) / 2.0, np.full(shape, 255.0), val * 255.0], -1)
    flat = np.round(hsv).astype(np.uint8).reshape(1, -1, 3)
    return cv2.cvtColor(flat, cv2.COLOR_HSV2RGB).reshape(*shape, 3)


def color_wheel_legend(size: int = 96, max_px_s: float | None = None) -> np.ndarray:
    """uint8 (size, size, 3) RGB disc showing the colour of each flow direction/magnitude (the
    rim = ``max_px_s``), white outside the disc, with the magnitude written below the centre
    when ``max_px_s`` is given."""
    r = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    dx, dy = (xx - r) / r, (yy - r) / r
    img = flow_to_rgb(dx, dy, 1.0)
    img[np.hypot(dx, dy) > 1.0] = WHITE
    if max_px_s is not None:
        text = f"{max_px_s:g} px/s"
        cv2.putText(img, text, (2, size - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.3, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _pixel_index(x, y, sensor_size, n: int | None, where: str) -> tuple[np.ndarray, int, int]:
    """Flat pixel index ``y * width + x`` of per-event coordinates, checked: a coordinate off
    the sensor (or a swapped width and height) would land on another row, not fail."""
    from evseg.errors import EventDataError
    from evseg.events import checked_sensor_size

    w, h = checked_sensor_size(sensor_size)
    x, y = np.asarray(x), np.asarray(y)
    if x.ndim != 1 or x.shape != y.shape or (n is not None and len(x) != n):
        raise EventDataError(f"{where}: x, y (and the per-event values) must be 1-D of one length, got "
                             f"{x.shape}, {y.shape}" + ("" if n is None else f" and {n} values"))
    for name, c, limit in (("x", x, w), ("y", y, h)):
        if len(c) and (not np.issubdtype(c.dtype, np.integer) and not np.all(c == np.round(c))):
            raise EventDataError(f"{where}: {name} must be whole pixels, got {c[c != np.round(c)][0]}")
        bad = np.flatnonzero((c < 0) | (c >= limit))
        if len(bad):
            raise EventDataError(f"{where}: {name} = {c[bad[0]]} at event {int(bad[0])} is outside the {w}x{h} "
                                 "sensor (sensor_size is (width, height))")
    return y.astype(np.int64) * w + x.astype(np.int64), w, h


def events_to_image(x: np.ndarray, y: np.ndarray, p: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Event image: white background, pixel coloured by the sign of its summed polarity (red =
    ON, blue = OFF). ``sensor_size = (width, height)``; returns uint8 (height, width, 3) RGB."""
    pix, w, h = _pixel_index(x, y, sensor_size, len(np.asarray(p)), "events_to_image")
    acc = np.zeros(h * w, np.int32)
    np.add.at(acc, pix, np.asarray(p, np.int32))
    img = np.full((h * w, 3), 255, np.uint8)
    img[acc > 0] = ON_RGB
    img[acc < 0] = OFF_RGB
    return img.reshape(h, w, 3)


def labels_to_image(x: np.ndarray, y: np.ndarray, labels: np.ndarray, sensor_size: tuple[int, int]) -> np.ndarray:
    """Per-event labels drawn at their pixels (the last event of a pixel wins): white where no
    event, light grey for 0 (background), grey for -1 (noise), a palette colour for k >= 1.
    Returns uint8 (height, width, 3) RGB."""
    labels = np.asarray(labels)
    pix, w, h = _pixel_index(x, y, sensor_size, len(labels), "labels_to_image")
    if len(labels) and (not np.issubdtype(labels.dtype, np.integer) or labels.min() < -1):
        from evseg.errors import EventDataError

        raise EventDataError(f"labels_to_image: labels must be integers >= -1 (-1 unassigned, 0 background, "
                             f"k >= 1 object), got dtype {labels.dtype}, minimum {labels.min()}")
    labels = labels.astype(np.int64)
    n_obj = int(labels.max(initial=0))
    colours = np.vstack([np.array([NOISE_RGB, BACKGROUND_RGB], np.uint8), label_palette(max(n_obj, 1))])
    img = np.full((h * w, 3), 255, np.uint8)
    img[pix] = colours[labels + 1]
    return img.reshape(h, w, 3)


def flow_events_to_image(x, y, flow: np.ndarray, sensor_size: tuple[int, int], max_px_s: float) -> np.ndarray:
    """Per-event flow vectors (N, 2) px/s drawn at their pixels with :func:`flow_to_rgb`
    (last event of a pixel wins; NaN flows are skipped); white where no event.
    Returns uint8 (height, width, 3) RGB."""
    flow = np.asarray(flow)
    pix, w, h = _pixel_index(x, y, sensor_size, len(flow), "flow_events_to_image")
    if flow.ndim != 2 or flow.shape[1] != 2:
        from evseg.errors import EventDataError

        raise EventDataError(f"flow_events_to_image: flow must be (N, 2) px/s, got shape {flow.shape}")
    ok = np.isfinite(flow).all(1)
    img = np.full((h * w, 3), 255, np.uint8)
    idx = pix[ok]
    img[idx] = flow_to_rgb(flow[ok, 0], flow[ok, 1], max_px_s)
    return img.reshape(h, w, 3)


def mask_outline(img: np.ndarray, mask: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    """Copy of ``img`` (H, W, 3) with the outline of bool ``mask`` (H, W) drawn in ``rgb``."""
    out = img.copy()
    m = mask.astype(np.uint8)
    edge = m - cv2.erode(m, np.ones((3, 3), np.uint8))
    out[edge > 0] = rgb
    return out


def titled(img: np.ndarray, title: str, scale: int = 1) -> np.ndarray:
    """``img`` enlarged ``scale`` times (nearest neighbour) with a white title bar on top."""
    if scale > 1:
        img = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    bar = np.full((18, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, title, (3, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])


def hstack_padded(images: list[np.ndarray], gap: int = 6) -> np.ndarray:
    """Place RGB images side by side, top-aligned, on white, ``gap`` px apart."""
    h = max(i.shape[0] for i in images)
    cols = []
    for k, im in enumerate(images):
        pad = np.full((h - im.shape[0], im.shape[1], 3), 255, np.uint8)
        cols.append(np.vstack([im, pad]))
        if k < len(images) - 1:
            cols.append(np.full((h, gap, 3), 255, np.uint8))
    return np.hstack(cols)


def vstack_padded(images: list[np.ndarray], gap: int = 6) -> np.ndarray:
    """Stack RGB images vertically, left-aligned, on white, ``gap`` px apart."""
    w = max(i.shape[1] for i in images)
    rows = []
    for k, im in enumerate(images):
        rows.append(np.hstack([im, np.full((im.shape[0], w - im.shape[1], 3), 255, np.uint8)]))
        if k < len(images) - 1:
            rows.append(np.full((gap, w, 3), 255, np.uint8))
    return np.vstack(rows)


def save_rgb(path: str | Path, img: np.ndarray) -> None:
    """Write an RGB uint8 image (PNG/JPEG by extension) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix or ".png"
    params = [cv2.IMWRITE_PNG_COMPRESSION, 9] if suffix.lower() == ".png" else []  # small files for docs
    ok, buf = cv2.imencode(suffix, np.ascontiguousarray(img[..., ::-1]), params)
    if not ok:
        raise ValueError(f"cannot encode image as {path.suffix}")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.tobytes())
    tmp.replace(path)
