"""Read a clip (video file or folder of frames) and its optional masks into memory.

OpenCV is imported inside the functions so that `import tomgs` stays cheap.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from tomgs.errors import InputError, counted
from tomgs.io.images import check_image, image_size, jpeg_size, read_image

if TYPE_CHECKING:
    import numpy as np

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
    decoded: frames the decoder produced to read it (a folder: images read); frames before the
             keyframe preceding the first selected one, and after the last, are never decoded.
    source_frames, source_size: the frames in the source and their (height, width) as stored,
             before any selection or resizing (0 and None for a clip made in memory).
    notes:   what a user may want to know of how the file was read (frames its edit list hides).
    """

    frames: np.ndarray
    masks: np.ndarray | None
    fps: float | None
    indices: np.ndarray
    path: Path
    decoded: int = 0
    source_frames: int = 0
    source_size: tuple[int, int] | None = None
    notes: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def times(self) -> np.ndarray:
        """float64 [T]: frame k of n at t = k / (n - 1); a single frame at t = 0."""
        import numpy as np

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


def _select(total: int, sel: slice, spec, what: Path) -> range:
    idx = range(total)[sel]
    if len(idx) == 0:
        raise InputError(f"frame range {spec!r} selects no frames of {what} ({total} frames): pick a range inside 0:{total}")
    return idx


def _resized_size(h: int, w: int, max_side: int | None) -> tuple[int, int]:
    if max_side is None or max(h, w) <= max_side:
        return h, w
    s = max_side / max(h, w)
    return max(1, round(h * s)), max(1, round(w * s))


def _frame_budget() -> int:
    """Bytes the kept frames may take: half of this machine's memory (16 GiB where it cannot be told).
    A short file can decode to any number of large frames; this stops before the machine runs out."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 16 << 30


def _check_budget(path, count: int, height: int, width: int) -> None:
    """InputError when `count` kept frames of `width` x `height` would pass _frame_budget."""
    need = count * height * width * 3
    if need > _frame_budget():
        raise InputError(f"{path}: {count} frames of {width}x{height} take {need / 2**30:.1f} GiB, more than half of "
                         f"this machine's memory: read fewer (--frames) or smaller (--max-side) frames")


DECODE_BYTES = 1 << 30  # RGB bytes of the frames a video's decoder threads may hold at once


class _Frames:
    """Frames kept while reading: RGB, resized as they arrive, checked for one size and for memory,
    written into one array allocated at the first frame (`count` frames expected), so the clip is
    never held twice (a list of frames stacked at the end was)."""

    def __init__(self, path: Path, max_side: int | None, count: int):
        import numpy as np

        self.path, self.max_side, self.count = path, max_side, count
        self.array: np.ndarray | None = None  # uint8 [count, h, w, 3] once the first frame is known
        self.kept = 0
        self.first: str | None = None  # name of the first kept frame
        self.size: tuple[int, int] | None = None  # source (h, w)
        self.flat = True

    def add(self, image: np.ndarray, name: str, bgr: bool = True) -> None:
        import numpy as np

        import cv2

        if image.ndim != 3 or image.shape[2] != 3:
            raise InputError(f"{name} decodes to an array of shape {image.shape}, not a colour frame: re-encode it")
        if self.size is None:
            self.size, self.first = image.shape[:2], name
            nh, nw = _resized_size(*self.size, self.max_side)
            _check_budget(self.path, self.count, nh, nw)
            self.array = np.empty((self.count, nh, nw, 3), np.uint8)
        elif image.shape[:2] != self.size:
            raise InputError(f"{name} is {image.shape[1]}x{image.shape[0]} but {self.first} is "
                             f"{self.size[1]}x{self.size[0]}: all frames must have one size")
        if self.kept >= self.count:
            raise InputError(f"{self.path}: more frames decode than its index lists: the file is corrupt; re-encode it")
        self.flat = self.flat and bool((image == image[:1, :1]).all())
        out = self.array[self.kept]
        if out.shape[:2] != image.shape[:2]:
            image = cv2.resize(image, (out.shape[1], out.shape[0]), interpolation=cv2.INTER_AREA)
        if bgr:
            cv2.cvtColor(image, cv2.COLOR_BGR2RGB, dst=out)
        else:
            out[...] = image
        self.kept += 1

    def frames(self) -> np.ndarray:
        """uint8 [kept, h, w, 3]: the frames read (fewer than expected where a file ended early)."""
        return self.array[:self.kept]


def read_video(path, frames=None, max_side: int | None = None, masks=None, progress=None) -> Video:
    """Read a clip into memory.

    path:     a video file (mp4/mov/avi/mkv/...) or a folder of jpg/png frames (natural sort order).
    frames:   None (all), or a range 'start:stop:step' such as '0:80' or '::2' (source frame numbers).
    max_side: if given, frames are resized (area filter) so that max(H, W) <= N.
    masks:    None, or a folder of mask images, one per source frame (same order and size as the
              frames); a pixel > 127 means moving foreground.
    progress: None, or callable(done, total) as frames are decoded (total: the frames to decode).
    Returns a `Video`. Frames stream: a video file's index is read first (no decoding), decoding
    starts at the keyframe before the first selected frame and stops after the last, only the
    selected frames are converted to RGB and resized, into one uint8 array; `Video.decoded` says
    how many frames the decoder produced.
    Raises `InputError` for a missing path, an unreadable or corrupt video, zero frames, a bad
    range, or masks of another count or size; for a video whose header declares frames larger than
    tomgs.constants.MAX_SIDE, whose frames change size, or whose frames are all one flat colour (what
    random bytes decode to); for images whose header declares more than MAX_SIDE a side; for
    selected frames that would take more than half of this machine's memory.
    """
    import numpy as np

    import cv2

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a video file or a folder of frames")
    sel = parse_frames(frames)
    if max_side is not None and int(max_side) < 1:
        raise InputError(f"max_side must be a positive number of pixels, got {max_side}")
    report = progress or (lambda done, total: None)

    fps, notes = None, []
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise InputError(f"{path} holds no jpg/png frames: point at a folder of images or a video file")
        total = len(files)
        idx = _select(total, sel, frames, path)
        kept = _Frames(path, max_side, len(idx))
        for n, i in enumerate(idx):
            kept.add(read_image(files[i], cv2.IMREAD_COLOR), str(files[i]))
            report(n + 1, len(idx))
        decoded = len(idx)
    else:
        if path.suffix.lower() not in VIDEO_EXTS:
            raise InputError(f"{path} is neither a video ({', '.join(sorted(VIDEO_EXTS))}) nor a folder of frames")
        fps, total, idx, kept, decoded, hidden = _read_video_file(path, sel, frames, max_side, report)
        if hidden:  # other tools count these: the difference explained
            notes.append(f"{counted(total, 'frame')} shown of {total + hidden} stored: the file's edit list hides "
                         f"{counted(hidden, 'frame')}, as players do")

    h, w = kept.size
    nh, nw = kept.array.shape[1:3]
    mask_arr = None if masks is None else _read_masks(Path(masks), Source(path, total, h, w), idx, (nh, nw))
    return Video(kept.frames(), mask_arr, fps, np.asarray(idx, dtype=np.int64), path, decoded, total, (h, w), notes)


@dataclass
class Source:
    """What a clip's source holds, read from a video's index and header or a folder's listing and
    first image, without decoding: `frames` in it, each `height` x `width` as shown (a display
    rotation applied)."""

    path: Path
    frames: int
    height: int
    width: int
    fps: float | None = None  # the average rate (None: a folder, or a file that does not say)
    variable: bool = False  # the intervals between frames differ (variable frame rate)
    rotation: int = 0  # degrees clockwise the frames are turned to be shown upright

    def facts(self) -> str:
        """What a plan says of the source: its frame rate, or that it varies, and a display rotation."""
        parts = ["variable frame rate" if self.variable else f"{self.fps:.4g} fps" if self.fps else ""]
        parts.append(f"turned {self.rotation}\N{DEGREE SIGN} as the file says" if self.rotation else "")
        return ", ".join(p for p in parts if p)


def probe_source(path) -> Source:
    """The `Source` of a video file or a folder of frames. InputError as `read_video` raises it for a
    missing path, an unknown extension, no frames, or a header past MAX_SIDE."""
    from tomgs.constants import MAX_SIDE

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist: give a video file or a folder of frames")
    if path.is_dir():
        files = list_images(path)
        if not files:
            raise InputError(f"{path} holds no jpg/png frames: point at a folder of images or a video file")
        w, h = check_image(files[0])[:2]
        return Source(path, len(files), h, w)
    if path.suffix.lower() not in VIDEO_EXTS:
        raise InputError(f"{path} is neither a video ({', '.join(sorted(VIDEO_EXTS))}) nor a folder of frames")
    import av

    try:
        with _open_av(path) as container:
            if not container.streams.video or container.streams.video[0].codec_context is None:
                raise InputError(f"cannot open video {path}: no decodable video stream")
            stream = container.streams.video[0]
            w, h = stream.codec_context.width, stream.codec_context.height
            if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
                raise InputError(f"video {path} declares {w}x{h} frames; frames are 1..{MAX_SIDE} pixels a side: "
                                 "the file is corrupt, or resize it")
            pts = _video_index(container, stream, path)[0]
            if not pts:
                raise InputError(f"video {path} has zero readable frames: the file is empty or corrupt")
            container.seek(0)
            first = next(container.decode(stream), None)  # one frame: the display rotation
            turns = _turns(first) if first is not None else 0
            if turns % 2:
                w, h = h, w
            rate = _frame_rate(stream, pts)  # while the container is open (PyAV 19 refuses a closed one's stream)
    except InputError:
        raise
    except (av.error.FFmpegError, UnicodeDecodeError, ValueError) as e:
        raise _unreadable(path, e) from None
    return Source(path, len(pts), h, w, *rate, rotation=(360 - 90 * turns) % 360)


def probe_clip(path, frames=None, max_side: int | None = None,
               source: Source | None = None) -> tuple[int, int, int, int]:
    """(selected frames, height, width, source pixels per frame) of a clip, from `probe_source`
    (or its `source`, already probed) without decoding the frames: what a fit plans with before it
    reads. Raises InputError as `read_video` does for a missing path or a bad or empty range, and
    for selected frames that would take more than half of this machine's memory."""
    sel = parse_frames(frames)
    source = source or probe_source(path)
    count = len(_select(source.frames, sel, frames, source.path))
    nh, nw = _resized_size(source.height, source.width, max_side)
    _check_budget(source.path, count, nh, nw)
    return count, nh, nw, source.height * source.width


def check_masks(folder, source: Source) -> Path:
    """`folder` once it holds one mask image per frame of `source`, the first of the source's size
    (read from its header); InputError saying what to give otherwise."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"mask folder {folder} does not exist" + (" (it is a file)" if folder.exists() else "")
                         + ": give a folder with one mask image per frame")
    files = list_images(folder)
    if len(files) != source.frames:
        raise InputError(f"{folder} holds {len(files)} masks but the clip has {source.frames} frames: "
                         "give exactly one mask per source frame, in the same order")
    found = image_size(files[0])
    if found is not None and (found[1], found[0]) != (source.height, source.width):
        raise InputError(f"mask {files[0]} is {found[0]}x{found[1]} but the frames are {source.width}x"
                         f"{source.height}: masks must have the size of the source frames")
    return folder


FRAME_BOXES = (b"mdat", b"moof")  # the top-level boxes of an MP4 or MOV that hold frames or their places


def _cut_frame_box(path) -> tuple[bytes, int] | None:
    """(type, bytes missing) of the top-level box of an MP4 or MOV file that runs past its end,
    when it is one that holds frames (FRAME_BOXES): a cut fragmented MP4 ends inside one, which its
    index cannot tell. None for a whole file, or one cut in a box that holds none (its last index)."""
    size = os.path.getsize(path)
    at = 0
    with open(path, "rb") as f:
        while size - at >= 8:  # a box header: 32-bit size (1: a 64-bit size follows; 0: to the end), type
            f.seek(at)
            head = f.read(16)
            length, kind = int.from_bytes(head[:4], "big"), head[4:8]
            if length == 1 and len(head) == 16:
                length = int.from_bytes(head[8:16], "big")
            if length < 8:  # 0: to the end; else not a box: trailing bytes that FFmpeg ignores too
                return None
            if at + length > size:
                return (kind, at + length - size) if kind in FRAME_BOXES else None
            at += length
    return None


def _video_index(container, stream, path) -> tuple[list, list, int]:
    """(pts, keyframe flags) of the stream's shown packets in file order (those an edit list hides
    left out), and the count of packets stored (those hidden included), read without decoding.
    InputError for a file shorter than its own index: an MP4, MOV or AVI whose index lists more
    frames than its bytes hold (frames an edit list hides count as held), an MP4 whose last frame
    box runs past its end (`_cut_frame_box`), an MKV, WebM or fragmented MP4 whose packets end more
    than two frames before the duration its header declares; and for a Motion JPEG frame that
    declares more pixels than its bytes can hold (each is a JPEG: `jpeg_size`)."""
    import io

    pts, keys = [], []
    stored = 0  # packets in the file, those an edit list hides included: what the index counts
    end = None  # seconds: where the last packet of any stream ends
    mjpeg = stream.codec_context.name == "mjpeg"
    for packet in container.demux():  # every stream: the demuxer reads them all anyway
        if packet.size == 0:  # the flush packet
            continue
        if packet.pts is not None and packet.time_base is not None:
            ends = float((packet.pts + (packet.duration or 0)) * packet.time_base)
            end = ends if end is None else max(end, ends)
        if packet.stream.index != stream.index:
            continue
        stored += 1
        if packet.is_discard:  # a frame the edit list hides (a trim's lead-in, a phone's last frame)
            continue
        if mjpeg:
            data = io.BytesIO(bytes(packet))
            found = jpeg_size(data) if data.read(2) == b"\xff\xd8" else None
            if found is not None and found[2] > packet.size:
                raise InputError(f"video {path}: frame {len(pts)} declares a {found[0]}x{found[1]} JPEG, more than "
                                 f"its {packet.size:,} bytes can hold: the file is corrupt; replace it")
        pts.append(packet.pts)
        keys.append(bool(packet.is_keyframe))
    listed = int(stream.frames or 0)  # what the container's index lists (0: it does not say)
    if listed > stored:
        raise InputError(f"video {path}: its index lists {listed} frames but the file holds {stored}: it is "
                         f"truncated (an interrupted copy or download); copy it again")
    cut = _cut_frame_box(path) if "mp4" in container.format.name else None
    if cut is not None:
        raise InputError(f"video {path}: its last {cut[0].decode('latin-1')} box lacks {cut[1]:,} bytes of its "
                         f"frames: it is truncated (an interrupted copy or download); copy it again")
    if not listed and pts:  # no count to check (MKV, WebM, fragmented MP4): the duration its header declares
        declared = (container.duration or 0) / 1e6
        fps = _frame_rate(stream, pts)[0]
        frame = 1 / fps if fps else 0.1
        covered = (end or 0.0) - (container.start_time or 0) / 1e6
        if declared - covered > 2 * frame + 0.005 * declared:
            raise InputError(f"video {path}: its header says it lasts {declared:.2f} s but its frames end at "
                             f"{max(covered, 0.0):.2f} s: it is truncated (an interrupted copy or download); copy "
                             "it again")
    return pts, keys, stored


def _read_video_file(path: Path, sel: slice, spec, max_side, report):
    """Decode the frames of video file `path` that `sel` picks: (fps or None, the total frame count,
    the kept source frame numbers, the _Frames holding them, the frames decoded, the frames its edit
    list hides).

    Frame k is the k-th in presentation order. The index (one pass over the packets, no decoding)
    gives the count, each packet's time and the keyframes: decoding seeks to the last keyframe at or
    before the first selected frame and stops after the last one."""
    import av

    from tomgs.constants import MAX_SIDE

    try:
        container = _open_av(path)
    except (av.error.FFmpegError, UnicodeDecodeError, ValueError) as e:
        raise _unreadable(path, e) from None
    idx, k, total = [], -1, 0  # what was read when FFmpeg fails: nothing, while the index is read
    try:
        if not container.streams.video:
            raise InputError(f"cannot open video {path}: it holds no video stream; {RE_ENCODE}")
        stream = container.streams.video[0]
        if stream.codec_context is None:
            raise InputError(f"cannot decode video {path}: no decoder for its video codec; {RE_ENCODE}")
        w, h = stream.codec_context.width, stream.codec_context.height
        if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
            raise InputError(f"video {path} declares {w}x{h} frames; frames are 1..{MAX_SIDE} pixels a side: "
                             f"the file is corrupt, or {RE_ENCODE}")
        pts, keys, stored = _video_index(container, stream, path)
        fps = _frame_rate(stream, pts)[0]
        total = len(pts)
        if total == 0:
            raise InputError(f"video {path} has zero readable frames: the file is empty or corrupt; {RE_ENCODE}")
        wanted = range(total)[sel]
        if not wanted:
            raise InputError(f"frame range {spec!r} selects no frames of {path} ({total} frames): "
                             f"pick a range inside 0:{total}")
        # presentation order: frame k has the k-th smallest time; without distinct times, decode order
        timed = None not in pts and len(set(pts)) == total
        order = sorted(pts) if timed else None
        rank = {t: k for k, t in enumerate(order)} if timed else {}
        # the decoder gives frames in presentation order; their times say which frame each is (a
        # frame it drops is seen missing), unless they are decode-order times: an AVI's B-frames
        # come out reordered under the times of the packets that carried them, so they are counted
        by_count = not timed or bool(stream.codec_context.has_b_frames and pts == order)
        start = 0  # back from the end of the index pass: to the keyframe before the first wanted frame
        if timed and wanted[0] > 0:
            first = order[wanted[0]]
            start = rank[max((t for t, key in zip(pts, keys) if key and t <= first), default=order[0])]
        if timed:
            container.seek(order[start], stream=stream, backward=True, any_frame=False)
        else:
            container.seek(0)
        _check_budget(path, len(wanted), *_resized_size(h, w, max_side))  # before a frame is decoded
        stream.thread_type = "AUTO"  # frame threads: phone clips decode several times faster
        # each thread holds a frame: as many as DECODE_BYTES of frames of the declared size allow
        stream.codec_context.thread_count = max(1, min(os.cpu_count() or 1, DECODE_BYTES // (w * h * 3)))
        kept = _Frames(path, max_side, len(wanted))
        todo, chosen = wanted[-1] + 1 - start, set(wanted)
        idx, decoded, k = [], 0, start - 1
        for frame in container.decode(stream):
            decoded += 1
            k = k + 1 if by_count else rank.get(frame.pts, k + 1)
            report(min(decoded, todo), todo)
            if k > wanted[-1]:
                break
            if k not in chosen or (idx and k <= idx[-1]):
                continue
            if kept.size is None and (frame.width, frame.height) not in {(w, h), (h, w)}:  # rotation metadata
                raise InputError(f"video {path} decodes to {frame.width}x{frame.height} frames but its header "
                                 f"says {w}x{h}: the file is corrupt; {RE_ENCODE}")
            kept.add(_upright(frame.to_ndarray(format="rgb24"), frame), f"frame {k} of {path}", bgr=False)
            idx.append(k)
    except av.error.FFmpegError as e:
        if not total:
            raise _unreadable(path, e) from None
        before = f", or read the frames before it (--frames {idx[0]}:{k + 1})" if idx else ""
        raise InputError(f"video {path} does not decode at frame {k + 1} of {total} ({_reason(e)}): the "
                         f"file is damaged or cut short; copy it again{before}") from None
    finally:
        container.close()
    read = set(idx)
    lost = [j for j in wanted if j not in read]
    if lost:
        before = f", or read the frames before them (--frames {wanted[0]}:{lost[0]})" if lost[0] > wanted[0] else ""
        which = f"frame {lost[0]}" if len(lost) == 1 else f"{len(lost)} frames from {lost[0]} to {lost[-1]}"
        raise InputError(f"video {path}: {which} of {total} do not decode: the file is damaged or cut short; copy it "
                         f"again{before}")
    if kept.flat:
        raise InputError(f"video {path} decodes to {len(idx)} frame{'s' if len(idx) > 1 else ''} of one flat colour "
                         f"and nothing else: there is no picture to fit. A file of random or damaged bytes decodes "
                         f"like this; if the video is real, pick frames with content (--frames); else {RE_ENCODE}")
    return fps, total, idx, kept, decoded, stored - total


def _frame_rate(stream, pts) -> tuple[float | None, bool]:
    """(frames per second or None, whether it varies) of a video stream: its average rate, and
    whether the intervals between its shown frames' times `pts` differ by over a quarter."""
    import math

    rate = stream.average_rate or stream.guessed_rate
    fps = float(rate) if rate else None
    fps = fps if fps is not None and math.isfinite(fps) and 0 < fps <= 1000 else None
    times = sorted(t for t in pts if t is not None)
    steps = sorted(b - a for a, b in zip(times, times[1:]))
    return fps, len(steps) >= 2 and steps[-1] - steps[0] > steps[len(steps) // 2] / 4


def _turns(frame) -> int:
    """Quarter turns counter-clockwise that show `frame` upright: phone clips store portrait frames
    sideways with a display rotation (counter-clockwise degrees), which players apply."""
    return round((getattr(frame, "rotation", 0) or 0) / 90) % 4


def _upright(image: np.ndarray, frame) -> np.ndarray:
    """The frame as it is shown (`_turns`)."""
    import numpy as np

    turns = _turns(frame)
    return np.ascontiguousarray(np.rot90(image, turns)) if turns else image


def _read_masks(folder: Path, source: Source, idx, size: tuple[int, int]) -> np.ndarray:
    """bool [len(idx), *size] from a folder with one mask per frame of `source` (of its size), each
    resized (nearest) to `size` as it is read."""
    import numpy as np

    import cv2

    files = list_images(check_masks(folder, source))
    h, w = source.height, source.width
    out = np.empty((len(idx), *size), dtype=bool)
    for k, i in enumerate(idx):
        m = read_image(files[i], cv2.IMREAD_GRAYSCALE)
        if m.shape != (h, w):
            raise InputError(f"mask {files[i]} is {m.shape[1]}x{m.shape[0]} but the frames are {w}x{h}: "
                             "masks must have the size of the source frames")
        if m.shape != size:
            m = cv2.resize(np.where(m > 127, 255, 0).astype(np.uint8), (size[1], size[0]),
                           interpolation=cv2.INTER_NEAREST)
        out[k] = m > 127
    return out


def read_video_for(path, cameras) -> np.ndarray:
    """uint8 [T,H,W,3]: the frames of `path` that `cameras` (a tomgs.Cameras) were made for, picked by
    source frame number and resized as `read_video` resizes, so a scene meets its own training frames.
    Only the frames the scene has are converted (a regular step is read as a stepped range)."""
    import numpy as np

    numbers = np.asarray(cameras.frame_indices, dtype=np.int64)
    sel = None
    if len(numbers):
        steps = np.unique(np.diff(numbers))
        step = int(steps[0]) if len(steps) == 1 and steps[0] > 0 else 1
        sel = slice(int(numbers.min()), int(numbers.max()) + 1, step)
    clip = read_video(path, frames=sel, max_side=max(cameras.width, cameras.height))
    position = {int(s): i for i, s in enumerate(clip.indices)}
    missing = [int(s) for s in numbers if int(s) not in position]
    if missing:
        raise InputError(f"{path} has {len(clip)} frames but the scene was fitted on source frame {missing[0]}; "
                         "give the video the scene was fitted on")
    order = [position[int(s)] for s in numbers]
    frames = clip.frames if order == list(range(len(clip))) else clip.frames[order]
    if frames.shape[1:3] != (cameras.height, cameras.width):
        raise InputError(f"{path} gives {frames.shape[2]}x{frames.shape[1]} frames but the scene is "
                         f"{cameras.width}x{cameras.height}; give the video the scene was fitted on")
    return frames


def read_video_against(path, cameras) -> tuple[np.ndarray, list[int], list[str]]:
    """What of `path` can be compared with a scene's `cameras` whatever the video (`eval --force`):
    (uint8 [N,H,W,3] frames, the positions in `cameras` they stand for, notes saying what was done):
    the scene's frames that the video has, by source frame number, each resized to the scene's size.
    InputError when the video has none of them."""
    import cv2
    import numpy as np

    numbers = np.asarray(cameras.frame_indices, dtype=np.int64)
    source, name = probe_source(path), Path(path).name
    keep = [k for k, s in enumerate(numbers) if s < source.frames]
    if not keep:
        raise InputError(f"{path} has {source.frames} frames, none of the scene's (source frames {numbers.min()} to "
                         f"{numbers.max()}): nothing to compare")
    wanted = numbers[keep]
    steps = np.unique(np.diff(wanted))
    step = int(steps[0]) if len(steps) == 1 and steps[0] > 0 else 1  # a regular step read as a stepped range
    clip = read_video(path, frames=slice(int(wanted.min()), int(wanted.max()) + 1, step),
                      max_side=max(cameras.width, cameras.height))
    position = {int(s): i for i, s in enumerate(clip.indices)}
    keep = [k for k in keep if int(numbers[k]) in position]
    frames = clip.frames[[position[int(numbers[k])] for k in keep]]
    notes = [] if len(keep) == len(numbers) else \
        [f"compared the {len(keep)} of the scene's {len(numbers)} frames that {name} has"]
    if frames.shape[1:3] != (cameras.height, cameras.width):
        frames = np.stack([cv2.resize(f, (cameras.width, cameras.height), interpolation=cv2.INTER_AREA)
                           for f in frames])
        notes.append(f"{name}'s {source.width}x{source.height} frames resized to the scene's "
                     f"{cameras.width}x{cameras.height}")
    return frames, keep, notes


THUMB = 4  # frames and masks are compared (a resume, an eval) as THUMB x THUMB area averages
THUMB_TOLERANCE = 2.0  # grey levels: decoders differ by less, another video or crop by more


def thumbnails(images) -> np.ndarray:
    """uint8 [T, THUMB * THUMB * C]: each image (uint8 or bool [T,H,W(,C)]) as area averages, what
    identifies a clip's frames."""
    import numpy as np

    import cv2

    out = []
    for image in images:
        image = np.asarray(image, dtype=np.uint8) * (255 if image.dtype == bool else 1)
        out.append(np.asarray(cv2.resize(image, (THUMB, THUMB), interpolation=cv2.INTER_AREA)).reshape(-1))
    return np.stack(out) if out else np.zeros((0, THUMB * THUMB * 3), np.uint8)


def differing_thumbnails(a: np.ndarray, b: np.ndarray) -> int:
    """How many rows of thumbnails `b` differ from `a`'s by more than THUMB_TOLERANCE (all of them
    when their shapes differ)."""
    import numpy as np

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape:
        return len(b)
    return int(np.sum(np.abs(a - b).max(axis=1, initial=0.0) > THUMB_TOLERANCE))


def clip_record(clip: Video) -> dict:
    """What a scene keeps of the clip it was fitted on (its info's "clip", JSON), so that `tomgs eval`
    knows its video again: the source's frame count and size, and each fitted frame's thumbnail
    (base64 of uint8 [T, THUMB * THUMB * 3])."""
    import base64

    record = {"thumbnails": base64.b64encode(thumbnails(clip.frames).tobytes()).decode("ascii")}
    if clip.source_frames:
        record["source_frames"] = int(clip.source_frames)
    if clip.source_size is not None:
        record["source_size"] = [int(clip.source_size[1]), int(clip.source_size[0])]  # width, height
    return record


def video_differences(path, cameras, record: dict | None) -> tuple[list[str], list[str]]:
    """(what makes a comparison impossible, what else differs) between the video `path` and the clip
    that a scene with `cameras` and clip record `record` (`clip_record`, None for a scene without
    one) was fitted on, read from the video's index and header (`probe_source`) without decoding:
    frame count and size as recorded; the aspect and the frame numbers the cameras need."""
    source = probe_source(path)
    record = record or {}
    impossible, differ = [], []
    name = Path(path).name
    last = int(cameras.frame_indices.max()) if len(cameras) else -1
    if last >= source.frames:
        impossible.append(f"{name} has {source.frames} frame{'s' if source.frames != 1 else ''}, the scene was "
                          f"fitted on source frame {last}")
    h, w = _resized_size(source.height, source.width, max(cameras.width, cameras.height))
    if (h, w) != (cameras.height, cameras.width):
        impossible.append(f"{name}'s frames are {source.width}x{source.height} (width / height "
                          f"{source.width / source.height:.3f}), the scene's {cameras.width}x{cameras.height} "
                          f"({cameras.width / cameras.height:.3f})")
    frames = record.get("source_frames")
    if isinstance(frames, int) and frames != source.frames and not impossible:
        differ.append(f"{name} has {source.frames} frame{'s' if source.frames != 1 else ''}, the scene's clip "
                      f"had {frames}")
    size = record.get("source_size")
    if isinstance(size, list) and size != [source.width, source.height] and not impossible:
        differ.append(f"{name} is {source.width}x{source.height}, the scene's clip was {size[0]}x{size[1]}")
    return impossible, differ


def frame_differences(path, frames: np.ndarray, record: dict | None) -> list[str]:
    """What differs between `frames` (uint8 [T,H,W,3], read from `path` for a scene by
    `read_video_for`) and the thumbnails of the scene's clip record (`clip_record`): nothing for a
    scene without them."""
    import numpy as np

    import base64
    import binascii

    text = (record or {}).get("thumbnails")
    if not isinstance(text, str):
        return []
    try:
        stored = np.frombuffer(base64.b64decode(text, validate=True), np.uint8)
    except (binascii.Error, ValueError):
        return []
    row = THUMB * THUMB * 3
    if stored.size != len(frames) * row:
        return []
    differ = differing_thumbnails(stored.reshape(-1, row), thumbnails(frames))
    if not differ:
        return []
    return [f"{differ} of the scene's {len(frames)} frames differ from {Path(path).name}'s (another clip, crop or "
            "grade)"]


RE_ENCODE = "re-encode it (e.g. ffmpeg -i in.mov -c:v libx264 out.mp4) or extract its frames to a folder"


def _reason(error: Exception) -> str:
    """What FFmpeg (or PyAV) said, without the file name it adds (the message names it once)."""
    return str(getattr(error, "strerror", None) or error).strip()[:200]


def _unreadable(path, error: Exception) -> InputError:
    """The refusal of a video file that FFmpeg cannot open or index: corrupt, not a video, or cut
    short (an MP4 whose index is at the end loses it)."""
    return InputError(f"cannot open video {path} ({_reason(error)}): the file is unreadable, corrupt or cut short; "
                      f"copy it again if it is an interrupted copy or download, else {RE_ENCODE}")


def _open_av(path):
    """av.open of a video file, undecodable metadata ignored where PyAV has the option (<= 18; 19
    dropped it and no longer fails on such metadata)."""
    import av

    try:
        return av.open(str(path), metadata_errors="ignore")
    except TypeError:
        return av.open(str(path))
