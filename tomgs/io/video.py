"""Read a clip (video file or folder of frames) and its optional masks into memory.

OpenCV is imported inside the functions so that `import tomgs` stays cheap.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tomgs.errors import InputError

VIDEO_EXTS = {".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v"}
IMAGE_EXTS = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"}


@dataclass
class Video:
    """A clip in memory.

    frames:  uint8 [T, H, W, 3], RGB.
    masks:   bool [T, H, W] (True = moving foreground, to be ignored by pose estimation) or None.
    fps:     frames per second of the source (None for a folder of frames).
    indices: int64 [T], the source frame number of each kept frame.
    path:    where the clip came from.
    """

    frames: np.ndarray
    masks: np.ndarray | None
    fps: float | None
    indices: np.ndarray
    path: Path

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def times(self) -> np.ndarray:
        """float64 [T]: frame k of n at t = k / (n - 1); a single frame at t = 0."""
        n = len(self.frames)
        return np.arange(n, dtype=np.float64) / max(n - 1, 1)


def natural_key(path: Path):
    """Sort key so that frame2.png comes before frame10.png."""
    return [int(s) if s.isdigit() else s.lower() for s in re.split(r"(\d+)", path.name)]


def list_images(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS), key=natural_key)


def parse_frames(spec, total: int | None = None) -> slice:
    """'a:b:c' (Python slice syntax, e.g. '0:80', '::2', '10:') or a single index 'k' -> slice.

    Raises InputError for malformed specs or a zero step. `total` is only used in messages.
    """
    if spec is None or isinstance(spec, slice):
        return spec if isinstance(spec, slice) else slice(None)
    text = str(spec).strip()
    parts = text.split(":")
    try:
        if len(parts) == 1:
            k = int(parts[0])
            return slice(k, k + 1 if k != -1 else None)
        if len(parts) > 3:
            raise ValueError
        vals = [int(p) if p.strip() else None for p in parts] + [None] * (3 - len(parts))
    except ValueError:
        raise InputError(
            f"bad frame range {text!r}: use Python slice syntax 'start:stop:step', e.g. '0:80' or '::2'"
        ) from None
    if vals[2] is not None and vals[2] <= 0:
        raise InputError(f"bad frame range {text!r}: the step must be a positive integer")
    return slice(*vals)


def _select(total: int, sel: slice, spec, what: Path) -> np.ndarray:
    idx = np.arange(total)[sel]
    if len(idx) == 0:
        raise InputError(f"frame range {spec!r} selects no frames of {what} ({total} frames): pick a range inside 0:{total}")
    return idx


def _resized_size(h: int, w: int, max_side: int | None) -> tuple[int, int]:
    if max_side is None or max(h, w) <= max_side:
        return h, w
    s = max_side / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


def _read_image(path: Path, flags: int) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), flags)
    if img is None:
        raise InputError(f"cannot read image {path}: the file is corrupt or not an image; remove or replace it")
    return img


def read_video(path, frames=None, max_side: int | None = None, masks=None) -> Video:
    """Read a clip into memory.

    path:     a video file (mp4/mov/avi/mkv/...) or a folder of jpg/png frames (natural sort order).
    frames:   None (all), or a range 'start:stop:step' such as '0:80' or '::2' (source frame numbers).
    max_side: if given, frames are resized (area filter) so that max(H, W) <= max_side.
    masks:    None, or a folder of mask images, one per source frame (same order and size as the
              frames); a pixel > 127 means moving foreground.
    Returns a `Video`. Raises `InputError` for a missing path, an unreadable or corrupt video, zero
    frames, a bad range, or masks of another count or size.
    """
    import cv2

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a video file or a folder of frames")
    sel = parse_frames(frames)
    if max_side is not None and int(max_side) < 1:
        raise InputError(f"max_side must be a positive number of pixels, got {max_side}")

    fps = None
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise InputError(f"{path} holds no jpg/png frames: point at a folder of images or a video file")
        total = len(files)
        idx = _select(total, sel, frames, path)
        imgs = [cv2.cvtColor(_read_image(files[i], cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) for i in idx]
        for f, im in zip((files[i] for i in idx), imgs):
            if im.shape != imgs[0].shape:
                raise InputError(f"{f} is {im.shape[1]}x{im.shape[0]} but {files[idx[0]]} is "
                                 f"{imgs[0].shape[1]}x{imgs[0].shape[0]}: all frames must have one size")
    else:
        if path.suffix.lower() not in VIDEO_EXTS:
            raise InputError(f"{path} is neither a video ({', '.join(sorted(VIDEO_EXTS))}) nor a folder of frames")
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise InputError(f"cannot open video {path}: the file is unreadable or corrupt; re-encode it "
                             "(e.g. ffmpeg -i in.mov -c:v libx264 out.mp4) or extract its frames to a folder")
        fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
        # decode everything once: frame counts in containers are unreliable, and masks need the total
        decoded = []
        while True:
            ok, im = cap.read()
            if not ok:
                break
            decoded.append(im)
        cap.release()
        if not decoded:
            raise InputError(f"video {path} has zero readable frames: the file is empty or corrupt; re-encode it")
        total = len(decoded)
        idx = _select(total, sel, frames, path)
        imgs = [cv2.cvtColor(decoded[i], cv2.COLOR_BGR2RGB) for i in idx]
        del decoded

    h, w = imgs[0].shape[:2]
    mask_arr = None
    if masks is not None:
        mask_arr = _read_masks(Path(masks), total, idx, h, w)

    nh, nw = _resized_size(h, w, max_side)
    if (nh, nw) != (h, w):
        imgs = [cv2.resize(im, (nw, nh), interpolation=cv2.INTER_AREA) for im in imgs]
        if mask_arr is not None:
            mask_arr = np.stack([cv2.resize(m.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST) > 0
                                 for m in mask_arr])
    return Video(np.ascontiguousarray(np.stack(imgs)), mask_arr, fps, idx.astype(np.int64), path)


def _read_masks(folder: Path, total: int, idx: np.ndarray, h: int, w: int) -> np.ndarray:
    """bool [len(idx), h, w] from a folder with one mask per source frame."""
    import cv2

    if not folder.is_dir():
        raise InputError(f"mask folder {folder} does not exist: give a folder with one mask image per frame")
    files = list_images(folder)
    if len(files) != total:
        raise InputError(f"{folder} holds {len(files)} masks but the clip has {total} frames: "
                         "give exactly one mask per source frame, in the same order")
    out = np.empty((len(idx), h, w), dtype=bool)
    for k, i in enumerate(idx):
        m = _read_image(files[i], cv2.IMREAD_GRAYSCALE)
        if m.shape != (h, w):
            raise InputError(f"mask {files[i]} is {m.shape[1]}x{m.shape[0]} but the frames are {w}x{h}: "
                             "masks must have the size of the source frames")
        out[k] = m > 127
    return out


def read_video_for(path, cameras) -> np.ndarray:
    """uint8 [T,H,W,3]: the frames of `path` that `cameras` (a tomgs.Cameras) were made for, picked by
    source frame number and resized as `read_video` resizes, so a scene meets its own training frames."""
    clip = read_video(path, max_side=max(cameras.width, cameras.height))
    position = {int(s): i for i, s in enumerate(clip.indices)}
    missing = [int(s) for s in cameras.frame_indices if int(s) not in position]
    if missing:
        raise InputError(f"{path} has {len(clip)} frames but the scene was fitted on source frame {missing[0]}; "
                         "give the video the scene was fitted on")
    frames = clip.frames[[position[int(s)] for s in cameras.frame_indices]]
    if frames.shape[1:3] != (cameras.height, cameras.width):
        raise InputError(f"{path} gives {frames.shape[2]}x{frames.shape[1]} frames but the scene is "
                         f"{cameras.width}x{cameras.height}; give the video the scene was fitted on")
    return frames
