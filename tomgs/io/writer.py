"""Frames out: an MP4/AVI/MOV/MKV file or a folder of numbered PNGs, written atomically.

Everything is written under a temporary name next to the target and moved into place at the end,
so an interrupted or failed write never leaves a half-written output behind. An existing output
is replaced only with `overwrite=True`; in a folder, that replaces and removes only numbered frame
PNGs (`00012.png`, the files tomgs writes there) and keeps every other file.
"""

from __future__ import annotations

import errno
import os
import re
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from tomgs.errors import InputError
from tomgs.outputs import check_file_output, check_folder_output, discard, publish, temporary, write_failed

if TYPE_CHECKING:
    import numpy as np

# suffix -> codec: H.264 (yuv420p, index first) through PyAV for the containers browsers and players
# read (OpenCV's mp4v, MPEG-4 Part 2, plays in no browser); Motion JPEG through OpenCV for .avi
VIDEO_SUFFIXES = {".mp4": "h264", ".mov": "h264", ".mkv": "h264", ".avi": "mjpg"}
H264_CRF = 18  # x264's constant quality: visually lossless for rendered frames
FPS_RANGE = (0.1, 1000.0)  # frames per second a video is written at (containers store the rate as a fraction)
_FRAME_PNG = re.compile(r"\d{5,}\.png")


def is_frame_png(name: str) -> bool:
    """True for the names tomgs gives PNG frames in an output folder (00000.png, ...)."""
    return bool(_FRAME_PNG.fullmatch(name))


def check_output(path, overwrite: bool = False) -> Path:
    """`path` as a Path when `write_frames` can write there now (a video suffix, or none for a
    folder of PNGs, in an existing writable folder; an existing output only with `overwrite`),
    else InputError saying how to proceed; lets a command check before any work."""
    path = Path(path)
    if path.suffix and path.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"{path}: unknown output type {path.suffix!r}; use one of "
                         f"{', '.join(sorted(VIDEO_SUFFIXES))} or a folder name without a suffix for PNG frames")
    if path.suffix:
        return check_file_output(path, overwrite, what="video")
    return check_folder_output(path, is_frame_png, overwrite)


def write_frames(frames: Iterable[np.ndarray], path, fps: float = 25.0, numbers: Iterable[int] | None = None,
                 overwrite: bool = False) -> int:
    """Write RGB uint8 frames [H,W,3] to `path`: a video file by suffix, else a folder of PNGs
    named by `numbers` (the frames' numbers, e.g. the scene's frame numbers; default 0, 1, ...),
    zero-padded to five digits: 00000.png, .... Returns the number of frames written. Existing
    output is refused unless `overwrite`, and then replaced only on success. Frames are staged in a
    temporary folder beside `path` (tomgs.outputs.temporary), removed on every exit path; the video
    writer is closed once. An OSError while writing (a full disk) names `path` and what was kept."""
    import numpy as np

    import cv2

    path = check_output(path, overwrite)
    is_video = bool(path.suffix)
    if is_video and not (isinstance(fps, (int, float)) and FPS_RANGE[0] <= fps <= FPS_RANGE[1]):
        raise InputError(f"{path}: {fps!r} frames per second; a video is written at "
                         f"{FPS_RANGE[0]:g}..{FPS_RANGE[1]:g}")
    staging = temporary(path, folder=True)
    count = 0
    writer = None
    names = None if numbers is None else iter(numbers)
    try:
        target = staging / f"out{path.suffix}" if is_video else staging
        for frame in frames:
            frame = np.ascontiguousarray(frame)
            if frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
                raise ValueError(f"frames must be uint8 [H,W,3], got {frame.dtype} {frame.shape}")
            if is_video:
                if writer is None:
                    make = _H264Writer if VIDEO_SUFFIXES[path.suffix.lower()] == "h264" else _MJPGWriter
                    writer = make(target, fps, frame.shape[1], frame.shape[0])
                writer.write(frame)
            else:
                number = count if names is None else int(next(names))
                ok, png = cv2.imencode(".png", frame[..., ::-1])
                if not ok:
                    raise InputError(f"{path}: could not encode PNG frame {number}")
                with open(target / f"{number:05d}.png", "wb") as f:
                    f.write(png.tobytes())
            count += 1
        if writer is not None:
            writer, closing = None, writer  # closed once, whether or not its close succeeds
            closing.close()
        if count == 0:
            raise InputError(f"{path}: no frames to write")
        if is_video or not path.exists():
            publish(target, path)
        else:
            _merge_frames(staging, path)
    except OSError as e:
        raise write_failed(e, path, None if is_video or not path.exists() else
                           "the frames already in the folder are kept") from None
    finally:
        if writer is not None:  # an exception before the close: release the writer, its error aside
            try:
                writer.close()
            except OSError:
                pass
        discard(staging)
    return count


class _Sink:
    """The file an H.264 container writes through: a write, read or seek that fails (a full disk; a
    buffered file's read and seek flush its pending bytes first) is kept in `error` rather than
    raised into FFmpeg, which would go on writing and seeking (PyAV prints each error after the
    first); the writer raises it after the call. A failed sink takes no more bytes, reads nothing
    and answers a seek with the error's negative number, as FFmpeg's own files do."""

    def __init__(self, path: Path):
        self.file = open(path, "w+b")  # noqa: SIM115 - closed by the writer's close()
        self.name = str(path)  # faststart opens the file again by its name to move the index to the front
        self.error: OSError | None = None

    def write(self, data: bytes) -> int:
        if self.error is None:
            try:
                self.file.write(data)
            except OSError as e:
                self.error = e
        return len(data)

    def read(self, size: int = -1) -> bytes:
        if self.error is None:
            try:
                return self.file.read(size)
            except OSError as e:
                self.error = e
        return b""

    def seek(self, offset: int, whence: int = 0) -> int:
        if self.error is None:
            try:
                return self.file.seek(offset, whence)
            except OSError as e:
                self.error = e
        return -(self.error.errno or errno.EIO)

    def tell(self) -> int:
        return self.file.tell()

    @property
    def closed(self) -> bool:
        return self.file.closed

    def check(self) -> None:
        if self.error is not None:
            raise self.error

    def close(self) -> None:
        try:
            self.file.close()  # its last bytes reach the disk here: a full disk may show only now
        except OSError as e:
            self.error = self.error or e


class _H264Writer:
    """H.264 High profile, yuv420p, constant quality H264_CRF, the index at the front of the file
    (`+faststart`: a browser starts playing before the whole file is loaded). yuv420p needs even
    sides: an odd width or height is padded by repeating the last column or row. The container
    writes through a `_Sink`; after a failed write the sink is closed before the container, which
    PyAV takes as no index to write (FFmpeg's faststart would build it by reading back a torn file:
    a segmentation fault)."""

    CONTAINERS = {".mp4": "mp4", ".mov": "mov", ".mkv": "matroska"}

    def __init__(self, path: Path, fps: float, width: int, height: int):
        from fractions import Fraction

        import av

        self.sink = _Sink(path)
        try:
            kind = self.CONTAINERS[path.suffix.lower()]
            self.container = av.open(self.sink, "w", format=kind,
                                     options={"movflags": "+faststart"} if kind in ("mp4", "mov") else {})
            self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        except BaseException:
            self.sink.close()
            raise
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(H264_CRF), "profile": "high"}
        self.pad = ((0, height % 2), (0, width % 2), (0, 0))
        self.av = av

    def write(self, rgb: np.ndarray) -> None:
        import numpy as np

        if any(self.pad[0] + self.pad[1]):
            rgb = np.pad(rgb, self.pad, mode="edge")
        for packet in self.stream.encode(self.av.VideoFrame.from_ndarray(rgb, format="rgb24")):
            self.container.mux(packet)
        self.sink.check()

    def close(self) -> None:
        """Flush the encoder's delayed frames and write the index (neither after a failed write);
        the container and the file are released either way. Call once."""
        try:
            if self.sink.error is None:
                for packet in self.stream.encode():
                    self.container.mux(packet)
        finally:
            if self.sink.error is not None:
                self.sink.close()
            try:
                self.container.close()
            finally:
                self.sink.close()
        self.sink.check()


class _MJPGWriter:
    """Motion JPEG in AVI through OpenCV."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        import cv2

        self.level = cv2.utils.logging.getLogLevel()  # its warning a frame on a full disk: the close says it once
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        self.writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
        if not self.writer.isOpened():
            cv2.utils.logging.setLogLevel(self.level)
            raise InputError(f"{path.name}: OpenCV cannot write .avi here; write .mp4 or PNG frames to a folder")
        self.path, self.count = path, 0

    def write(self, rgb: np.ndarray) -> None:
        import numpy as np

        self.writer.write(np.ascontiguousarray(rgb[..., ::-1]))
        self.count += 1

    def close(self) -> None:
        """Release the writer, then read the file's index back: OpenCV's writer does not report a
        failed write (a full disk), a file short of frames does."""
        import cv2

        try:
            self.writer.release()
        finally:
            cv2.utils.logging.setLogLevel(self.level)
        video = cv2.VideoCapture(str(self.path))
        found = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if video.isOpened() else 0
        video.release()
        if found != self.count:
            full = os.statvfs(self.path.parent).f_bavail == 0 if hasattr(os, "statvfs") else False
            code = errno.ENOSPC if full else errno.EIO
            raise OSError(code, f"{os.strerror(code)} (the video holds {found} of its {self.count} frames)",
                          str(self.path))


def _merge_frames(staging: Path, folder: Path) -> None:
    """Move the staged frames into the existing `folder`, then remove its other frame PNGs (an
    earlier render's, which would otherwise mix with this one); other files are kept."""
    written = set()
    for entry in os.scandir(staging):
        publish(entry.path, folder / entry.name)
        written.add(entry.name)
    for entry in os.scandir(folder):
        if is_frame_png(entry.name) and entry.name not in written and entry.is_file(follow_symlinks=False):
            os.unlink(entry.path)
