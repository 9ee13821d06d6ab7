"""tomgs.edit: Gaussians <-> tetrahedra, cages, selections, edits and the tets/sequence files (CPU, tiny)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from plyfile import PlyData

from scenes import object_scene
from tomgs.edit.cage import build_cage, make_tets
from tomgs.edit.selection import parse_selector, select
from tomgs.edit.tets import THICKEN, deform, gaussians_to_tets, tets_to_gaussians
from tomgs.edit.transforms import (Keyframes, affine, edit_model, keyframed_clouds, load_keyframes,
                                   transform_gaussians)
from tomgs.geometry import covariances, signed_volumes
from tomgs.io import InputError
from tomgs.io.scene import Scene
from tomgs.io.tets import FACES, load_sequence, load_tets, save_sequence, save_tets, to_blender
from tomgs.render.sequence import render_sequence


def random_gaussians(n: int, seed: int = 0):
    """Means, quats, scales with extreme anisotropy (scales 1e-4..1e2) and some near-flat ones."""
    rng = np.random.default_rng(seed)
    means = rng.normal(size=(n, 3)) * 3.0
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(np.log(1e-4), np.log(1e2), size=(n, 3)))
    scales[: n // 4, 0] = 1e-9  # near-flat
    return means, quats, scales


def rel_err(a, b):
    return float(np.max(np.linalg.norm(a - b, axis=(-2, -1)) / np.linalg.norm(b, axis=(-2, -1))))


def random_affine(rng, kind: str):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    if kind == "rotation":
        return Q
    if kind == "scale":
        return np.diag(rng.uniform(0.2, 5.0, 3))
    F = rng.normal(size=(3, 3))
    return F if np.linalg.det(F) > 0 else F @ np.diag([1.0, 1.0, -1.0])


def test_tet_round_trip_is_exact():
    means, quats, scales = random_gaussians(400)
    tets = gaussians_to_tets(means, quats, scales)
    m2, q2, s2 = tets_to_gaussians(tets)
    assert np.abs(m2 - means).max() < 1e-6
    assert rel_err(covariances(q2, s2), covariances(quats, scales)) < 1e-6
    assert np.allclose(np.linalg.norm(q2, axis=1), 1.0) and (q2[:, 0] >= 0).all()
    # and back again: the rebuilt Gaussian gives the same tet up to its symmetries (same covariance)
    assert rel_err(covariances(*tets_to_gaussians(gaussians_to_tets(m2, q2, s2))[1:]), covariances(q2, s2)) < 1e-6


def test_thickened_tets_are_positive_and_deform_stays_exact():
    means, quats, scales = random_gaussians(200, seed=1)
    rest = gaussians_to_tets(means, quats, scales, thicken=THICKEN)
    assert (signed_volumes(rest[:, [0, 1, 3, 2]]) > 0).all()
    assert np.abs(rest.mean(1) - means).max() < 1e-9  # thickening keeps the centroid
    # the identity motion of a thickened tet returns the Gaussian's own (flat) covariance
    m2, q2, s2 = deform(rest, rest, means, quats, scales)
    assert np.abs(m2 - means).max() < 1e-9 and rel_err(covariances(q2, s2), covariances(quats, scales)) < 1e-6


@pytest.mark.parametrize("kind", ["rotation", "scale", "general"])
def test_affine_edit_of_vertices_equals_edit_of_mean_and_covariance(kind):
    rng = np.random.default_rng(2)
    means, quats, scales = random_gaussians(300, seed=3)
    F, b = random_affine(rng, kind), rng.normal(size=3)
    for thicken in (0.0, THICKEN):
        rest = gaussians_to_tets(means, quats, scales, thicken=thicken)
        m2, q2, s2 = deform(rest, rest @ F.T + b, means, quats, scales)
        assert np.abs(m2 - (means @ F.T + b)).max() < 1e-6
        assert rel_err(covariances(q2, s2), F @ covariances(quats, scales) @ F.T) < 1e-6


def test_cage_binding_reproduces_tets_and_follows_affine_motion():
    means, quats, scales = random_gaussians(300, seed=4)
    scales = np.minimum(scales, 0.3)  # some tet vertices still stick out of the cage: extrapolated exactly
    rest = gaussians_to_tets(means, quats, scales, thicken=THICKEN)
    cage = build_cage(rest, means, np.arange(300))
    assert len(cage.tets) % 6 == 0 and (signed_volumes(cage.vertices[cage.tets]) > 0).all()
    assert np.abs(cage.gaussian_tets() - rest).max() < 1e-9
    assert np.allclose(cage.binding_weights.sum(1), 1.0)
    F, b = random_affine(np.random.default_rng(5), "general"), np.array([0.3, -1.0, 2.0])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = F, b
    moved = cage.gaussian_tets(cage.vertices @ F.T + b)
    assert np.abs(moved - (rest @ F.T + b)).max() < 1e-9
    got = deform(cage.gaussian_tets(), moved, means, quats, scales)
    want = transform_gaussians(means, quats, scales, M)
    assert np.abs(got[0] - want[0]).max() < 1e-6
    assert rel_err(covariances(*got[1:]), covariances(*want[1:])) < 1e-6


def test_cage_is_connected_and_sized_by_cell():
    means = np.stack(np.meshgrid(*[np.linspace(0, 1, 12)] * 3, indexing="ij"), -1).reshape(-1, 3)
    n = len(means)
    tets = gaussians_to_tets(means, np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), 0.01))
    coarse, fine = build_cage(tets, means, np.arange(n)), build_cage(tets, means, np.arange(n), cell=0.25)
    assert len(coarse.vertices) == 9 ** 3 and len(coarse.tets) == 6 * 8 ** 3  # default cell: extent / 8
    assert len(fine.vertices) == 5 ** 3  # shared grid points: one connected mesh


def test_tets_file_round_trip_axes_order_and_faces(tmp_path):
    model, cams, obj = object_scene()
    for kind in ("gaussian", "cage"):
        mesh = make_tets(model, obj, kind)
        mesh.vertices += np.array([0.0, -1.0, 0.0]) - mesh.vertices[0]  # vertex 0 at "up" in OpenCV axes
        path = save_tets(tmp_path / f"{kind}.ply", mesh)
        raw = PlyData.read(str(path))
        assert {"tomgs tets 1", f"kind {kind}", "axes blender"} <= set(raw.comments)
        xyz = np.stack([raw["vertex"].data[c] for c in "xyz"], 1).astype(np.float64)
        assert np.allclose(xyz[0], (0.0, 0.0, 1.0))  # z up in Blender
        assert np.allclose(xyz, to_blender(mesh.vertices), atol=1e-6)  # vertex order kept
        back = load_tets(path)
        assert back.kind == kind and np.array_equal(back.tets, mesh.tets)
        assert np.array_equal(back.gaussians, obj) and np.abs(back.vertices - mesh.vertices).max() < 1e-6
        if kind == "cage":
            assert np.array_equal(back.binding_tet, mesh.binding_tet)
            assert np.abs(back.binding_weights - mesh.binding_weights).max() < 1e-6
        faces = np.stack(list(raw["face"].data["vertex_indices"]))
        assert len(faces) == 4 * len(mesh.tets)
        p = xyz[faces]  # [4T,3,3] in Blender axes: outward = away from the tet's centroid
        normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        centroid = np.repeat(xyz[mesh.tets].mean(1), 4, axis=0)
        assert (np.einsum("ij,ij->i", normals, p.mean(1) - centroid) > 0).all()
        assert np.array_equal(faces[:4], mesh.tets[0][FACES])


def test_sequence_round_trip_and_bad_frames(tmp_path):
    model, _, obj = object_scene()
    mesh = make_tets(model, obj, "cage")
    frames = np.stack([mesh.vertices + [0.0, -0.1 * f, 0.0] for f in range(3)])
    save_sequence(tmp_path / "seq.npz", frames, frames=[0, 2, 4])
    got, numbers = load_sequence(tmp_path / "seq.npz", mesh)
    assert np.abs(got - frames).max() < 1e-5 and numbers.tolist() == [0, 2, 4]

    def bad(vertices, message):
        np.savez(tmp_path / "bad.npz", vertices=to_blender(vertices).astype(np.float32))
        with pytest.raises(InputError, match=message):
            load_sequence(tmp_path / "bad.npz", mesh)

    bad(frames[:, :-1], "row 0: .* vertices, but the tets file has")
    nan = frames.copy()
    nan[1, 5, 2] = np.nan
    bad(nan, "row 1: NaN")
    inverted = frames.copy()
    inverted[2] = 2 * mesh.vertices.mean(0) - mesh.vertices  # a point reflection turns every tet inside out
    bad(inverted, "row 2: tet 0 is inverted")


def test_selections_and_their_errors(tmp_path):
    model, cams, obj = object_scene()
    assert np.array_equal(select(model, cams, ["sphere:0,0,2.5,0.9"]), obj)
    assert np.array_equal(select(model, cams, ["box:-1,-1,1.5,1,1,3.5", "sphere:0,0,2.5,5"]), obj)
    (tmp_path / "idx.txt").write_text("3, 5\n7")
    assert select(model, cams, [f"index:{tmp_path / 'idx.txt'}"]).tolist() == [3, 5, 7]
    with torch.no_grad():
        model.t_means[obj] = 0.9
        model.log_t_scales[obj] = float(np.log(0.02))
    assert np.array_equal(select(model, cams, ["time:0.8,1"]), np.arange(len(model)))
    assert np.array_equal(select(model, cams, ["time:0.85,0.95", "sphere:0,0,2.5,0.9"]), obj)
    with pytest.raises(InputError, match="matches nothing"):
        select(model, cams, ["time:0,0.5", "sphere:0,0,2.5,0.9"])
    for text in ("cube:1,2,3", "box:1,2", "sphere:0,0,0,-1", "time:a,b", "mask:"):
        with pytest.raises(InputError, match="--select"):
            parse_selector(text)


def test_mask_selection_picks_the_object_by_majority():
    model, cams, obj = object_scene()
    keep = np.setdiff1d(np.arange(len(model)), obj)
    obj_only, _ = edit_model(model, keep, remove=True)
    masks = np.stack([img.numpy().max(-1) > 0.3 for _, img, _ in
                      render_sequence(obj_only.render_inputs(), cams, background=(0.0, 0.0, 0.0))])
    masks[0] = False  # one frame disagrees: the majority still wins
    from tomgs.edit.selection import mask_vote

    picked = np.flatnonzero(mask_vote(model, cams, masks))
    assert len(np.intersect1d(picked, obj)) >= 0.9 * len(obj)
    # a projected mean does not know about occlusion: wall Gaussians right behind the ball vote "inside"
    # too; intersecting with a box in front of the wall leaves the object
    behind = np.setdiff1d(picked, obj)
    assert 0 < len(behind) < 40 and (model.means.detach().numpy()[behind, 2] == 4.0).all()
    assert np.array_equal(np.intersect1d(picked, select(model, cams, ["box:-9,-9,0,9,9,3.5"])), obj)


def render_all(gaussians, cams):
    return torch.stack([img for _, img, _ in render_sequence(gaussians, cams, background=(0.0, 0.0, 0.0))])


def test_remove_reveals_the_background():
    model, cams, obj = object_scene()
    removed, _ = edit_model(model, obj, remove=True)
    background_only = torch.stack([img for _, img, _ in render_sequence(
        {k: v[: obj[0]] for k, v in model.render_inputs().items()}, cams, background=(0.0, 0.0, 0.0))])
    full, edited = render_all(model.render_inputs(), cams), render_all(removed.render_inputs(), cams)
    assert (full - background_only).abs().max() > 0.3  # the ball covered part of the wall
    assert (edited - background_only).abs().max() < 1e-5
    assert len(removed) == len(model) - len(obj)


def test_duplicate_doubles_the_selection_and_both_render():
    model, cams, obj = object_scene()
    dup, rows = edit_model(model, obj, duplicate=(0.8, 0.0, 0.0))
    assert len(dup) == len(model) + len(obj) and rows.tolist() == list(range(len(model), len(dup)))
    assert torch.allclose(dup.means[rows], model.means[obj] + torch.tensor([0.8, 0.0, 0.0]))
    assert torch.equal(dup.sh_dc[rows], model.sh_dc[obj]) and torch.equal(dup.t_means[rows], model.t_means[obj])
    before, after = render_all(model.render_inputs(), cams)[0], render_all(dup.render_inputs(), cams)[0]
    W = before.shape[1]
    centre, offset = W // 2, W // 2 + round(26.0 * 0.8 / 2.5)  # pixel of the ball and of its copy
    assert (after[:, offset] - before[:, offset]).abs().max() > 0.3  # the copy is drawn
    assert (after[:, centre] - before[:, centre]).abs().max() < 0.05  # the original is still there


def test_affine_edit_moves_and_keeps_the_rest():
    model, cams, obj = object_scene()
    M = affine(translate=(0.1, 0.2, 0.3), rotate=(10.0, 20.0, 30.0), scale=(1.0, 2.0, 0.5), centre=(0.0, 0.0, 2.5))
    moved, rows = edit_model(model, obj, M)
    assert np.array_equal(rows, obj)
    want = model.means.detach().double().numpy()[obj] @ M[:3, :3].T + M[:3, 3]
    assert np.abs(moved.means.detach().numpy()[obj] - want).max() < 1e-5
    others = np.setdiff1d(np.arange(len(model)), obj)
    for name in ("means", "quats", "log_scales"):
        assert torch.equal(getattr(moved, name)[others], getattr(model, name)[others])
    for name in ("opacity_logits", "sh_dc", "t_means", "log_t_scales"):
        assert torch.equal(getattr(moved, name), getattr(model, name))


def test_time_varying_edit_changes_only_its_window(tmp_path):
    model, cams, obj = object_scene()  # 5 frames at t = 0, .25, .5, .75, 1
    (tmp_path / "keys.json").write_text(json.dumps({"keyframes": [
        {"t": 0.3, "translate": [0, 0, 0]}, {"frame": 2, "translate": [0.5, 0, 0], "rotate": [0, 0, 45]},
        {"t": 0.7, "translate": [0, 0.5, 0], "scale": 0.5}]}))
    keys = load_keyframes(tmp_path / "keys.json", cams)
    assert isinstance(keys, Keyframes) and keys.times.tolist() == [0.3, 0.5, 0.7]
    base = render_all(model.render_inputs(), cams)
    edited = render_all(keyframed_clouds(model, cams, obj, keys), cams)
    for k in (0, 1, 3, 4):
        assert torch.equal(edited[k], base[k])
    assert (edited[2] - base[2]).abs().max() > 0.3
    held = Keyframes(keys.times, keys.translate, keys.rotations, keys.scale, hold=True)
    assert (render_all(keyframed_clouds(model, cams, obj, held), cams)[4] - base[4]).abs().max() > 0.3


def test_keyframe_interpolation_lerps_and_slerps():
    keys = Keyframes(np.array([0.0, 1.0]), np.array([[0.0, 0, 0], [2.0, 0, 0]]),
                     np.array([[1.0, 0, 0, 0], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]]),
                     np.array([[1.0, 1, 1], [3.0, 3, 3]]))
    M = keys.matrix(0.5, centre=np.zeros(3))
    c, s = np.cos(np.pi / 4), np.sin(np.pi / 4)  # halfway to 90 degrees about z
    assert np.allclose(M[:3, :3], 2.0 * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])) and np.allclose(M[:3, 3], [1, 0, 0])
    assert keys.matrix(1.5, np.zeros(3)) is None


def test_scene_edit_records_itself():
    from tomgs.edit.transforms import edit_scene

    model, cams, obj = object_scene()
    edited, rows = edit_scene(Scene(model, cams, {"fps": 10}), ["sphere:0,0,2.5,0.9"], translate=(1.0, 0.0, 0.0))
    assert edited.info["fps"] == 10 and edited.info["edits"][0]["selected"] == len(obj)
    assert edited.info["edits"][0]["translate"] == [1.0, 0.0, 0.0] and edited.cameras is cams


def test_bad_index_files_are_refused(tmp_path):
    """Numbers past int64 (OverflowError), binary bytes, a file far larger than any index list, negatives."""
    model, cams, _ = object_scene()
    n = len(model)
    cases = {"huge.txt": ("1" + "0" * 30, "whole numbers"), "binary.txt": (b"\xff\xfe\x00\x81", "whole numbers"),
             "big.txt": ("1 " * (20 * n + 2**20), "more than an index file"), "neg.txt": ("-1", "outside"),
             "float.txt": ("1.5", "whole numbers")}
    for name, (content, message) in cases.items():
        path = tmp_path / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        with pytest.raises(InputError, match=message):
            select(model, cams, [f"index:{path}"])
