"""The compressed scene file (.tsog): a scene's Gaussians quantised onto sorted 2D grids, each grid a
lossless WebP image, with the same clip (cameras, frame times, settings) a PLY scene carries.

`write_tsog(path, arrays, clip, records)` and `read_tsog(path)` move the stored parameters (float32
numpy, tomgs.model's names and shapes) of a scene; tomgs.io.scene's `save_scene` and `load_scene`
call them for a path ending in .tsog and for a file starting with MAGIC, so every command that reads
or writes a scene takes one. docs/scene-format.md gives the layout and the why; in short:

    MAGIC                              9 bytes, b"\\x89TSOG\\r\\n\\x1a\\n"
    u64 little endian L                the length of the header
    L bytes of JSON                    {"format": "tomgs-tsog", "version": 1, "count": N,
                                        "grid": [W, H], "images": [{"name", "channels", "bytes"}],
                                        one entry per attribute below with its dequantisation,
                                        "clip": the PLY scene's clip JSON (tomgs.io.scene)}
    the images, in "images" order      lossless WebP, W x H pixels each, Gaussian k at pixel k
                                       (row k // W); unused pixels repeat the last
    T camera records, 144 bytes each   as the PLY scene's (tomgs.io.scene.CAMERA_RECORD)

Attributes (Gaussians sorted along a Z-order curve of their quantised means):
    means          `bits` (16 by default) an axis of sign(x) log(1 + |x|) between the header's mins
                   and maxs, high bytes in image means_hi (RGB), low bytes in means_lo (RGB), as SOG
    quats          smallest three, 8 bits each, and 252 + the largest's index (RGBA), as SOG
    log_scales     indices (RGB) into a 256-entry codebook shared by the three axes
    sh_dc          indices (RGB) into a 256-entry codebook shared by the three channels
    opacities      index (grey) into a 256-entry codebook of sigmoid(opacity_logit)
    t_means        `bits` (16 by default) between the header's min and max: t_hi and t_lo (grey)
    log_t_scales   index (grey) into a 256-entry codebook
    sh_rest        (SH degree > 0 only) a palette of up to PALETTE_SIZE vectors: labels 16 bits
                   (sh_labels: R low byte, G high byte) and the palette as an image of 64 entries a
                   row, each entry (D+1)^2-1 pixels wide, RGB indices into a 256-entry codebook
A file is read with every size checked before the bytes it sizes are touched: the header's length
and JSON, the image sizes against the file's (they must add up exactly), each image's dimensions
against the grid before a pixel is decoded, and the count against the file's size (at most
MAX_GAUSSIANS_PER_BYTE Gaussians a byte): a small file cannot make the reader allocate much.
"""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import numpy as np

from tomgs.constants import sh_degree_of
from tomgs.errors import InputError, short_repr
from tomgs.io import quantise
from tomgs.outputs import atomic_file

MAGIC = b"\x89TSOG\r\n\x1a\n"  # PNG's pattern: a high byte, the name, CRLF and LF to catch text-mode copies
FORMAT = "tomgs-tsog"
VERSION = 1
SUFFIX = ".tsog"
MAX_HEADER = 64 << 20  # the header holds codebooks (kilobytes) and the clip's settings
MEANS_BITS = 16  # the default bits an axis of the means and of t_mean; a file may hold 1..16 (its header says)
T_MEANS_BITS = 16
PALETTE_SIZE = 4096  # most SH rest vectors in the palette (k-means on the CPU stays seconds at 1M)
PALETTE_ROW = 64  # palette entries per image row, as SOG
OPACITY_FLOOR = 1e-7  # opacities are stored in [1e-7, 1 - 1e-7]: logits of +-16, past what the renderer tells apart
FLOAT32_MAX = float(np.finfo(np.float32).max)
MAX_GAUSSIANS = 1 << 27  # a grid of 134M pixels: WebP's 16383-pixel sides hold it
MAX_GAUSSIANS_PER_BYTE = 64
"""A real scene takes bytes per Gaussian (sorted means alone need several); a file that declares
more Gaussians than 64 per byte is damaged or crafted, and is refused before anything is decoded."""
FIX = "write compressed scenes with `tomgs compress SCENE -o OUT.tsog` or `tomgs fit ... -o scene.tsog`"


def is_tsog(path) -> bool:
    """Whether the file `path` starts with MAGIC (False for a missing or unreadable file)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


# ---- the attributes' images --------------------------------------------------------------------

def _images(max_sh_degree: int) -> list[tuple[str, int]]:
    """(name, channels) of every image of a file of SH degree `max_sh_degree`, in file order."""
    images = [("means_hi", 3), ("means_lo", 3), ("quats", 4), ("scales", 3), ("colours", 3), ("opacities", 1),
              ("t_hi", 1), ("t_lo", 1), ("t_scales", 1)]
    return images + ([("sh_labels", 2), ("sh_palette", 3)] if max_sh_degree > 0 else [])


def encode_gaussians(arrays: dict, means_bits: int = MEANS_BITS,
                     t_bits: int = T_MEANS_BITS) -> tuple[dict, list[bytes], np.ndarray]:
    """(the header's attribute entries and grid, the images in _images order, the order [N]: the
    k-th Gaussian of the file is row order[k] of `arrays`). `arrays`: the stored parameters, float32
    numpy: means [N,3], quats [N,4], log_scales [N,3], opacity_logits [N], sh_dc [N,1,3], sh_rest
    [N,K-1,3], t_means [N], log_t_scales [N]. `means_bits` and `t_bits` (1..16): the precision of
    the means (an axis) and of t_mean; below 16 the high bytes' images hold fewer bits."""
    if not (1 <= means_bits <= 16 and 1 <= t_bits <= 16):
        raise ValueError(f"means_bits and t_bits must be 1..16, got {means_bits} and {t_bits}")
    n = len(arrays["means"])
    degree = sh_degree_of(arrays["sh_rest"].shape[1] + 1)
    f64 = {name: np.asarray(value, np.float64).reshape(n, int(np.prod(np.shape(value)[1:])))
           for name, value in arrays.items()}
    width, height = quantise.grid_shape(n)

    log_means = quantise.signed_log(f64["means"])
    lo, hi = (log_means.min(0), log_means.max(0)) if n else (np.zeros(3), np.zeros(3))
    q_means = quantise.fixed(log_means, lo, hi, means_bits)
    t = f64["t_means"][:, 0]
    t_lo, t_hi = (float(t.min()), float(t.max())) if n else (0.0, 0.0)
    q_t = quantise.fixed(t, t_lo, t_hi, t_bits)
    order = quantise.morton_order(q_means)  # t_mean left out of the curve: see docs/scene-format.md

    # opacities kept inside float32's logit range: an opacity that rounds to 0 or 1 has no logit to load
    opacities = np.clip(0.5 + 0.5 * np.tanh(0.5 * f64["opacity_logits"][:, 0]), OPACITY_FLOOR, 1.0 - OPACITY_FLOOR)
    books = {"scales": quantise.codebook(f64["log_scales"]), "colours": quantise.codebook(f64["sh_dc"]),
             "opacities": np.clip(quantise.codebook(opacities), OPACITY_FLOOR, 1.0 - OPACITY_FLOOR),
             "t_scales": quantise.codebook(f64["log_t_scales"])}
    columns = {
        "means_hi": (q_means >> 8).astype(np.uint8), "means_lo": (q_means & 0xFF).astype(np.uint8),
        "quats": quantise.smallest_three(f64["quats"]),
        "scales": quantise.encode_codebook(f64["log_scales"], books["scales"]),
        "colours": quantise.encode_codebook(f64["sh_dc"], books["colours"]),
        "opacities": quantise.encode_codebook(opacities, books["opacities"])[:, None],
        "t_hi": (q_t >> 8).astype(np.uint8)[:, None], "t_lo": (q_t & 0xFF).astype(np.uint8)[:, None],
        "t_scales": quantise.encode_codebook(f64["log_t_scales"], books["t_scales"]),
    }
    entries = {
        "means": {"mins": lo.tolist(), "maxs": hi.tolist(), "bits": means_bits},
        "quats": {},
        "log_scales": {"codebook": _short_floats(books["scales"])},
        "sh_dc": {"codebook": _short_floats(books["colours"])},
        "opacities": {"codebook": _short_floats(books["opacities"])},
        "t_means": {"min": t_lo, "max": t_hi, "bits": t_bits},
        "log_t_scales": {"codebook": _short_floats(books["t_scales"])},
    }
    palette_image = None
    if degree > 0:
        rest = f64["sh_rest"]  # [N, 3 (K-1)], coefficient-major as the model stores it
        centroids, labels = quantise.palette(rest, PALETTE_SIZE) if n else (np.zeros((1, rest.shape[1])),
                                                                            np.zeros(0, np.int64))
        book = quantise.codebook(centroids)
        count = len(centroids)
        coefficients = rest.shape[1] // 3
        cells = quantise.encode_codebook(centroids, book).reshape(count, coefficients, 3)
        rows = -(-count // PALETTE_ROW)
        padded = np.zeros((rows * PALETTE_ROW, coefficients, 3), np.uint8)
        padded[:count] = cells
        palette_image = padded.reshape(rows, PALETTE_ROW * coefficients, 3)
        columns["sh_labels"] = np.stack([labels & 0xFF, labels >> 8], axis=1).astype(np.uint8)
        entries["sh_rest"] = {"count": count, "codebook": _short_floats(book)}

    images = []
    for name, channels in _images(degree):
        if name == "sh_palette":
            images.append(quantise.encode_webp(palette_image))
            continue
        images.append(quantise.encode_webp(quantise.grid_image(columns[name].reshape(n, channels)[order], width,
                                                               height)))
    return dict(entries, count=n, grid=[width, height]), images, order


def _short_floats(book: np.ndarray) -> list[float]:
    """A float32 codebook as the shortest decimals that read back as the same float32 values (the
    header's JSON is then ~10 characters a value, not 20): decoded values are float32 in the end."""
    return [float(str(v)) for v in np.asarray(book, np.float32)]


def decode_gaussians(header: dict, images: dict[str, np.ndarray], what: str) -> dict:
    """The stored parameters (float32 numpy, `encode_gaussians`' names and shapes) of a checked
    header and its decoded images ({name: uint8 [H, W, C]}), in the file's order."""
    n = header["count"]
    column = {name: image.reshape(-1, image.shape[2])[:n] for name, image in images.items() if name != "sh_palette"}
    means = header["means"]
    q_means = (column["means_hi"].astype(np.int64) << 8) | column["means_lo"]
    t = header["t_means"]
    q_t = (column["t_hi"][:, 0].astype(np.int64) << 8) | column["t_lo"][:, 0]
    for name, q, bits in (("means", q_means, means["bits"]), ("t_means", q_t, t["bits"])):
        if n and int(q.max()) >= 1 << bits:
            raise InputError(f"{what}: {name} reach {int(q.max())}, past the {bits} bits the header gives them: the "
                             f"file is damaged: {FIX}")
    log_means = quantise.unfixed(q_means, means["mins"], means["maxs"], means["bits"])
    tags = column["quats"][:, 3]
    bad = (tags < quantise.QUAT_TAG) | (tags > quantise.QUAT_TAG + 3)
    if bad.any():
        raise InputError(f"{what}: {int(bad.sum()):,} quaternions carry a tag outside {quantise.QUAT_TAG}.."
                         f"{quantise.QUAT_TAG + 3}: the file is damaged: {FIX}")

    def book(name):
        return np.asarray(header[name]["codebook"], np.float64)

    with np.errstate(divide="ignore", over="ignore"):
        opacities = book("opacities")[column["opacities"][:, 0]]
        out = {
            "means": np.clip(quantise.signed_exp(log_means), -FLOAT32_MAX, FLOAT32_MAX),
            "quats": quantise.unpack_quats(column["quats"]),
            "log_scales": book("log_scales")[column["scales"]],
            "opacity_logits": np.log(opacities) - np.log1p(-opacities),
            "sh_dc": book("sh_dc")[column["colours"]].reshape(n, 1, 3),
            "t_means": quantise.unfixed(q_t, t["min"], t["max"], t["bits"]),
            "log_t_scales": book("log_t_scales")[column["t_scales"][:, 0]],
        }
    degree = header["max_sh_degree"]
    coefficients = (degree + 1) ** 2 - 1
    if degree > 0:
        count = header["sh_rest"]["count"]
        labels = column["sh_labels"][:, 0].astype(np.int64) | (column["sh_labels"][:, 1].astype(np.int64) << 8)
        if n and int(labels.max()) >= count:
            raise InputError(f"{what}: SH labels reach {int(labels.max())} but the palette holds {count} entries: "
                             f"the file is damaged: {FIX}")
        cells = images["sh_palette"].reshape(-1, coefficients, 3)[:count]
        palette = book("sh_rest")[cells].reshape(count, coefficients * 3)
        out["sh_rest"] = palette[labels].reshape(n, coefficients, 3)
    else:
        out["sh_rest"] = np.zeros((n, 0, 3))
    return {name: np.ascontiguousarray(value, np.float32) for name, value in out.items()}


# ---- the file ------------------------------------------------------------------------------------

def write_tsog(path, arrays: dict, clip: dict, records: np.ndarray, means_bits: int = MEANS_BITS,
               t_bits: int = T_MEANS_BITS) -> Path:
    """Write a .tsog file atomically: the Gaussians `arrays` (encode_gaussians' input), `clip` (the
    PLY scene's clip JSON object: format, version, size, K, SH degrees, cameras, info) and the camera
    `records` (tomgs.io.scene.CAMERA_RECORD [T])."""
    path = Path(path)
    header, images, _ = encode_gaussians(arrays, means_bits, t_bits)
    degree = sh_degree_of(arrays["sh_rest"].shape[1] + 1)
    header = {"format": FORMAT, "version": VERSION, **header,
              "images": [{"name": name, "channels": channels, "bytes": len(data)}
                         for (name, channels), data in zip(_images(degree), images)],
              "clip": clip}
    try:  # NaN and infinities in info are written as Python's JSON does, as the PLY scene's are
        text = json.dumps(header, ensure_ascii=True, separators=(",", ":")).encode("ascii")
    except (TypeError, ValueError) as e:
        raise ValueError(f"info must be JSON-serialisable ({e})") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, durable=True) as tmp, open(tmp, "wb") as f:
        f.write(MAGIC + struct.pack("<Q", len(text)) + text)
        for data in images:
            f.write(data)
        f.write(np.ascontiguousarray(records).tobytes())
    return path


def read_tsog_clip(path, record_dtype: np.dtype, check_clip) -> tuple[dict, np.ndarray]:
    """(clip JSON object, camera records [T] of `record_dtype`) of the .tsog file `path`, its images
    skipped, not decoded: what a command checks its other arguments against before any work. InputError
    as `read_tsog` raises it for the header and the records."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        text = _header_text(f, size, path)
        header = _checked_header(text, size, f.tell(), record_dtype.itemsize, path, check_clip)
        f.seek(sum(entry["bytes"] for entry in header["images"]), 1)
        records = np.frombuffer(f.read(), dtype=record_dtype).copy()
    return header["clip"], records


def read_tsog(path, record_dtype: np.dtype, check_clip) -> tuple[dict, np.ndarray, dict]:
    """(clip JSON object, camera records [T] of `record_dtype`, the stored parameters) of the .tsog
    file `path`. `check_clip(clip) -> clip` checks the clip object (tomgs.io.scene's checker, which
    raises InputError). Every size is checked before what it sizes is read or allocated; InputError
    naming the file and the fix for anything malformed."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        text = _header_text(f, size, path)
        header = _checked_header(text, size, f.tell(), record_dtype.itemsize, path, check_clip)
        images = {}
        for entry in header["images"]:
            data = f.read(entry["bytes"])
            images[entry["name"]] = data
        records = np.frombuffer(f.read(), dtype=record_dtype).copy()
    width, height = header["grid"]
    decoded = {}
    for entry in header["images"]:
        name, channels = entry["name"], entry["channels"]
        shape = (width, height)
        if name == "sh_palette":
            coefficients = (header["clip"]["max_sh_degree"] + 1) ** 2 - 1
            shape = (PALETTE_ROW * coefficients, -(-header["sh_rest"]["count"] // PALETTE_ROW))
        decoded[name] = quantise.decode_webp(images.pop(name), *shape, channels, f"{path}: image {name!r}")
    arrays = decode_gaussians(dict(header, max_sh_degree=header["clip"]["max_sh_degree"]), decoded, str(path))
    return header["clip"], records, arrays


def image_sizes(path) -> dict[str, int]:
    """{image name: bytes} of the .tsog file `path`, from its header alone (what each attribute
    costs); InputError when the file does not start as a .tsog does."""
    path = Path(path)
    with open(path, "rb") as f:
        text = _header_text(f, path.stat().st_size, path)
    try:
        images = json.loads(text)["images"]
        return {str(entry["name"]): int(entry["bytes"]) for entry in images}
    except (ValueError, TypeError, KeyError, RecursionError) as e:
        raise InputError(f"{path}: the header does not list its images ({str(e)[:100]}): {FIX}") from None


def _header_text(f, size: int, path: Path) -> bytes:
    """The header JSON's bytes of the .tsog file open as `f` (at its start; left after the header),
    its magic and length checked against the file's `size` before the header is read."""
    damaged = f"{path} is a damaged or truncated compressed scene"
    lead = len(MAGIC) + 8
    start = f.read(lead)
    if start[:len(MAGIC)] != MAGIC:
        raise InputError(f"{path} is not a compressed tomgs scene (it does not start with the .tsog magic): {FIX}")
    if len(start) < lead:
        raise InputError(f"{damaged}: it ends inside its first {lead} bytes: {FIX}")
    (length,) = struct.unpack("<Q", start[len(MAGIC):])
    if length > min(MAX_HEADER, size - lead):
        raise InputError(f"{damaged}: its header claims {length:,} bytes, more than "
                         f"{'the file holds' if length <= MAX_HEADER else f'{MAX_HEADER:,}'}: {FIX}")
    return f.read(length)


def _checked_header(text: bytes, size: int, data_start: int, record: int, path: Path, check_clip) -> dict:
    """The .tsog header JSON, its fields checked, its image sizes and camera records (`record` bytes
    each) adding up to the file's `size` exactly (the images start at `data_start`)."""
    damaged = f"{path} is a damaged or truncated compressed scene"
    try:
        header = json.loads(text)
    except RecursionError:
        raise InputError(f"{path}: the header nests too deeply to read: {FIX}") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: the header is not valid JSON ({str(e)[:200]}): {FIX}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(f"{path}: the header lacks \"format\": \"{FORMAT}\": {FIX}")
    if header.get("version") != VERSION:
        raise InputError(f"{path} is compressed scene version {short_repr(header.get('version'))}; this tomgs reads "
                         f"version {VERSION}: install the tomgs that wrote it")
    if not isinstance(header.get("clip"), dict):
        raise InputError(f"{path}: the header's \"clip\" (the cameras' size, K and settings) is missing: {FIX}")
    header["clip"] = check_clip(header["clip"])
    degree = header["clip"]["max_sh_degree"]

    def bad(key):
        return InputError(f"{path}: header field {key!r} is missing or invalid ({short_repr(header.get(key))}): {FIX}")

    count = header.get("count")
    if not _integer(count) or not 0 <= count <= MAX_GAUSSIANS:
        raise bad("count")
    if count > MAX_GAUSSIANS_PER_BYTE * size:
        raise InputError(f"{damaged}: it declares {count:,} Gaussians in {size:,} bytes (at most "
                         f"{MAX_GAUSSIANS_PER_BYTE} a byte); nothing was decoded: {FIX}")
    if header.get("grid") != list(quantise.grid_shape(count)):
        raise InputError(f"{path}: header field 'grid' is {short_repr(header.get('grid'))}, but {count:,} Gaussians "
                         f"are laid out on a {'x'.join(map(str, quantise.grid_shape(count)))} grid: {FIX}")
    expected = _images(degree)
    images = header.get("images")
    if not (isinstance(images, list) and len(images) == len(expected) and all(
            isinstance(e, dict) and e.get("name") == name and e.get("channels") == channels
            and _integer(e.get("bytes")) and e["bytes"] >= 0 for e, (name, channels) in zip(images, expected))):
        raise InputError(f"{path}: header field 'images' must list {', '.join(n for n, _ in expected)} with their "
                         f"channels and byte counts (SH degree {degree}), got {short_repr(images)}: {FIX}")
    for key, fields in (("means", ("mins", "maxs")),):
        entry = header.get(key)
        if not (isinstance(entry, dict) and all(_numbers(entry.get(f), 3) for f in fields)
                and _integer(entry.get("bits")) and 1 <= entry["bits"] <= 16):
            raise bad(key)
    t = header.get("t_means")
    if not (isinstance(t, dict) and _numbers([t.get("min"), t.get("max")], 2)
            and _integer(t.get("bits")) and 1 <= t["bits"] <= 16):
        raise bad("t_means")
    books = ["log_scales", "sh_dc", "opacities", "log_t_scales"] + (["sh_rest"] if degree > 0 else [])
    for key in books:
        entry = header.get(key)
        if not (isinstance(entry, dict) and _numbers(entry.get("codebook"), quantise.CODEBOOK_SIZE)):
            raise bad(key)
    opacity = np.asarray(header["opacities"]["codebook"])
    if not ((opacity > 0) & (opacity < 1)).all():
        raise InputError(f"{path}: the opacity codebook holds values outside (0, 1): {FIX}")
    if degree > 0:
        palette = header["sh_rest"].get("count")
        if not (_integer(palette) and 1 <= palette <= 1 << 16):
            raise InputError(f"{path}: header field 'sh_rest' count must be 1..65536, got {short_repr(palette)}: {FIX}")
    cameras = header["clip"].get("cameras")
    left = size - data_start - sum(e["bytes"] for e in images)
    if not (_integer(cameras) and cameras >= 1 and left == cameras * record):
        raise InputError(f"{damaged}: its images and {short_repr(cameras)} camera records of {record} bytes do not "
                         f"add up to its {size:,} bytes: {FIX}")
    return header


def _integer(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _numbers(v, count: int) -> bool:
    """`v` is a list of `count` finite numbers."""
    return (isinstance(v, list) and len(v) == count
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v))
