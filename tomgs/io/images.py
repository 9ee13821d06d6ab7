"""A folder's frames, one image at a time: the header read before any pixel (format, size, how many pixels
its bytes can hold at most) and the decoding of a checked image.

OpenCV is imported inside the functions so that `import tomgs` stays cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from tomgs.errors import InputError

if TYPE_CHECKING:
    import numpy as np


PNG_MAX_RATIO = 1032  # deflate's largest expansion: a PNG's pixels cannot outgrow 1032 x its bytes
TIFF_MAX_RATIO = 131072  # pixels a byte of a compressed TIFF can code at most (CCITT G4: a bit a row of 16384)


def jpeg_size(f) -> tuple[int, int, int] | None:
    """(width, height, least bytes) from the markers of a JPEG in the binary file `f`, positioned just
    after its SOI (FFD8); None for markers too damaged to say. Least bytes, by the frame's coding:
    baseline and extended Huffman, 2 bits per 8x8 block (a DC code and an end of block); progressive
    Huffman, 1 bit per block (its first DC scan codes every block); lossless, 1 bit per pixel; 0 for
    arithmetic or hierarchical coding, which can code a block for a small fraction of a bit."""
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
            least = {0xC0: blocks // 4, 0xC1: blocks // 4, 0xC2: blocks // 8, 0xC3: w * h // 8}.get(kind, 0)
            return w, h, least
        f.seek(length - 2, 1)
    return None


def _tiff_size(f, head: bytes) -> tuple[int, int, int] | None:
    """(width, height, least bytes) from a TIFF's first image directory; least: an uncompressed
    image's rows, else its pixels over TIFF_MAX_RATIO."""
    order = "little" if head[:2] == b"II" else "big"
    f.seek(int.from_bytes(head[4:8], order))
    count = int.from_bytes(f.read(2), order)
    entries = f.read(12 * min(count, 1000))
    tags = {}
    for at in range(0, len(entries) - 11, 12):
        entry = entries[at:at + 12]
        tag, kind, n = (int.from_bytes(entry[a:b], order) for a, b in ((0, 2), (2, 4), (4, 8)))
        width = 2 if kind == 3 else 4  # SHORT or LONG: the first of its values, inline or at its offset
        value = entry[8:8 + width]
        if n * width > 4:
            f.seek(int.from_bytes(entry[8:12], order))
            value = f.read(width)
        tags[tag] = int.from_bytes(value, order)
    if 256 not in tags or 257 not in tags:
        return None
    w, h = tags[256], tags[257]
    if tags.get(259, 1) == 1:
        bits = max(tags.get(258, 1), 1) * max(tags.get(277, 1), 1)
        return w, h, h * ((w * bits + 7) // 8)
    return w, h, w * h // TIFF_MAX_RATIO


def image_size(path: Path) -> tuple[int, int, str, int] | None:
    """(width, height, format, least bytes those pixels take in this format) that a PNG, JPEG, BMP or
    TIFF file declares in its header, read without decoding; None for other formats or a header too
    damaged to say. Least bytes: PNG, deflate's 1032:1 over one bit per pixel and the filter bytes;
    uncompressed BMP, its rows; RLE BMP, 2 bytes per 255 pixels; JPEG as `jpeg_size` says; TIFF as
    `_tiff_size` says; 0 where a format can code pixels for almost nothing (other BMP codings)."""
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
                found = jpeg_size(f)
                return None if found is None else (found[0], found[1], "jpeg", found[2])
            if head[:4] in (b"II*\x00", b"MM\x00*"):
                found = _tiff_size(f, head)
                return None if found is None else (found[0], found[1], "tiff", found[2])
    except OSError:
        return None
    return None


def check_image(path: Path) -> tuple[int, int, str, int]:
    """InputError when the image's header is not one of a PNG, JPEG, BMP or TIFF (OpenCV would decode
    other formats by their content, unchecked), declares a size beyond MAX_SIDE, or more pixels than
    its bytes can hold, before the decoder allocates it; else what image_size found."""
    from tomgs.constants import MAX_SIDE

    found = image_size(path)
    if found is None:
        raise InputError(f"cannot read image {path}: the file is corrupt or not a PNG, JPEG, BMP or TIFF image; "
                         "remove or replace it")
    w, h, kind, least = found
    if not (1 <= w <= MAX_SIDE and 1 <= h <= MAX_SIDE):
        raise InputError(f"{path}: its header declares a {w}x{h} image; frames are 1..{MAX_SIDE} pixels a side: "
                         "the file is corrupt, or resize it")
    if least > path.stat().st_size:
        raise InputError(f"{path}: its header declares a {w}x{h} {kind.upper()} image, more than its "
                         f"{path.stat().st_size:,} bytes can hold: the file is corrupt or truncated; replace it")
    return found


def read_image(path: Path, flags: int) -> np.ndarray:
    import cv2

    check_image(path)
    try:
        img = cv2.imread(str(path), flags)
    except cv2.error:
        img = None
    if img is None:
        raise InputError(f"cannot read image {path}: the file is corrupt or not an image; remove or replace it")
    return img
