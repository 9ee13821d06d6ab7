"""Scene files and `tomgs export` in other people's readers: INRIA's load_ply logic, gsply, open3d, a
parser that sums every property line (antimatter15/splat, gsplat.js), .splat and .spz decoders;
the decoded values against what tomgs renders with, an exported frame against `tomgs render`, the
clip's cameras as COLMAP and nerfstudio files, and a scene that lost its cameras getting them back."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from plyfile import PlyData

import tomgs
from tests.scenes import inria_load_ply
from tomgs.cameras import Cameras
from tomgs.cli import main
from tomgs.demo import demo_scene
from tomgs.io.scene import load_scene, save_scene
from tomgs.io.splats import RDF_TO_RUB, SPZ_SH_FLIPS
from tomgs.model import PARAM_NAMES, GaussianModel, rgb_to_sh_dc
from tomgs.temporal import frozen_at

C0 = 0.28209479177387814
FRAMES = 12


def cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def demo_model(sh_degree: int = 1, seed: int = 0) -> tuple[GaussianModel, Cameras]:
    """The demo scene (a wall, a floor and a ball that travels by fading copies) as a model, with a
    little view-dependent colour."""
    g, cams = demo_scene(FRAMES, 96, 54, seed=seed)
    n = len(g["means"])
    rest = torch.randn(n, (sh_degree + 1) ** 2 - 1, 3, generator=torch.Generator().manual_seed(seed)) * 0.05
    model = GaussianModel(g["means"], g["quats"], torch.log(g["scales"]), torch.logit(g["opacities"]),
                          rgb_to_sh_dc(g["colors"]), rest, g["t_means"], torch.log(g["t_scales"]), sh_degree=sh_degree)
    return model, cams


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    model, cams = demo_model()
    return save_scene(tmp_path_factory.mktemp("scene") / "scene.ply", model, cams, {"fps": 12.0})


# ---- readers, written from their sources' logic ------------------------------------------------

def stride_summing_parse(path) -> dict:
    """antimatter15/splat's and gsplat.js's PLY parsing: the first 10 kB hold the header, one row
    stride from every `property` line whatever element it is in, float only (gsplat.js), rows
    from the end of the header; each property by its offset in that stride."""
    data = open(path, "rb").read()
    head = data[:10 * 1024].decode("latin-1")
    end = head.index("end_header\n")
    count = int(re.search(r"element vertex (\d+)\n", head).group(1))
    names, stride = [], 0
    for line in head[:end].split("\n"):
        if line.startswith("property "):
            _, kind, name = line.split(" ")
            if kind != "float":
                raise ValueError(f"Unsupported property type: {kind}")
            names.append(name)
            stride += 4
    body = data[end + len("end_header\n"):][:count * stride]
    if len(body) != count * stride:
        raise ValueError("the rows run past the end of the file")  # a RangeError in JavaScript
    rows = np.frombuffer(body, "<f4").reshape(count, len(names))
    return {name: rows[:, j] for j, name in enumerate(names)}


def expected_static(model, t: float) -> dict:
    """What tomgs renders with at t: the alive Gaussians' activated values, opacity at t (float32)."""
    return {k: v.detach().numpy() for k, v in frozen_at(model.render_inputs(), t).items()}


def assert_matches(decoded: dict, want: dict, what: str):
    """positions exact, activations within 1e-6 (relative for scales), quaternions as stored."""
    np.testing.assert_array_equal(decoded["means"], want["means"], err_msg=what)
    np.testing.assert_array_equal(decoded["quats"], want["quats"], err_msg=what)
    np.testing.assert_allclose(np.exp(decoded["log_scales"].astype(np.float64)), want["scales"], rtol=1e-6,
                               err_msg=what)
    opacity = 1.0 / (1.0 + np.exp(-decoded["opacity_logits"].astype(np.float64)))
    np.testing.assert_allclose(opacity, want["opacities"], atol=1e-6, rtol=0, err_msg=what)
    rgb = 0.5 + C0 * decoded["sh_dc"].astype(np.float64)
    np.testing.assert_allclose(rgb, 0.5 + C0 * want["colors"][:, 0], atol=1e-6, err_msg=what)


def by_names(columns: dict) -> dict:
    """A stride-summing parser's columns in the stored form of `assert_matches`."""
    stack = lambda names: np.stack([columns[n] for n in names], axis=1)  # noqa: E731
    return {"means": stack("xyz"), "quats": stack([f"rot_{i}" for i in range(4)]),
            "log_scales": stack([f"scale_{i}" for i in range(3)]), "opacity_logits": columns["opacity"],
            "sh_dc": stack([f"f_dc_{i}" for i in range(3)])}


# ---- the native scene file in other readers ----------------------------------------------------

def test_native_scene_loads_in_other_readers(scene_path):
    import gsply
    import open3d as o3d

    model = load_scene(scene_path).model
    want = {k: v.detach().numpy() for k, v in model.render_inputs().items()}
    header = scene_path.read_bytes()[:4096].split(b"end_header\n")[0]
    assert max(len(line) for line in header.split(b"\n")) <= 1000  # open3d's RPly aborts past ~1,000

    inria = inria_load_ply(scene_path, model.max_sh_degree)
    assert_matches(inria, want, "INRIA load_ply")
    np.testing.assert_array_equal(inria["sh_rest"], model.sh_rest.detach().numpy())

    columns = stride_summing_parse(scene_path)  # the temporal properties are just more floats to them
    assert_matches(by_names(columns), want, "stride-summing parser")
    np.testing.assert_array_equal(columns["t_mean"], want["t_means"])
    np.testing.assert_allclose(np.exp(columns["t_log_sigma"].astype(np.float64)), want["t_scales"], rtol=1e-6)

    g = gsply.plyread(str(scene_path))
    np.testing.assert_array_equal(np.asarray(g.means), want["means"])
    np.testing.assert_allclose(np.asarray(g.sh0).reshape(-1, 3), model.sh_dc.detach().numpy()[:, 0], atol=1e-6)

    points = o3d.t.io.read_point_cloud(str(scene_path)).point
    np.testing.assert_array_equal(points.positions.numpy(), want["means"])
    np.testing.assert_array_equal(points.t_mean.numpy()[:, 0], want["t_means"])


# ---- exports --------------------------------------------------------------------------------------

@pytest.mark.parametrize("frame", [0, 5, 11])
def test_exported_ply_loads_everywhere_with_what_tomgs_renders(scene_path, tmp_path, frame):
    import gsply
    import open3d as o3d

    scene = load_scene(scene_path)
    t = float(scene.cameras.times[frame])
    want = expected_static(scene.model, t)
    assert 0 < len(want["means"]) < len(scene.model)  # the ball's other copies are dead at t
    out = tmp_path / "f.ply"
    result = cli("export", scene_path, "--frame", frame, "-o", out)
    assert result.exit_code == 0, result.output
    assert f"{len(want['means']):,} of {len(scene.model):,} Gaussians alive at frame {frame}" in result.output
    lines = out.read_bytes().split(b"end_header\n")[0].split(b"\n")
    assert lines[2] == f"element vertex {len(want['means'])}".encode() and not any(b"comment" in x for x in lines)
    assert not any(b"t_mean" in x for x in lines)

    inria = inria_load_ply(out, 1)
    assert_matches(inria, want, "INRIA load_ply")
    np.testing.assert_array_equal(inria["sh_rest"], want["colors"][:, 1:])
    assert_matches(by_names(stride_summing_parse(out)), want, "stride-summing parser")
    g = gsply.plyread(str(out))
    np.testing.assert_array_equal(np.asarray(g.means), want["means"])
    np.testing.assert_allclose(1 / (1 + np.exp(-np.asarray(g.opacities, np.float64).reshape(-1))),
                               want["opacities"], atol=1e-6)
    np.testing.assert_array_equal(o3d.io.read_point_cloud(str(out)).points, want["means"].astype(np.float64))

    padded = tmp_path / "sibr.ply"  # SIBR and INRIA's default loader: exactly 62 floats a row
    assert cli("export", scene_path, "--frame", frame, "-o", padded, "--sh-degree", 3).exit_code == 0
    inria = inria_load_ply(padded, 3)
    assert inria["sh_rest"].shape[1:] == (15, 3) and not inria["sh_rest"][:, 3:].any()
    assert padded.stat().st_size - len(padded.read_bytes().split(b"end_header\n")[0]) - 11 == 62 * 4 * len(want["means"])


def test_splat_and_spz_decode_to_what_tomgs_renders(scene_path, tmp_path):
    import gsply

    scene = load_scene(scene_path)
    want = expected_static(scene.model, float(scene.cameras.times[7]))
    n = len(want["means"])
    assert cli("export", scene_path, "--frame", 7, "-o", tmp_path / "f.splat").exit_code == 0
    rows = np.frombuffer((tmp_path / "f.splat").read_bytes(), dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4),
                                                                      ("r", "u1", 4)])
    assert len(rows) == n
    order = np.lexsort(want["means"].T[::-1])
    got = np.lexsort(rows["p"].T[::-1])
    np.testing.assert_array_equal(rows["p"][got], want["means"][order])
    np.testing.assert_allclose(rows["s"][got], want["scales"][order], rtol=1e-6)
    rgb = np.clip(0.5 + C0 * want["colors"][:, 0].astype(np.float64), 0, 1) * 255
    assert np.abs(rows["c"][got, :3] - rgb[order]).max() <= 0.5 + 1e-6
    assert np.abs(rows["c"][got, 3] - want["opacities"][order] * 255).max() <= 0.5 + 1e-6
    q = want["quats"][order] / np.linalg.norm(want["quats"][order], axis=1, keepdims=True)
    assert np.abs(rows["r"][got] - np.clip(q * 128.0 + 128.0, 0, 255)).max() <= 0.5 + 1e-4  # 1.0 clips to 255
    size = np.exp(np.log(rows["s"].astype(np.float64)).sum(1)) * rows["c"][:, 3]
    assert (np.diff(size) <= 1e-6).all()  # largest first, as the viewers' files are

    assert cli("export", scene_path, "--frame", 7, "-o", tmp_path / "f.spz").exit_code == 0
    g = gsply.read_spz(str(tmp_path / "f.spz"))  # as stored: SPZ's RUB axes (y up, z back), ours turned half round x
    means = np.asarray(g.means) * RDF_TO_RUB
    assert len(means) == n
    np.testing.assert_allclose(means, want["means"], atol=0.5 / 4096 + 1e-6)  # 12 fractional bits
    np.testing.assert_allclose(np.asarray(g.scales), np.log(want["scales"]), atol=0.5 / 16 + 1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-np.asarray(g.opacities, np.float64).reshape(-1))),
                               want["opacities"], atol=0.5 / 255 + 1e-4)
    np.testing.assert_allclose(np.asarray(g.sh0).reshape(-1, 3), want["colors"][:, 0], atol=0.5 / (0.15 * 255) + 1e-5)
    np.testing.assert_allclose(np.asarray(g.shN).reshape(n, -1, 3) * SPZ_SH_FLIPS[:3, None], want["colors"][:, 1:],
                               atol=0.5 / 128 + 1e-5)
    unit = want["quats"] / np.linalg.norm(want["quats"], axis=1, keepdims=True)
    dots = np.abs((np.asarray(g.quats, np.float64) * [1.0, 1.0, -1.0, -1.0] * unit).sum(1))
    assert dots.min() > 1 - 1e-4  # the same rotation (q and -q alike), to the 9-bit smallest three


def test_spz_opacities_decode_finite_as_the_format_s_reader_decodes_them(tmp_path):
    """PlayCanvas's splat-transform read 110 of a moment's 10,287 .spz opacities as +inf: a byte of 255
    (or 0) is the logit of 1 (or 0) to the reader Niantic ships (load-spz.cc: invSigmoid(alpha / 255.0f)
    in float32). Every opacity, however close to 0 or 1, is written as a byte it decodes finitely."""
    import gzip
    import struct

    from tomgs.io.splats import StaticGaussians, write_static

    logits = np.array([-30.0, -8.0, -0.5, 0.0, 3.0, 6.0, 8.0, 30.0], np.float32)
    n = len(logits)
    g = StaticGaussians(np.zeros((n, 3), np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                        np.full((n, 3), -3.0, np.float32), logits, np.zeros((n, 3), np.float32),
                        np.zeros((n, 0, 3), np.float32))
    data = gzip.decompress(write_static(tmp_path / "o.spz", g).read_bytes())
    magic, version, count = struct.unpack_from("<III", data)
    assert count == n and version >= 2
    alphas = np.frombuffer(data, np.uint8, count=n, offset=16 + 9 * n).astype(np.float32)  # after the positions
    with np.errstate(divide="ignore"):
        decoded = np.log((alphas / np.float32(255)) / (np.float32(1) - alphas / np.float32(255)))
    assert np.isfinite(decoded).all(), alphas
    opacity = 1 / (1 + np.exp(-logits.astype(np.float64)))
    assert np.abs(1 / (1 + np.exp(-decoded.astype(np.float64))) - opacity).max() <= 1 / 255 + 1e-6


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0**2 / mse)


def render_static(columns: dict, cams: Cameras, k: int) -> np.ndarray:
    """An exported PLY rendered as a static scene (no time: every Gaussian at its stored opacity)."""
    n = len(columns["means"])
    image, _, _ = tomgs.rasterize(
        means=torch.as_tensor(columns["means"]), quats=torch.as_tensor(columns["quats"]),
        scales=torch.exp(torch.as_tensor(columns["log_scales"])), opacities=torch.sigmoid(torch.as_tensor(
            columns["opacity_logits"])), colors=torch.cat([torch.as_tensor(columns["sh_dc"])[:, None],
                                                           torch.as_tensor(columns["sh_rest"])], 1),
        t_means=torch.zeros(n), t_scales=torch.full((n,), 1e30), viewmat=cams.viewmats("cpu")[k], K=cams.Ks("cpu")[k],
        width=cams.width, height=cams.height, t=0.0, background=torch.zeros(3))
    return (image.numpy() * 255 + 0.5).astype(np.uint8)


def test_an_exported_frame_renders_as_tomgs_render_does(scene_path, tmp_path):
    import cv2

    scene = load_scene(scene_path)
    for frame in (3, 9):
        assert cli("export", scene_path, "--frame", frame, "-o", tmp_path / f"{frame}.ply").exit_code == 0
        assert cli("render", scene_path, "--frames", frame, "-o", tmp_path / f"r{frame}", "--background",
                   "0,0,0").exit_code == 0
        want = cv2.cvtColor(cv2.imread(str(tmp_path / f"r{frame}" / f"{frame:05d}.png")), cv2.COLOR_BGR2RGB)
        got = render_static(inria_load_ply(tmp_path / f"{frame}.ply", 1), scene.cameras, frame)
        assert want.std() > 20 and psnr(got, want) >= 45.0, psnr(got, want)


def test_layers_join_the_moment_in_front(tmp_path):
    """A foreground layer (flat Gaussians on its own plane cameras) exported with the background
    renders from the base camera as `tomgs render --layer` composites them."""
    import cv2

    from tomgs.render.layers import plane_cameras

    model, cams = demo_model(sh_degree=0)
    bg = save_scene(tmp_path / "bg.ply", model, cams)
    front, _ = plane_cameras(FRAMES, cams.width, cams.height)
    g = torch.Generator().manual_seed(3)
    n = 300
    # distinct depths: coplanar overlapping Gaussians have no order, and any two sorts may differ
    means = torch.cat([torch.rand(n, 2, generator=g) * 0.5 - 0.25, torch.rand(n, 1, generator=g) * 0.2 - 0.1], 1)
    fg_model = GaussianModel(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.log(torch.full((n, 3), 0.02)),
                             torch.full((n,), 2.0), rgb_to_sh_dc(torch.rand(n, 3, generator=g)), torch.zeros(n, 0, 3),
                             torch.rand(n, generator=g), torch.full((n,), math.log(0.2)))
    fg = save_scene(tmp_path / "fg.ply", fg_model, front)
    k = 6
    result = cli("export", bg, "--layer", fg, "--frame", k, "-o", tmp_path / "both.ply")
    assert result.exit_code == 0, result.output
    assert cli("render", bg, "--layer", fg, "--frames", k, "-o", tmp_path / "r", "--background", "0,0,0").exit_code == 0
    want = cv2.cvtColor(cv2.imread(str(tmp_path / "r" / f"{k:05d}.png")), cv2.COLOR_BGR2RGB)
    got = render_static(inria_load_ply(tmp_path / "both.ply", 0), cams, k)
    alone = render_static(inria_load_ply(_export(bg, k, tmp_path / "bg_only.ply"), 0), cams, k)
    assert psnr(alone, want) < 30  # the layer shows
    assert psnr(got, want) >= 40.0, psnr(got, want)


def _export(scene, frame, out):
    assert cli("export", scene, "--frame", frame, "-o", out).exit_code == 0
    return out


# ---- cameras out, and back in ---------------------------------------------------------------------

def test_cameras_out_as_colmap_nerfstudio_and_tomgs(scene_path, tmp_path):
    cams = load_scene(scene_path).cameras
    result = cli("export", scene_path, "--cameras-out", tmp_path / "cams")
    assert result.exit_code == 0, result.output
    back = Cameras.load(tmp_path / "cams" / "cameras.json")
    for name in ("c2w", "K", "times", "frame_indices"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cams, name))
    colmap = Cameras.from_colmap(tmp_path / "cams" / "sparse" / "0")  # re-anchored on frame 0, as ours already are
    np.testing.assert_allclose(colmap.c2w, cams.c2w, atol=1e-12)
    np.testing.assert_array_equal(colmap.K, cams.K)
    images = (tmp_path / "cams" / "sparse" / "0" / "images.txt").read_text().split("\n")
    assert images[1].endswith(" 1 00000.png") and images[3].endswith(" 1 00001.png")
    ns = json.loads((tmp_path / "cams" / "transforms.json").read_text())
    assert (ns["w"], ns["h"], ns["fl_x"], ns["cx"]) == (cams.width, cams.height, cams.K[0, 0], cams.K[0, 2])
    opencv = np.array([f["transform_matrix"] for f in ns["frames"]]) @ np.diag([1.0, -1.0, -1.0, 1.0])
    np.testing.assert_allclose(opencv, cams.c2w, atol=1e-15)
    assert [f["file_path"] for f in ns["frames"]][:2] == ["images/00000.png", "images/00001.png"]
    # a folder that is not empty is kept unless --overwrite, and then only these files are replaced
    (tmp_path / "cams" / "notes.txt").write_text("mine")
    assert cli("export", scene_path, "--cameras-out", tmp_path / "cams").exit_code == 2
    assert cli("export", scene_path, "--cameras-out", tmp_path / "cams", "-y").exit_code == 0
    assert (tmp_path / "cams" / "notes.txt").read_text() == "mine"


def resaved_like_splat_transform(src, dst):
    """What SuperSplat and splat-transform write back: the vertex properties (temporal ones kept as
    extra columns), no comment, nothing after the rows."""
    from tomgs.io.scene import ply_header

    rows = PlyData.read(str(src))["vertex"].data
    dst.write_bytes(ply_header(rows.dtype.names, len(rows)) + rows.tobytes())
    return dst


def test_a_resaved_scene_gets_its_cameras_back(scene_path, tmp_path):
    import cv2

    stripped = resaved_like_splat_transform(scene_path, tmp_path / "edited.ply")
    result = cli("render", stripped, "--frames", 4, "-o", tmp_path / "x")
    assert result.exit_code == 2 and "--cameras cameras.json" in result.output and not (tmp_path / "x").exists()
    assert cli("export", scene_path, "--cameras-out", tmp_path / "cams").exit_code == 0
    result = cli("render", stripped, "--cameras", tmp_path / "cams" / "cameras.json", "--frames", 4, "-o", tmp_path / "a")
    assert result.exit_code == 0, result.output
    assert cli("render", scene_path, "--frames", 4, "-o", tmp_path / "b").exit_code == 0
    a, b = (cv2.imread(str(tmp_path / d / "00004.png")) for d in "ab")
    np.testing.assert_array_equal(a, b)
    scene = load_scene(stripped, cameras=tmp_path / "cams" / "cameras.json")
    original = load_scene(scene_path)
    assert scene.model.max_sh_degree == original.model.max_sh_degree and scene.info == {}
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "t_means", "log_t_scales"):
        torch.testing.assert_close(getattr(scene.model, name), getattr(original.model, name), rtol=0, atol=0)
    result = cli("info", stripped, "--cameras", tmp_path / "cams" / "cameras.json", "--json")
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("args, message", [
    (["--frame", 99, "-o", "{out}/a.ply"], "not one of the scene's frames"),
    (["--frame", -1, "-o", "{out}/a.ply"], "--frame -1: out of range; give a frame number in 0.."),
    (["--time", 1.5, "-o", "{out}/a.ply"], "--time 1.5: out of range; give clip time in 0..1"),
    (["--time", "nan", "-o", "{out}/a.ply"], "--time nan: not a finite number"),
    (["--frame", 1, "--time", 0.5, "-o", "{out}/a.ply"], "exactly one"),
    (["-o", "{out}/a.ply"], "--frame K"),
    (["--frame", 1, "-o", "{out}/a.obj"], "unknown format '.obj'"),
    (["--frame", 1, "-o", "{out}/a"], "unknown format '(no extension)'"),
    (["--frame", 1], "give -o OUT"),
    (["--frame", 1, "--cameras-out", "{out}/c"], "give -o too"),
    (["--frame", 1, "-o", "{out}/a.ply", "--layer", "{out}/nothere.ply"], "does not exist"),
    (["--frame", 1, "-o", "{out}/nofolder/a.ply"], "does not exist"),
])
def test_bad_export_input_exits_2_and_writes_nothing(scene_path, tmp_path, args, message):
    out = tmp_path / "out"
    out.mkdir()
    result = cli("export", scene_path, *[str(a).format(out=out) for a in args])
    assert result.exit_code == 2 and message in result.output, result.output
    assert list(out.iterdir()) == []


def test_export_refuses_to_replace_a_file_without_overwrite(scene_path, tmp_path):
    out = tmp_path / "a.splat"
    out.write_bytes(b"keep")
    assert cli("export", scene_path, "--frame", 1, "-o", out).exit_code == 2 and out.read_bytes() == b"keep"
    assert cli("export", scene_path, "--frame", 1, "-o", out, "-y").exit_code == 0 and out.read_bytes() != b"keep"


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_a_moment_with_nothing_alive_exports_an_empty_sog(tmp_path, sh_degree):
    """A scene whose Gaussians all die before the frame, and one with none at all: a valid SOG of 0."""
    import zipfile

    model, cams = demo_model(sh_degree)
    with torch.no_grad():
        model.t_means[:] = 0.0
        model.log_t_scales[:] = -8.0
    empty = GaussianModel(**{name: getattr(model, name).detach()[:0] for name in PARAM_NAMES}, sh_degree=sh_degree)
    for name, scene in (("dead", model), ("empty", empty)):
        path = save_scene(tmp_path / f"{name}.ply", scene, cams, {})
        out = tmp_path / f"{name}.sog"
        result = cli("export", path, "--frame", FRAMES - 1, "-o", out)
        assert result.exit_code == 0, result.output
        with zipfile.ZipFile(out) as archive:
            assert json.loads(archive.read("meta.json"))["count"] == 0
            assert {"means_l.webp", "quats.webp", "sh0.webp"} <= set(archive.namelist())
