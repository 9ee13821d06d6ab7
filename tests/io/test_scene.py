"""Scene files: exact round trip, the INRIA layout, frame selection, summaries, and bad files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

import tomgs
from tests.scenes import clip_parts, inria_load_ply, patch_clip
from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.io import InputError
from tomgs.io.scene import TRAILER_MAGIC, load_scene, save_scene
from tomgs.render.jobs import render_defaults, select_frames
from tomgs.model import PARAM_NAMES, GaussianModel
from tomgs.io.summary import alive_per_frame, format_summary, log_histogram, summarize

# written out by hand from INRIA's GaussianModel.construct_list_of_attributes, not from tomgs
INRIA_DEGREE_3 = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                  + [f"f_rest_{i}" for i in range(45)]
                  + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def random_model(n: int, max_degree: int, degree: int, seed: int = 0) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=g)  # noqa: E731
    model = GaussianModel(r(n, 3) * 0.4 + torch.tensor([0.0, 0.0, 3.0]), r(n, 4), r(n, 3) * 0.3 - 2.5, r(n) + 1.0,
                          r(n, 1, 3), r(n, (max_degree + 1) ** 2 - 1, 3) * 0.2, torch.rand(n, generator=g),
                          r(n) * 0.5 - 2.0, sh_degree=degree)
    if n >= 4:  # awkward float32 values: signed zero, a subnormal, extremes
        with torch.no_grad():
            model.means[0, 0] = -0.0
            model.means[1, 1] = 1e-45
            model.opacity_logits[2] = 3.4e38
            model.t_means[3] = -1e-38
    return model


def random_cameras(T: int, seed: int = 0, width: int = 64, height: int = 36) -> Cameras:
    rng = np.random.default_rng(seed)
    c2w = np.stack([look_at(rng.normal(size=3) * 0.1, [0.0, 0.0, 3.0]) for _ in range(T)])
    c2w[:, :3, 3] += rng.normal(size=(T, 3)) * 1e-9  # digits a float32 or a short repr would lose
    K = intrinsics(57.123456789012345, width, height)
    K[0, 2] += 1 / 3
    times = np.sort(rng.uniform(0, 1, T))
    return Cameras(c2w, K, width, height, times, 10 + 3 * np.arange(T))


def assert_same_scene(a_model, a_cams, b):
    for name in PARAM_NAMES:
        x, y = getattr(a_model, name), getattr(b.model, name)
        assert x.dtype == y.dtype == torch.float32 and x.shape == y.shape, name
        assert x.detach().numpy().tobytes() == y.detach().numpy().tobytes(), name  # bit-identical
    assert (b.model.sh_degree, b.model.max_sh_degree) == (a_model.sh_degree, a_model.max_sh_degree)
    for name in ("c2w", "K", "times", "frame_indices"):
        x, y = getattr(a_cams, name), getattr(b.cameras, name)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
    assert (b.cameras.width, b.cameras.height) == (a_cams.width, a_cams.height)


@pytest.mark.parametrize("max_degree, degree", [(0, 0), (1, 1), (2, 1), (3, 0), (3, 3)])
def test_round_trip_is_exact(tmp_path, max_degree, degree):
    model, cams = random_model(50, max_degree, degree, seed=max_degree), random_cameras(7, seed=degree)
    info = {"fps": 29.97, "psnr": [31.25, 0.1 + 0.2, float("inf")], "nested": {"a": None, "b": True},
            "text": "end_header é\n"}
    path = save_scene(tmp_path / "scene.ply", model, cams, info)
    scene = load_scene(path)
    assert_same_scene(model, cams, scene)
    assert scene.info == info and isinstance(scene, tomgs.Scene)
    # saving what was loaded writes the same bytes again
    save_scene(tmp_path / "again.ply", scene.model, scene.cameras, scene.info)
    assert (tmp_path / "again.ply").read_bytes() == path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.ply", "scene.ply"]  # no temporaries


def test_loaded_scene_does_not_keep_the_file(tmp_path):
    model, cams = random_model(40, 2, 2), random_cameras(5)
    path = save_scene(tmp_path / "s.ply", model, cams)
    scene = load_scene(path)
    size = path.stat().st_size
    with open(path, "r+b") as f:  # overwrite the data in place: a memory-mapped view would change too
        f.seek(size - 2000)
        f.write(b"\xff" * 2000)
    assert_same_scene(model, cams, scene)


def test_empty_model_and_single_frame(tmp_path):
    model, cams = random_model(0, 1, 0), random_cameras(1)
    scene = load_scene(save_scene(tmp_path / "s.ply", model, cams))
    assert_same_scene(model, cams, scene)
    assert scene.info == {}


def test_layout_is_inria_first_then_temporal(tmp_path):
    model, cams = random_model(20, 3, 2), random_cameras(4)
    with torch.no_grad():  # sh_rest[i, j, c] = 1000 i + 10 j + c: where each coefficient lands is visible
        i, j, c = torch.meshgrid(torch.arange(20), torch.arange(15), torch.arange(3), indexing="ij")
        model.sh_rest.copy_((1000 * i + 10 * j + c).float())
    path = save_scene(tmp_path / "s.ply", model, cams, {"notes": "x" * 5000})
    ply = PlyData.read(str(path))
    assert [e.name for e in ply.elements] == ["vertex"]  # one element: parsers that sum every property line
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    assert names[:len(INRIA_DEGREE_3)] == INRIA_DEGREE_3
    assert names[len(INRIA_DEGREE_3):] == ["t_mean", "t_log_sigma"]
    assert not any(n.startswith(("scale_", "rot", "f_rest_")) for n in names[len(INRIA_DEGREE_3):])
    assert all(vertex.data.dtype[n] == np.dtype("<f4") for n in names)
    assert ply.text is False and ply.byte_order == "<"
    # channel-major f_rest: all 15 R coefficients, then G, then B (INRIA's transpose(1, 2).flatten)
    for channel in range(3):
        for coeff in range(15):
            np.testing.assert_array_equal(vertex[f"f_rest_{channel * 15 + coeff}"],
                                          1000 * np.arange(20) + 10 * coeff + channel)
    np.testing.assert_array_equal(vertex["opacity"], model.opacity_logits.detach().numpy())
    np.testing.assert_array_equal(vertex["rot_0"], model.quats[:, 0].detach().numpy())
    np.testing.assert_array_equal(vertex["t_log_sigma"], model.log_t_scales.detach().numpy())
    # the header: short lines, `element vertex` third (SIBR), far under 10 kB (antimatter15/splat reads that much)
    data = path.read_bytes()
    header = data[:data.index(b"end_header\n") + len(b"end_header\n")]
    lines = header.decode("ascii").splitlines()
    assert lines[2] == "element vertex 20" and max(map(len, lines)) <= 200 and len(header) < 4096
    # the clip after the vertex rows: magic, JSON, then float64 camera records
    rest = data[len(header) + 20 * len(names) * 4:]
    assert rest.startswith(b"\ntomgs-scene-data\n")
    length = int.from_bytes(rest[18:26], "little")
    clip = json.loads(rest[26:26 + length])
    assert clip["version"] == 2 and clip["cameras"] == 4 and clip["info"]["notes"] == "x" * 5000
    records = np.frombuffer(rest[26 + length:], dtype=[("c2w", "<f8", (16,)), ("time", "<f8"), ("index", "<i8")])
    np.testing.assert_array_equal(records["c2w"].reshape(-1, 4, 4), cams.c2w)
    np.testing.assert_array_equal(records["time"], cams.times)
    np.testing.assert_array_equal(records["index"], cams.frame_indices)


def test_inria_loader_reads_the_gaussians(tmp_path):
    """INRIA's GaussianModel.load_ply, transcribed (tests.scenes.inria_load_ply): first element, names
    matched by prefix, the f_rest_ count of its degree asserted."""
    model = random_model(30, 3, 3)
    inria = inria_load_ply(save_scene(tmp_path / "s.ply", model, random_cameras(2)), 3)
    np.testing.assert_array_equal(inria["means"], model.means.detach().numpy())
    np.testing.assert_array_equal(inria["opacity_logits"], model.opacity_logits.detach().numpy())
    np.testing.assert_array_equal(inria["sh_dc"], model.sh_dc.detach().numpy()[:, 0])
    np.testing.assert_array_equal(inria["sh_rest"], model.sh_rest.detach().numpy())
    np.testing.assert_array_equal(inria["log_scales"], model.log_scales.detach().numpy())
    np.testing.assert_array_equal(inria["quats"], model.quats.detach().numpy())


def test_degree_zero_has_no_f_rest(tmp_path):
    ply = PlyData.read(str(save_scene(tmp_path / "s.ply", random_model(5, 0, 0), random_cameras(2))))
    names = [p.name for p in ply["vertex"].properties]
    assert names == INRIA_DEGREE_3[:9] + INRIA_DEGREE_3[54:] + ["t_mean", "t_log_sigma"]


def test_save_refuses_what_would_not_load_and_keeps_the_old_file(tmp_path, monkeypatch):
    path = save_scene(tmp_path / "s.ply", random_model(5, 1, 0), random_cameras(2))
    before = path.read_bytes()
    bad = random_model(5, 1, 0)
    with torch.no_grad():
        bad.log_t_scales[3] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        save_scene(path, bad, random_cameras(2))
    with pytest.raises(ValueError, match="JSON"):
        save_scene(path, random_model(5, 1, 0), random_cameras(2), {"x": object()})

    class DiskFull:  # the header and the Gaussians are written, then the disk fills up
        @staticmethod
        def pack(*args):
            raise OSError("disk full")

    monkeypatch.setattr("tomgs.io.scene.struct", DiskFull)
    with pytest.raises(OSError):
        save_scene(path, random_model(6, 1, 0), random_cameras(3))
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["s.ply"]


# ---- bad files ---------------------------------------------------------------------------------

def _write_ply(path, elements, comments):
    PlyData(elements, text=False, byte_order="<", comments=comments).write(str(path))


def save_version_1(path, model, cams, info=None):
    """A scene file as tomgs 0.1 wrote it (format version 1): the header JSON in a comment, the cameras
    as a second element `camera`. Written here from the format's description, so that old files stay
    readable whatever save_scene writes now."""
    scene = load_scene(save_scene(path, model, cams, info))  # the vertex rows are the same in both versions
    vertex = PlyData.read(str(path))["vertex"].data.copy()
    c2w = [f"c2w_{r}{c}" for r in range(4) for c in range(4)]
    camera = np.empty(len(cams), dtype=[(n, "<f8") for n in c2w] + [("time", "<f8"), ("index", "<i4")])
    for j, name in enumerate(c2w):
        camera[name] = cams.c2w.reshape(len(cams), 16)[:, j]
    camera["time"], camera["index"] = cams.times, cams.frame_indices
    header = {"format": "tomgs-scene", "version": 1, "width": cams.width, "height": cams.height,
              "K": cams.K.tolist(), "sh_degree": scene.model.sh_degree, "max_sh_degree": scene.model.max_sh_degree,
              "tomgs": "0.1.0", "info": info or {}}
    _write_ply(path, [PlyElement.describe(vertex, "vertex"), PlyElement.describe(camera, "camera")],
               ["tomgs-scene " + json.dumps(header, separators=(",", ":"))])
    return path


@pytest.mark.parametrize("max_degree, degree", [(0, 0), (3, 1)])
def test_version_1_files_still_load(tmp_path, max_degree, degree):
    model, cams = random_model(30, max_degree, degree), random_cameras(5)
    path = save_version_1(tmp_path / "old.ply", model, cams, {"fps": 12.0})
    assert [e.name for e in PlyData.read(str(path)).elements] == ["vertex", "camera"]
    scene = load_scene(path)
    assert_same_scene(model, cams, scene)
    assert scene.info == {"fps": 12.0}


def _rewrite(src, dst, *, drop_vertex=(), drop_camera=False, comment=None, vertex_fn=None):
    ply = PlyData.read(str(src))
    v = ply["vertex"].data
    keep = [n for n in v.dtype.names if n not in drop_vertex]
    v2 = np.empty(len(v), dtype=[(n, v.dtype[n]) for n in keep])
    for n in keep:
        v2[n] = v[n]
    if vertex_fn:
        vertex_fn(v2)
    elements = [PlyElement.describe(v2, "vertex")]
    if not drop_camera:
        elements.append(PlyElement.describe(ply["camera"].data, "camera"))
    _write_ply(dst, elements, ply.comments if comment is None else comment)
    return dst


@pytest.fixture
def good(tmp_path):
    return save_version_1(tmp_path / "good.ply", random_model(8, 1, 1), random_cameras(3))


@pytest.fixture
def good2(tmp_path):
    return save_scene(tmp_path / "good2.ply", random_model(8, 1, 1), random_cameras(3), {"fps": 3.0})


def _file(path, data: bytes):
    path.write_bytes(data)
    return path


def _nan_opacity(v):
    v["opacity"][2] = np.nan


@pytest.mark.parametrize("make, message", [
    (lambda d, g: d / "missing.ply", "does not exist"),
    (lambda d, g: d, "does not exist"),
    (lambda d, g: _file(d / "x.ply", b"hello, not a ply"), "not a PLY file"),
    (lambda d, g: _file(d / "t.ply", g.read_bytes()[:-40]), "damaged or truncated"),
    (lambda d, g: _file(d / "h.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n"),
     "damaged or truncated"),
    (lambda d, g: _rewrite(g, d / "p.ply", drop_vertex=("t_log_sigma",)), "lacks properties t_log_sigma"),
    (lambda d, g: _rewrite(g, d / "r.ply", drop_vertex=("rot_3", "f_rest_8")), "f_rest_8, rot_3"),
    (lambda d, g: _rewrite(g, d / "c.ply", drop_camera=True), "no 'camera' element"),
    (lambda d, g: _rewrite(g, d / "i.ply", comment=["made by a 3DGS trainer"]), "--cameras cameras.json"),
    (lambda d, g: _rewrite(g, d / "j.ply", comment=["tomgs-scene {not json"]), "not valid JSON"),
    (lambda d, g: _rewrite(g, d / "v.ply", comment=['tomgs-scene {"format": "tomgs-scene", "version": 9}']),
     "version 9"),
    (lambda d, g: _rewrite(g, d / "n.ply", vertex_fn=_nan_opacity), "non-finite"),
])
def test_bad_files_raise_input_error(tmp_path, good, make, message):
    bad = make(tmp_path, good)
    with pytest.raises(InputError, match=message) as e:
        load_scene(bad)
    assert str(bad) in str(e.value)


@pytest.mark.parametrize("make, message", [
    (lambda d, g: _file(d / "a.ply", clip_parts(g)[0]), "cameras and settings after the Gaussians are missing"),
    (lambda d, g: _file(d / "b.ply", clip_parts(g)[0] + b"\nsomething-else-entirely\n" + b"0" * 400),
     "do not start the clip's data"),
    (lambda d, g: _file(d / "c.ply", g.read_bytes()[:-1]), "holds 431 bytes of camera records"),
    (lambda d, g: _file(d / "d.ply", g.read_bytes() + b"\0" * 144), "declares 3 cameras but holds 576"),
    (lambda d, g: _file(d / "e.ply", clip_parts(g)[0] + TRAILER_MAGIC + (2**63).to_bytes(8, "little")),
     "claim"),
    (lambda d, g: patch_clip(g, d / "f.ply", cameras=0), "declares 0 cameras"),
    (lambda d, g: patch_clip(g, d / "g.ply", cameras=True), "declares True cameras"),
    (lambda d, g: patch_clip(g, d / "h.ply", width=None), "'width' is missing"),
    (lambda d, g: patch_clip(g, d / "i.ply", version=7), "version 7"),
    (lambda d, g: _file(d / "j.ply", g.read_bytes().replace(b"tomgs-scene 2:", b"tomgs-scene 9:")), "version 9"),
    (lambda d, g: patch_clip(g, d / "k.ply", K=[[-57.0, 0, 32], [0, 57.0, 18], [0, 0, 1]]), "bad cameras"),
])
def test_bad_version_2_files_raise_input_error(tmp_path, good2, make, message):
    assert load_scene(good2).info == {"fps": 3.0}
    bad = make(tmp_path, good2)
    with pytest.raises(InputError, match=message) as e:
        load_scene(bad)
    assert str(bad) in str(e.value)


def test_more_f_rest_than_the_header_says(tmp_path, good):
    ply = PlyData.read(str(good))
    header = json.loads(ply.comments[0].split(None, 1)[1])
    header["max_sh_degree"] = 0
    header["sh_degree"] = 0
    bad = _rewrite(good, tmp_path / "d.ply", comment=["tomgs-scene " + json.dumps(header)])
    with pytest.raises(InputError, match="f_rest_"):
        load_scene(bad)


# ---- frames and summaries ----------------------------------------------------------------------

def test_select_frames_uses_the_scene_numbering():
    cams = Cameras.create(np.tile(np.eye(4), (5, 1, 1)), np.eye(3), 8, 8, frame_indices=[10, 12, 14, 16, 18])
    assert select_frames(cams, None).tolist() == [0, 1, 2, 3, 4]
    assert select_frames(cams, "12:17").tolist() == [1, 2, 3]
    assert select_frames(cams, "10:19:4").tolist() == [0, 2, 4]
    assert select_frames(cams, "14").tolist() == [2]
    assert select_frames(cams, "-1").tolist() == [4]
    assert select_frames(cams, "12:").tolist() == [1, 2, 3, 4]
    assert select_frames(cams, "12:40").tolist() == [1, 2, 3, 4]  # a stop past the end is clamped, as slicing does
    assert select_frames(cams, "10:90:4").tolist() == [0, 2, 4]  # 10, 14, 18
    for spec in ("0:5", "19", "19:40", "13", "13:40:2", "x:y", "::0", "-30:"):
        with pytest.raises(InputError):
            select_frames(cams, spec)


def test_render_defaults_come_from_info_when_valid():
    assert render_defaults({}) == ((0.0, 0.0, 0.0), 25.0)
    assert render_defaults({"fps": 12, "background": [1, 0.5, 0]}) == ((1.0, 0.5, 0.0), 12.0)
    assert render_defaults({"fps": "fast", "background": [2, 0, 0]}) == ((0.0, 0.0, 0.0), 25.0)
    assert render_defaults({"fps": -1, "background": "white"}) == ((0.0, 0.0, 0.0), 25.0)


def test_alive_per_frame_matches_the_renderer():
    from tomgs.render.sequence import render_sequence

    model, cams = random_model(200, 0, 0, seed=3), Cameras.create(
        np.tile(np.eye(4), (4, 1, 1)), intrinsics(40.0, 32, 18), 32, 18)
    counts, ever = alive_per_frame(model, cams)
    rendered = [int(meta["n_alive"]) for _, _, meta in render_sequence(model.render_inputs(), cams)]
    assert counts.tolist() == rendered
    assert 0 < min(rendered) < len(model) and ever.sum() >= max(rendered)


def test_log_histogram_bins_by_doubling():
    edges, counts = log_histogram(np.array([0.3, 0.6, 0.7, 1.5, 3.0, 100.0]))
    assert edges.tolist() == [0.25, 0.5, 1, 2, 4, 8, 16, 32, 64, 128]
    assert counts.tolist() == [1, 2, 1, 1, 0, 0, 0, 0, 1] and counts.sum() == 6
    edges, counts = log_histogram(np.geomspace(1e-9, 1e9, 1000), max_bins=10)
    assert len(counts) == 10 and counts.sum() == 1000  # extremes fall into the outer bins


def test_summary_numbers(tmp_path):
    model, cams = random_model(30, 2, 1), random_cameras(5)
    with torch.no_grad():
        model.opacity_logits[:3] = -20.0  # three Gaussians that can never be seen
    path = save_scene(tmp_path / "s.ply", model, cams, {"fps": 12})
    s = summarize(load_scene(path), path)
    assert (s["gaussians"], s["frames"], s["width"], s["height"]) == (30, 5, 64, 36)
    assert (s["sh_degree"], s["max_sh_degree"]) == (1, 2)
    assert s["file_bytes"] == path.stat().st_size and s["frame_numbers"] == [10, 22]
    assert s["never_alive"] >= 3 and s["opacity"]["below_1_255"] == 3
    assert sum(s["temporal_sigma_frames"]["counts"]) == 30
    sigma = np.exp(model.log_t_scales.detach().double().numpy()) * 4
    assert s["temporal_sigma_frames"]["median"] == pytest.approx(np.median(sigma))
    json.dumps(s)  # plain JSON
    text = format_summary(s)
    assert "30 Gaussians" in text and "5 frames" in text and "SH degree 1 of 2" in text and "#" in text


def test_rows_written_in_chunks_round_trip_exactly(tmp_path, monkeypatch):
    """save_scene writes the vertex rows a chunk at a time (no host copy of the whole cloud): chunk
    boundaries inside the cloud change no byte."""
    model, cams = random_model(25, 3, 2), random_cameras(3)
    whole = save_scene(tmp_path / "whole.ply", model, cams).read_bytes()
    monkeypatch.setattr("tomgs.io.scene.SAVE_CHUNK", 7)
    path = save_scene(tmp_path / "chunked.ply", model, cams)
    assert path.read_bytes() == whole
    assert_same_scene(model, cams, load_scene(path))
