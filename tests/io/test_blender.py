"""The Blender round trip with real Blender: tomgs/data/blender_softbody.py (`tomgs example
blender_softbody.py` prints its installed path) drops a tets cage headless.

Skips when `blender` is not on PATH, unless TOMGS_REQUIRE_BLENDER=1 (CI sets it), then fails
(the `blender` fixture in conftest.py).
"""

from __future__ import annotations

import itertools
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tomgs.io.tets import Tets, load_sequence, load_tets, save_tets

SCRIPT = Path(__file__).resolve().parents[2] / "tomgs" / "data" / "blender_softbody.py"
W = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float64)  # world (OpenCV) -> Blender axes
FRAMES, DROP = 24, 0.5


def block_cage(n=2, size=1.0):
    """A cube of n^3 cells, 6 Kuhn tets each, in world axes: vertices [V,3], tets [T,4] with
    positive volume."""
    g = np.arange(n + 1)
    verts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) * (size / n)
    idx = lambda p: (p[0] * (n + 1) + p[1]) * (n + 1) + p[2]  # noqa: E731
    tets = []
    for cell in itertools.product(range(n), repeat=3):
        for perm in itertools.permutations(range(3)):
            p, tet = np.array(cell), [idx(cell)]
            for axis in perm:
                p = p.copy()
                p[axis] += 1
                tet.append(idx(p))
            tets.append(tet)
    tets = np.array(tets)
    vol = signed_volumes(verts, tets)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return verts, tets


def signed_volumes(verts, tets):
    x = verts[..., tets, :]
    e = x[..., 1:, :] - x[..., :1, :]
    return np.linalg.det(np.swapaxes(e, -1, -2)) / 6.0


def write_cage_ply(path, world_verts, tets):
    """A `cage` tets file (tomgs.io.tets.save_tets) bound to no Gaussian: the script needs only the mesh."""
    save_tets(path, Tets("cage", world_verts, tets, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4))))


def run_blender(blender, *args, timeout=240):
    cmd = [blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(SCRIPT), "--", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def dropped(blender, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("blender")
    world, tets = block_cage(2, 1.0)
    ply, out = tmp / "cage.ply", tmp / "seq.npz"
    write_cage_ply(ply, world, tets)
    r = run_blender(blender, "--tets", str(ply), "--out", str(out), "--frames", str(FRAMES),
                    "--drop", str(DROP), "--substeps", "4")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return world @ W.T, tets, out, r.stdout, ply


def test_softbody_drop(dropped):
    rest, tets, out, log, _ = dropped
    with np.load(out) as z:
        seq, frames = z["vertices"], z["frames"]
    assert seq.dtype == np.float32 and seq.shape == (FRAMES, len(rest), 3)
    np.testing.assert_array_equal(frames, np.arange(FRAMES))
    assert np.isfinite(seq).all()
    # Frame 0 is the file's vertices, in the file's order, raised by --drop along Blender Z.
    np.testing.assert_allclose(seq[0], rest + [0, 0, DROP], atol=1e-5)
    com_z = seq[:, :, 2].mean(1)
    assert (np.diff(com_z[:6]) < 0).all(), com_z  # falls from the start
    # ... at the real rate: before it reaches the floor (t = 0.32 s) it has fallen g t^2 / 2.
    t = np.arange(1, 7) / 24.0
    np.testing.assert_allclose(com_z[0] - com_z[1:7], 9.81 * t**2 / 2, rtol=0.15)
    floor = rest[:, 2].min()
    lowest = seq[-1, :, 2].min()
    assert floor - 1e-3 <= lowest <= floor + 0.05, (lowest, floor)  # rests on the floor, not in it
    assert seq[:, :, 2].min() >= floor - 0.02  # never sinks far into it either
    assert com_z[-1] < com_z[0] - 0.8 * DROP
    vol = signed_volumes(seq.astype(np.float64), tets)
    assert (vol > 0).all(), np.argwhere(vol <= 0)[:5]
    assert "blender_softbody:" in log


def test_sequence_loads_back(dropped):
    rest, _, out, _, ply = dropped
    vertices, frames = load_sequence(out, like=load_tets(ply))
    assert vertices.shape == (FRAMES, len(rest), 3)
    np.testing.assert_array_equal(frames, np.arange(FRAMES))
    # Back in world axes: frame 0 is the rest pose raised by --drop, i.e. moved along -y (up).
    np.testing.assert_allclose(vertices[0], rest @ W + [0, -DROP, 0], atol=1e-5)


@pytest.mark.parametrize("case", ["missing", "not_ply", "bad_frames"])
def test_softbody_bad_input(blender, tmp_path, case):
    out = tmp_path / "seq.npz"
    args = {"missing": ["--tets", str(tmp_path / "nope.ply")],
            "not_ply": ["--tets", str(tmp_path / "x.ply")],
            "bad_frames": ["--tets", str(tmp_path / "x.ply"), "--frames", "1"]}[case]
    (tmp_path / "x.ply").write_text("hello")
    r = run_blender(blender, *args, "--out", str(out), timeout=120)
    assert r.returncode == 2, r.stdout[-2000:] + r.stderr[-2000:]
    assert "error:" in r.stderr and not out.exists()
