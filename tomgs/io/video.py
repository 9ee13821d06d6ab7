"""Read a clip (video file or folder of frames) and its optional masks into memory.

OpenCV is imported inside the functions so that `import tomgs` stays cheap.
"""

from __future__ import annotations

import re
import sys
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


PNG_MAX_RATIO = 1032  # deflate's largest expansion: a PNG's pixels cannot outgrow 1032 x its bytes


def image_size(path: Path) -> tuple[int, int, str, int] | None:
    """(width, height, format, least bytes those pixels take in this format) that a PNG, JPEG or BMP
    file declares in its header, read without decoding; None for other formats or a header too
    damaged to say. Least bytes: PNG, deflate's 1032:1 over one bit per pixel and the filter bytes;
    uncompressed BMP, its rows; RLE BMP, 2 bytes per 255 pixels; baseline JPEG, 2 bits per 8x8 block
    (a DC code and an end of block); 0 where a format can code pixels for almost nothing (progressive
    or arithmetic JPEG, other BMP codings)."""
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            if head.startswith(b"\x89PNG\r\n\x1a\n") and head[12:16] == b"IHDR":
                w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
                return w, h, "png", h * (1 + (w + 7) // 8) // PNG_MAX_RATIO
            if head.startswith(b"BM") and len(head) >= 32:
                w = abs(int.from_bytes(head[18:22], "little", signed=True))
                h = abs(int.from_bytes(head[22:26], "little", signed=True))
                bits, coding = int.from_bytes(head[28:30], "little"), int.from_bytes(head[30:32], "little")
                least = h * ((w * bits + 31) // 32 * 4) if coding in (0, 3) else \
                    2 * (w * h // 255) if coding in (1, 2) else 0
                return w, h, "bmp", least
            if head.startswith(b"\xff\xd8"):
                f.seek(2)
                for _ in range(1000):  # markers before the frame header: APPn, DQT, DHT, ... (64 kB each at most)
                    marker = f.read(4)
                    if len(marker) < 4 or marker[0] != 0xFF:
                        return None
                    kind, length = marker[1], int.from_bytes(marker[2:4], "big")
                    if 0xC0 <= kind <= 0xCF and kind not in (0xC4, 0xC8, 0xCC):  # SOFn: P, height, width
                        sof = f.read(5)
                        if len(sof) < 5:
                            return None
                        w, h = int.from_bytes(sof[3:5], "big"), int.from_bytes(sof[1:3], "big")
                        blocks = ((w + 7) // 8) * ((h + 7) // 8)
                        return w, h, "jpeg", blocks // 4 if kind in (0xC0, 0xC1) else 0
                    f.seek(length - 2, 1)
    except OSError:
        return None
    return None


def _check_image(path: Path) -> None:
    """InputError when the image's header declares a size beyond MAX_SIDE, or (PNG) more pixels than
    its bytes can hold, before the decoder allocates it."""
    from tomgs.cameras import MAX_SIDE

    found = image_size(path)
    if found is None:
        return
    w, h, kind, least = found
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise InputError(f"{path}: its header declares a {w}x{h} image; frames are 1..{MAX_SIDE} pixels a side: "
                         "the file is corrupt, or resize it")
    if least > path.stat().st_size:
        raise InputError(f"{path}: its header declares a {w}x{h} {kind.upper()} image, more than its "
                         f"{path.stat().st_size:,} bytes can hold: the file is corrupt or truncated; replace it")


def _read_image(path: Path, flags: int) -> np.ndarray:
    import cv2

    _check_image(path)
    try:
        img = cv2.imread(str(path), flags)
    except cv2.error:
        img = None
    if img is None:
        raise InputError(f"cannot read image {path}: the file is corrupt or not an image; remove or replace it")
    return img


def _frame_budget() -> int:
    """Bytes the kept frames may take: half of this machine's memory (16 GiB where it cannot be told).
    A short file can decode to any number of large frames; this stops before the machine runs out."""
    import os

    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 16 << 30


class _Frames:
    """Frames kept while reading: RGB, resized as they arrive, checked for one size and for memory."""

    def __init__(self, path: Path, max_side: int | None):
        self.path, self.max_side = path, max_side
        self.images: list[np.ndarray] = []
        self.first: tuple | None = None  # (source, name) of the first kept frame
        self.size: tuple[int, int] | None = None  # source (h, w)
        self.flat = True
        self.bytes, self.budget = 0, _frame_budget()

    def add(self, image: np.ndarray, name: str, bgr: bool = True) -> None:
        import cv2

        if image.ndim != 3 or image.shape[2] != 3:
            raise InputError(f"{name} decodes to an array of shape {image.shape}, not a colour frame: re-encode it")
        if self.size is None:
            self.size, self.first = image.shape[:2], name
        elif image.shape[:2] != self.size:
            raise InputError(f"{name} is {image.shape[1]}x{image.shape[0]} but {self.first} is "
                             f"{self.size[1]}x{self.size[0]}: all frames must have one size")
        self.flat = self.flat and bool((image == image[:1, :1]).all())
        rgb = cv2.cvtColor(image, cv2.COLOR_BGR2RGB) if bgr else image
        nh, nw = _resized_size(*self.size, self.max_side)
        if (nh, nw) != tuple(self.size):
            rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_AREA)
        self.bytes += rgb.nbytes
        if self.bytes > self.budget:
            raise InputError(f"{self.path}: the {len(self.images) + 1} frames read so far take {self.bytes / 2**30:.1f} "
                             f"GiB, more than half of this machine's memory: read fewer (--frames) or smaller "
                             f"(--max-side) frames")
        self.images.append(rgb)


def read_video(path, frames=None, max_side: int | None = None, masks=None) -> Video:
    """Read a clip into memory.

    path:     a video file (mp4/mov/avi/mkv/...) or a folder of jpg/png frames (natural sort order).
    frames:   None (all), or a range 'start:stop:step' such as '0:80' or '::2' (source frame numbers).
    max_side: if given, frames are resized (area filter) so that max(H, W) <= max_side.
    masks:    None, or a folder of mask images, one per source frame (same order and size as the
              frames); a pixel > 127 means moving foreground.
    Returns a `Video`. Frames stream: only the selected ones are kept, resized as they are read.
    Raises `InputError` for a missing path, an unreadable or corrupt video, zero frames, a bad
    range, or masks of another count or size; for a video whose header declares frames larger than
    tomgs.cameras.MAX_SIDE, whose frames change size, or whose frames are all one flat colour (what
    random bytes decode to); for images whose header declares more than MAX_SIDE a side.
    """
    import cv2

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a video file or a folder of frames")
    sel = parse_frames(frames)
    if max_side is not None and int(max_side) < 1:
        raise InputError(f"max_side must be a positive number of pixels, got {max_side}")

    fps = None
    kept = _Frames(path, max_side)
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise InputError(f"{path} holds no jpg/png frames: point at a folder of images or a video file")
        total = len(files)
        idx = _select(total, sel, frames, path)
        for i in idx:
            kept.add(_read_image(files[i], cv2.IMREAD_COLOR), str(files[i]))
    else:
        if path.suffix.lower() not in VIDEO_EXTS:
            raise InputError(f"{path} is neither a video ({', '.join(sorted(VIDEO_EXTS))}) nor a folder of frames")
        fps, total, idx = _read_video_file(path, sel, frames, masks is not None, kept)

    h, w = kept.size
    mask_arr = None
    if masks is not None:
        mask_arr = _read_masks(Path(masks), total, idx, h, w)
        nh, nw = _resized_size(h, w, max_side)
        if (nh, nw) != (h, w):
            mask_arr = np.stack([cv2.resize(m.astype(np.uint8), (nw, nh), interpolation=cv2.INTER_NEAREST) > 0
                                 for m in mask_arr])
    return Video(np.ascontiguousarray(np.stack(kept.images)), mask_arr, fps, np.asarray(idx, dtype=np.int64), path)


def _read_video_file(path: Path, sel: slice, spec, need_total: bool, kept: _Frames):
    """Decode the frames of video file `path` that `sel` picks into `kept`: (fps or None, the total
    frame count or None where decoding stopped early, the kept source frame numbers)."""
    import math

    import cv2

    from tomgs.cameras import MAX_SIDE

    fix = "re-encode it (e.g. ffmpeg -i in.mov -c:v libx264 out.mp4) or extract its frames to a folder"

    def open_capture():
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise InputError(f"cannot open video {path}: the file is unreadable or corrupt; {fix}")
        return cap

    cap = open_capture()
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        fps = fps if math.isfinite(fps) and 0 < fps <= 1000 else None
        w, h = (float(cap.get(p)) for p in (cv2.CAP_PROP_FRAME_WIDTH, cv2.CAP_PROP_FRAME_HEIGHT))
        if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
            raise InputError(f"video {path} declares {w:g}x{h:g} frames; frames are 1..{MAX_SIDE} pixels a side: "
                             f"the file is corrupt, or {fix}")
        declared = {(round(w), round(h)), (round(h), round(w))}  # either way round: rotation metadata
        # negative bounds count from the end, and masks must match the total: count first (no colour conversion)
        need_total = need_total or any(v is not None and v < 0 for v in (sel.start, sel.stop))
        total = None
        if need_total:
            total = 0
            while cap.grab():
                total += 1
            cap.release()
            cap = open_capture()
            if total == 0:
                raise InputError(f"video {path} has zero readable frames: the file is empty or corrupt; {fix}")
            wanted = range(total)[sel]
        else:
            wanted = range(sel.start or 0, sys.maxsize if sel.stop is None else sel.stop, sel.step or 1)
        if not wanted:  # (len() of a range overflows past 2^63)
            what = f"{path} ({total} frames)" if total is not None else str(path)
            raise InputError(f"frame range {spec!r} selects no frames of {what}: pick a range inside the clip")
        idx, k = [], 0
        while k <= wanted[-1]:
            if k in wanted:
                ok, image = cap.read()
            else:
                ok, image = cap.grab(), None
            if not ok:
                break
            if image is not None:
                if kept.size is None and (image.shape[1], image.shape[0]) not in declared:
                    raise InputError(f"video {path} decodes to {image.shape[1]}x{image.shape[0]} frames but its header "
                                     f"says {w:g}x{h:g}: the file is corrupt; {fix}")
                kept.add(image, f"frame {k} of {path}")
                idx.append(k)
            k += 1
        else:
            k = None  # stopped after the last selected frame: the total is not known
    except cv2.error as e:
        raise InputError(f"cannot decode video {path} ({str(e).strip()[:200]}): {fix}") from None
    finally:
        cap.release()
    total = total if total is not None else k
    if total == 0:
        raise InputError(f"video {path} has zero readable frames: the file is empty or corrupt; {fix}")
    if not idx:
        raise InputError(f"frame range {spec!r} selects no frames of {path} ({total} frames): "
                         f"pick a range inside 0:{total}")
    if kept.flat:
        raise InputError(f"video {path} decodes to {len(idx)} frame{'s' if len(idx) > 1 else ''} of one flat colour "
                         f"and nothing else: there is no picture to fit. A file of random or damaged bytes decodes "
                         f"like this; if the video is real, pick frames with content (--frames); else {fix}")
    return fps, total, idx


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
    numbers = cameras.frame_indices
    clip = read_video(path, frames=slice(int(numbers.min()), int(numbers.max()) + 1) if len(numbers) else None,
                      max_side=max(cameras.width, cameras.height))
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
