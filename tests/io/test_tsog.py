"""Compressed scenes (.tsog): the round trip within each attribute's quantisation step, the render
within a stated PSNR, the clip kept exactly, and malformed files refused (one line, exit 2 from the
CLI, nothing decoded past a size that does not fit, nothing written)."""

from __future__ import annotations

import json
import re
import struct
import warnings
import zlib

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.cli import main
from tomgs.errors import InputError
from tomgs.io import quantise, tsog
from tomgs.io.scene import load_scene, save_scene
from tomgs.metrics import evaluate
from tomgs.model import PARAM_NAMES, GaussianModel
from tomgs.render.sequence import render_sequence

W, H, T = 64, 36, 6


def wall_model(n: int = 400, max_sh_degree: int = 0, seed: int = 7) -> GaussianModel:
    """A textured wall of Gaussians at depth ~3: random colours, sizes, rotations, opacities and
    temporal windows (some alive the whole clip, some a few frames)."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    xy = rand(n, 2) * torch.tensor([2.6, 1.6]) - torch.tensor([1.3, 0.8])
    means = torch.cat([xy, 3.0 + 0.2 * rand(n, 1)], 1)
    rest = (max_sh_degree + 1) ** 2 - 1
    return GaussianModel(means, torch.randn(n, 4, generator=g), torch.log(0.03 + 0.1 * rand(n, 3)),
                         torch.randn(n, generator=g) + 1.5, (rand(n, 1, 3) - 0.5) * 3.0,
                         (rand(n, rest, 3) - 0.5) * 0.4, rand(n), torch.log(0.05 + 0.5 * rand(n)),
                         sh_degree=max_sh_degree)


def wall_cameras(first: int = 20) -> Cameras:
    c2w = np.stack([look_at([0.05 * k, 0.0, 0.0], [0.0, 0.0, 3.0]) for k in range(T)])
    return Cameras.create(c2w, intrinsics(50.0, W, H), W, H, frame_indices=np.arange(first, first + T))


def arrays_of(model) -> dict:
    return {name: getattr(model, name).detach().numpy() for name in PARAM_NAMES}


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """(model, cameras, info, .tsog path) of the wall."""
    model, cams = wall_model(), wall_cameras()
    info = {"fps": 12.0, "background": [0.0, 0.0, 0.2], "note": "a wall", "odd": float("nan")}
    path = tmp_path_factory.mktemp("tsog") / "wall.tsog"
    save_scene(path, model, cams, info)
    return model, cams, info, path


# ---- the round trip ---------------------------------------------------------------------------------

def _nearest_entry(values, book):
    """The entry of `book` nearest each value (brute force: the reference for encode_codebook)."""
    book = np.asarray(book, np.float64)
    return book[np.abs(np.asarray(values, np.float64)[..., None] - book).argmin(-1)]


def _assert_means_and_times_within_their_steps(header, a, b, means_bits, t_bits):
    """The means within half a step of their grid about the header's centre: (u, v) of the direction's
    octahedral map on [-1, 1] and log r between the header's ends; t_means within half a step after
    `squash`. `a`: the original arrays in the file's order, `b`: the decoded ones."""
    entry, t = header["means"], header["t_means"]
    r_lo, r_hi = entry["log_r"]
    step = np.array([2.0, 2.0, r_hi - r_lo]) / ((1 << means_bits) - 1)
    pa, pb = quantise.polar(a["means"], entry["centre"]), quantise.polar(b["means"], entry["centre"])
    pa[:, 2] = np.clip(pa[:, 2], r_lo, r_hi)
    assert (np.abs(pb - pa) <= step / 2 * 1.0001 + 1e-6).all(), np.abs(pb - pa).max(0) / step
    sa, sb = (quantise.squash(x["t_means"], *t["linear"]) for x in (a, b))
    assert np.abs(sb - sa).max() <= (t["max"] - t["min"]) / ((1 << t_bits) - 1) / 2 * 1.0001 + 1e-6


@pytest.mark.parametrize("max_sh_degree", [0, 2])
def test_round_trip_within_each_quantisation_step(tmp_path, max_sh_degree):
    model, cams = wall_model(300, max_sh_degree), wall_cameras()
    path = save_scene(tmp_path / "s.tsog", model, cams, {})
    assert path.read_bytes().startswith(tsog.MAGIC)
    back = load_scene(path)
    header, _, order = tsog.encode_gaussians(arrays_of(model), centre=cams.c2w[:, :3, 3].mean(0))
    a = {name: value[order].astype(np.float64) for name, value in arrays_of(model).items()}  # the file's order
    b = {name: value.astype(np.float64) for name, value in arrays_of(back.model).items()}
    assert back.model.max_sh_degree == max_sh_degree and len(back.model) == 300

    _assert_means_and_times_within_their_steps(header, a, b, 16, 16)
    for name, key in (("log_scales", "log_scales"), ("sh_dc", "sh_dc"), ("log_t_scales", "log_t_scales")):
        np.testing.assert_allclose(b[name], _nearest_entry(a[name], header[key]["codebook"]), rtol=0, atol=1e-6)
    opacity = 1 / (1 + np.exp(-a["opacity_logits"]))
    np.testing.assert_allclose(1 / (1 + np.exp(-b["opacity_logits"])),
                               _nearest_entry(opacity, header["opacities"]["codebook"]), rtol=0, atol=1e-6)
    unit = a["quats"] / np.linalg.norm(a["quats"], axis=1, keepdims=True)
    sign = np.sign((unit * b["quats"]).sum(1, keepdims=True))
    assert np.abs(b["quats"] - sign * unit).max() <= 2 / 255  # kept components 1/(255 sqrt 2), the largest from them
    if max_sh_degree:  # 300 vectors, a palette of up to 4096: every vector is its own entry, then the codebook
        np.testing.assert_allclose(b["sh_rest"], _nearest_entry(a["sh_rest"], header["sh_rest"]["codebook"]),
                                   rtol=0, atol=1e-6)
    else:
        assert b["sh_rest"].shape == (300, 0, 3)


@pytest.mark.parametrize("means_bits, t_bits", [(12, 16), (16, 10), (8, 8)])
def test_fewer_bits_round_trip_within_their_step(tmp_path, means_bits, t_bits):
    model, cams = wall_model(300), wall_cameras()
    arrays = arrays_of(model)
    records = np.zeros(len(cams), np.dtype([("c2w", "<f8", (16,)), ("time", "<f8"), ("index", "<i8")]))
    records["c2w"] = cams.c2w.reshape(-1, 16)
    records["time"], records["index"] = cams.times, cams.frame_indices
    clip = {"format": "tomgs-scene", "version": 2, "width": W, "height": H, "K": cams.K.tolist(), "sh_degree": 0,
            "max_sh_degree": 0, "tomgs": "test", "cameras": T, "info": {}}
    path = tsog.write_tsog(tmp_path / "s.tsog", arrays, clip, records, means_bits=means_bits, t_bits=t_bits)
    header, _, order = tsog.encode_gaussians(arrays, means_bits, t_bits, tsog.camera_centre(records))
    back = arrays_of(load_scene(path).model)
    a = {name: value[order].astype(np.float64) for name, value in arrays.items()}
    _assert_means_and_times_within_their_steps(header, a, {k: v.astype(np.float64) for k, v in back.items()},
                                               means_bits, t_bits)
    assert path.stat().st_size < save_scene(tmp_path / "full.tsog", model, cams, {}).stat().st_size


def far_scene(n: int = 800, focal: float = 100.0, width: int = 96, height: int = 54):
    """(model, cameras): sharp isotropic Gaussians of 1.5 px between 0.05 and 2 in front of a camera
    that slides 6 mm, and strays: five Gaussians 20-705 away, a t_mean of 1e4, log scales of -30 and 8
    (the last one all but transparent)."""
    g = torch.Generator().manual_seed(5)
    rand = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    depth = 0.05 * torch.exp(rand(n) * np.log(40.0))
    means = torch.stack([(rand(n) - 0.5) * width / focal * depth, (rand(n) - 0.5) * height / focal * depth, depth], 1)
    log_scales = torch.log(1.5 * depth / focal)[:, None].repeat(1, 3)  # isotropic: the rotations do not show
    t_means, opacity_logits = rand(n), torch.full((n,), 3.0)
    means[-5:] = torch.tensor([[300.0, -200, 700], [-500, 100, 650], [0, 0, 705], [50, 400, -600], [-700, -3, 20]])
    t_means[-6] = 1e4
    log_scales[-7], log_scales[-8], opacity_logits[-8] = -30.0, 8.0, -20.0
    model = GaussianModel(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), log_scales, opacity_logits,
                          (rand(n, 1, 3) - 0.5) * 3, torch.zeros(n, 0, 3), t_means, torch.zeros(n))
    c2w = np.stack([look_at([0.002 * k, 0.0, 0.0], [0.002 * k, 0.0, 1.0]) for k in range(4)])
    return model, Cameras.create(c2w, intrinsics(focal, width, height), width, height, frame_indices=np.arange(4))


def test_far_gaussians_do_not_coarsen_the_near_ones(tmp_path):
    """A few Gaussians hundreds of units out and a stray t_mean: the .tsog still renders within what
    a loss of 0.2 dB of a 40 dB scene allows (53.3 dB against the PLY's renders)."""
    from tomgs.metrics import copy_psnr, required_copy_psnr

    model, cams = far_scene()
    back = load_scene(save_scene(tmp_path / "far.tsog", model, cams, {})).model
    assert copy_psnr(model, back, cams) >= required_copy_psnr(40.0, 0.2)


def test_a_stray_t_mean_leaves_the_others_fine(tmp_path):
    model, cams = far_scene()
    arrays = arrays_of(model)
    header, _, order = tsog.encode_gaussians(arrays, centre=cams.c2w[:, :3, 3].mean(0))
    back = arrays_of(load_scene(save_scene(tmp_path / "t.tsog", model, cams, {})).model)
    error = np.abs(back["t_means"] - arrays["t_means"][order])
    bulk = arrays["t_means"][order] < 2
    assert error[bulk].max() < 2e-4  # 16 bits over [0, 1.75] and the stray's log: steps of 2.6e-4 (min/max: 0.15)
    assert abs(back["t_means"][~bulk][0] - 1e4) < 1e4 * 1e-3


def test_codebook_outliers_get_their_own_entries():
    """Extreme values no longer spread the bulk's histogram over their range: the bulk is coded as
    well as without them, and the extremes are entries themselves."""
    rng = np.random.default_rng(0)
    bulk = rng.normal(-5.0, 1.0, 200_000)
    alone = np.abs(_nearest_entry(bulk, quantise.codebook(bulk)) - bulk)
    book = quantise.codebook(np.concatenate([bulk, [-1e4, -3e3, 40.0, 1e4]]))
    error = np.abs(_nearest_entry(bulk, book) - bulk)
    assert np.quantile(error, 0.999) < 0.1 and np.sqrt(np.mean(error ** 2)) < 1.05 * np.sqrt(np.mean(alone ** 2))
    assert book.min() == -1e4 and book.max() == 1e4


def test_clip_and_info_come_back_exactly(saved):
    model, cams, info, path = saved
    back = load_scene(path)
    for name in ("c2w", "K", "times", "frame_indices"):
        x, y = getattr(cams, name), getattr(back.cameras, name)
        assert x.dtype == y.dtype and x.tobytes() == y.tobytes(), name
    assert (back.cameras.width, back.cameras.height) == (W, H) and back.model.sh_degree == model.sh_degree
    assert back.info["note"] == "a wall" and back.info["fps"] == 12.0 and np.isnan(back.info["odd"])


def test_render_within_stated_psnr_of_the_original(saved):
    """The compressed wall renders within 40 dB PSNR of the original at every frame (float renders)."""
    model, cams, _, path = saved
    original = np.stack([image.numpy() for _, image, _ in render_sequence(model.render_inputs(), cams,
                                                                          device="cpu")])
    report = evaluate(load_scene(path).model, cams, original, device="cpu")
    assert min(report.psnr) > 40.0, report.psnr


def test_empty_and_awkward_models_round_trip(tmp_path):
    cams = wall_cameras()
    empty = wall_model(0)
    back = load_scene(save_scene(tmp_path / "e.tsog", empty, cams, {}))
    assert len(back.model) == 0 and back.model.means.shape == (0, 3)
    model = wall_model(20)
    with torch.no_grad():  # extremes a float32 scene can hold: saturated opacities, a subnormal, a zero quaternion
        model.opacity_logits[0], model.opacity_logits[1] = 3.4e38, -3.4e38
        model.means[2, 0] = 1e-45
        model.quats[3] = 0.0
        model.means[4] = torch.tensor([1e30, -1e30, 3.0])
    back = load_scene(save_scene(tmp_path / "a.tsog", model, cams, {}))
    assert all(torch.isfinite(getattr(back.model, name)).all() for name in PARAM_NAMES)
    assert back.model.opacities.max() > 0.999 and back.model.opacities.min() < 1e-3


def test_a_version_1_file_without_checksums_still_loads(saved, tmp_path):
    """Version 1: the means per axis in sign(x) log(1 + |x|) between mins and maxs, t_mean between its
    min and max, no checksums. Made here from the version 2 file's decoded scene."""
    *_, path = saved
    now = arrays_of(load_scene(path).model)
    header, rest = _parts(path)
    width, height = header["grid"]
    log_means = quantise.signed_log(now["means"])
    mins, maxs = log_means.min(0), log_means.max(0)
    q = quantise.fixed(log_means, mins, maxs, 16)
    t = now["t_means"].astype(np.float64)
    q_t = quantise.fixed(t, t.min(), t.max(), 16)[:, None]
    columns = {"means_hi": q >> 8, "means_lo": q & 0xFF, "t_hi": q_t >> 8, "t_lo": q_t & 0xFF}
    images, at = [], 0
    for entry in header["images"]:
        data = rest[at:at + entry["bytes"]]
        at += entry["bytes"]
        if entry["name"] in columns:
            data = quantise.encode_webp(quantise.grid_image(columns[entry["name"]], width, height))
        entry.update(bytes=len(data))
        entry.pop("crc32")
        images.append(data)
    header.update(version=1, means={"mins": mins.tolist(), "maxs": maxs.tolist(), "bits": 16},
                  t_means={"min": float(t.min()), "max": float(t.max()), "bits": 16})
    header.pop("records_crc32")
    text = json.dumps(header).encode()
    old = tmp_path / "v1.tsog"
    old.write_bytes(tsog.MAGIC + struct.pack("<Q", len(text)) + text + b"".join(images) + rest[at:])
    back = arrays_of(load_scene(old).model)
    step = (maxs - mins) / 65535
    assert (np.abs(quantise.signed_log(back["means"]) - log_means) <= step / 2 * 1.0001 + 1e-6).all()
    assert np.abs(back["t_means"] - t).max() <= (t.max() - t.min()) / 65535
    for name in ("quats", "log_scales", "opacity_logits", "sh_dc", "log_t_scales"):
        assert np.array_equal(back[name], now[name]), name


def test_a_scene_of_one_repeated_gaussian_is_padded_to_a_byte_a_gaussian(tmp_path):
    """Its images compress to almost nothing; the header's padding keeps it readable under the count's
    bound."""
    n = 40_000
    model = GaussianModel(torch.zeros(n, 3) + 3.0, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                          torch.full((n, 3), -3.0), torch.ones(n), torch.zeros(n, 1, 3), torch.zeros(n, 0, 3),
                          torch.zeros(n), torch.zeros(n))
    path = save_scene(tmp_path / "same.tsog", model, wall_cameras(), {})
    assert path.stat().st_size >= n
    assert len(load_scene(path).model) == n


def test_decoding_takes_little_more_than_the_images_and_the_result(tmp_path, monkeypatch):
    """Float32 a chunk at a time: the peak is the file, its images (20 bytes a Gaussian at SH degree 0)
    and the float32 result (64), not float64 intermediates of every Gaussian."""
    import tracemalloc

    monkeypatch.setattr(tsog, "DECODE_CHUNK", 4096, raising=False)
    n = 60_000
    path = save_scene(tmp_path / "big.tsog", wall_model(n), wall_cameras(), {})
    from tomgs.io.scene import CAMERA_RECORD

    tracemalloc.start()
    try:
        tsog.read_tsog(path, CAMERA_RECORD, lambda clip: clip)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < path.stat().st_size + 110 * n, peak / n


@pytest.mark.parametrize("content", [b"", b"PK\x03\x04" + bytes(300), bytes(range(256)) * 8])
def test_a_tsog_path_that_is_no_tsog_is_told_so(tmp_path, content):
    bad = tmp_path / "x.tsog"
    bad.write_bytes(content)
    result = run("info", bad)
    assert result.exit_code == 2 and "not a compressed tomgs scene" in result.output, result.output
    assert "PLY" not in result.output


def test_a_scene_named_ply_but_compressed_loads_by_its_bytes(saved, tmp_path):
    *_, path = saved
    renamed = tmp_path / "looks_like.ply"
    renamed.write_bytes(path.read_bytes())
    assert len(load_scene(renamed).model) == 400


# ---- quantisation pieces ------------------------------------------------------------------------------

def test_codebook_is_nearest_entry_and_exact_on_few_values():
    rng = np.random.default_rng(0)
    values = np.concatenate([rng.normal(size=5000), rng.normal(size=100) * 40])
    book = quantise.codebook(values)
    assert book.shape == (256,) and (np.diff(book) >= 0).all()
    np.testing.assert_array_equal(book[quantise.encode_codebook(values, book)], _nearest_entry(values, book))
    few = rng.choice(np.float32([-3.5, 0.25, 7.0, 1e-30]), size=1000)
    book = quantise.codebook(few)
    assert np.array_equal(book[quantise.encode_codebook(few, book)], few)  # exact: four values, four entries


def test_grid_holds_the_count_in_whole_rows():
    for n in (0, 1, 255, 256, 257, 5000, 10 ** 6):
        width, height = quantise.grid_shape(n)
        assert width % 4 == 0 and height % 4 == 0 and width * height >= n
        assert width * (height - 4) < max(n, 1) and abs(width - height) <= width // 4 + 4  # no spare row of 4


def test_palette_labels_each_vector_near_its_nearest_entry():
    rng = np.random.default_rng(2)
    centres = rng.normal(size=(600, 9))
    x = (centres[rng.integers(0, 600, 30000)] + 0.05 * rng.normal(size=(30000, 9))).astype(np.float32)
    book, labels = quantise.palette(x, 1024)
    assert book.shape == (1024, 9) and labels.min() >= 0 and labels.max() < 1024
    error = ((x - book[labels]) ** 2).sum(1)
    nearest = ((x[:, None] - book[None]) ** 2).sum(-1).min(1)  # every entry: the reference
    assert error.mean() <= 1.05 * nearest.mean() and (error <= nearest + 1e-6).mean() > 0.99


def test_smallest_three_round_trip():
    q = np.random.default_rng(1).normal(size=(2000, 4))
    back = quantise.unpack_quats(quantise.smallest_three(q))
    unit = q / np.linalg.norm(q, axis=1, keepdims=True)
    assert np.abs(np.abs((back * unit).sum(1)) - 1).max() < 1e-4


# ---- malformed files ---------------------------------------------------------------------------------

def _parts(path):
    """(header dict, the bytes after the header and its CRC-32) of a .tsog file."""
    data, lead = path.read_bytes(), len(tsog.MAGIC) + 8
    (length,) = struct.unpack("<Q", data[lead - 8:lead])
    return json.loads(data[lead:lead + length]), data[lead + length + 4:]


def _with_header(path, dst, header, rest=None):
    """`dst`: `header` (its CRC-32 after it, as a version 2 file has) and `rest` (by default `path`'s)."""
    text = json.dumps(header).encode()
    parts_rest = _parts(path)[1] if rest is None else rest
    dst.write_bytes(tsog.MAGIC + struct.pack("<Q", len(text)) + text + struct.pack("<I", zlib.crc32(text))
                    + parts_rest)
    return dst


def _with_image(path, dst, name, data):
    """`dst`: `path` with image `name` replaced by the bytes `data`, its size and CRC-32 in the header."""
    header, rest = _parts(path)
    sizes = [entry["bytes"] for entry in header["images"]]
    index = [entry["name"] for entry in header["images"]].index(name)
    start = sum(sizes[:index])
    header["images"][index].update(bytes=len(data), crc32=zlib.crc32(data))
    return _with_header(path, dst, header, rest[:start] + data + rest[start + sizes[index]:])


def _edit(path, dst, change):
    header, rest = _parts(path)
    change(header)
    return _with_header(path, dst, header, rest)


def _set(*keys, value):
    def change(header):
        target = header
        for key in keys[:-1]:
            target = target[key]
        target[keys[-1]] = value
    return change


def _bomb_image(path, dst):
    """The opacities image replaced by a 4000x4000 WebP of one colour: a few hundred bytes that decode
    to 16 million pixels."""
    return _with_image(path, dst, "opacities", quantise.encode_webp(np.zeros((4000, 4000, 1), np.uint8)))


def _flip(at):
    """A maker of a copy with one bit flipped at byte `at` (negative: from the end)."""
    def make(path, dst):
        data = bytearray(path.read_bytes())
        data[at] ^= 1  # a digit stays a digit
        return dst.write_bytes(bytes(data))
    return make


def _in_image(name):
    """The offset of the middle byte of image `name` of a .tsog."""
    def offset(path):
        header, rest = _parts(path)
        names = [entry["name"] for entry in header["images"]]
        sizes = [entry["bytes"] for entry in header["images"]]
        index = names.index(name)
        return len(path.read_bytes()) - len(rest) + sum(sizes[:index]) + sizes[index] // 2
    return offset


CASES = {
    "truncated": (lambda p, d: d.write_bytes(p.read_bytes()[:-100]), "do not add up"),
    "truncated in the header": (lambda p, d: d.write_bytes(p.read_bytes()[:200]), "claims"),
    "only the magic": (lambda p, d: d.write_bytes(tsog.MAGIC + b"\x01"), "ends inside its first 17 bytes"),
    "header longer than the file": (lambda p, d: d.write_bytes(tsog.MAGIC + struct.pack("<Q", 10 ** 12) + b"{}"),
                                    "claims 1,000,000,000,000 bytes"),
    "bad JSON": (lambda p, d: d.write_bytes(tsog.MAGIC + struct.pack("<Q", 5) + b"{nope" + bytes(200)),
                 "not valid JSON"),
    "JSON not an object": (lambda p, d: _with_header(p, d, [1, 2]), "lacks \"format\""),
    "wrong version": (lambda p, d: _edit(p, d, _set("version", value=99)), "version 99"),
    "empty": (lambda p, d: d.write_bytes(b""), "is empty, not a compressed tomgs scene"),
    "a ZIP": (lambda p, d: d.write_bytes(b"PK\x03\x04" + bytes(300)), "not a compressed tomgs scene"),
    "random bytes": (lambda p, d: d.write_bytes(np.random.default_rng(0).bytes(3000)), "not a compressed tomgs scene"),
    "no clip": (lambda p, d: _edit(p, d, lambda h: h.pop("clip")), "\"clip\""),
    "bad clip": (lambda p, d: _edit(p, d, _set("clip", "width", value="wide")), "'width'"),
    "count bomb": (lambda p, d: _edit(p, d, _set("count", value=100_000_000)), "at least a byte a Gaussian"),
    "count 100x what the bytes hold": (lambda p, d: _edit(p, d, lambda h: h.update(
        count=h["count"] * 100, grid=list(quantise.grid_shape(h["count"] * 100)))), "at least a byte a Gaussian"),
    "a flipped byte in the header": (lambda p, d: _flip(re.search(rb'"codebook":\[-?(\d)', p.read_bytes()).start(1))(p, d),
                                     "header fails its checksum"),  # a codebook's digit: still valid JSON
    "a flipped byte in an image": (lambda p, d: _flip(_in_image("colours")(p))(p, d),
                                   "image 'colours' fails its checksum"),
    "a flipped byte in a camera record": (_flip(-100), "camera records fail their checksum"),
    "a codebook of 1e308": (lambda p, d: _edit(p, d, lambda h: h["log_scales"]["codebook"].__setitem__(3, 1e308)),
                            "'log_scales'"),
    "a codebook of -1e308": (lambda p, d: _edit(p, d, lambda h: h["sh_dc"]["codebook"].__setitem__(0, -1e308)),
                             "'sh_dc'"),
    "means' range past float32": (lambda p, d: _edit(p, d, _set("means", "log_r", value=[0.0, 1e308])), "'means'"),
    "means' centre past float32": (lambda p, d: _edit(p, d, _set("means", "centre", value=[1e308, 0, 0])), "'means'"),
    "t_means past float32 once unsquashed": (lambda p, d: _edit(p, d, _set("t_means", "max", value=1e30)),
                                             "'t_means'"),
    "t_means' range past float32": (lambda p, d: _edit(p, d, _set("t_means", "max", value=1e308)), "'t_means'"),
    "no image checksum": (lambda p, d: _edit(p, d, lambda h: h["images"][0].pop("crc32")), "'images'"),
    "count past the cap": (lambda p, d: _edit(p, d, _set("count", value=1 << 40)), "'count'"),
    "negative count": (lambda p, d: _edit(p, d, _set("count", value=-1)), "'count'"),
    "wrong grid": (lambda p, d: _edit(p, d, _set("grid", value=[16, 28])), "'grid'"),
    "more Gaussians than pixels hold": (lambda p, d: _edit(p, d, _set("count", value=500)), "'grid'"),
    "image sizes bigger than the bytes": (lambda p, d: _edit(p, d, _set("images", 0, "bytes", value=10 ** 9)),
                                          "do not add up"),
    "images missing": (lambda p, d: _edit(p, d, lambda h: h["images"].pop()), "'images'"),
    "image renamed": (lambda p, d: _edit(p, d, _set("images", 2, "name", value="rotations")), "'images'"),
    "decompression bomb image": (_bomb_image, "4000x4000 image, not the"),
    "NaN in a codebook": (lambda p, d: _edit(p, d, lambda h: h["log_scales"]["codebook"].__setitem__(3, float("nan"))),
                          "'log_scales'"),
    "short codebook": (lambda p, d: _edit(p, d, _set("sh_dc", "codebook", value=[0.0] * 10)), "'sh_dc'"),
    "NaN in the means' range": (lambda p, d: _edit(p, d, _set("means", "centre", value=[0.0, float("nan"), 0.0])),
                                "'means'"),
    "opacity codebook outside (0, 1)": (lambda p, d: _edit(p, d, lambda h: h["opacities"]["codebook"]
                                                           .__setitem__(0, 0.0)), "outside (0, 1)"),
    "an image that is not WebP": (lambda p, d: _corrupt_image(p, d, "means_lo"), "not a readable lossless WebP"),
    "means past their bits": (lambda p, d: _edit(p, d, _set("means", "bits", value=4)), "past the 4 bits"),
    "bits out of range": (lambda p, d: _edit(p, d, _set("t_means", "bits", value=17)), "'t_means'"),
    "wrong quaternion tags": (lambda p, d: _replace_image(p, d, "quats", np.full((20, 20, 4), 7, np.uint8)),
                              "tag outside 252..255"),
}


def _corrupt_image(path, dst, name):
    return _with_image(path, dst, name, bytes(range(256)) * 4)


def _replace_image(path, dst, name, image):
    return _with_image(path, dst, name, quantise.encode_webp(image))


@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_files_raise_input_error_before_decoding_too_much(saved, tmp_path, monkeypatch, case):
    *_, path = saved
    make, message = CASES[case]
    bad = tmp_path / "bad.tsog"
    make(path, bad)
    decoded = []  # pixels decoded: never more than the grid's
    real = quantise.decode_webp

    def counting(data, width, height, channels, what):
        image = real(data, width, height, channels, what)
        decoded.append(image.size)
        return image

    monkeypatch.setattr(quantise, "decode_webp", counting)
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)")) as caught, \
            warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing printed before the one line
        load_scene(bad)
    assert "\n" not in str(caught.value) and str(bad) in str(caught.value)
    assert max(decoded, default=0) <= 20 * 20 * 4  # the wall's grid: 400 Gaussians on 20 x 20 pixels, 4 channels


def test_the_bomb_is_refused_before_its_pixels_are_decoded(saved, tmp_path, monkeypatch):
    from PIL import Image

    *_, path = saved
    bad = _bomb_image(path, tmp_path / "bomb.tsog")
    load = Image.Image.load
    monkeypatch.setattr(Image.Image, "load",
                        lambda self: pytest.fail("decoded the bomb") if self.size == (4000, 4000) else load(self))
    with pytest.raises(InputError, match="4000x4000"):
        load_scene(bad)


@pytest.mark.parametrize("command", [["render", "{bad}", "-o", "{out}/out.mp4", "--device", "cpu"],
                                     ["info", "{bad}"], ["compress", "{bad}", "-o", "{out}/c.tsog"],
                                     ["export", "{bad}", "--frame", "20", "-o", "{out}/f.ply"]])
def test_cli_refuses_a_malformed_file_with_exit_2_and_writes_nothing(saved, tmp_path, command):
    *_, path = saved
    bad = tmp_path / "bad.tsog"
    bad.write_bytes(path.read_bytes()[:-300])
    out = tmp_path / "out"
    out.mkdir()
    result = run(*(word.format(bad=bad, out=out) for word in command))
    assert result.exit_code == 2, result.output
    message = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(message) == 1 and "damaged or truncated compressed scene" in message[0]
    assert list(out.iterdir()) == []
