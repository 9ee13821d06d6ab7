"""Other people's readers against tomgs's files: the native scene and each `tomgs export` format.

For every (reader, file) pair: does it load, and are the positions, colours, opacities and scales it
decodes the ones tomgs renders with (the alive Gaussians at the exported frame, opacity at that
time; for the native scene every Gaussian, base opacity)? Lossy formats are held to their own
quantisation (.splat: 8-bit colour and opacity; .spz: 12 fractional bits of position, 8-bit rest).

Readers: plyfile with INRIA's load_ply logic (at the file's SH degree, and at degree 3 as INRIA's
trainer starts), gsply, open3d (legacy and tensor API; RPly underneath), a parser that adds up every
`property` line into one stride (antimatter15/splat, gsplat.js), and @playcanvas/splat-transform
(SuperSplat's converter, through npx) converting each file to PLY, which is read back. Then the
round trip a SuperSplat user makes: the native scene through splat-transform, loaded again with
`--cameras`, rendered against the original.

    python -m benchmarks.interop                      # the demo scene
    python -m benchmarks.interop --scene camel.ply --frame 40 --npm /tmp/npm --out <out>
    python -m benchmarks.interop --smoke              # the demo scene, no splat-transform

Run from the repository root: the readers' transcriptions are the tests' (tests/scenes.py,
tests/io/test_export.py). `--npm DIR` is a folder where `npm install @playcanvas/splat-transform` was run
(default: install it into a temporary folder when npm is there; skipped with a note when not). Writes
interop.md / .json.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from tests.scenes import inria_load_ply  # the readers, transcribed once, for the tests and this table
from tests.io.test_export import C0, demo_model, resaved_like_splat_transform, stride_summing_parse
from tomgs import load_scene, render_sequence, save_scene
from tomgs.edit.export import pick_moment, static_moment, write_cameras
from tomgs.io.splats import RDF_TO_RUB, write_static
from tomgs.temporal import frozen_at

if __package__:
    from .common import environment, output_folder, write_report
else:  # run as a file (PYTHONPATH=. python benchmarks/interop.py): Python puts this folder first on sys.path
    from common import environment, output_folder, write_report

FIELDS = ("positions", "colours", "opacities", "scales")


def expected(model, t: float | None) -> dict:
    """What tomgs renders with: every Gaussian (t None, the native scene) or the alive ones at t."""
    g = model.render_inputs() if t is None else frozen_at(model.render_inputs(), t)
    g = {k: v.detach().double().numpy() for k, v in g.items()}
    return {"positions": g["means"], "colours": 0.5 + C0 * g["colors"][:, 0], "opacities": g["opacities"],
            "scales": g["scales"]}


def from_ply_columns(c: dict) -> dict:
    """Decoded values of INRIA-named columns (stored form) as `expected` gives them."""
    stack = lambda names: np.stack([np.asarray(c[n], np.float64) for n in names], axis=1)  # noqa: E731
    return {"positions": stack("xyz"), "colours": 0.5 + C0 * stack([f"f_dc_{i}" for i in range(3)]),
            "opacities": 1 / (1 + np.exp(-np.asarray(c["opacity"], np.float64))),
            "scales": np.exp(stack([f"scale_{i}" for i in range(3)]))}


def from_inria(d: dict) -> dict:
    return from_ply_columns({"x": d["means"][:, 0], "y": d["means"][:, 1], "z": d["means"][:, 2],
                             **{f"f_dc_{i}": d["sh_dc"][:, i] for i in range(3)}, "opacity": d["opacity_logits"],
                             **{f"scale_{i}": d["log_scales"][:, i] for i in range(3)}})


def from_splat(path: Path) -> dict:
    rows = np.frombuffer(path.read_bytes(), dtype=[("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])
    return {"positions": rows["p"].astype(np.float64), "colours": rows["c"][:, :3] / 255.0,
            "opacities": rows["c"][:, 3] / 255.0, "scales": rows["s"].astype(np.float64)}


def from_gsply(g) -> dict:
    return {"positions": np.asarray(g.means, np.float64), "colours": 0.5 + C0 * np.asarray(g.sh0, np.float64).reshape(-1, 3),
            "opacities": 1 / (1 + np.exp(-np.asarray(g.opacities, np.float64).reshape(-1))),
            "scales": np.exp(np.asarray(g.scales, np.float64))}


def compare(got: dict, want: dict) -> dict:
    """Largest error of each field over the Gaussians (matched by position order), and the count."""
    if len(got["positions"]) != len(want["positions"]):
        return {"count": f"{len(got['positions'])} != {len(want['positions'])}"}
    a = b = np.arange(len(got["positions"]))  # in file order; a reader that reorders (a .splat is sorted by
    if len(a) and np.abs(got["positions"] - want["positions"]).max() > 1e-2:  # size): matched to the nearest
        b = np.concatenate([torch.cdist(torch.from_numpy(chunk), torch.from_numpy(want["positions"])).argmin(1).numpy()
                            for chunk in np.array_split(got["positions"], max(1, len(a) // 2048))])
    out = {"count": len(a)}
    for name in FIELDS:
        if name in got:
            x, y = got[name][a], want[name][b]
            err = np.abs(x - y) / (np.abs(y) if name == "scales" else 1.0)
            out[name] = float(err.max()) if len(err) else 0.0
    return out


def splat_transform(npm: Path | None, src: Path, dst: Path) -> None:
    subprocess.run(["npx", "--prefix", str(npm), "splat-transform", "-w", str(src), str(dst)], check=True,
                   capture_output=True, timeout=300)


def readers(npm: Path | None):
    """(name, reader(path) -> decoded dict) of each reader of PLY files."""
    import gsply
    import open3d as o3d
    from plyfile import PlyData

    def inria_file_degree(path):
        names = [p.name for p in PlyData.read(str(path))["vertex"].properties]
        rest = sum(n.startswith("f_rest_") for n in names)
        return from_inria(inria_load_ply(path, {0: 0, 9: 1, 24: 2, 45: 3}[rest]))

    def o3d_tensor(path):  # open3d 0.19+ groups 3DGS properties: f_dc [N,3], scale [N,3] (exp taken), opacity [N,1]
        p = o3d.t.io.read_point_cloud(str(path)).point
        return {"positions": p.positions.numpy().astype(np.float64),
                "colours": 0.5 + C0 * p.f_dc.numpy().astype(np.float64),
                "opacities": 1 / (1 + np.exp(-p.opacity.numpy()[:, 0].astype(np.float64))),
                "scales": p.scale.numpy().astype(np.float64)}

    def o3d_legacy(path):
        return {"positions": np.asarray(o3d.io.read_point_cloud(str(path)).points)}

    found = [("INRIA load_ply (file's degree)", inria_file_degree),
             ("INRIA load_ply (degree 3)", lambda p: from_inria(inria_load_ply(p, 3))),
             ("gsply", lambda p: from_gsply(gsply.plyread(str(p)))),
             ("open3d tensor", o3d_tensor), ("open3d legacy", o3d_legacy),
             ("stride-summing (antimatter15, gsplat.js)", lambda p: from_ply_columns(stride_summing_parse(p)))]
    if npm is not None:
        def through_splat_transform(path):
            out = Path(tempfile.mkdtemp()) / "out.ply"
            splat_transform(npm, path, out)
            return from_ply_columns({k: v for k, v in zip(*_columns(out))})
        found.append(("splat-transform -> .ply", through_splat_transform))
    return found


def _columns(path):
    from plyfile import PlyData

    v = PlyData.read(str(path))["vertex"].data
    return v.dtype.names, [v[n] for n in v.dtype.names]


def find_npm(arg) -> Path | None:
    if arg:
        return Path(arg)
    if shutil.which("npm") is None:
        return None
    folder = Path(tempfile.mkdtemp(prefix="tomgs-npm-"))
    subprocess.run(["npm", "install", "--prefix", str(folder), "@playcanvas/splat-transform"], check=True,
                   capture_output=True, timeout=600)
    return folder


def run(scene_path: Path, frame: int, npm: Path | None, work: Path) -> dict:
    import gsply

    scene = load_scene(scene_path)
    moment = pick_moment(scene.cameras, frame=frame)
    files = {"native scene": (scene_path, expected(scene.model, None))}
    for suffix, degree in ((".ply", None), (".ply", 3), (".splat", None), (".spz", None)):
        name = f"export {suffix}" + (" --sh-degree 3" if degree is not None else "")
        path = work / (f"frame{suffix}" if degree is None else f"frame_sh{degree}{suffix}")
        write_static(path, static_moment(scene.model, moment.time, degree))
        files[name] = (path, expected(scene.model, moment.time))
    table = {}
    for file_name, (path, want) in files.items():
        row = {}
        if path.suffix == ".ply":
            for reader_name, reader in readers(npm):
                try:
                    row[reader_name] = compare(reader(path), want)
                except Exception as e:  # a reader that refuses the file: what the table is for
                    row[reader_name] = {"error": f"{type(e).__name__}: {str(e)[:120]}"}
        elif path.suffix == ".splat":
            row["splat (antimatter15 layout)"] = compare(from_splat(path), want)
        else:
            decoded = from_gsply(gsply.read_spz(str(path)))  # as stored: SPZ's RUB axes; ours are y and z negated
            decoded["positions"] = decoded["positions"] * RDF_TO_RUB
            row["gsply read_spz (RUB axes turned back)"] = compare(decoded, want)
        if npm is not None and path.suffix in (".splat", ".spz"):
            out = work / f"st_{path.stem}{path.suffix[1:]}.ply"
            try:
                splat_transform(npm, path, out)
                row["splat-transform -> .ply"] = compare(from_ply_columns(dict(zip(*_columns(out)))), want)
            except Exception as e:
                row["splat-transform -> .ply"] = {"error": f"{type(e).__name__}: {str(e)[:120]}"}
        table[file_name] = row
    result = {"scene": str(scene_path), "gaussians": len(scene.model), "frame": moment.frame, "table": table}
    result["round trip"] = supersplat_round_trip(scene_path, scene, npm, work, moment.position)
    return result


def supersplat_round_trip(scene_path: Path, scene, npm, work: Path, k: int) -> dict:
    """The native scene re-saved (by splat-transform when there, else as it writes), loaded with
    --cameras, rendered at frame k against the original: max pixel difference."""
    resaved = work / "resaved.ply"
    if npm is not None:
        splat_transform(npm, scene_path, resaved)
    else:
        resaved_like_splat_transform(scene_path, resaved)
    try:
        load_scene(resaved)
        refused = "loaded without cameras (unexpected)"
    except Exception as e:
        refused = str(e)[:160]
    write_cameras(work / "cams", scene.cameras)
    back = load_scene(resaved, cameras=work / "cams" / "cameras.json")

    def image(s):
        return next(iter(render_sequence(s.model.render_inputs(), s.cameras, [k], background=(0.0, 0.0, 0.0))))[1]

    diff = float((image(back) - image(scene)).abs().max())
    return {"by": "splat-transform" if npm is not None else "a re-save as splat-transform writes",
            "without --cameras": refused, "max pixel difference with --cameras": diff}


def markdown(result: dict) -> str:
    lines = [f"Scene {result['scene']} ({result['gaussians']:,} Gaussians), exports of frame {result['frame']}; "
             "largest error of positions / colours / opacities / scales (relative) against what tomgs renders with.",
             "", "| file | reader | loads | Gaussians | positions | colours | opacities | scales |",
             "|---|---|---|---|---|---|---|---|"]
    for file_name, row in result["table"].items():
        for reader, r in row.items():
            if "error" in r:
                lines.append(f"| {file_name} | {reader} | no: {r['error']} | | | | | |")
                continue
            cells = [f"{r[f]:.1e}" if isinstance(r.get(f), float) else "-" for f in FIELDS]
            lines.append(f"| {file_name} | {reader} | yes | {r['count']} | " + " | ".join(cells) + " |")
    trip = result["round trip"]
    lines += ["", f"Round trip through {trip['by']}: without --cameras: \"{trip['without --cameras']}\"; with "
              f"--cameras the render differs from the original's by at most {trip['max pixel difference with --cameras']:.1e}."]
    return "\n".join(lines)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default=None, help="a tomgs scene (default: the demo scene, made here)")
    parser.add_argument("--frame", type=int, default=5)
    parser.add_argument("--npm", default=None, help="folder with @playcanvas/splat-transform installed")
    parser.add_argument("--out", default=None, help="default bench_out/interop")
    parser.add_argument("--smoke", action="store_true", help="the demo scene, splat-transform left out")
    args = parser.parse_args(argv)
    out = output_folder(args.out, args.smoke, "interop")
    work = Path(tempfile.mkdtemp(prefix="tomgs-interop-", dir=out))
    scene_path = Path(args.scene) if args.scene else None
    if scene_path is None:
        model, cams = demo_model()
        scene_path = save_scene(work / "demo.ply", model, cams)
    npm = None
    if not args.smoke:
        try:
            npm = find_npm(args.npm)
        except (subprocess.SubprocessError, OSError) as e:
            print(f"splat-transform not available ({e}); its rows are left out", file=sys.stderr)
    with torch.no_grad():
        result = run(scene_path, args.frame, npm, work)
    write_report(out, "interop", "interop: tomgs's files in other readers", environment("cpu", "interop", argv),
                 markdown(result), result)
    return result


if __name__ == "__main__":
    main()
