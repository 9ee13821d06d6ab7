"""Frames out: an MP4/AVI/MOV/MKV file or a folder of numbered PNGs, written atomically.

Everything is written under a temporary name next to the target and moved into place at the end,
so an interrupted or failed write never leaves a half-written output behind. An existing output
is replaced only with `overwrite=True`; in a folder, that replaces and removes only numbered frame
PNGs (`00012.png`, the files tomgs writes there) and keeps every other file.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from tomgs.errors import InputError
from tomgs.outputs import check_file_output, check_folder_output, publish

# suffix -> codec: H.264 (yuv420p, index first) through PyAV for the containers browsers and players
# read (OpenCV's mp4v, MPEG-4 Part 2, plays in no browser); Motion JPEG through OpenCV for .avi
VIDEO_SUFFIXES = {".mp4": "h264", ".mov": "h264", ".mkv": "h264", ".avi": "mjpg"}
H264_CRF = 18  # x264's constant quality: visually lossless for rendered frames
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
    output is refused unless `overwrite`, and then replaced only on success."""
    import cv2

    path = check_output(path, overwrite)
    is_video = bool(path.suffix)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
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
                if not cv2.imwrite(str(target / f"{number:05d}.png"), frame[..., ::-1]):
                    raise InputError(f"{path}: could not write PNG frame {number}")
            count += 1
        if writer is not None:
            writer.close()
            writer = None
        if count == 0:
            raise InputError(f"{path}: no frames to write")
        if is_video or not path.exists():
            publish(target, path)
        else:
            _merge_frames(staging, path)
    finally:
        if writer is not None:
            writer.close()
        shutil.rmtree(staging, ignore_errors=True)
    return count


class _H264Writer:
    """H.264 High profile, yuv420p, constant quality H264_CRF, the index at the front of the file
    (`+faststart`: a browser starts playing before the whole file is loaded). yuv420p needs even
    sides: an odd width or height is padded by repeating the last column or row."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        from fractions import Fraction

        import av

        self.container = av.open(str(path), "w", options={"movflags": "+faststart"})
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": str(H264_CRF), "profile": "high"}
        self.pad = ((0, height % 2), (0, width % 2), (0, 0))
        self.av = av

    def write(self, rgb: np.ndarray) -> None:
        if any(self.pad[0] + self.pad[1]):
            rgb = np.pad(rgb, self.pad, mode="edge")
        for packet in self.stream.encode(self.av.VideoFrame.from_ndarray(rgb, format="rgb24")):
            self.container.mux(packet)

    def close(self) -> None:
        try:
            for packet in self.stream.encode():  # flush the encoder's delayed frames
                self.container.mux(packet)
        finally:
            self.container.close()


class _MJPGWriter:
    """Motion JPEG in AVI through OpenCV."""

    def __init__(self, path: Path, fps: float, width: int, height: int):
        import cv2

        self.writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
        if not self.writer.isOpened():
            raise InputError(f"{path.name}: OpenCV cannot write .avi here; write .mp4 or PNG frames to a folder")

    def write(self, rgb: np.ndarray) -> None:
        self.writer.write(np.ascontiguousarray(rgb[..., ::-1]))

    def close(self) -> None:
        self.writer.release()


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
