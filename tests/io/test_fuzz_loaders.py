"""Seeded fuzz of every loader: random and mutated files must give InputError or a valid result.

For each loader a few valid files are made here, then mutated (random bytes, truncation, flipped and
spliced bytes, numbers in headers replaced by 0, -1, 2^31, 1e400, ..., JSON values replaced by nasty
ones, PLY header lines changed, zip directories and .npy headers rewritten). Every input must:
- give InputError (the CLI's exit 2) or a result that passes the loader's own invariants (no
  mismatch: a scene that loads re-saves and loads to the same thing; cameras are consistent; ...);
- allocate no more than a bound that follows the file's size (tracemalloc sees Python and numpy;
  the whole run is also under RLIMIT_AS, so an allocation OpenCV or onnxruntime makes beyond it fails
  as a MemoryError, which is reported);
- finish in a few seconds.
Set TOMGS_FUZZ_SEED for another family of inputs and TOMGS_FUZZ_SCALE (default 8) to try more or
fewer of them; the counts below are per unit of scale.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import resource
import shutil
import time
import tracemalloc
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.errors import InputError
from tomgs.geometry import rotmat_to_quat

SEED = int(os.environ.get("TOMGS_FUZZ_SEED", "0"))
SCALE = float(os.environ.get("TOMGS_FUZZ_SCALE", "8"))  # 8: about 15,600 inputs, a minute on 2 CPU cores
BOUND_BASE = 48 << 20  # bytes any loader may allocate beyond 64 per byte of its input (tracemalloc)
BOUND_PER_BYTE = 64
SECONDS = 10.0  # the most one input may take (a 50 MB header comment once took 93 s)
ADDRESS_HEADROOM = 3 << 30  # RLIMIT_AS over the address space in use when the fuzz starts

NASTY_NUMBERS = ["0", "-1", "1", "255", "256", "65535", "65536", "2147483647", "2147483648", "4294967296",
                 "9223372036854775808", "99999999999999999999999", "1e400", "-1e400", "nan", "1.5", "-0"]
NASTY_JSON = [0, -1, 1, 0.5, -0.0, 2**31, 2**63, 2**70, 10**30, 1e308, float("nan"), float("inf"), float("-inf"),
              "", "x" * 1000, None, True, False, [], {}, [[]], [0] * 5, [[0, 0, 0]] * 3, {"a": 1},
              [[[[[[[[[[0]]]]]]]]]]]


# ---- valid seed files ----------------------------------------------------------------------------

def _model(n: int, degree: int, seed: int):
    import torch

    from tomgs.model import GaussianModel

    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=g)  # noqa: E731
    return GaussianModel(r(n, 3) * 0.3 + torch.tensor([0.0, 0.0, 3.0]), r(n, 4), r(n, 3) * 0.3 - 2.5, r(n) + 1.0,
                         r(n, 1, 3), r(n, (degree + 1) ** 2 - 1, 3) * 0.2, torch.rand(n, generator=g),
                         r(n) * 0.5 - 2.0, sh_degree=degree)


def _cameras(T: int, width=48, height=36, seed=0) -> Cameras:
    rng = np.random.default_rng(seed)
    c2w = np.stack([look_at(rng.normal(size=3) * 0.1, [0.0, 0.0, 3.0]) for _ in range(T)])
    return Cameras(c2w, intrinsics(40.0, width, height), width, height, np.linspace(0, 1, T), 2 * np.arange(T))


def _texture(k: int, h=48, w=64) -> np.ndarray:
    rng = np.random.default_rng(7)
    base = cv2.resize(rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_LINEAR)
    return np.roll(base, 2 * k, axis=1)


@dataclass
class Corpus:
    """Valid files and everything the loaders need beside them, in one folder."""

    root: Path
    files: dict = field(default_factory=dict)  # name -> path of a valid file (or folder)
    mesh: object = None  # the Tets that sequences move
    cage: object = None
    scene_cameras: Cameras = None


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> Corpus:
    from tomgs.edit.cage import make_tets
    from tomgs.io.scene import save_scene
    from tomgs.io.tets import load_tets, save_sequence, save_tets

    root = tmp_path_factory.mktemp("fuzz_corpus")
    c = Corpus(root)
    model = _model(6, 1, 0)
    cams = _cameras(3)
    c.scene_cameras = cams
    c.files["scene"] = save_scene(root / "scene.ply", model, cams, {"fps": 12, "notes": ["a", "b"]})
    c.files["scene0"] = save_scene(root / "scene0.ply", _model(3, 0, 1), _cameras(1), {})
    c.files["tets"] = save_tets(root / "tets.ply", make_tets(model, [0, 2, 4], "gaussian"))
    c.files["cage"] = save_tets(root / "cage.ply", make_tets(model, [1, 3], "cage", 0.3))
    c.mesh, c.cage = load_tets(c.files["tets"]), load_tets(c.files["cage"])
    rest = c.mesh.vertices
    moved = np.stack([rest, rest + [0.01, 0.0, 0.0], rest + [0.0, 0.02, 0.0]])
    c.files["seq"] = save_sequence(root / "seq.npz", moved, frames=[0, 2, 4])
    from tomgs.io.tets import to_blender

    np.savez_compressed(root / "seqz.npz", vertices=to_blender(moved).astype(np.float32))
    c.files["seqz"] = root / "seqz.npz"
    c.files["cams"] = cams.save(root / "cams.json")
    np.save(root / "c2w.npy", cams.c2w)
    np.save(root / "K.npy", cams.K)
    np.savetxt(root / "K.txt", cams.K)
    c.files["c2w"], c.files["Knpy"], c.files["Ktxt"] = root / "c2w.npy", root / "K.npy", root / "K.txt"
    colmap = root / "colmap"
    colmap.mkdir()
    (colmap / "cameras.txt").write_text("# Camera list\n1 PINHOLE 48 36 40 40 24 18\n")
    lines = ["# Image list"]
    for k in range(3):
        w2c = np.linalg.inv(cams.c2w[k])
        q = rotmat_to_quat(w2c[:3, :3])
        lines += [f"{k + 1} {' '.join(map(str, q))} {' '.join(map(str, w2c[:3, 3]))} 1 f{k}.png", "1.0 2.0 -1"]
    (colmap / "images.txt").write_text("\n".join(lines) + "\n")
    c.files["colmap"] = colmap
    c.files["keys"] = root / "keys.json"
    c.files["keys"].write_text(json.dumps({"keyframes": [{"t": 0, "translate": [0, 0, 0]},
                                                         {"frame": 2, "rotate": [0, 30, 0], "scale": 1.2},
                                                         {"t": 1, "scale": [1, 2, 1]}], "hold": True,
                                           "centre": [0, 0, 3]}))
    for name, codec, ext in (("avi", "MJPG", ".avi"), ("mp4", "mp4v", ".mp4")):
        path = root / f"clip{ext}"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), 25, (64, 48))
        for k in range(6):
            writer.write(_texture(k))
        writer.release()
        c.files[name] = path
    frames, masks = root / "frames", root / "masks"
    frames.mkdir()
    masks.mkdir()
    for k in range(4):
        cv2.imwrite(str(frames / f"f{k}{'.jpg' if k == 3 else '.png'}"), _texture(k))
        m = np.zeros((48, 64), np.uint8)
        m[10:30, 5 * k:5 * k + 20] = 255
        cv2.imwrite(str(masks / f"m{k}{'.bmp' if k == 2 else '.png'}"), m)
    c.files["frames"], c.files["masks"] = frames, masks
    c.files["spec"] = root / "spec.txt"
    c.files["spec"].write_text("0:5:2")
    # LPIPS weights of the right shapes (stored, as LPIPS ships them), small values
    from tomgs.metrics import lpips_shapes

    rng = np.random.default_rng(1)
    np.savez(root / "lpips.npz", **{k: (rng.normal(size=s) * 0.01).astype(np.float32)
                                    for k, s in lpips_shapes().items()})
    c.files["lpips"] = root / "lpips.npz"
    try:
        import torch

        from tests.poses.test_poses_onnx import TinyPoses, _export

        c.files["onnx"] = _export(TinyPoses(), root / "poses.onnx", ["c2w", "K"])
        del torch
    except Exception:  # noqa: BLE001 -- onnx export unavailable: the onnx loader is fuzzed with random bytes only
        (root / "poses.onnx").write_bytes(b"")
        c.files["onnx"] = root / "poses.onnx"
    return c


# ---- mutations -----------------------------------------------------------------------------------

def pick(rng, options):
    """One of `options` (Python objects kept as they are, unlike rng.choice's array conversion)."""
    return options[int(rng.integers(len(options)))]


def random_bytes(rng, data: bytes) -> bytes:
    return rng.bytes(pick(rng, [0, 1, 3, 16, 100, 1000, 10_000, 100_000]))


def truncate(rng, data: bytes) -> bytes:
    return data[:int(rng.integers(0, max(len(data), 1)))]


def flip(rng, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 30))):
        if b:
            b[int(rng.integers(len(b)))] = int(rng.integers(256))
    return bytes(b)


def flip_head(rng, data: bytes) -> bytes:
    """Flipped bytes in the first 600 (headers: sizes and counts live there)."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 6))):
        if b:
            b[int(rng.integers(min(len(b), 600)))] = int(rng.integers(256))
    return bytes(b)


def splice(rng, data: bytes) -> bytes:
    i = int(rng.integers(0, len(data) + 1))
    j = min(len(data), i + int(rng.integers(0, 200)))
    block = pick(rng, [b"\x00", b"\xff", b"\x7f"]) * int(rng.integers(1, 64)) if rng.random() < 0.5 \
        else rng.bytes(int(rng.integers(1, 64)))
    return data[:i] + block + data[j:]


def int_fields(rng, data: bytes) -> bytes:
    """A 2-, 4- or 8-byte field somewhere in the first 4 kB set to 0, -1 or a large count."""
    b = bytearray(data)
    if len(b) < 8:
        return bytes(b)
    width = pick(rng, [2, 4, 8])
    value = pick(rng, [0, 2**(8 * width) - 1, 2**(8 * width - 1) - 1, 2**(8 * width - 1), 65536 % 2**(8 * width)])
    i = int(rng.integers(0, min(len(b), 4096) - width + 1))
    b[i:i + width] = value.to_bytes(width, pick(rng, ["little", "big"]))
    return bytes(b)


def numbers(rng, data: bytes) -> bytes:
    """One run of digits in the text part (header) replaced by a nasty number."""
    head = data[:65536]
    runs = list(re.finditer(rb"-?\d+(\.\d+)?(e-?\d+)?", head))
    if not runs:
        return flip(rng, data)
    m = runs[int(rng.integers(len(runs)))]
    return data[:m.start()] + str(pick(rng, NASTY_NUMBERS)).encode() + data[m.end():]


def lines(rng, data: bytes) -> bytes:
    """A text line (of the header, for a PLY) deleted, duplicated, swapped or rewritten."""
    end = data.find(b"end_header\n")
    head, body = (data[:end], data[end:]) if end > 0 else (data, b"")
    rows = head.split(b"\n")
    k = int(rng.integers(len(rows)))
    op = int(rng.integers(6))
    if op == 0:
        del rows[k]
    elif op == 1:
        rows.insert(k, rows[k])
    elif op == 2:
        j = int(rng.integers(len(rows)))
        rows[k], rows[j] = rows[j], rows[k]
    else:
        rows[k] = bytes(pick(rng, [b"property list uchar int x", b"property double x", b"property float32 t_mean",
                                    b"element vertex 4294967295", b"element camera -1", b"format ascii 1.0",
                                    b"format binary_big_endian 1.0", b"element face 0", b"comment kind cage",
                                    b"comment tomgs-scene " + b"[" * 3000, b"property uchar rot_0", b""]))
    return b"\n".join(rows) + body


def deep_json(rng, data: bytes) -> bytes:
    depth = pick(rng, [100, 1000, 100_000])
    return (b"[" * depth + b"]" * depth) if rng.random() < 0.5 else b'{"a":' + b"[" * depth + b"]" * depth + b"}"


def json_values(rng, data: bytes) -> bytes:
    """One value anywhere in the JSON tree replaced by a nasty value (or a key deleted)."""
    try:
        tree = json.loads(data)
    except ValueError:
        return flip(rng, data)
    slots = []

    def walk(node):
        if isinstance(node, dict):
            for key in list(node):
                slots.append((node, key))
                walk(node[key])
        elif isinstance(node, list):
            for i in range(len(node)):
                slots.append((node, i))
                walk(node[i])

    walk(tree)
    for _ in range(int(rng.integers(1, 4))):
        if not slots:
            break
        parent, key = slots[int(rng.integers(len(slots)))]
        if isinstance(parent, dict) and rng.random() < 0.2:
            parent.pop(key, None)
        else:
            with contextlib.suppress(IndexError, KeyError):
                parent[key] = NASTY_JSON[int(rng.integers(len(NASTY_JSON)))]
    return json.dumps(tree).encode()


def _npz_members(data: bytes) -> dict | None:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            return {i.filename: (z.read(i), i.compress_type) for i in z.infolist()}
    except Exception:  # noqa: BLE001
        return None


def npy_headers(rng, data: bytes) -> bytes:
    """An .npz rebuilt with one member's .npy header declaring another shape or dtype (the data kept)."""
    members = _npz_members(data)
    if not members:
        return flip(rng, data)
    name = list(members)[int(rng.integers(len(members)))]
    raw, method = members[name]
    try:
        array = np.load(io.BytesIO(raw))
    except Exception:  # noqa: BLE001
        return flip(rng, data)
    header = np.lib.format.header_data_from_array_1_0(array)
    choice = int(rng.integers(5))
    if choice == 0:
        header["shape"] = tuple(pick(rng, [0, 1, 3, 2**20, 2**31, 2**40]) for _ in range(len(array.shape) or 1))
    elif choice == 1:
        header["shape"] = (int(rng.integers(1, 10)),) * int(rng.integers(0, 5))
    elif choice == 2:
        header["descr"] = str(pick(rng, ["<f8", "<i8", ">f4", "|u1", "|O", "<c16", "|b1", "<U4"]))
    elif choice == 3:
        header["fortran_order"] = True
    else:
        header["shape"] = (array.shape[0] * 1000,) + array.shape[1:] if array.shape else (1000,)
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    members[name] = (buf.getvalue() + raw[len(raw) - array.nbytes:], method)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as z:
        for n, (content, m) in members.items():
            z.writestr(n, content, compress_type=m)
    return out.getvalue()


def zip_directory(rng, data: bytes) -> bytes:
    """Bytes of the zip's central directory (its last part) set to large or zero sizes."""
    b = bytearray(data)
    start = data.rfind(b"PK\x01\x02")
    if start < 0 or len(b) < 30:
        return flip(rng, data)
    for _ in range(int(rng.integers(1, 4))):
        i = int(rng.integers(max(0, start - 200), len(b) - 4))
        b[i:i + 4] = pick(rng, [0, 2**32 - 1, 2**31, 10**9, 12345]).to_bytes(4, "little")
    return bytes(b)


BYTES = [random_bytes, truncate, flip, flip_head, splice, int_fields]
PLY = BYTES + [numbers, lines, lines, numbers]
JSON = BYTES[:5] + [numbers, json_values, json_values, json_values, deep_json]
NPZ = BYTES + [npy_headers, npy_headers, zip_directory]
TEXT = BYTES[:5] + [numbers, numbers, lines]


# ---- loaders and what a loaded result must satisfy -----------------------------------------------

def check_cameras(cams: Cameras):
    T = len(cams)
    assert T >= 1 and cams.c2w.shape == (T, 4, 4) and cams.times.shape == (T,) and cams.frame_indices.shape == (T,)
    again = Cameras.from_dict(json.loads(json.dumps(cams.to_dict())))
    assert np.array_equal(again.c2w, cams.c2w) and np.array_equal(again.frame_indices, cams.frame_indices)
    assert np.isfinite(cams.viewmats()).all()


def check_scene(scene, tmp: Path):
    from tomgs.io.scene import load_scene, save_scene

    import torch

    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales"):
        assert bool(torch.isfinite(getattr(scene.model, name)).all()), name
    check_cameras(scene.cameras)
    again = load_scene(save_scene(tmp / "again.ply", scene.model, scene.cameras, scene.info))
    assert again.info == scene.info or json.dumps(again.info) == json.dumps(scene.info)
    for name in ("means", "t_means", "sh_rest"):
        assert torch.equal(getattr(again.model, name), getattr(scene.model, name))
    assert np.array_equal(again.cameras.c2w, scene.cameras.c2w)


def check_tets(mesh):
    from tomgs.geometry import signed_volumes as volumes
    from tomgs.io.tets import KINDS

    assert mesh.kind in KINDS and mesh.vertices.ndim == 2 and mesh.vertices.shape[1] == 3
    assert np.isfinite(mesh.vertices).all() and mesh.tets.min() >= 0 and mesh.tets.max() < len(mesh.vertices)
    assert (volumes(mesh.vertices, mesh.tets) > 0).all()
    assert mesh.gaussian_tets().shape == (len(mesh.gaussians), 4, 3)


def check_sequence(result, like):
    vertices, frames = result
    assert vertices.ndim == 3 and vertices.shape[1:] == (len(like.vertices), 3) and np.isfinite(vertices).all()
    assert frames is None or frames.shape == (len(vertices),)


def check_video(video):
    T = len(video.frames)
    assert video.frames.dtype == np.uint8 and video.frames.ndim == 4 and video.frames.shape[3] == 3 and T >= 1
    assert video.indices.shape == (T,) and (np.diff(video.indices) > 0).all()
    assert video.masks is None or video.masks.shape == video.frames.shape[:3]
    assert video.fps is None or 0 < video.fps <= 1000


def check_keyframes(keys):
    assert (np.diff(keys.times) > 0).all() and np.isfinite(keys.times).all()


@dataclass
class Loader:
    name: str
    seeds: list  # corpus names of the valid files it mutates
    mutators: list
    cases: int
    load: Callable  # (path, corpus) -> result
    check: Callable = lambda result, corpus, tmp: None  # noqa: E731
    suffix: str | None = None  # the mutated file's suffix (default: the seed's)
    folder_member: str | None = None  # mutate this file inside a copied folder seed (None: a random one)


def _load_scene(path, c):
    from tomgs.io.scene import load_scene

    return load_scene(path)


def _load_tets(path, c):
    from tomgs.io.tets import load_tets

    return load_tets(path)


def _load_sequence(path, c):
    from tomgs.io.tets import load_sequence

    return load_sequence(path, c.mesh, max_frames=len(c.scene_cameras))


def _anycam(path, c):
    from tomgs.poses.estimate import load_cameras

    return load_cameras(path, 48, 36)


def _keyframes(path, c):
    from tomgs.edit.transforms import load_keyframes

    return load_keyframes(path, c.scene_cameras)


def _video(path, c):
    from tomgs.io import read_video

    return read_video(path)


def _video_range(path, c):
    from tomgs.io import read_video

    return read_video(path, frames="-4::2", max_side=32)


def _frames_folder(path, c):
    from tomgs.io import read_video

    return read_video(path, masks=c.files["masks"])


def _masks_folder(path, c):
    from tomgs.io import read_video

    return read_video(c.files["frames"], masks=path, frames="1:")


def _frame_ranges(path, c):
    """A --frames spec (the file's text) at both users of it: a video and a scene's frame numbers."""
    from tomgs.io import read_video
    from tomgs.render.jobs import select_frames

    spec = path.read_bytes().decode("latin-1")
    positions = select_frames(c.scene_cameras, spec)
    assert positions.dtype == np.int64 and len(positions) >= 1 and positions.max() < len(c.scene_cameras)
    return read_video(c.files["avi"], frames=spec)


def _lpips(path, c):
    from tomgs.metrics import LPIPS

    return LPIPS(path)


def _onnx(path, c):
    from tomgs.poses import estimate_cameras

    frames = np.stack([_texture(k, 24, 32) for k in range(3)])
    return estimate_cameras(frames, method=str(path))[0]


LOADERS = [
    Loader("scene", ["scene", "scene0"], PLY, 260, _load_scene, lambda r, c, t: check_scene(r, t)),
    Loader("tets", ["tets", "cage"], PLY, 220, _load_tets, lambda r, c, t: check_tets(r)),
    Loader("sequence npz", ["seq", "seqz"], NPZ, 200, _load_sequence, lambda r, c, t: check_sequence(r, c.mesh)),
    Loader("sequence ply", ["tets"], PLY, 60, _load_sequence, lambda r, c, t: check_sequence(r, c.mesh)),
    Loader("cameras json", ["cams"], JSON, 260, lambda p, c: Cameras.load(p), lambda r, c, t: check_cameras(r)),
    Loader("anycam npy", ["c2w"], BYTES + [int_fields, flip_head], 120, _anycam, lambda r, c, t: check_cameras(r)),
    Loader("anycam K", ["Knpy", "Ktxt"], BYTES + [numbers], 60,
           lambda p, c: Cameras.from_anycam(c.files["c2w"], p, 48, 36), lambda r, c, t: check_cameras(r)),
    Loader("colmap", ["colmap"], TEXT, 120, lambda p, c: Cameras.from_colmap(p), lambda r, c, t: check_cameras(r)),
    Loader("keyframes", ["keys"], JSON, 200, _keyframes, lambda r, c, t: check_keyframes(r)),
    Loader("video", ["avi", "mp4"], BYTES + [int_fields, flip_head], 160, _video, lambda r, c, t: check_video(r)),
    Loader("video range", ["avi", "mp4"], BYTES, 40, _video_range, lambda r, c, t: check_video(r)),
    Loader("random .mp4", ["mp4"], [random_bytes], 60, _video, lambda r, c, t: check_video(r)),
    Loader("frame folder", ["frames"], BYTES + [int_fields, flip_head], 80, _frames_folder,
           lambda r, c, t: check_video(r)),
    Loader("mask folder", ["masks"], BYTES + [int_fields, flip_head], 50, _masks_folder,
           lambda r, c, t: check_video(r)),
    Loader("frame range", ["spec"], [random_bytes, flip, splice, numbers, numbers, numbers], 60, _frame_ranges,
           lambda r, c, t: check_video(r)),
    Loader("lpips weights", ["lpips"], [random_bytes, truncate, flip_head, npy_headers, npy_headers, zip_directory],
           24, _lpips),
    Loader("onnx model", ["onnx"], [random_bytes, truncate, flip, flip_head], 40, _onnx,
           lambda r, c, t: check_cameras(r)),
]


def _mutated(loader: Loader, corpus: Corpus, rng, case_dir: Path) -> Path:
    """A mutated copy of one of the loader's seeds in `case_dir`; its path (the folder for folder seeds)."""
    seed = corpus.files[loader.seeds[int(rng.integers(len(loader.seeds)))]]
    mutate = loader.mutators[int(rng.integers(len(loader.mutators)))]
    if seed.is_dir():
        target = case_dir / seed.name
        shutil.copytree(seed, target)
        members = sorted(target.iterdir())
        victim = members[int(rng.integers(len(members)))]
        victim.write_bytes(mutate(rng, victim.read_bytes()))
        return target
    target = case_dir / (seed.stem + (loader.suffix or seed.suffix))
    target.write_bytes(mutate(rng, seed.read_bytes()))
    return target


@contextlib.contextmanager
def address_space_cap(headroom: int):
    """RLIMIT_AS (soft) at the address space in use plus `headroom`, restored afterwards."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    in_use = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmSize")) * 1024
    cap = in_use + headroom if hard == resource.RLIM_INFINITY else min(in_use + headroom, hard)
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size


@pytest.mark.slow
def test_random_malformed_files_at_every_loader(corpus, tmp_path):
    """Each loader against its share of mutated files: InputError or a valid result, within the memory
    and time bounds. Prints the count per loader."""
    import warnings

    rng = np.random.default_rng(SEED)
    counts, failures = {}, []
    slowest = (0.0, "")
    start = time.perf_counter()
    warnings.simplefilter("ignore")  # numpy/onnxruntime chatter about the bad values is not the point here
    with address_space_cap(ADDRESS_HEADROOM):
        for loader in LOADERS:
            refused = loaded = failed = 0
            for case in range(int(loader.cases * SCALE)):
                case_dir = tmp_path / f"{loader.name.replace(' ', '_')}_{case}"
                case_dir.mkdir()
                path = _mutated(loader, corpus, rng, case_dir)
                size = _size(path)
                bound = BOUND_BASE + BOUND_PER_BYTE * size
                tracemalloc.start()
                t0 = time.perf_counter()
                outcome = None
                try:
                    result = loader.load(path, corpus)
                except InputError as e:
                    refused += 1
                    if not str(e).strip():
                        outcome = "an empty InputError message"
                except BaseException as e:  # noqa: BLE001 -- the point: anything else is a finding
                    outcome = f"{type(e).__name__}: {str(e)[:300]}"
                else:
                    loaded += 1
                    try:
                        loader.check(result, corpus, case_dir)
                    except BaseException as e:  # noqa: BLE001
                        outcome = f"loaded but inconsistent: {type(e).__name__}: {str(e)[:300]}"
                seconds = time.perf_counter() - t0
                peak = tracemalloc.get_traced_memory()[1]
                tracemalloc.stop()
                slowest = max(slowest, (seconds, f"{loader.name} case {case}"))
                if outcome is None and peak > bound:
                    outcome = f"allocated {peak:,} bytes, more than {bound:,} for a {size:,}-byte input"
                if outcome is None and seconds > SECONDS:
                    outcome = f"took {seconds:.1f} s"
                if outcome is not None:
                    keep = tmp_path / "failures" / f"{loader.name.replace(' ', '_')}_{case}"
                    shutil.copytree(case_dir, keep)
                    failures.append(f"{loader.name} case {case} ({path.name}, kept in {keep}): {outcome}")
                    failed += 1
                else:
                    shutil.rmtree(case_dir, ignore_errors=True)
            counts[loader.name] = (refused, loaded, failed)
    total = sum(sum(c) for c in counts.values())
    print(f"\nfuzz seed {SEED}: {total} inputs in {time.perf_counter() - start:.0f} s; slowest {slowest[0]:.2f} s "
          f"({slowest[1]})")
    for name, (refused, loaded, failed) in counts.items():
        print(f"  {name:16s} {refused:5d} refused (InputError), {loaded:5d} loaded and consistent, {failed:5d} failed")
    assert not failures, f"{len(failures)} of {total} inputs:\n" + "\n".join(failures[:40])
    assert all(refused > 0 for refused, _, _ in counts.values())


# ---- every command: a malformed file is exit 2 with the file named, no traceback, nothing written ---

def _refused(loader_name: str, corpus: Corpus, rng, folder: Path, tries: int = 40) -> Path:
    """A mutated file that the loader refuses (InputError)."""
    loader = next(l for l in LOADERS if l.name == loader_name)
    for k in range(tries):
        case_dir = folder / f"{loader_name.replace(' ', '_')}_{k}"
        case_dir.mkdir(parents=True)
        path = _mutated(loader, corpus, rng, case_dir)
        try:
            loader.load(path, corpus)
        except InputError:
            return path
    raise AssertionError(f"no refused {loader_name} input in {tries} tries")


# (command line with {slot} for the bad file, loader that makes it); {scene} {tets} {seq} {video} {out} are good
COMMANDS = [
    ("poses {bad} -o {out}/c.json --method identity", "video"),
    ("poses {bad} -o {out}/c.json --method identity", "random .mp4"),
    ("poses {bad} -o {out}/c.json --method identity", "frame folder"),
    ("poses {frames} --masks {bad} -o {out}/c.json --method identity", "mask folder"),
    ("poses {video} -o {out}/c.json --method {bad}", "cameras json"),
    ("poses {video} -o {out}/c.json --method {bad}", "anycam npy"),
    ("poses {video} -o {out}/c.json --method {bad}", "colmap"),
    ("poses {video} -o {out}/c.json --method {bad}", "onnx model"),
    ("fit {bad} -o {out}/s.ply --iterations 1 --device cpu --poses identity", "video"),
    ("fit {video} -o {out}/s.ply --iterations 1 --device cpu --poses {bad}", "cameras json"),
    ("render {bad} -o {out}/r.mp4 --device cpu", "scene"),
    ("render {scene} --layer {bad} -o {out}/r.mp4 --device cpu", "scene"),
    ("info {bad}", "scene"),
    ("eval {bad} {video} --device cpu", "scene"),
    ("eval {scene} {bad} --device cpu", "random .mp4"),
    ("eval {scene} {video} --lpips {bad} --device cpu", "lpips weights"),
    ("edit {bad} -o {out}/e.ply --translate 1,0,0", "scene"),
    ("edit {scene} -o {out}/k --keyframes {bad} --device cpu", "keyframes"),
    ("tets export {bad} -o {out}/t.ply", "scene"),
    ("tets import {bad} {tets} {seq} -o {out}/i", "scene"),
    ("tets import {scene} {bad} {seq} -o {out}/i", "tets"),
    ("tets import {scene} {tets} {bad} -o {out}/i", "sequence npz"),
    ("tets import {scene} {tets} {bad} -o {out}/i", "sequence ply"),
    ("simulate {bad} -o {out}/s.npz --drop 0.1", "scene"),
]
PER_COMMAND = 4


def test_every_command_refuses_malformed_files_with_exit_2(corpus, tmp_path):
    from tomgs.cli import main

    rng = np.random.default_rng(SEED + 1)
    good = dict(scene=corpus.files["scene"], tets=corpus.files["tets"], seq=corpus.files["seq"],
                frames=corpus.files["frames"], video=corpus.root / "scene_clip.avi")
    writer = cv2.VideoWriter(str(good["video"]), cv2.VideoWriter_fourcc(*"MJPG"), 25, (48, 36))
    for k in range(5):  # the scene's frames are numbers 0, 2, 4 at 48x36
        writer.write(_texture(k, 36, 48))
    writer.release()
    failures, tried = [], 0
    for template, loader_name in COMMANDS:
        for k in range(PER_COMMAND):
            bad = _refused(loader_name, corpus, rng, tmp_path / "bad" / f"{len(failures)}_{tried}")
            out = tmp_path / "out" / str(tried)
            out.mkdir(parents=True)
            args = template.format(bad=bad, out=out, **good).split()
            result = CliRunner().invoke(main, args)
            tried += 1
            problem = None
            if result.exit_code != 2:
                problem = f"exit {result.exit_code}"
            elif result.exception is not None and not isinstance(result.exception, SystemExit):
                problem = f"{type(result.exception).__name__}"
            elif "Traceback" in result.output or bad.name not in result.output:
                problem = "the message does not name the file"
            elif list(out.iterdir()):
                problem = f"wrote {[p.name for p in out.iterdir()]}"
            if problem:
                failures.append(f"tomgs {' '.join(args)}: {problem}\n{result.output[-500:]}")
    print(f"\n{tried} malformed files over {len(COMMANDS)} command slots, every one exit 2")
    assert not failures, "\n".join(failures[:20])
