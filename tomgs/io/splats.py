"""Static 3DGS files for other tools: the INRIA PLY, antimatter15's `.splat`, Niantic's `.spz` and
PlayCanvas's `.sog` (tomgs.io.sog).

Each writer takes one `StaticGaussians` (what `tomgs.edit.export.static_moment` makes of a moment of a
clip) and writes atomically. The layouts, as the readers expect them:

    .ply    one `vertex` element of float32: x y z nx ny nz f_dc_0..2 f_rest_* (channel-major)
            opacity (logit) scale_0..2 (log) rot_0..3 (w x y z); no comment, no other element,
            `element vertex N` on line 3 (SIBR reads a fixed 62-float row: SH degree 3)
    .splat  32 bytes a Gaussian, largest first (exp(sum of log scales) x opacity): position
            3 x float32, scale 3 x float32 (linear), RGBA 4 x uint8 ((0.5 + C0 f_dc) 255, opacity
            255), rotation 4 x uint8 (unit quaternion w x y z, 128 q + 128)
    .spz    gzip of a 16-byte header (magic "NGSP", version 3, N, SH degree, fractional bits,
            flags, 0) and the sections positions (24-bit fixed point), alphas, colours
            (0.15 x 255 f_dc + 127.5), scales ((log + 10) 16), rotations (smallest three in 32 bits)
            and SH rest (128 + 128 x coefficient, coefficient-major then channel), each a uint8
            rounding; lossy by design (about 1/4096 of a unit in position at 12 fractional bits).
            SPZ keeps its data in RUB axes (x right, y up, z back; Niantic's spz library converts
            on load): our OpenCV (RDF) axes turn half round x, y and z negated, quaternions
            (w, x, -y, -z), SH coefficients odd in y + z negated (SPZ_SH_FLIPS)
"""

from __future__ import annotations

import gzip
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tomgs.constants import SH_C0, sh_degree_of
from tomgs.io.kinds import STATIC_FORMATS
from tomgs.io.sog import sog_bytes
from tomgs.outputs import atomic_file

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")  # StaticGaussians' arrays


@dataclass
class StaticGaussians:
    """Gaussians of one moment in the stored form static tools read, float32 numpy:
    means [N,3], quats [N,4] (w x y z, raw), log_scales [N,3], opacity_logits [N] (opacity at that
    moment), sh_dc [N,3], sh_rest [N,K-1,3] (K = (degree + 1)^2; K-1 = 0 for degree 0)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(self.sh_rest.shape[1] + 1)

    def rows(self, index) -> StaticGaussians:
        """The Gaussians `index` (a bool mask or indices) picks."""
        return StaticGaussians(*(getattr(self, name)[index] for name in FIELDS))

    def with_sh_degree(self, degree: int) -> StaticGaussians:
        """SH truncated or padded with zeros to `degree` (0..3)."""
        rest = (degree + 1) ** 2 - 1
        sh_rest = np.zeros((len(self), rest, 3), np.float32)
        keep = min(rest, self.sh_rest.shape[1])
        sh_rest[:, :keep] = self.sh_rest[:, :keep]
        return StaticGaussians(self.means, self.quats, self.log_scales, self.opacity_logits, self.sh_dc, sh_rest)


def write_static(path, gaussians: StaticGaussians) -> Path:
    """Write `gaussians` in the format of `path`'s extension (STATIC_FORMATS), atomically."""
    path = Path(path)
    writers = {".ply": _ply_bytes, ".splat": _splat_bytes, ".spz": _spz_bytes, ".sog": sog_bytes}
    writer = writers.get(path.suffix.lower())
    if writer is None:
        raise ValueError(f"unknown static format {path.suffix!r}; one of {', '.join(STATIC_FORMATS)}")
    data = writer(gaussians)
    with atomic_file(path, durable=True) as tmp:
        Path(tmp).write_bytes(data)
    return path


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x.astype(np.float64)))


def _ply_bytes(g: StaticGaussians) -> bytes:
    from tomgs.io.scene import inria_properties, ply_header

    n = len(g)
    columns = [g.means, np.zeros((n, 3), np.float32), g.sh_dc,
               g.sh_rest.transpose(0, 2, 1),  # channel-major, as INRIA
               g.opacity_logits[:, None], g.log_scales, g.quats]
    # each column's width from its own shape: reshape(n, -1) cannot tell it when n = 0
    rows = np.concatenate([np.asarray(c, np.float32).reshape(n, math.prod(np.shape(c)[1:])) for c in columns],
                          axis=1).astype("<f4")
    names = inria_properties(g.sh_degree)
    assert rows.shape == (n, len(names))
    return ply_header(names, n) + np.ascontiguousarray(rows).tobytes()


def _unit_quats(quats: np.ndarray) -> np.ndarray:
    """float64 unit quaternions [N,4] (a zero quaternion is the identity, as the renderer reads it)."""
    q = quats.astype(np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])


def _bytes(x) -> np.ndarray:
    """uint8 of values in [0, 255] (rounded, clipped)."""
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _splat_bytes(g: StaticGaussians) -> bytes:
    n = len(g)
    opacity = _sigmoid(g.opacity_logits)
    order = np.argsort(-(np.exp(g.log_scales.astype(np.float64).sum(axis=1)) * opacity), kind="stable")
    rows = np.zeros(n, dtype=[("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])
    rows["position"] = g.means
    rows["scale"] = np.exp(g.log_scales.astype(np.float64))
    rows["rgba"][:, :3] = _bytes((0.5 + SH_C0 * g.sh_dc.astype(np.float64)) * 255.0)
    rows["rgba"][:, 3] = _bytes(opacity * 255.0)
    rows["rotation"] = _bytes(_unit_quats(g.quats) * 128.0 + 128.0)
    return rows[order].tobytes()


SPZ_MAGIC = 0x5053474E  # "NGSP"
SPZ_VERSION = 3  # smallest-three rotations; Niantic's loader and gsply read versions 1-3
SPZ_COLOR_SCALE = 0.15


def spz_fractional_bits(means: np.ndarray) -> int:
    """The most fractional bits (<= 12, Niantic's default) whose 24-bit fixed point holds every position."""
    reach = float(np.abs(means).max()) if len(means) else 0.0
    bits = 12
    while bits > 0 and reach * (1 << bits) >= (1 << 23) - 1:
        bits -= 1
    if reach * (1 << bits) >= (1 << 23) - 1:
        raise ValueError(f"positions up to {reach:g} do not fit SPZ's 24-bit fixed point (at most {(1 << 23) - 1})")
    return bits


def _smallest_three(quats: np.ndarray) -> np.ndarray:
    """uint32 [N]: unit quaternions (w x y z in) packed as SPZ v3 stores them: x y z w order, the
    largest component's index in the top 2 bits (made positive), the other three as sign + 9-bit
    magnitude of |c| / (1/sqrt 2), the last axis in the lowest bits."""
    xyzw = _unit_quats(quats)[:, [1, 2, 3, 0]]
    largest = np.argmax(np.abs(xyzw), axis=1)
    xyzw *= np.where(xyzw[np.arange(len(xyzw)), largest] < 0, -1.0, 1.0)[:, None]
    packed = np.zeros(len(xyzw), np.uint32)
    for axis in range(4):
        keep = largest != axis
        value = xyzw[:, axis]
        magnitude = np.clip(np.rint(np.abs(value) * np.sqrt(2.0) * 511.0), 0, 511).astype(np.uint32)
        field = ((value < 0).astype(np.uint32) << 9) | magnitude
        packed = np.where(keep, (packed << 10) | field, packed)
    return packed | (largest.astype(np.uint32) << 30)


# signs of the 15 SH rest coefficients (3DGS order: degree 1 y z x; degree 2 xy yz z^2 xz x^2-y^2; degree 3
# y(3x^2-y^2) xyz y(4z^2-..) z(2z^2-..) x(4z^2-..) z(x^2-y^2) x(x^2-3y^2)) when y and z change sign
SPZ_SH_FLIPS = np.array([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], np.float64)
RDF_TO_RUB = np.array([1.0, -1.0, -1.0])


def _spz_bytes(g: StaticGaussians) -> bytes:
    n, degree = len(g), g.sh_degree
    means = g.means.astype(np.float64) * RDF_TO_RUB
    quats = g.quats.astype(np.float64) * np.array([1.0, 1.0, -1.0, -1.0])  # conjugated by the half turn about x
    sh_rest = g.sh_rest.astype(np.float64) * SPZ_SH_FLIPS[:g.sh_rest.shape[1], None]
    bits = spz_fractional_bits(means)
    fixed = np.rint(means * (1 << bits)).astype(np.int64) & 0xFFFFFF  # two's complement
    positions = np.stack([(fixed >> shift) & 0xFF for shift in (0, 8, 16)], axis=-1).astype(np.uint8)  # [N,3,3]
    sections = [
        positions.reshape(-1),
        # 1..254: the format's reader decodes a byte as the logit of byte / 255, infinite at 0 and 255
        np.clip(_bytes(_sigmoid(g.opacity_logits) * 255.0), 1, 254),
        _bytes(g.sh_dc.astype(np.float64) * (SPZ_COLOR_SCALE * 255.0) + 127.5).reshape(-1),
        _bytes((g.log_scales.astype(np.float64) + 10.0) * 16.0).reshape(-1),
        _smallest_three(quats).astype("<u4").view(np.uint8),
        _bytes(sh_rest * 128.0 + 128.0).reshape(-1),
    ]
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, SPZ_VERSION, n, degree, bits, 0, 0)
    return gzip.compress(header + b"".join(s.tobytes() for s in sections), compresslevel=6, mtime=0)
