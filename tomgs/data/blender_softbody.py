"""Drop a tomgs tets cage as a soft body onto a floor in Blender, headless, and write the frames.

    blender -b --factory-startup --python-exit-code 1 --python "$(tomgs example blender_softbody.py)" -- \
        --tets cage.ply --out seq.npz [--frames 80] [--fps 24] [--drop 0.5] [--stiffness 0.9]

Input: a tets PLY written by `tomgs tets export` (binary little endian, Blender axes, Z up; see
docs/editing.md, "Blender round trip"). It should be of kind `cage`: its tets share vertices, so the soft
body's edge springs hold them together as one body. A `gaussian` file (one separate tet per
Gaussian) is accepted with a warning, but every tet then falls on its own.

Output: an .npz vertex sequence, `vertices` float32 [F, V, 3] in Blender axes in the file's
vertex order and `frames` int [F] = 0..F-1; frame 0 is the start pose (the input raised by
--drop). Bring it back with `tomgs tets import SCENE TETS.ply SEQ.npz -o out.mp4`.

The PLY is read here, not with Blender's importer, so that the vertex order is the file's by
construction (the importer keeps it too with "merge vertices" off, but this does not depend on
the add-on's version). Exit codes: 2 bad input (message says which file and why), 1 the
simulation broke (a tet inverted, vertices changed); nothing is written then.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

try:
    import bpy
except ImportError:  # run outside Blender
    sys.exit("blender_softbody.py runs inside Blender: blender -b --python \"$(tomgs example blender_softbody.py)\" -- ...")
try:
    import numpy as np
except ImportError:  # Debian's blender only recommends it
    sys.exit("blender_softbody.py needs numpy in Blender's Python: apt-get install python3-numpy")

PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4",
             "uint": "<u4", "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1",
             "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
             "float32": "<f4", "float64": "<f8"}

# Blender's soft body advances a fixed time per frame whatever the scene's frame rate, and slower
# than real time (its source, softbody.c sb_time_scale, notes a unit pendulum swinging in 65
# frames where theory says 50). Measured here on Blender 3.4: a free fall matches g = 9.81 when
# speed = SPEED_FPS / fps (checked at 24 and 48 fps).
SPEED_FPS = 31.6


class BadInput(Exception):
    """Bad input file or option: exit 2 with the message."""


class SimulationFailed(Exception):
    """The soft body produced frames that would not import: exit 1 with the message."""


def parse_args(argv):
    p = argparse.ArgumentParser(
        prog="blender -b --factory-startup --python blender_softbody.py --",
        description="Drop a tomgs tets CAGE (kind cage: tets sharing vertices, one connected body) "
                    "as a soft body onto a floor at its lowest vertex and write the vertex sequence. "
                    "A kind-gaussian file (disconnected tets) falls apart into separate pieces.")
    p.add_argument("--tets", required=True, help="tets PLY (tomgs tets export, kind cage), Blender axes")
    p.add_argument("--out", required=True, help="output .npz: vertices [F,V,3] float32, frames [F]")
    p.add_argument("--frames", type=int, default=80, help="frames to simulate, start pose included")
    p.add_argument("--fps", type=float, default=24.0, help="frame rate: one frame is 1/fps seconds")
    p.add_argument("--drop", type=float, default=0.5,
                   help="start this far above the floor (scene units; the floor is at the lowest vertex)")
    p.add_argument("--stiffness", type=float, default=0.9,
                   help="edge spring pull and push, in (0, 1): higher keeps the shape better")
    p.add_argument("--bend", type=float, default=2.0, help="bending stiffness, 0..10")
    p.add_argument("--damping", type=float, default=5.0, help="edge spring damping, 0..50")
    p.add_argument("--substeps", type=int, default=10, help="minimum solver steps per frame")
    a = p.parse_args(argv)
    if a.frames < 2:
        raise BadInput(f"--frames {a.frames}: needs at least 2 frames")
    if not 1 <= a.fps <= 1000:
        raise BadInput(f"--fps {a.fps}: must be in 1..1000")
    if not 0 <= a.drop < 1e6:
        raise BadInput(f"--drop {a.drop}: must be >= 0")
    if not 0 < a.stiffness < 1:
        raise BadInput(f"--stiffness {a.stiffness}: must be in (0, 1)")
    if not 0 <= a.bend <= 10 or not 0 <= a.damping <= 50 or not 1 <= a.substeps <= 1000:
        raise BadInput("--bend must be in 0..10, --damping in 0..50, --substeps in 1..1000")
    if not a.out.endswith(".npz"):
        raise BadInput(f"--out {a.out}: must end in .npz")
    return a


def read_ply(path):
    """Binary little-endian PLY -> (comments, {element: array}). Scalar elements become
    structured arrays; an element with one list property becomes an int64 [count, n] array
    (every row must have the same length n, as faces and tets in a tets file do)."""
    if not os.path.isfile(path):
        raise BadInput(f"{path}: no such file")
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise BadInput(f"{path}: not a PLY file")
    lines = data[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise BadInput(f"{path}: not a binary little-endian PLY (write it with tomgs tets export)")
    comments, elements = [], []
    for line in lines[1:]:
        w = line.split()
        if not w or w[0] in ("format", "obj_info"):
            continue
        if w[0] == "comment":
            comments.append(line[len("comment "):].strip())
        elif w[0] == "element" and len(w) == 3:
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements and len(w) in (3, 5):
            elements[-1][2].append(w[1:])
        else:
            raise BadInput(f"{path}: unreadable header line {line!r}")
    pos, out = end + len(b"end_header\n"), {}
    for name, count, props in elements:
        lists = [q for q in props if q[0] == "list"]
        try:
            if not lists:
                dt = np.dtype([(q[1], PLY_TYPES[q[0]]) for q in props])
                arr = np.frombuffer(data, dt, count, pos)
            elif len(props) == 1:
                ct, it = np.dtype(PLY_TYPES[props[0][1]]), np.dtype(PLY_TYPES[props[0][2]])
                n = int(np.frombuffer(data, ct, 1, pos)[0]) if count else 0
                dt = np.dtype([("n", ct), ("v", it, (n,))])
                rows = np.frombuffer(data, dt, count, pos)
                if np.any(rows["n"] != n):
                    raise BadInput(f"{path}: element {name} mixes list lengths")
                arr = rows["v"].astype(np.int64).reshape(count, n)
            else:
                raise BadInput(f"{path}: element {name} mixes lists and scalars")
        except (KeyError, ValueError) as e:
            raise BadInput(f"{path}: element {name} cannot be read ({e}); truncated or unknown type") from None
        pos += count * dt.itemsize
        out[name] = arr
    return comments, out


def load_tets(path):
    """-> (vertices [V,3] float64 Blender axes, faces [F,3] int, tets [T,4] int, kind)."""
    comments, el = read_ply(path)
    if "tomgs tets 1" not in comments or "axes blender" not in comments:
        raise BadInput(f"{path}: not a tomgs tets file (no 'comment tomgs tets 1' / 'axes blender'); "
                       "write it with tomgs tets export")
    kinds = [c.split()[1] for c in comments if c.startswith("kind ") and len(c.split()) == 2]
    for need in ("vertex", "face", "tet"):
        if need not in el:
            raise BadInput(f"{path}: no '{need}' element")
    v = el["vertex"]
    if not all(k in (v.dtype.names or ()) for k in "xyz"):
        raise BadInput(f"{path}: vertex element has no x, y, z")
    verts = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    faces, tets = el["face"], el["tet"]
    if len(verts) < 4 or faces.shape[1:] != (3,) or tets.shape[1:] != (4,):
        raise BadInput(f"{path}: needs >= 4 vertices, triangle faces and 4-vertex tets")
    if not np.isfinite(verts).all():
        raise BadInput(f"{path}: vertex coordinates are not finite")
    for what, idx in (("face", faces), ("tet", tets)):
        if idx.min() < 0 or idx.max() >= len(verts):
            raise BadInput(f"{path}: {what} indices outside 0..{len(verts) - 1}")
    if (signed_volumes(verts, tets) <= 0).any():
        raise BadInput(f"{path}: {int((signed_volumes(verts, tets) <= 0).sum())} tets have "
                       "non-positive volume (the file says a tet's 4 vertices in positive order)")
    return verts, faces, tets, (kinds[0] if kinds else "unknown")


def signed_volumes(verts, tets):
    """[..., V, 3], [T, 4] -> [..., T]: det(x1 - x0, x2 - x0, x3 - x0) / 6."""
    x = verts[..., tets, :]
    e = x[..., 1:, :] - x[..., :1, :]
    return np.linalg.det(np.swapaxes(e, -1, -2)) / 6.0


def build_scene(verts, faces, args):
    """Empty scene with the body (raised by --drop) and a passive floor at its lowest vertex."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = max(1, round(args.fps))
    scene.render.fps_base = scene.render.fps / args.fps
    scene.frame_start, scene.frame_end = 1, args.frames
    # Shared faces of a cage come twice (once per tet); one copy is enough for the edges.
    _, first = np.unique(np.sort(faces, 1), axis=0, return_index=True)
    faces = faces[np.sort(first)]
    start = verts + np.array([0.0, 0.0, args.drop])
    mesh = bpy.data.meshes.new("tets")
    mesh.from_pydata(start.tolist(), [], faces.tolist())
    mesh.update()
    body = bpy.data.objects.new("tets", mesh)
    scene.collection.objects.link(body)

    lo, hi = verts.min(0), verts.max(0)
    size = float(max(hi - lo))
    cx, cy, half, z = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, 5 * size, float(lo[2])
    fmesh = bpy.data.meshes.new("floor")
    fmesh.from_pydata([(cx - half, cy - half, z), (cx + half, cy - half, z),
                       (cx + half, cy + half, z), (cx - half, cy + half, z)], [], [(0, 1, 2, 3)])
    floor = bpy.data.objects.new("floor", fmesh)
    scene.collection.objects.link(floor)
    floor.modifiers.new("Collision", "COLLISION")
    # Vertices stop this far above the plane: small against the body, so it rests on the floor.
    floor.collision.thickness_outer = max(1e-3, 0.01 * size)
    floor.collision.damping = 0.5

    sb = body.modifiers.new("Softbody", "SOFT_BODY")
    s = sb.settings
    s.use_goal = False  # free body: nothing pins vertices to the rest shape
    s.use_edges = True  # springs along every tet edge
    s.use_self_collision = False
    s.pull = s.push = args.stiffness
    s.bend = args.bend
    s.damping = args.damping
    s.friction = 0.1  # air friction (drag): low, so the fall is close to free fall
    s.mass = 1.0
    s.speed = SPEED_FPS / args.fps  # real time: one frame is 1/fps seconds
    s.step_min = args.substeps
    s.step_max = max(args.substeps, 300)
    s.use_auto_step = True
    sb.point_cache.frame_start, sb.point_cache.frame_end = 1, args.frames
    return scene, body, sb


def simulate(scene, body, sb, n_vertices, frames):
    """Bake the point cache, then read the evaluated vertices of every frame: [F, V, 3] float32."""
    with bpy.context.temp_override(scene=scene, active_object=body, object=body,
                                   point_cache=sb.point_cache):
        bpy.ops.ptcache.bake(bake=True)
    if not sb.point_cache.is_baked:
        raise SimulationFailed("Blender did not bake the soft body point cache")
    out = np.empty((frames, n_vertices, 3), np.float32)
    buf = np.empty(n_vertices * 3, np.float32)
    for f in range(frames):
        scene.frame_set(1 + f)
        dg = bpy.context.evaluated_depsgraph_get()
        ev = body.evaluated_get(dg)
        mesh = ev.to_mesh()
        if len(mesh.vertices) != n_vertices:
            raise SimulationFailed(f"frame {f}: the evaluated mesh has {len(mesh.vertices)} vertices, "
                                   f"the file {n_vertices}; a modifier changed the mesh")
        mesh.vertices.foreach_get("co", buf)
        ev.to_mesh_clear()
        # The object's transform stays the identity, so local coordinates are world (Blender) ones.
        out[f] = buf.reshape(-1, 3)
    return out


def write_npz(path, vertices):
    """Atomically: a temp file in the target folder, then rename."""
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise BadInput(f"--out {path}: folder {folder} does not exist")
    fd, tmp = tempfile.mkstemp(suffix=".npz", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, vertices=vertices, frames=np.arange(len(vertices), dtype=np.int64))
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


def main(argv):
    args = parse_args(argv)
    verts, faces, tets, kind = load_tets(args.tets)
    if kind != "cage":
        print(f"warning: {args.tets} is of kind {kind!r}, not 'cage': its tets are not connected and "
              "fall as separate pieces", file=sys.stderr)
    scene, body, sb = build_scene(verts, faces, args)
    seq = simulate(scene, body, sb, len(verts), args.frames)
    if not np.isfinite(seq).all():
        raise SimulationFailed("the simulation produced non-finite vertices; lower --drop or raise --substeps")
    vol = signed_volumes(seq.astype(np.float64), tets)
    bad = np.nonzero((vol <= 0).any(1))[0]
    if len(bad):
        raise SimulationFailed(f"tets inverted from frame {bad[0]} on ({int((vol[bad[0]] <= 0).sum())} "
                               "tets); raise --stiffness / --bend / --substeps or lower --drop")
    write_npz(args.out, seq)
    com = seq.mean(1)
    print(f"blender_softbody: {args.out}: {args.frames} frames x {len(verts)} vertices; centre z "
          f"{com[0, 2]:.4f} -> {com[-1, 2]:.4f}, lowest z {seq[-1, :, 2].min():.4f} "
          f"(floor {verts[:, 2].min():.4f}), smallest tet volume ratio {(vol / vol[0]).min():.3f}")


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    try:
        main(argv)
    except BadInput as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except SimulationFailed as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(1)
