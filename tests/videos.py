"""Real-world video variants made with PyAV from a small source: what phones, editors and stream
copies write (edit lists, B-frames, rotations, other containers) and what damage leaves."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np

W, H = 64, 48


def picture(k: int, w: int = W, h: int = H) -> np.ndarray:
    """Frame k (< 150): its number on the left half as red 8 (k % 30) and blue 50 (k // 30), a white
    block at the top left (which way is up), a horizontal green ramp."""
    image = np.zeros((h, w, 3), np.uint8)
    image[:, : w // 2, 0] = 8 * (k % 30)
    image[:, : w // 2, 2] = 50 * (k // 30)
    image[:, :, 1] = np.linspace(0, 200, w, dtype=np.uint8)[None]
    image[: h // 4, : w // 4] = 255
    return image


def frame_numbers(frames: np.ndarray) -> list[int]:
    """The k of each frame that `picture` drew (read from its red left half)."""
    def number(f):
        half = f[f.shape[0] // 2 :, 2 : f.shape[1] // 2 - 2].reshape(-1, 3).mean(0)
        return int(round(half[0] / 8)) + 30 * int(round(half[2] / 50))

    return [number(f) for f in frames]


def encode(path: Path, count: int = 40, codec: str = "libx264", rate=30, size=(W, H), options=None,
           bframes: int = 2, gop: int = 10, audio_first: bool = False, container_options=None,
           pix_fmt: str = "yuv420p", turn: int = 0, stamps=None) -> Path:
    """`count` frames of `picture` encoded with `codec` into `path` (its suffix picks the
    container), each stored turned `turn` quarter turns counter-clockwise (`size` is as shown);
    frame k shown at `stamps[k]` milliseconds where given (a variable frame rate)."""
    import av

    w, h = size if turn % 2 == 0 else size[::-1]
    with av.open(str(path), "w", options=container_options or {}) as out:
        if audio_first:
            audio = out.add_stream("aac", rate=48000)
        stream = out.add_stream(codec, rate=rate)
        stream.width, stream.height, stream.pix_fmt = w, h, pix_fmt
        if stamps is not None:
            stream.codec_context.time_base = Fraction(1, 1000)
        stream.codec_context.gop_size = gop
        opts = {"bf": str(bframes)} if codec in ("libx264", "mpeg4") else {}
        if codec == "libx264":
            opts.update(sc_threshold="0", crf="12")
        if codec == "libx265":
            opts.update(crf="12")
        stream.options = {**opts, **(options or {})}
        if audio_first:
            for n in range(count * 48000 // 1024 // int(rate) + 1):  # the clip's length of silence
                samples = av.AudioFrame.from_ndarray(np.zeros((1, 1024), np.float32), format="fltp", layout="mono")
                samples.sample_rate, samples.pts = 48000, n * 1024
                for packet in audio.encode(samples):
                    out.mux(packet)
        for k in range(count):
            image = np.ascontiguousarray(np.rot90(picture(k, *size), turn))
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            if stamps is not None:
                frame.pts, frame.time_base = stamps[k], Fraction(1, 1000)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
        if audio_first:
            for packet in audio.encode():
                out.mux(packet)
    return path


def stream_copy(source: Path, path: Path, start: int, stop: int | None = None) -> Path:
    """What `ffmpeg -ss -i source -c copy path` writes when the cut at frame `start` misses a
    keyframe: the packets from the keyframe before it, those before `start` given negative times
    (the MP4 muxer writes an edit list that hides them); up to frame `stop` (None: the end)."""
    import av

    with av.open(str(source)) as src:
        vin = src.streams.video[0]
        packets = [p for p in src.demux(vin) if p.size]
    times = sorted(p.pts for p in packets)
    cut = times[start]
    keys = [p for p in packets if p.is_keyframe and p.pts <= cut]
    first_key = max(keys, key=lambda p: p.pts)
    begin = packets.index(first_key)
    end = None if stop is None else times[stop]
    with av.open(str(source)) as src, av.open(str(path), "w") as out:
        vin = src.streams.video[0]
        vout = out.add_stream_from_template(vin)
        for n, p in enumerate(src.demux(vin)):
            if not p.size or n < begin:
                continue
            if end is not None and p.pts >= end:
                continue
            p.pts -= cut
            p.dts -= cut
            p.stream = vout
            out.mux(p)
    return path


def hide_last(source: Path, path: Path, frames: int = 1, fps: float = 30) -> Path:
    """`source` (an MP4 with an edit list) with its edit `frames` frames shorter: the last ones
    stay stored, as phones and editors leave them, but are not shown."""
    data = bytearray(source.read_bytes())
    at = data.find(b"elst") + 4
    assert data[at] == 0 and int.from_bytes(data[at + 4 : at + 8], "big") == 1  # version 0, one edit
    scale = int.from_bytes(data[data.find(b"mvhd") + 16 : data.find(b"mvhd") + 20], "big")
    shown = int.from_bytes(data[at + 8 : at + 12], "big") - round(frames * scale / fps)
    data[at + 8 : at + 12] = shown.to_bytes(4, "big")
    path.write_bytes(bytes(data))
    return path


def rotate(source: Path, path: Path, degrees: int) -> Path:
    """`source` (an MP4 of one track) with a display matrix that turns its frames `degrees`
    clockwise when shown, as a phone writes it for a clip held upright or upside down."""
    data = bytearray(source.read_bytes())
    at = data.find(b"tkhd") + 4
    at += 40 + (12 if data[at] == 1 else 0)  # the matrix, after the times, duration, layer and volume
    cos, sin = {0: (1, 0), 90: (0, 1), 180: (-1, 0), 270: (0, -1)}[degrees % 360]
    for n, value in enumerate((cos, sin, 0, -sin, cos, 0, 0, 0, 1 << 14)):  # 16.16 fixed point, w 2.30
        data[at + 4 * n : at + 4 * n + 4] = ((value << 16) if n != 8 else value).to_bytes(4, "big", signed=True)
    path.write_bytes(bytes(data))
    return path


def damage(source: Path, path: Path, frame: int, zero: bool = False) -> Path:
    """`source` with the middle of the packet of frame `frame` (in file order) overwritten by
    random bytes, or the whole packet zeroed."""
    import av

    with av.open(str(source)) as src:
        packets = [(p.pos, p.size) for p in src.demux(src.streams.video[0]) if p.size]
    pos, size = packets[frame]
    data = bytearray(source.read_bytes())
    if zero:
        data[pos : pos + size] = bytes(size)
    else:
        data[pos + size // 3 : pos + 2 * size // 3] = np.random.default_rng(frame).bytes(2 * size // 3 - size // 3)
    path.write_bytes(bytes(data))
    return path


def cut(source: Path, path: Path, percent: float) -> Path:
    """The first `percent` % of `source`'s bytes: an interrupted copy or download."""
    data = source.read_bytes()
    path.write_bytes(data[: int(len(data) * percent / 100)])
    return path
