"""Inputs checked at the door: one test per way a file could make a loader misbehave.

Every loader raises InputError (exit 2 from the CLI) for anything a file holds, and sizes read from a
file are checked against what the file can hold before anything is allocated. Allocation bounds are
checked in a subprocess whose address space is capped (RLIMIT_AS), so a regression fails with a
MemoryError there instead of taking the machine's memory.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import time
import zipfile

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from tests.scenes import clip_parts, patch_clip, with_clip_text
from tomgs.cameras import Cameras, intrinsics
from tomgs.cli import main
from tomgs.errors import InputError
from tomgs.io import read_video


def cli(*args):
    result = CliRunner().invoke(main, [str(a) for a in args])
    assert result.exception is None or isinstance(result.exception, SystemExit), \
        "".join(__import__("traceback").format_exception(result.exception))
    return result


def limited(body: str, headroom_mb: int = 768, timeout: float = 120) -> str:
    """Run `body` in a fresh Python whose address space may grow by only `headroom_mb` over what
    importing tomgs (torch, OpenCV, plyfile) took; returns its stdout, fails on a non-zero exit."""
    code = textwrap.dedent("""
        import resource, sys
        import numpy, torch, cv2, plyfile, zipfile, json
        import tomgs.cli.app, tomgs.io.scene, tomgs.io.tets, tomgs.cameras, tomgs.metrics, tomgs.edit.transforms
        size = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmSize")) * 1024
        resource.setrlimit(resource.RLIMIT_AS, (size + HEADROOM, size + HEADROOM))
    """).replace("HEADROOM", str(headroom_mb << 20)) + textwrap.dedent(body)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def write_video(path, frames, fps=25, codec="MJPG"):
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def small_scene(path, frame_indices=(0, 1), width=32, height=24, times=None):
    import torch

    from tomgs.io.scene import save_scene
    from tomgs.model import GaussianModel

    n = 4
    g = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    model = GaussianModel(means, torch.randn(n, 4, generator=g), torch.full((n, 3), -2.0), torch.ones(n),
                          torch.rand(n, 1, 3, generator=g), torch.zeros(n, 0, 3), torch.rand(n, generator=g),
                          torch.full((n,), -1.0))
    T = len(frame_indices)
    cams = Cameras(np.tile(np.eye(4), (T, 1, 1)), intrinsics(30.0, width, height), width, height,
                   np.linspace(0, 1, T) if times is None else times, frame_indices)
    return save_scene(path, model, cams)


def cameras_json(path, **changes):
    cams = Cameras.create(np.tile(np.eye(4), (3, 1, 1)), intrinsics(40.0, 64, 48), 64, 48)
    d = cams.to_dict()
    frame = changes.pop("frame", None)
    if frame is not None:
        d["frames"][1].update(frame)
    d.update(changes)
    path.write_text(json.dumps(d))
    return path


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """A 6-frame 64x48 video with texture (MJPG)."""
    d = tmp_path_factory.mktemp("clip")
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 255, (12, 16, 3), dtype=np.uint8), (64, 48), interpolation=cv2.INTER_LINEAR)
    return write_video(d / "clip.avi", [np.roll(base, k, axis=1) for k in range(6)])


# ---- "A 200 kB file of random bytes named .mp4 decodes as one grey frame" ------------------------

def test_random_bytes_named_mp4_is_not_a_video(tmp_path):
    # seed 6: FFmpeg probes these bytes as a raw H.263 stream and decodes one flat 352x288 frame
    bad = tmp_path / "random.mp4"
    bad.write_bytes(np.random.default_rng(6).bytes(200_000))
    with pytest.raises(InputError, match="random.mp4"):
        read_video(bad)
    result = cli("poses", bad, "-o", tmp_path / "cams.json", "--method", "identity")
    assert result.exit_code == 2 and "random.mp4" in result.output
    result = cli("fit", bad, "-o", tmp_path / "s.ply", "--iterations", "1", "--device", "cpu", "--poses", "identity")
    assert result.exit_code == 2 and "random.mp4" in result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["random.mp4"]


@pytest.mark.parametrize("count", [1, 5])
def test_a_video_of_one_flat_colour_is_refused(tmp_path, count):
    flat = write_video(tmp_path / "grey.avi", [np.full((48, 64, 3), 128, np.uint8)] * count)
    with pytest.raises(InputError, match="flat"):
        read_video(flat)


def test_a_real_video_still_reads(clip):
    video = read_video(clip, frames="1:5")
    assert video.frames.shape == (4, 48, 64, 3) and list(video.indices) == [1, 2, 3, 4]
    assert video.fps == pytest.approx(25)
    assert read_video(clip, frames="-2:").indices.tolist() == [4, 5]


# ---- "Memory follows numbers in files" ------------------------------------------------------------

def test_render_frames_does_not_allocate_by_the_largest_frame_number(tmp_path):
    """`render --frames` picks frames through select_frames: 8 bytes x 2^31 (16 GiB) before the fix."""
    scene = small_scene(tmp_path / "s.ply", frame_indices=(0, 2**31 - 1))
    out = limited(f"""
        from tomgs.io.scene import load_scene
        from tomgs.render.jobs import select_frames
        cams = load_scene({str(scene)!r}).cameras
        print(select_frames(cams, "2147483647").tolist(), select_frames(cams, "0:2147483647").tolist(),
              select_frames(cams, "1000:").tolist(), select_frames(cams, "::2147483647").tolist())
    """, headroom_mb=512)
    assert out.split("\n")[0] == "[1] [0] [1] [0, 1]"


@pytest.mark.parametrize("field, value", [("width", 65536), ("height", 65536), ("width", 0), ("height", -3)])
def test_scene_header_image_size_is_bounded(tmp_path, field, value):
    scene = patch_clip(small_scene(tmp_path / "s.ply"), tmp_path / "big.ply", **{field: value})
    from tomgs.io.scene import load_scene

    with pytest.raises(InputError, match="big.ply"):
        load_scene(scene)
    result = cli("render", scene, "-o", tmp_path / "out.mp4", "--device", "cpu")
    assert result.exit_code == 2 and "big.ply" in result.output
    assert not (tmp_path / "out.mp4").exists()


def _tets(tmp_path):
    """A one-Gaussian tets file (4 vertices, one positive tet), written and read back."""
    from tomgs.edit.tets import DIRECTIONS
    from tomgs.io.tets import Tets, gaussian_tet_indices, load_tets, save_tets

    save_tets(tmp_path / "t.ply", Tets("gaussian", DIRECTIONS.copy(), gaussian_tet_indices(1), np.array([0])))
    return load_tets(tmp_path / "t.ply")


def _bomb(path, name, shape, dtype="<f4", zeros_mb=None):
    """An .npz whose member `name` declares `shape` and decompresses to zeros: a zip bomb."""
    header = np.lib.format.header_data_from_array_1_0(np.zeros((0,), dtype))
    header["shape"] = tuple(shape)
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, header)
    nbytes = int(np.prod(shape)) * np.dtype(dtype).itemsize
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z, z.open(name + ".npy", "w", force_zip64=True) as f:
        f.write(buf.getvalue())
        chunk = bytes(1 << 24)
        left = nbytes if zeros_mb is None else zeros_mb << 20
        while left > 0:
            f.write(chunk[:min(left, len(chunk))])
            left -= len(chunk)
    return path


def test_npz_zip_bomb_is_refused_before_decompressing(tmp_path):
    """A 1 MB .npz whose 'vertices' expands to 1 GiB (a 4.7 MB one once reached 4.9 GB)."""
    mesh = _tets(tmp_path)
    bomb = _bomb(tmp_path / "bomb.npz", "vertices", (2**30 // 48, 4, 3), "<f4")  # V = 4 like the tets file
    wrong = _bomb(tmp_path / "wrong.npz", "vertices", (2**30 // 60, 5, 3), "<f4")  # V = 5: not this mesh
    assert bomb.stat().st_size < 2 << 20
    out = limited(f"""
        from tomgs.errors import InputError
        from tomgs.io.tets import load_tets, load_sequence
        mesh = load_tets({str(tmp_path / "t.ply")!r})
        for path, kw in (({str(wrong)!r}, {{}}), ({str(bomb)!r}, {{"max_frames": 10}})):
            try:
                load_sequence(path, mesh, **kw)
            except InputError as e:
                print("InputError", e)
    """, headroom_mb=512)
    lines = out.strip().split("\n")
    assert len(lines) == 2 and all(l.startswith("InputError") for l in lines), out
    assert "5 vertices, but the tets file has 4" in lines[0]
    assert "10" in lines[1]
    assert mesh is not None


def test_lpips_weights_bomb_is_refused_before_decompressing(tmp_path):
    bomb = _bomb(tmp_path / "lpips.npz", "conv0.weight", (2**28,), "<f4")
    out = limited(f"""
        from tomgs.errors import InputError
        from tomgs.metrics import LPIPS
        try:
            LPIPS({str(bomb)!r})
        except InputError as e:
            print("InputError", e)
    """, headroom_mb=512)
    assert out.startswith("InputError") and "conv0.weight" in out


def test_huge_ply_element_counts_are_refused_before_allocating(tmp_path):
    """Counts x row sizes against the file's size: an ascii or list element of 2^31 rows in 200 bytes."""
    scene = tmp_path / "count.ply"
    scene.write_bytes(b"ply\nformat ascii 1.0\ncomment tomgs-scene {}\nelement vertex 2147483647\n"
                      b"property float x\nelement camera 1\nproperty double time\nend_header\n1\n")
    tets = tmp_path / "tets.ply"
    tets.write_bytes(b"ply\nformat binary_little_endian 1.0\ncomment tomgs tets 1\ncomment kind gaussian\n"
                     b"comment axes blender\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
                     b"element tet 2147483647\nproperty list uchar int vertex_indices\nend_header\n" + bytes(100))
    out = limited(f"""
        from tomgs.errors import InputError
        from tomgs.io.scene import load_scene
        from tomgs.io.tets import load_tets
        for load, path in ((load_scene, {str(scene)!r}), (load_tets, {str(tets)!r})):
            try:
                load(path)
            except InputError as e:
                print("InputError", e)
    """, headroom_mb=512)
    lines = out.strip().split("\n")
    assert len(lines) == 2 and all(l.startswith("InputError") and "2,147,483,647 rows" in l for l in lines), out


def test_a_50_mb_header_comment_is_refused_quickly(tmp_path):
    from tomgs.io.scene import load_scene

    good = small_scene(tmp_path / "s.ply")
    data = good.read_bytes()
    big = tmp_path / "big.ply"
    big.write_bytes(data.replace(b"comment tomgs-scene ", b"comment " + b"x" * (50 << 20) + b"\ncomment tomgs-scene ", 1))
    start = time.perf_counter()
    with pytest.raises(InputError, match="header"):
        load_scene(big)
    assert time.perf_counter() - start < 2.0


# ---- "Tracebacks (exit 1) instead of a message" ---------------------------------------------------

def _deep(depth=100_000):
    return "[" * depth + "]" * depth


def test_deeply_nested_json_is_an_input_error(tmp_path, clip):
    from tomgs.edit.transforms import load_keyframes
    from tomgs.io.scene import load_scene

    deep = tmp_path / "deep.json"
    deep.write_text(_deep())
    with pytest.raises(InputError, match="deep.json"):
        Cameras.load(deep)
    keys = tmp_path / "keys.json"
    keys.write_text('{"keyframes": ' + _deep() + "}")
    scene = small_scene(tmp_path / "s.ply")
    with pytest.raises(InputError, match="keys.json"):
        load_keyframes(keys, load_scene(scene).cameras)
    nested = tmp_path / "nested.ply"
    text = clip_parts(scene)[1]
    with_clip_text(scene, nested, text.replace(b'"info":{}', b'"info":{"a":' + _deep(50_000).encode() + b"}", 1))
    with pytest.raises(InputError, match="nested.ply"):
        load_scene(nested)
    middling = tmp_path / "middling.ply"  # Python reads 500 levels, but every later json.dumps of info would fail
    with_clip_text(scene, middling, text.replace(b'"info":{}', b'"info":{"a":' + _deep(500).encode() + b"}", 1))
    with pytest.raises(InputError, match="middling.ply.*nest deeper"):
        load_scene(middling)
    result = cli("poses", clip, "-o", tmp_path / "c.json", "--method", deep)
    assert result.exit_code == 2 and "deep.json" in result.output
    result = cli("info", nested)
    assert result.exit_code == 2 and "nested.ply" in result.output


SINGULAR = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1]]


@pytest.mark.parametrize("case, changes, message", [
    ("singular c2w", dict(frame={"c2w": SINGULAR}), "singular"),
    ("c2w bottom row", dict(frame={"c2w": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}), "c2w"),
    ("fx = 0", dict(K=[[0, 0, 32], [0, 40, 24], [0, 0, 1]]), "focal"),
    ("fy < 0", dict(K=[[40, 0, 32], [0, -40, 24], [0, 0, 1]]), "focal"),
    ("K bottom row", dict(K=[[40, 0, 32], [0, 40, 24], [0, 1, 1]]), "K"),
    ("width 0", dict(width=0), "width"),
    ("height 65536", dict(height=65536), "height"),
    ("width 1.5", dict(width=1.5), "width"),
    ("width string", dict(width="64"), "width"),
    ("huge frame index", dict(frame={"index": 2**70}), "frame number"),
    ("negative frame index", dict(frame={"index": -1}), "frame number"),
    ("float frame index", dict(frame={"index": 1e30}), "frame number"),
    ("NaN time", dict(frame={"time": float("nan")}), "time"),
    ("infinite time", dict(frame={"time": float("inf")}), "time"),
    ("huge width", dict(width=10**400), "width"),
])
def test_bad_cameras_file_is_an_input_error(tmp_path, clip, case, changes, message):
    path = cameras_json(tmp_path / "cams.json", **changes)
    with pytest.raises(InputError, match=message) as e:
        Cameras.load(path)
    assert "cams.json" in str(e.value), case
    from tomgs.poses import estimate_cameras

    frames = read_video(clip, frames="0:3")
    with pytest.raises(InputError, match="cams.json"):
        estimate_cameras(frames, method=str(path))
    result = cli("poses", clip, "--frames", "0:3", "-o", tmp_path / "out.json", "--method", path)
    assert result.exit_code == 2 and "cams.json" in result.output, (case, result.output)
    assert not (tmp_path / "out.json").exists()


@pytest.mark.parametrize("case, kwargs, message", [
    ("singular c2w", dict(c2w=np.array([np.eye(4), SINGULAR], float)), "singular"),
    ("fx = 0", dict(K=np.diag([0.0, 40.0, 1.0])), "focal"),
    ("width 0", dict(width=0), "width"),
    ("height 65536", dict(height=65536), "height"),
    ("NaN time", dict(times=[0.0, np.nan]), "time"),
    ("huge frame index", dict(frame_indices=[0, 2**40]), "frame number"),
])
def test_cameras_refuse_bad_values_for_python_callers_too(case, kwargs, message):
    args = dict(c2w=np.tile(np.eye(4), (2, 1, 1)), K=intrinsics(40.0, 64, 48), width=64, height=48, times=[0.0, 1.0],
                frame_indices=[0, 1])
    args.update(kwargs)
    with pytest.raises(InputError, match=message):
        Cameras(**args)


def test_nan_frame_time_in_a_scene_is_refused_at_load(tmp_path):
    from tomgs.io.scene import load_scene

    data = bytearray(small_scene(tmp_path / "s.ply").read_bytes())
    # the last camera record: 16 doubles of c2w, then the time (double), then the index (int64)
    end = len(data)
    data[end - 16:end - 8] = np.array([np.nan], "<f8").tobytes()
    (tmp_path / "nan.ply").write_bytes(bytes(data))
    with pytest.raises(InputError, match="time"):
        load_scene(tmp_path / "nan.ply")


def test_nan_frame_time_fails_fit_before_training(tmp_path, clip):
    cams = cameras_json(tmp_path / "cams.json", frame={"time": float("nan")})
    start = time.perf_counter()
    result = cli("fit", clip, "--frames", "0:3", "-o", tmp_path / "s.ply", "--poses", cams, "--device", "cpu",
                 "--preset", "quick")
    assert result.exit_code == 2 and "cams.json" in result.output and "time" in result.output
    assert time.perf_counter() - start < 30
    assert not (tmp_path / "s.ply").exists()


# ---- "`--poses nothere.json` says 'unknown method' instead of 'file not found'" -------------------

@pytest.mark.parametrize("method", ["nothere.json", "poses/c2w.npy", "colmap/sparse/0/", "model.onnx"])
def test_a_missing_pose_file_is_named_as_missing(tmp_path, clip, method):
    from tomgs.poses import estimate_cameras

    frames = read_video(clip, frames="0:3")
    with pytest.raises(InputError, match="does not exist") as e:
        estimate_cameras(frames, method=str(tmp_path / method))
    assert "unknown method" not in str(e.value)
    result = cli("poses", clip, "-o", tmp_path / "c.json", "--method", tmp_path / method)
    assert result.exit_code == 2 and "does not exist" in result.output
    result = cli("poses", clip, "-o", tmp_path / "c.json", "--method", "superglue")
    assert result.exit_code == 2 and "unknown method" in result.output
