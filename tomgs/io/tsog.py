"""The compressed scene file (.tsog): a scene's Gaussians quantised onto sorted 2D grids, each grid a
lossless WebP image, with the same clip (cameras, frame times, settings) a PLY scene carries.

`write_tsog(path, arrays, clip, records)` and `read_tsog(path)` move the stored parameters (float32
numpy, tomgs.model's names and shapes) of a scene; tomgs.io.scene's `save_scene` and `load_scene`
call them for a path ending in .tsog and for a file starting with MAGIC, so every command that reads
or writes a scene takes one. docs/scene-format.md gives the layout and the why; in short:

    MAGIC                              9 bytes, b"\\x89TSOG\\r\\n\\x1a\\n"
    u64 little endian L                the length of the header
    L bytes of JSON                    {"format": "tomgs-tsog", "version": 2, "count": N,
                                        "grid": [W, H], "images": [{"name", "channels", "bytes",
                                        "crc32"}], "records_crc32", one entry per attribute below
                                        with its dequantisation, "clip": the PLY scene's clip JSON
                                        (tomgs.io.scene)}, padded with spaces to a byte a Gaussian
    u32 little endian                  the CRC-32 of the L bytes of JSON (version 2; version 1,
                                       still read, has no checksums)
    the images, in "images" order      lossless WebP, W x H pixels each, Gaussian k at pixel k
                                       (row k // W); unused pixels repeat the last
    T camera records, 144 bytes each   as the PLY scene's (tomgs.io.scene.CAMERA_RECORD)

Attributes (Gaussians sorted along a Z-order curve of their quantised means):
    means          about the header's centre (the mean camera centre): the direction's octahedral
                   map (u, v) on [-1, 1] and log r between the header's log_r ends, `bits` (16 by
                   default) each (quantise.polar): a step is a fixed fraction of the distance, which
                   no far Gaussian coarsens; high bytes in image means_hi (RGB), low in means_lo.
                   Version 1: per axis sign(x) log(1 + |x|) between the header's mins and maxs
    quats          smallest three, 8 bits each, and 252 + the largest's index (RGBA), as SOG
    log_scales     indices (RGB) into a 256-entry codebook shared by the three axes (codebooks:
                   quantise.codebook, outliers in entries of their own)
    sh_dc          indices (RGB) into a 256-entry codebook shared by the three channels
    opacities      index (grey) into a 256-entry codebook of sigmoid(opacity_logit)
    t_means        `bits` (16 by default) of quantise.squash(t) (linear inside the header's "linear"
                   range, logarithmic past it) between the header's min and max: t_hi and t_lo
                   (grey). Version 1: t itself between min and max
    log_t_scales   index (grey) into a 256-entry codebook
    sh_rest        (SH degree > 0 only) a palette of up to PALETTE_SIZE vectors: labels 16 bits
                   (sh_labels: R low byte, G high byte) and the palette as an image of 64 entries a
                   row, each entry (D+1)^2-1 pixels wide, RGB indices into a 256-entry codebook
A file is read with every size checked before the bytes it sizes are touched: the header's length
and JSON, the image sizes against the file's (they must add up exactly), each image's dimensions
against the grid before a pixel is decoded, and the count against the file's size (at most
MAX_GAUSSIANS_PER_BYTE Gaussians a byte): a small file cannot make the reader allocate much. The
checksums tell a damaged file (a flipped byte) from another scene; values are dequantised in float32,
a chunk of Gaussians at a time.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np

from tomgs.constants import sh_degree_of
from tomgs.errors import InputError, short_repr
from tomgs.io import quantise
from tomgs.outputs import atomic_file

MAGIC = b"\x89TSOG\r\n\x1a\n"  # PNG's pattern: a high byte, the name, CRLF and LF to catch text-mode copies
FORMAT = "tomgs-tsog"
VERSION = 2
VERSIONS = (1, 2)  # the versions this reader takes: 2 adds a CRC-32 to each image and to the camera records
SUFFIX = ".tsog"
MAX_HEADER = 64 << 20  # the header holds codebooks (kilobytes) and the clip's settings
MEANS_BITS = 16  # the default bits an axis of the means and of t_mean; a file may hold 1..16 (its header says)
T_MEANS_BITS = 16
PALETTE_SIZE = 4096  # most SH rest vectors in the palette (k-means on the CPU stays seconds at 1M)
PALETTE_ROW = 64  # palette entries per image row, as SOG
OPACITY_FLOOR = 1e-7  # opacities are stored in [1e-7, 1 - 1e-7]: logits of +-16, past what the renderer tells apart
FLOAT32_MAX = float(np.finfo(np.float32).max)
MAX_LOG_MEAN = 88.0  # means' distances (log r; version 1: sign(x) log(1 + |x|)) at most e^88 = 1.7e38
MAX_CENTRE = 1e30  # the means' centre, inside float32's range with room for the distances
MAX_GAUSSIANS = 1 << 27  # a grid of 134M pixels: WebP's 16383-pixel sides hold it
MAX_GAUSSIANS_PER_BYTE = 1
"""Real files take 13-25 bytes a Gaussian (the noisiest image, means_lo, ~3 alone), and the writer pads
the header with JSON whitespace so that a file of few distinct Gaussians (whose images compress to
almost nothing) still takes a byte a Gaussian: a file declaring more Gaussians than its bytes is damaged
or crafted, and is refused before anything is decoded. Decoding takes ~100 bytes a Gaussian, so a
file can make the reader allocate ~100x its size, never more."""
DECODE_CHUNK = 1 << 14  # Gaussians dequantised at a time: float64 intermediates of ~4 MiB
FIX = "write compressed scenes with `tomgs compress SCENE -o OUT.tsog` or `tomgs fit ... -o scene.tsog`"


def is_tsog(path) -> bool:
    """Whether the file `path` is read as a .tsog: it starts with MAGIC, or it is named .tsog and does
    not start as a PLY does (so an empty file, a ZIP or noise named .tsog is told it is not a .tsog, not
    that it is not a PLY). False for a missing or unreadable file."""
    try:
        with open(path, "rb") as f:
            start = f.read(len(MAGIC))
    except OSError:
        return False
    return start == MAGIC or (Path(path).suffix.lower() == SUFFIX and not start.startswith(b"ply"))


# ---- the attributes' images --------------------------------------------------------------------

def _images(max_sh_degree: int) -> list[tuple[str, int]]:
    """(name, channels) of every image of a file of SH degree `max_sh_degree`, in file order."""
    images = [("means_hi", 3), ("means_lo", 3), ("quats", 4), ("scales", 3), ("colours", 3), ("opacities", 1),
              ("t_hi", 1), ("t_lo", 1), ("t_scales", 1)]
    return images + ([("sh_labels", 2), ("sh_palette", 3)] if max_sh_degree > 0 else [])


def encode_gaussians(arrays: dict, means_bits: int = MEANS_BITS, t_bits: int = T_MEANS_BITS,
                     centre=(0.0, 0.0, 0.0)) -> tuple[dict, list[bytes], np.ndarray]:
    """(the header's attribute entries and grid, the images in _images order, the order [N]: the
    k-th Gaussian of the file is row order[k] of `arrays`). `arrays`: the stored parameters, float32
    numpy: means [N,3], quats [N,4], log_scales [N,3], opacity_logits [N], sh_dc [N,1,3], sh_rest
    [N,K-1,3], t_means [N], log_t_scales [N]. `means_bits` and `t_bits` (1..16): the precision of
    the means (an axis) and of t_mean; below 16 the high bytes' images hold fewer bits. `centre`:
    the point the means are stored about (write_tsog: the mean camera centre)."""
    if not (1 <= means_bits <= 16 and 1 <= t_bits <= 16):
        raise ValueError(f"means_bits and t_bits must be 1..16, got {means_bits} and {t_bits}")
    n = len(arrays["means"])
    degree = sh_degree_of(arrays["sh_rest"].shape[1] + 1)
    f64 = {name: np.asarray(value, np.float64).reshape(n, int(np.prod(np.shape(value)[1:])))
           for name, value in arrays.items()}
    width, height = quantise.grid_shape(n)

    centre = [float(c) for c in centre]
    coords = quantise.polar(f64["means"], centre)
    log_r = coords[:, 2]
    finite = log_r[np.isfinite(log_r)]  # -inf: a mean at the centre
    r_hi = min(float(finite.max()), MAX_LOG_MEAN) if len(finite) else 0.0
    r_lo = max(float(finite.min()), r_hi - quantise.POLAR_DEPTHS) if len(finite) else 0.0
    coords[:, 2] = np.clip(np.nan_to_num(log_r, neginf=r_lo), r_lo, r_hi)
    q_means = quantise.fixed(coords, [-1.0, -1.0, r_lo], [1.0, 1.0, r_hi], means_bits)
    t = f64["t_means"][:, 0]
    linear = quantise.linear_range(t)
    squashed = quantise.squash(t, *linear)
    t_lo, t_hi = (float(squashed.min()), float(squashed.max())) if n else (0.0, 0.0)
    q_t = quantise.fixed(squashed, t_lo, t_hi, t_bits)
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
        "means": {"centre": centre, "log_r": [r_lo, r_hi], "bits": means_bits},
        "quats": {},
        "log_scales": {"codebook": _short_floats(books["scales"])},
        "sh_dc": {"codebook": _short_floats(books["colours"])},
        "opacities": {"codebook": _short_floats(books["opacities"])},
        "t_means": {"linear": linear, "min": t_lo, "max": t_hi, "bits": t_bits},
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
    header and its decoded images ({name: uint8 [H, W, C]}), in the file's order. Dequantised
    DECODE_CHUNK Gaussians at a time into float32 arrays: the peak is the images and the result."""
    n = header["count"]
    column = {name: image.reshape(-1, image.shape[2])[:n] for name, image in images.items() if name != "sh_palette"}
    means, t = header["means"], header["t_means"]
    degree = header["max_sh_degree"]
    coefficients = (degree + 1) ** 2 - 1
    palette = None
    if degree > 0:
        count = header["sh_rest"]["count"]
        cells = images["sh_palette"].reshape(-1, coefficients, 3)[:count]
        palette = np.asarray(header["sh_rest"]["codebook"], np.float32)[cells].reshape(count, coefficients, 3)
    books = {name: np.asarray(header[name]["codebook"], np.float64)
             for name in ("log_scales", "sh_dc", "opacities", "log_t_scales")}
    opacities = books["opacities"]
    books["opacities"] = np.log(opacities) - np.log1p(-opacities)  # logits: the checked header keeps them in (0, 1)
    out = {"means": np.empty((n, 3), np.float32), "quats": np.empty((n, 4), np.float32),
           "log_scales": np.empty((n, 3), np.float32), "opacity_logits": np.empty(n, np.float32),
           "sh_dc": np.empty((n, 1, 3), np.float32), "sh_rest": np.zeros((n, coefficients, 3), np.float32),
           "t_means": np.empty(n, np.float32), "log_t_scales": np.empty(n, np.float32)}
    for start in range(0, n, DECODE_CHUNK):
        rows = slice(start, min(n, start + DECODE_CHUNK))
        c = {name: values[rows] for name, values in column.items()}
        q_means = (c["means_hi"].astype(np.int64) << 8) | c["means_lo"]
        q_t = (c["t_hi"][:, 0].astype(np.int64) << 8) | c["t_lo"][:, 0]
        for name, q, bits in (("means", q_means, means["bits"]), ("t_means", q_t, t["bits"])):
            if int(q.max()) >= 1 << bits:
                raise InputError(f"{what}: {name} reach {int(q.max())}, past the {bits} bits the header gives them: "
                                 f"the file is damaged: {FIX}")
        tags = c["quats"][:, 3]
        bad = (tags < quantise.QUAT_TAG) | (tags > quantise.QUAT_TAG + 3)
        if bad.any():
            raise InputError(f"{what}: quaternions carry a tag outside {quantise.QUAT_TAG}..{quantise.QUAT_TAG + 3}: "
                             f"the file is damaged: {FIX}")
        out["means"][rows] = _means(q_means, means)
        out["quats"][rows] = quantise.unpack_quats(c["quats"])
        out["log_scales"][rows] = books["log_scales"][c["scales"]]
        out["opacity_logits"][rows] = books["opacities"][c["opacities"][:, 0]]
        out["sh_dc"][rows] = books["sh_dc"][c["colours"]].reshape(-1, 1, 3)
        out["t_means"][rows] = _t_means(q_t, t)
        out["log_t_scales"][rows] = books["log_t_scales"][c["t_scales"][:, 0]]
        if palette is not None:
            labels = c["sh_labels"][:, 0].astype(np.int64) | (c["sh_labels"][:, 1].astype(np.int64) << 8)
            if int(labels.max()) >= len(palette):
                raise InputError(f"{what}: SH labels reach {int(labels.max())} but the palette holds {len(palette)} "
                                 f"entries: the file is damaged: {FIX}")
            out["sh_rest"][rows] = palette[labels]
    return out


def _means(q: np.ndarray, entry: dict) -> np.ndarray:
    """float64 [N, 3]: the means of their cells `q` [N, 3] and the header's checked entry: about a
    centre (version 2) or per axis in sign(x) log(1 + |x|) between mins and maxs (version 1)."""
    bits = entry["bits"]
    if "centre" in entry:
        r_lo, r_hi = entry["log_r"]
        return quantise.unpolar(quantise.unfixed(q, [-1.0, -1.0, r_lo], [1.0, 1.0, r_hi], bits), entry["centre"])
    return quantise.signed_exp(quantise.unfixed(q, entry["mins"], entry["maxs"], bits))


def _t_means(q: np.ndarray, entry: dict) -> np.ndarray:
    """float64 [N]: t_means of their values `q` and the header's checked entry (squashed past the
    entry's "linear" range in version 2)."""
    t = quantise.unfixed(q, entry["min"], entry["max"], entry["bits"])
    return quantise.unsquash(t, *entry["linear"]) if "linear" in entry else t


# ---- the file ------------------------------------------------------------------------------------

def camera_centre(records: np.ndarray) -> list[float]:
    """The point a file's means are stored about: the mean of its cameras' centres (records of
    tomgs.io.scene.CAMERA_RECORD), inside MAX_CENTRE."""
    centre = np.asarray(records["c2w"], np.float64).reshape(-1, 4, 4)[:, :3, 3].mean(0)
    return np.clip(np.nan_to_num(centre), -MAX_CENTRE, MAX_CENTRE).tolist()


def write_tsog(path, arrays: dict, clip: dict, records: np.ndarray, means_bits: int = MEANS_BITS,
               t_bits: int = T_MEANS_BITS) -> Path:
    """Write a .tsog file atomically: the Gaussians `arrays` (encode_gaussians' input), `clip` (the
    PLY scene's clip JSON object: format, version, size, K, SH degrees, cameras, info) and the camera
    `records` (tomgs.io.scene.CAMERA_RECORD [T])."""
    path = Path(path)
    records = np.ascontiguousarray(records)
    header, images, _ = encode_gaussians(arrays, means_bits, t_bits, camera_centre(records))
    degree = sh_degree_of(arrays["sh_rest"].shape[1] + 1)
    header = {"format": FORMAT, "version": VERSION, **header,
              "images": [{"name": name, "channels": channels, "bytes": len(data), "crc32": zlib.crc32(data)}
                         for (name, channels), data in zip(_images(degree), images)],
              "records_crc32": zlib.crc32(records.tobytes()), "clip": clip}
    try:  # NaN and infinities in info are written as Python's JSON does, as the PLY scene's are
        text = json.dumps(header, ensure_ascii=True, separators=(",", ":")).encode("ascii")
    except (TypeError, ValueError) as e:
        raise ValueError(f"info must be JSON-serialisable ({e})") from None
    size = len(MAGIC) + 8 + len(text) + 4 + sum(map(len, images)) + records.nbytes
    text += b" " * max(0, -(-header["count"] // MAX_GAUSSIANS_PER_BYTE) - size)  # see MAX_GAUSSIANS_PER_BYTE
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, durable=True) as tmp, open(tmp, "wb") as f:
        f.write(MAGIC + struct.pack("<Q", len(text)) + text + struct.pack("<I", zlib.crc32(text)))
        for data in images:
            f.write(data)
        f.write(records.tobytes())
    return path


def read_tsog_clip(path, record_dtype: np.dtype, check_clip) -> tuple[dict, np.ndarray]:
    """(clip JSON object, camera records [T] of `record_dtype`) of the .tsog file `path`, its images
    skipped, not decoded: what a command checks its other arguments against before any work. InputError
    as `read_tsog` raises it for the header and the records."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        text = _header_text(f, size, path)
        header = _checked_header(text, f, size, record_dtype.itemsize, path, check_clip)
        f.seek(sum(entry["bytes"] for entry in header["images"]), 1)
        records = _records(f.read(), header, record_dtype, path)
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
        header = _checked_header(text, f, size, record_dtype.itemsize, path, check_clip)
        images = {}
        for entry in header["images"]:
            data = f.read(entry["bytes"])
            if "crc32" in entry and zlib.crc32(data) != entry["crc32"]:
                raise InputError(f"{path} is a damaged compressed scene: image {entry['name']!r} fails its checksum "
                                 f"(CRC-32): {FIX}")
            images[entry["name"]] = data
        records = _records(f.read(), header, record_dtype, path)
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


def _records(data: bytes, header: dict, record_dtype: np.dtype, path: Path) -> np.ndarray:
    """The camera records of a checked header's file, `data` their bytes, checked against the header's
    CRC-32 (version 2)."""
    if "records_crc32" in header and zlib.crc32(data) != header["records_crc32"]:
        raise InputError(f"{path} is a damaged compressed scene: its camera records fail their checksum (CRC-32): {FIX}")
    return np.frombuffer(data, dtype=record_dtype).copy()


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
    if not start:
        raise InputError(f"{path} is empty, not a compressed tomgs scene: {FIX}")
    if start[:len(MAGIC)] != MAGIC:
        raise InputError(f"{path} is not a compressed tomgs scene (it does not start with the .tsog magic): {FIX}")
    if len(start) < lead:
        raise InputError(f"{damaged}: it ends inside its first {lead} bytes: {FIX}")
    (length,) = struct.unpack("<Q", start[len(MAGIC):])
    if length > min(MAX_HEADER, size - lead):
        raise InputError(f"{damaged}: its header claims {length:,} bytes, more than "
                         f"{'the file holds' if length <= MAX_HEADER else f'{MAX_HEADER:,}'}: {FIX}")
    return f.read(length)


def _checked_header(text: bytes, f, size: int, record: int, path: Path, check_clip) -> dict:
    """The .tsog header JSON `text`, its fields checked, its image sizes and camera records (`record`
    bytes each) adding up to the file's `size` exactly; `f` is the file, left where the images start
    (after the header's CRC-32 in version 2)."""
    damaged = f"{path} is a damaged or truncated compressed scene"
    try:
        header = json.loads(text)
    except RecursionError:
        raise InputError(f"{path}: the header nests too deeply to read: {FIX}") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: the header is not valid JSON ({str(e)[:200]}): {FIX}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise InputError(f"{path}: the header lacks \"format\": \"{FORMAT}\": {FIX}")
    version = header.get("version")
    if not _integer(version) or version not in VERSIONS:
        raise InputError(f"{path} is compressed scene version {short_repr(version)}; this tomgs reads versions "
                         f"{', '.join(map(str, VERSIONS))}: install the tomgs that wrote it")
    if version >= 2 and f.read(4) != struct.pack("<I", zlib.crc32(text)):
        raise InputError(f"{damaged}: its header fails its checksum (CRC-32): {FIX}")
    data_start = f.tell()
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
        raise InputError(f"{damaged}: it declares {count:,} Gaussians in {size:,} bytes (a .tsog takes at least a "
                         f"byte a Gaussian); nothing was decoded: {FIX}")
    if header.get("grid") != list(quantise.grid_shape(count)):
        raise InputError(f"{path}: header field 'grid' is {short_repr(header.get('grid'))}, but {count:,} Gaussians "
                         f"are laid out on a {'x'.join(map(str, quantise.grid_shape(count)))} grid: {FIX}")
    expected = _images(degree)
    images = header.get("images")
    checksums = version >= 2

    def crc(value):  # a CRC-32 in version 2, none before
        return (_integer(value) and 0 <= value < 1 << 32) if checksums else value is None

    if not (isinstance(images, list) and len(images) == len(expected) and all(
            isinstance(e, dict) and e.get("name") == name and e.get("channels") == channels
            and _integer(e.get("bytes")) and e["bytes"] >= 0 and crc(e.get("crc32"))
            for e, (name, channels) in zip(images, expected))):
        raise InputError(f"{path}: header field 'images' must list {', '.join(n for n, _ in expected)} with their "
                         f"channels, byte counts{' and CRC-32s' if checksums else ''} (SH degree {degree}), got "
                         f"{short_repr(images)}: {FIX}")
    if not crc(header.get("records_crc32")):
        raise bad("records_crc32")
    entry = header.get("means")
    fields = {"centre": (3, MAX_CENTRE), "log_r": (2, MAX_LOG_MEAN)} if version >= 2 else \
        {"mins": (3, MAX_LOG_MEAN), "maxs": (3, MAX_LOG_MEAN)}
    if not (isinstance(entry, dict) and all(_numbers(entry.get(f), *shape) for f, shape in fields.items())
            and _integer(entry.get("bits")) and 1 <= entry["bits"] <= 16):
        raise bad("means")
    t = header.get("t_means")
    if not (isinstance(t, dict) and _numbers([t.get("min"), t.get("max")], 2, FLOAT32_MAX / 2)
            and (version < 2 or _numbers(t.get("linear"), 2, FLOAT32_MAX / 2))
            and _integer(t.get("bits")) and 1 <= t["bits"] <= 16):
        raise bad("t_means")
    if version >= 2:  # the decoded range, past the linear part, inside float32's
        with np.errstate(over="ignore"):
            ends = quantise.unsquash(np.array([t["min"], t["max"]]), *t["linear"])
        if not (np.abs(ends) <= FLOAT32_MAX / 2).all():
            raise bad("t_means")
    books = ["log_scales", "sh_dc", "opacities", "log_t_scales"] + (["sh_rest"] if degree > 0 else [])
    for key in books:
        entry = header.get(key)
        if not (isinstance(entry, dict) and _numbers(entry.get("codebook"), quantise.CODEBOOK_SIZE, FLOAT32_MAX)):
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


def _numbers(v, count: int, bound: float) -> bool:
    """`v` is a list of `count` numbers of magnitude at most `bound` (so finite): what a float32 holds
    once dequantised, checked here so that no arithmetic below overflows."""
    return (isinstance(v, list) and len(v) == count
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and abs(x) <= bound for x in v))
