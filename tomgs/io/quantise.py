"""Quantisation and lossless image coding of per-Gaussian attributes, shared by the compressed
scene (tomgs.io.tsog) and PlayCanvas's SOG export (tomgs.io.sog).

    signed_log / fixed           positions' transform, sign(x) log(1 + |x|), and values between a min and
                                 a max as unsigned integers of some bits (with their inverses)
    morton_order(cells)          the order that sorts integer 3D or 4D cells along a Z-order curve
    grid_shape(n) / grid_image   the 2D grid a sorted cloud is laid out on, in rows, and an image of it
    codebook / encode_codebook   a 256-entry 1D k-means codebook of values, and each value's index
    palette                      a k-means palette of vectors (SH rest), labels and centroids
    smallest_three / unpack_quats   unit quaternions as three 8-bit components and the largest's index
    encode_webp / decode_webp    lossless WebP (Pillow) of uint8 [H, W, C] images; the decoder checks
                                 the image's size and mode before it decodes a pixel

Everything here is numpy or torch on the CPU, vectorised: a million Gaussians take seconds.
"""

from __future__ import annotations

import io
import warnings
from typing import TYPE_CHECKING

import numpy as np

from tomgs.errors import InputError

if TYPE_CHECKING:
    import torch

WEBP_MAX_SIDE = 16383  # the most pixels a WebP image has on a side (libwebp's limit)
CODEBOOK_SIZE = 256
_HISTOGRAM_BINS = 1 << 16  # codebook k-means runs on a histogram of this many bins: O(bins) a step
_CODEBOOK_STEPS = 40


# ---- fixed point ---------------------------------------------------------------------------------

def signed_log(x: np.ndarray) -> np.ndarray:
    """sign(x) log(1 + |x|), float64: positions' transform (SOG's), fine near 0 and coarse far out."""
    x = np.asarray(x, np.float64)
    return np.sign(x) * np.log1p(np.abs(x))


def signed_exp(v: np.ndarray) -> np.ndarray:
    """The inverse of `signed_log`, float64."""
    v = np.asarray(v, np.float64)
    return np.sign(v) * np.expm1(np.abs(v))


def fixed(values: np.ndarray, lo, hi, bits: int) -> np.ndarray:
    """int64: float `values` between `lo` and `hi` (broadcast) as round((v - lo) / (hi - lo) (2^bits - 1)),
    clipped to 0 .. 2^bits - 1 (a range of zero width gives 0)."""
    top = (1 << bits) - 1
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    span = np.where(hi > lo, hi - lo, 1.0)
    return np.clip(np.rint((np.asarray(values, np.float64) - lo) / span * top), 0, top).astype(np.int64)


def unfixed(q: np.ndarray, lo, hi, bits: int) -> np.ndarray:
    """float64: the inverse of `fixed`."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return lo + np.asarray(q, np.float64) / ((1 << bits) - 1) * (hi - lo)


# ---- positions about a centre, times about the clip ---------------------------------------------------

POLAR_DEPTHS = 20.0  # log r spans at most this (a ratio of 5e8): points nearer the centre than that clamp to it


def polar(points: np.ndarray, centre) -> np.ndarray:
    """float64 [N, 3]: `points` [N, 3] as (u, v, log r) about `centre`: (u, v) in [-1, 1]^2 the
    octahedral map of the direction, r the distance. A step in u or v is an angle, in log r a ratio:
    quantised on one grid, a point's error is a fixed fraction of its distance from the centre (a
    fraction of a pixel for a camera near the centre), however far the farthest point is."""
    d = np.asarray(points, np.float64) - np.asarray(centre, np.float64)
    r = np.linalg.norm(d, axis=1)
    unit = np.where(r[:, None] > 0, d / np.where(r > 0, r, 1.0)[:, None], [0.0, 0.0, 1.0])
    uv = unit[:, :2] / np.abs(unit).sum(1, keepdims=True)
    folded = (1.0 - np.abs(uv[:, ::-1])) * np.where(uv >= 0, 1.0, -1.0)
    uv = np.where(unit[:, 2:] < 0, folded, uv)
    with np.errstate(divide="ignore"):
        return np.concatenate([uv, np.log(r)[:, None]], axis=1)


def unpolar(coords: np.ndarray, centre) -> np.ndarray:
    """float64 [N, 3]: the points of `polar`'s (u, v, log r) [N, 3]."""
    coords = np.asarray(coords, np.float64)
    uv = coords[:, :2]
    z = 1.0 - np.abs(uv).sum(1)
    folded = (1.0 - np.abs(uv[:, ::-1])) * np.where(uv >= 0, 1.0, -1.0)
    xy = np.where(z[:, None] < 0, folded, uv)
    unit = np.concatenate([xy, z[:, None]], axis=1)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    return np.asarray(centre, np.float64) + unit * np.exp(coords[:, 2:])


def linear_range(t: np.ndarray) -> list[float]:
    """[lo, hi]: where `squash` keeps values linear: the quartiles widened by twice the interquartile
    range, inside [min, max] (a stray value, even a quarter of them, stays out of it)."""
    t = np.asarray(t, np.float64)
    if len(t) == 0:
        return [0.0, 1.0]
    q1, q3 = np.quantile(t, [0.25, 0.75])
    return [float(max(t.min(), q1 - 2 * (q3 - q1))), float(min(t.max(), q3 + 2 * (q3 - q1)))]


def squash(t: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """float64: `t` unchanged inside [lo, hi] and logarithmic past it (lo - L log(1 + (lo - t) / L)
    below, L = hi - lo or 1): a stray value far out widens a fixed-point range by its log only."""
    t = np.asarray(t, np.float64)
    span = hi - lo if hi > lo else 1.0
    return np.where(t > hi, hi + span * np.log1p(np.maximum(t - hi, 0) / span),
                    np.where(t < lo, lo - span * np.log1p(np.maximum(lo - t, 0) / span), t))


def unsquash(s: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """float64: the inverse of `squash`."""
    s = np.asarray(s, np.float64)
    span = hi - lo if hi > lo else 1.0
    with np.errstate(over="ignore"):
        return np.where(s > hi, hi + span * np.expm1(np.maximum(s - hi, 0) / span),
                        np.where(s < lo, lo - span * np.expm1(np.maximum(lo - s, 0) / span), s))


# ---- order and layout ---------------------------------------------------------------------------

_SPREAD = {  # (shift, mask) steps that move bit k of a value to bit k * dims (the classic magic numbers)
    3: ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F), (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249)),
    4: ((24, 0x000000FF000000FF), (12, 0x000F000F000F000F), (6, 0x0303030303030303), (3, 0x1111111111111111)),
}


def _spread(v: np.ndarray, dims: int) -> np.ndarray:
    """uint64 [N]: the bits of `v` (< 2^(64 // dims)) spread `dims` apart (bit k moves to k * dims)."""
    v = v.astype(np.uint64) & np.uint64((1 << (64 // dims)) - 1)
    for shift, mask in _SPREAD[dims]:
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def morton_order(cells: np.ndarray) -> np.ndarray:
    """int64 [N]: the stable order of integer cells [N, D] (D = 3 or 4, each < 2^(64 // D)) along a
    Z-order curve, the first column in the lowest bit of each triple or quadruple."""
    cells = np.asarray(cells)
    dims = cells.shape[1]
    code = np.zeros(len(cells), np.uint64)
    for axis in range(dims):
        code |= _spread(cells[:, axis], dims) << np.uint64(axis)
    return np.argsort(code, kind="stable")


def grid_shape(n: int) -> tuple[int, int]:
    """(width, height) of the grid `n` Gaussians are laid out on in rows, k-th of the sort at pixel k
    (row k // width): both sides multiples of 4, about square, as PlayCanvas's SOG sizes its images.
    Rows beat a tiled Z-order layout: WebP predicts a pixel from its left neighbour best, and along
    a row that is the previous Gaussian of the sort (camel's first fit: 10.2 against 10.5 bytes a
    Gaussian)."""
    width = max(4, 4 * int(np.ceil(np.sqrt(max(n, 1)) / 4)))
    return width, max(4, 4 * int(np.ceil(max(n, 1) / width / 4)))


def grid_image(values: np.ndarray, width: int, height: int) -> np.ndarray:
    """uint8 [height, width, C]: `values` [N, C] (in the grid's order) row by row, the pixels past N
    repeating the last value (nothing new for the coder; zeros when N = 0)."""
    values = np.asarray(values, np.uint8)
    grid = np.empty((width * height, values.shape[1]), np.uint8)
    grid[len(values):] = values[-1] if len(values) else 0
    grid[:len(values)] = values
    return grid.reshape(height, width, values.shape[1])


# ---- codebooks ----------------------------------------------------------------------------------

OUTLIER_FENCE = 3.0  # values past the quartiles by this many interquartile ranges are outliers (Tukey's far
OUTLIER_ENTRIES = 8  # fence; 4.7 sigma of a normal bulk): up to this many entries a side of their own


def codebook(values: np.ndarray, size: int = CODEBOOK_SIZE) -> np.ndarray:
    """float32 [size], ascending: a 1D k-means codebook of `values` (any shape, finite). Values that
    fill at most `size` bins come back exactly as they are (the rest of the book repeats the largest).
    Otherwise the values past OUTLIER_FENCE interquartile ranges from the quartiles get up to
    OUTLIER_ENTRIES entries a side of their own (their quantiles, the extreme value included), and
    the rest k-means (`_lloyd`) on the values between: a stray value cannot pull entries out of the
    bulk nor coarsen its histogram."""
    v = np.asarray(values, np.float64).ravel()
    if len(v) == 0:
        return np.zeros(size, np.float32)
    distinct = np.unique(v)
    if len(distinct) <= size:
        return distinct[np.minimum(np.arange(size), len(distinct) - 1)].astype(np.float32)
    q1, q3 = np.quantile(v, [0.25, 0.75])
    low, high = q1 - OUTLIER_FENCE * (q3 - q1), q3 + OUTLIER_FENCE * (q3 - q1)
    below, above = v[v < low], v[v > high]
    ends = []
    for side in (below, above):
        k = min(OUTLIER_ENTRIES, len(np.unique(side)))
        ends.append(np.quantile(side, np.linspace(0.0, 1.0, k)) if k else np.zeros(0))
    inner = v[(v >= low) & (v <= high)]
    bulk = _lloyd(inner, size - len(ends[0]) - len(ends[1]))
    return np.sort(np.concatenate([ends[0], bulk, ends[1]])).astype(np.float32)


def _lloyd(v: np.ndarray, size: int) -> np.ndarray:
    """float64 [size] ascending: Lloyd steps weighted by a histogram of _HISTOGRAM_BINS bins of `v`
    (each bin stands for its values' mean), from the values' quantiles, so a step costs O(bins)
    whatever the count; the bins' means when they are `size` or fewer."""
    lo, hi = float(v.min()), float(v.max())
    if hi == lo:
        return np.full(size, lo)
    bins = np.minimum(((v - lo) / (hi - lo) * _HISTOGRAM_BINS).astype(np.int64), _HISTOGRAM_BINS - 1)
    count = np.bincount(bins, minlength=_HISTOGRAM_BINS).astype(np.float64)
    sums = np.bincount(bins, weights=v, minlength=_HISTOGRAM_BINS)
    used = count > 0
    weight, centre = count[used], sums[used] / count[used]  # ascending: bins are
    if len(centre) <= size:
        return np.concatenate([centre, np.full(size - len(centre), centre[-1])])
    cumulative = np.concatenate([[0.0], np.cumsum(weight)])
    moments = np.concatenate([[0.0], np.cumsum(centre * weight)])
    # started where squared error wants them in the end (a density of the values' to the 1/3), not at the
    # values' quantiles: Lloyd steps move entries into sparse tails slowly
    spread = np.cumsum(weight ** (1.0 / 3.0))
    centroids = centre[np.searchsorted(spread, (np.arange(size) + 0.5) / size * spread[-1])]
    for _ in range(_CODEBOOK_STEPS):
        # each centroid takes the bins between the midpoints to its neighbours: a step is `size` searches
        edges = np.concatenate([[0], np.searchsorted(centre, (centroids[1:] + centroids[:-1]) / 2), [len(centre)]])
        mass = np.diff(cumulative[edges])
        total = np.diff(moments[edges])
        moved = np.sort(np.where(mass > 0, total / np.maximum(mass, 1e-300), centroids))
        if np.array_equal(moved, centroids):
            break
        centroids = moved
    return centroids


def encode_codebook(values: np.ndarray, book: np.ndarray) -> np.ndarray:
    """uint8 (shape of `values`): the index of the entry of `book` (ascending float32 [256]) nearest
    each value."""
    book = np.asarray(book, np.float64)
    v = np.asarray(values, np.float64)
    index = np.searchsorted((book[1:] + book[:-1]) / 2, v)
    return np.minimum(index, len(book) - 1).astype(np.uint8)


def palette(vectors: np.ndarray, size: int, steps: int = 6, sample: int = 1 << 16,
            seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(centroids float32 [K, D], labels int64 [N]) of k-means over `vectors` [N, D]: K = min(size,
    N) centroids from a random sample of at most `sample` rows refined `steps` Lloyd steps on that
    sample, then every row labelled with its nearest centroid (`_nearest`: past 256 centroids, the
    nearest of the centroids in the two groups of them nearest the row, of about sqrt(K) groups)."""
    import torch  # only here: reading a file with no palette loads no torch

    x = torch.from_numpy(np.ascontiguousarray(vectors, np.float32))
    n = x.shape[0]
    k = max(1, min(size, n))
    generator = torch.Generator().manual_seed(seed)
    rows = x[torch.randperm(n, generator=generator)[:min(n, max(sample, k))]]
    centroids = rows[torch.randperm(rows.shape[0], generator=generator)[:k]].clone()
    for _ in range(steps):
        label = _nearest(rows, centroids)
        total = torch.zeros_like(centroids).index_add_(0, label, rows)
        count = torch.bincount(label, minlength=k).to(rows.dtype)[:, None]
        centroids = torch.where(count > 0, total / count.clamp_min(1), centroids)
    return centroids.numpy(), _nearest(x, centroids).numpy()


def _nearest(x: torch.Tensor, centroids: torch.Tensor, probes: int = 2) -> torch.Tensor:
    """int64 [N]: a near centroid of each row of `x` [N, D]. Up to 256 centroids, the nearest (every
    distance); past that, the centroids are grouped by k-means into about sqrt(K) groups and a row
    takes the nearest centroid of its `probes` nearest groups': (1 + probes) sqrt(K) distances a row,
    not K (4,096 centroids: 192), now and then a second-best for a row far from every group centre."""
    import torch

    k = centroids.shape[0]
    if k <= 256:
        return _nearest_of_all(x, centroids)[0]
    groups = int(np.ceil(np.sqrt(k)))
    centres = centroids[torch.linspace(0, k - 1, groups).long()].clone()
    for _ in range(4):
        member = _nearest_of_all(centroids, centres)[0]
        total = torch.zeros_like(centres).index_add_(0, member, centroids)
        count = torch.bincount(member, minlength=groups).to(centres.dtype)[:, None]
        centres = torch.where(count > 0, total / count.clamp_min(1), centres)
    member = _nearest_of_all(centroids, centres)[0]
    members = torch.argsort(member)
    member_edges = torch.searchsorted(member[members], torch.arange(groups + 1)).tolist()
    near_groups = torch.cdist(x, centres).topk(min(probes, groups), dim=1, largest=False).indices  # [N, probes]
    best = torch.zeros(x.shape[0], dtype=torch.int64)
    best_distance = torch.full((x.shape[0],), float("inf"), dtype=x.dtype)
    for probe in range(near_groups.shape[1]):
        group = near_groups[:, probe]
        rows = torch.argsort(group)
        row_edges = torch.searchsorted(group[rows], torch.arange(groups + 1)).tolist()
        for j in range(groups):
            mine = rows[row_edges[j]:row_edges[j + 1]]
            candidates = members[member_edges[j]:member_edges[j + 1]]
            if len(mine) and len(candidates):
                label, distance = _nearest_of_all(x[mine], centroids[candidates])
                closer = distance < best_distance[mine]
                best[mine[closer]] = candidates[label[closer]]
                best_distance[mine[closer]] = distance[closer]
    return best


def _nearest_of_all(x: torch.Tensor, centroids: torch.Tensor,
                    chunk: int = 1 << 12) -> tuple[torch.Tensor, torch.Tensor]:
    """(int64 [N] the nearest of all `centroids` [K, D] to each row of `x` [N, D], its squared
    distance [N] less the row's own squared norm), in chunks of rows: memory O(chunk x K)."""
    import torch

    norms = centroids.square().sum(1)
    label = torch.empty(x.shape[0], dtype=torch.int64)
    distance = torch.empty(x.shape[0], dtype=x.dtype)
    for start in range(0, x.shape[0], chunk):
        block = x[start:start + chunk]
        distance[start:start + chunk], label[start:start + chunk] = (norms[None, :] - 2 * block @ centroids.T).min(1)
    return label, distance


# ---- quaternions ----------------------------------------------------------------------------------

QUAT_TAG = 252  # the fourth byte: 252 + the index (w x y z) of the largest component, as SOG stores it


def smallest_three(quats: np.ndarray) -> np.ndarray:
    """uint8 [N, 4]: quaternions (w x y z, any length; zero is the identity, as the renderer reads it)
    normalised and made positive in their largest component; the other three, in w x y z order,
    times sqrt(2) (so in [-1, 1]), as round(255 (c + 1) / 2); the fourth byte QUAT_TAG + the largest's
    index."""
    q = np.asarray(quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), [1.0, 0.0, 0.0, 0.0])
    largest = np.argmax(np.abs(q), axis=1)
    rows = np.arange(len(q))
    q = q * np.where(q[rows, largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    kept = np.take_along_axis(q, others, axis=1) * np.sqrt(2.0)
    out = np.empty((len(q), 4), np.uint8)
    out[:, :3] = np.clip(np.rint((kept + 1.0) * 127.5), 0, 255)
    out[:, 3] = QUAT_TAG + largest
    return out


def unpack_quats(packed: np.ndarray) -> np.ndarray:
    """float32 [N, 4] unit quaternions (w x y z) of `smallest_three`'s bytes [N, 4] (tags checked by
    the caller: QUAT_TAG..QUAT_TAG + 3)."""
    packed = np.asarray(packed)
    largest = packed[:, 3].astype(np.int64) - QUAT_TAG
    kept = (packed[:, :3].astype(np.float64) / 127.5 - 1.0) / np.sqrt(2.0)
    q = np.zeros((len(packed), 4), np.float64)
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    np.put_along_axis(q, others, kept, axis=1)
    q[np.arange(len(q)), largest] = np.sqrt(np.maximum(0.0, 1.0 - np.square(kept).sum(1)))
    return q.astype(np.float32)


# ---- lossless WebP ----------------------------------------------------------------------------------

WEBP_EFFORT = 0  # libwebp's lossless effort (Pillow's `quality`, 0..100) and method (0..6) below:
WEBP_METHOD = 1  # sorted grids gain under 1% from more effort, which costs 4-50x the time


def encode_webp(image: np.ndarray) -> bytes:
    """Lossless WebP of `image`, uint8 [H, W, C] (C = 1..4; one channel is stored grey, two as R and
    G of an RGB image whose B is zero)."""
    from PIL import Image, WebPImagePlugin  # noqa: F401  (registered: Pillow then skips importing every plugin)

    image = np.ascontiguousarray(image, np.uint8)
    channels = image.shape[2]
    if channels == 2:
        image = np.concatenate([image, np.zeros_like(image[:, :, :1])], axis=2)
    mode = {1: "L", 2: "RGB", 3: "RGB", 4: "RGBA"}[channels]
    picture = Image.fromarray(image[:, :, 0] if channels == 1 else image, mode)
    out = io.BytesIO()
    picture.save(out, "WEBP", lossless=True, quality=WEBP_EFFORT, method=WEBP_METHOD, exact=True)
    return out.getvalue()


def decode_webp(data: bytes, width: int, height: int, channels: int, what: str) -> np.ndarray:
    """uint8 [height, width, channels] of a lossless WebP that `encode_webp` wrote. The image's size
    is read from its header and checked against (width, height) before any pixel is decoded, so a
    small file that claims a huge image (a decompression bomb) costs nothing; InputError naming
    `what` for anything that is not such an image."""
    from PIL import Image, UnidentifiedImageError, WebPImagePlugin  # noqa: F401  (as in encode_webp)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the size check below is tighter than Pillow's bomb warning
            picture = Image.open(io.BytesIO(data), formats=["WEBP"])
            if picture.size != (width, height):
                raise InputError(f"{what} is a {picture.size[0]}x{picture.size[1]} image, not the {width}x{height} "
                                 f"grid the file declares")
            if getattr(picture, "n_frames", 1) != 1:
                raise InputError(f"{what} is an animation, not one image")
            picture.load()
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError) as e:
        raise InputError(f"{what} is not a readable lossless WebP image ({str(e)[:120]})") from None
    want = {1: ("L", "RGB", "RGBA"), 2: ("RGB", "RGBA"), 3: ("RGB", "RGBA"), 4: ("RGBA",)}[channels]
    if picture.mode not in want:
        raise InputError(f"{what} is a {picture.mode} image; the file declares {channels} channel(s)")
    array = np.asarray(picture)
    if array.ndim == 2:
        array = array[:, :, None]
    return np.ascontiguousarray(array[:, :, :channels])
