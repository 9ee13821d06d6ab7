"""Picking Gaussians: by a 3D box or sphere, a time window, an index list, or per-frame masks.

Selectors are written as text (the CLI's `--select`), all in world (OpenCV) axes and clip time:
    box:x0,y0,z0,x1,y1,z1   means inside the axis-aligned box with these two corners
    sphere:x,y,z,r          means within distance r of (x, y, z)
    time:t0,t1              alive (o_i(t) >= 1/255) somewhere in the clip-time window [t0, t1]
    index:FILE.txt          the scene indices listed in the file (whitespace or comma separated)
    mask:FOLDER             means that project inside the masks (white = selected) in most of the
                            frames where the Gaussian is alive and in view; one mask per scene frame,
                            or one per source frame (picked by the scene's frame numbers)
Several selectors intersect. A selection that matches nothing raises InputError.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from tomgs.errors import InputError

if TYPE_CHECKING:
    import numpy as np

SYNTAX = "box:x0,y0,z0,x1,y1,z1, sphere:x,y,z,r, time:t0,t1, index:FILE.txt or mask:FOLDER"
_NUMBERS = {"box": 6, "sphere": 4, "time": 2}


@dataclass(frozen=True)
class Selector:
    """One parsed `--select`: kind in box/sphere/time/index/mask, numbers or a path, and its text."""

    kind: str
    numbers: tuple[float, ...] = ()
    path: str | None = None
    text: str = ""


def parse_selector(text: str) -> Selector:
    """'kind:arguments' -> Selector; InputError naming the syntax when it does not parse."""
    kind, sep, rest = str(text).partition(":")
    kind = kind.strip().lower()
    if not sep or kind not in (*_NUMBERS, "index", "mask") or not rest.strip():
        raise InputError(f"--select {text!r}: use {SYNTAX}")
    if kind in ("index", "mask"):
        return Selector(kind, path=rest.strip(), text=text)
    try:
        numbers = tuple(float(v) for v in rest.split(","))
    except ValueError:
        numbers = ()
    if len(numbers) != _NUMBERS[kind] or not all(math.isfinite(v) for v in numbers):
        raise InputError(f"--select {text!r}: {kind} takes {_NUMBERS[kind]} comma-separated numbers; use {SYNTAX}")
    if kind == "sphere" and numbers[3] <= 0:
        raise InputError(f"--select {text!r}: the sphere's radius must be positive")
    return Selector(kind, numbers, text=text)


def select(model, cameras, selectors) -> np.ndarray:
    """Sorted scene indices int64 [n] of the Gaussians of `model` (a GaussianModel seen by `cameras`)
    that every selector (Selector or text) picks; all Gaussians when there is none."""
    import numpy as np

    selectors = [s if isinstance(s, Selector) else parse_selector(s) for s in selectors]
    means = model.means.detach().cpu().double().numpy()
    keep = np.ones(len(means), dtype=bool)
    for s in selectors:
        keep &= _pick(s, model, cameras, means)
    if not keep.any():
        described = " and ".join(repr(s.text) for s in selectors) or "(all)"
        raise InputError(f"selection {described} matches nothing among the scene's {len(means):,} Gaussians: "
                         f"widen it (`tomgs info` shows the scene; boxes and spheres are in world axes, x right, "
                         f"y down, z forward)")
    return np.flatnonzero(keep)


def _pick(s: Selector, model, cameras, means: np.ndarray) -> np.ndarray:
    import numpy as np

    if s.kind == "box":
        lo, hi = np.minimum(s.numbers[:3], s.numbers[3:]), np.maximum(s.numbers[:3], s.numbers[3:])
        return ((means >= lo) & (means <= hi)).all(1)
    if s.kind == "sphere":
        return np.linalg.norm(means - np.array(s.numbers[:3]), axis=1) <= s.numbers[3]
    if s.kind == "time":
        return _alive_between(model, min(s.numbers), max(s.numbers))
    if s.kind == "index":
        return _index_file(Path(s.path), len(means))
    return mask_vote(model, cameras, read_masks(Path(s.path), cameras))


def _temporal(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float64 (opacities, t_means, t_scales) [N] of `model`."""
    return tuple(v.detach().cpu().double().numpy() for v in (model.opacities, model.t_means, model.t_scales))


def _alive_between(model, t0: float, t1: float) -> np.ndarray:
    """bool [N]: o_i(t) >= 1/255 for some t in [t0, t1] (tomgs.temporal, float64)."""
    from tomgs.temporal import alive_between

    return alive_between(*_temporal(model), t0, t1)


def _index_file(path: Path, n: int) -> np.ndarray:
    import numpy as np

    if not path.is_file():
        raise InputError(f"--select index:{path}: the file does not exist; give a text file of Gaussian indices")
    limit = 32 * n + 2**20  # room for every index, repeated, with separators and comments of a sane file
    if path.stat().st_size > limit:
        raise InputError(f"{path}: {path.stat().st_size:,} bytes is more than an index file of {n:,} Gaussians "
                         f"can need ({limit:,}); give a text file of Gaussian indices")
    try:
        idx = np.array([int(v) for v in path.read_text().replace(",", " ").split()], dtype=np.int64)
    except (ValueError, OverflowError, UnicodeDecodeError):  # OverflowError: a number past int64
        raise InputError(f"{path}: an index file holds whole numbers 0..{n - 1} separated by spaces, commas or "
                         f"lines") from None
    bad = idx[(idx < 0) | (idx >= n)]
    if len(bad):
        raise InputError(f"{path}: index {bad[0]} is outside the scene's Gaussians 0..{n - 1}")
    keep = np.zeros(n, dtype=bool)
    keep[idx] = True
    return keep


def read_masks(folder: Path, cameras) -> np.ndarray:
    """bool [T,H,W] at the scene's image size, one per scene frame, from a folder of mask images:
    one per scene frame, or one per source frame (then picked by the scene's frame numbers)."""
    import numpy as np

    import cv2

    from tomgs.io.images import read_image
    from tomgs.io.video import list_images

    if not folder.is_dir():
        raise InputError(f"mask folder {folder} does not exist: give a folder with one mask image per frame")
    files = list_images(folder)
    T, numbers = len(cameras), cameras.frame_indices
    if len(files) == T:
        picked = files
    elif len(files) > int(numbers.max()):
        picked = [files[int(i)] for i in numbers]
    else:
        raise InputError(f"{folder} holds {len(files)} masks; the scene has {T} frames numbered "
                         f"{int(numbers.min())}..{int(numbers.max())}: give one mask per scene frame or per source frame")
    out = np.empty((T, cameras.height, cameras.width), dtype=bool)
    for k, f in enumerate(picked):  # masks of the source frames may be larger than a --max-side fit
        m = read_image(f, cv2.IMREAD_GRAYSCALE)
        out[k] = cv2.resize(m, (cameras.width, cameras.height), interpolation=cv2.INTER_NEAREST) > 127
    return out


def mask_vote(model, cameras, masks: np.ndarray) -> np.ndarray:
    """bool [N]: the Gaussian's mean falls inside `masks` [T,H,W] in more than half of the frames where
    it is alive (o_i(t_k) >= 1/255) and in front of the camera inside the image."""
    import numpy as np

    from tomgs.temporal import alive_at

    means = model.means.detach().cpu().double().numpy()
    window = _temporal(model)
    inside = np.zeros(len(means), dtype=np.int64)
    seen = np.zeros(len(means), dtype=np.int64)
    for k, w2c in enumerate(cameras.viewmats()):
        cam = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.maximum(cam[:, 2], 1e-12)
        u = np.floor(cameras.K[0, 0] * cam[:, 0] / z + cameras.K[0, 2]).astype(np.int64)  # pixel u covers [u, u+1)
        v = np.floor(cameras.K[1, 1] * cam[:, 1] / z + cameras.K[1, 2]).astype(np.int64)
        alive = alive_at(*window, cameras.times[k])
        ok = alive & (cam[:, 2] > 0.01) & (u >= 0) & (u < cameras.width) & (v >= 0) & (v < cameras.height)
        seen += ok
        inside[ok] += masks[k, v[ok], u[ok]]
    return 2 * inside > seen
