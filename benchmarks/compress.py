"""What a compressed scene (.tsog) costs and keeps: bytes, bits per pixel of its clip, the time to
compress and to load it, and the PSNR of the scene before and after against the clip's frames.

    python -m benchmarks.compress scene.ply .clips/camel/images --out $OUT
    python -m benchmarks.compress scene.ply                          # PSNR of the .tsog against the PLY's renders
    python -m benchmarks.compress scene.ply frames/ --means-bits 16,14,12 --t-bits 16,12   # precisions swept
    python -m benchmarks.compress --synthetic 1000000                # times at 1M Gaussians, no PSNR
    python -m benchmarks.compress --davis ROOT --scenes DIR --clips camel,cows   # clips: one table (below)
    python -m benchmarks.compress --smoke                            # tiny CPU run (tests/test_benchmarks.py)

With --davis ROOT (a folder of <clip>/images JPEG folders) each clip's scene is DIR/<clip>.ply, fitted
first when it is missing (`tomgs fit ROOT/<clip>/images -o DIR/<clip>.ply --budget 60 x --minutes`);
each is compressed and both evaluated against the clip, one row a clip: Gaussians, the PLY's and the
.tsog's PSNR, the loss, the .tsog's renders against the PLY's (what `tomgs compress` checks) and the
loss that predicts, bytes a Gaussian, and the .tsog against the clip's JPEGs.

Reports: the input's bytes, the .tsog's bytes (and by image, per Gaussian), bits per pixel of the
clip (8 bytes / (width x height x frames), the scene's cameras), compress time (tomgs.save_scene to
.tsog), load time (tomgs.load_scene of the .tsog, and of the input for comparison), and, with
CLIP_FRAMES, the mean PSNR over every frame of the input scene and of the .tsog against the clip
(tomgs.evaluate: float renders against the 8-bit frames); without them, the .tsog's renders against
the input's. With --means-bits / --t-bits lists, each other pair of precisions adds a row to
"sweep" (bytes, bits per pixel, PSNR). Public API only. The .tsog and compress.{md,json} are written to
--out (default bench_out/compress; a temporary folder for --smoke).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

import tomgs
from tomgs.cameras import Cameras, intrinsics, look_at
from tomgs.io.scene import bits_per_pixel
from tomgs.io.tsog import image_sizes
from tomgs.io.video import read_video_for
from tomgs.metrics import copy_psnr, loss_db
from tomgs.model import GaussianModel
from tomgs.runtime import resolve_device
from tomgs.render.sequence import render_sequence

if __package__:
    from .common import environment, markdown_table, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, write_report


def synthetic_scene(n: int, frames: int = 24, width: int = 854, height: int = 480, seed: int = 0):
    """(model, cameras) of `n` Gaussians laid like a fitted video scene: on a few depth layers seen by a
    camera that slides sideways, colours smooth across each layer, each alive around its own frame."""
    g = torch.Generator().manual_seed(seed)
    rand = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    layer = torch.randint(0, 4, (n,), generator=g).float()
    depth = 2.0 + 3.0 * layer + 0.05 * torch.randn(n, generator=g)
    uv = rand(n, 2) * 2 - 1
    means = torch.stack([uv[:, 0] * depth * 0.6, uv[:, 1] * depth * 0.35, depth], 1)
    colour = 0.5 + 0.4 * torch.stack([torch.sin(3 * uv[:, 0] + layer), torch.cos(2 * uv[:, 1]),
                                      torch.sin(uv[:, 0] * uv[:, 1] * 4)], 1) + 0.05 * torch.randn(n, 3, generator=g)
    model = GaussianModel.from_points(means, colour.clamp(0, 1), rand(n), t_scale=0.05, max_sh_degree=0,
                                      opacity=0.7, sizes=0.004 * depth)
    with torch.no_grad():
        model.quats.copy_(torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1))
        model.log_scales.add_(0.5 * torch.randn(n, 3, generator=g))
        model.log_t_scales.add_(torch.randn(n, generator=g))
        model.opacity_logits.add_(torch.randn(n, generator=g))
    c2w = np.stack([look_at([0.02 * k, 0.0, 0.0], [0.02 * k, 0.0, 5.0]) for k in range(frames)])
    cams = Cameras.create(c2w, intrinsics(0.9 * width, width, height), width, height)
    return model, cams


def mean_psnr(model, cameras, frames, device) -> float:
    """Mean over frames of the PSNR of `model` rendered at `cameras` against `frames` (uint8 or float)."""
    return float(np.mean(tomgs.evaluate(model, cameras, frames, device=device).psnr))


def timed(fn, repeats: int = 1):
    """(the result of fn(), (its quickest wall time, the process's CPU time in that call) in seconds
    over `repeats` calls). CPU time counts every thread: on a shared machine it shows the work that
    wall time hides behind other processes."""
    best, out = (math.inf, math.inf), None
    for _ in range(repeats):
        started, cpu = time.perf_counter(), time.process_time()
        out = fn()
        best = min(best, (time.perf_counter() - started, time.process_time() - cpu))
    return out, best


def measure(scene_path: Path, frames_path: Path | None, out_dir: Path, device, repeats: int = 1,
            precisions=((16, 16),)) -> dict:
    """The report of one scene file (see the module's docstring); `precisions`: (means_bits, t_bits)
    pairs, the first timed and reported in full, the others in "sweep"."""
    scene, (load_input, _) = timed(lambda: tomgs.load_scene(scene_path), repeats)
    cams, n = scene.cameras, len(scene.model)
    target = out_dir / (scene_path.stem + ".tsog")
    (means_bits, t_bits), *others = precisions
    _, (compress_seconds, compress_cpu) = timed(lambda: tomgs.save_scene(
        target, scene.model, scene.cameras, scene.info, means_bits=means_bits, t_bits=t_bits), repeats)
    compressed, (load_seconds, load_cpu) = timed(lambda: tomgs.load_scene(target), repeats)
    size_in, size_out = scene_path.stat().st_size, target.stat().st_size
    report = {
        "scene": str(scene_path), "means_bits": means_bits, "t_bits": t_bits, "gaussians": n, "frames": len(cams), "width": cams.width, "height": cams.height,
        "input_bytes": size_in, "output_bytes": size_out, "ratio": size_in / size_out,
        "bytes_per_gaussian": size_out / max(n, 1), "bits_per_pixel": bits_per_pixel(size_out, cams),
        "input_bits_per_pixel": bits_per_pixel(size_in, cams),
        "image_bytes_per_gaussian": {name: size / max(n, 1) for name, size in image_sizes(target).items()},
        "compress_seconds": compress_seconds, "compress_cpu_seconds": compress_cpu, "load_seconds": load_seconds,
        "load_cpu_seconds": load_cpu, "input_load_seconds": load_input,
        "device": str(device), "torch_threads": torch.get_num_threads(),
    }
    if frames_path is not None:
        clip = read_video_for(frames_path, cams)
        report["clip_frames"] = str(frames_path)
        jpeg = sum(p.stat().st_size for p in Path(frames_path).glob("*.jp*g"))
        report["clip_jpeg_bytes"] = jpeg or None
        report["clip_jpeg_bits_per_pixel"] = bits_per_pixel(jpeg, cams) if jpeg else None
        report["psnr_input"] = mean_psnr(scene.model.to(device), cams, clip, device)
    else:
        clip = np.stack([image.numpy() for _, image, _ in
                         render_sequence(scene.model.to(device).render_inputs(), cams, device=device)])
        report["psnr_input"] = None  # the clip is the input's own render

    def scored(model) -> dict:
        psnr = mean_psnr(model.to(device), cams, clip, device)
        if report["psnr_input"] is None:
            return {"psnr_output_against_input": psnr}
        return {"psnr_output": psnr, "psnr_drop": report["psnr_input"] - psnr}

    report.update(scored(compressed.model))
    report["psnr_output_against_input_renders"] = copy_psnr(scene.model.to(device), compressed.model.to(device), cams,
                                                            frames=len(cams), max_side=max(cams.width, cams.height),
                                                            device=device)
    if report["psnr_input"] is not None:
        report["predicted_drop"] = loss_db(report["psnr_input"], report["psnr_output_against_input_renders"])
    report["sweep"] = []
    for means_bits, t_bits in others:
        path = out_dir / f"{scene_path.stem}_m{means_bits}_t{t_bits}.tsog"
        tomgs.save_scene(path, scene.model, cams, scene.info, means_bits=means_bits, t_bits=t_bits)
        size = path.stat().st_size
        report["sweep"].append({"means_bits": means_bits, "t_bits": t_bits, "output_bytes": size,
                                "bytes_per_gaussian": size / max(n, 1), "bits_per_pixel": bits_per_pixel(size, cams),
                                **scored(tomgs.load_scene(path).model)})
    return report


def measure_synthetic(n: int, out_dir: Path, repeats: int) -> dict:
    """Bytes and times of a synthetic scene of `n` Gaussians (no PSNR: it has no clip)."""
    model, cams = synthetic_scene(n)
    target = out_dir / f"synthetic_{n}.tsog"
    _, (compress_seconds, compress_cpu) = timed(lambda: tomgs.save_scene(target, model, cams, {}), repeats)
    back, (load_seconds, load_cpu) = timed(lambda: tomgs.load_scene(target), repeats)
    assert len(back.model) == n
    size = target.stat().st_size
    return {"scene": f"synthetic {n}", "gaussians": n, "output_bytes": size, "bytes_per_gaussian": size / n,
            "image_bytes_per_gaussian": {name: b / n for name, b in image_sizes(target).items()},
            "compress_seconds": compress_seconds, "compress_cpu_seconds": compress_cpu, "load_seconds": load_seconds,
            "load_cpu_seconds": load_cpu, "torch_threads": torch.get_num_threads()}


def smoke(out_dir: Path) -> list[dict]:
    """A tiny CPU run: a synthetic scene of 3,000 Gaussians at 96x54, its own renders as the clip
    (a folder of JPEGs), through the clips' table."""
    import cv2

    model, cams = synthetic_scene(3000, frames=4, width=96, height=54)
    clip = out_dir / "smoke" / "images"
    clip.mkdir(parents=True, exist_ok=True)
    for k, (_, image, _) in enumerate(render_sequence(model.render_inputs(), cams, device="cpu")):
        pixels = np.clip(np.rint(image.numpy() * 255), 0, 255).astype(np.uint8)
        cv2.imwrite(str(clip / f"{k:05d}.jpg"), pixels[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    tomgs.save_scene(out_dir / "smoke.ply", model, cams, {})
    return clips(out_dir, ["smoke"], out_dir, 0.0, torch.device("cpu"), out_dir)


def clips(root: Path, names: list[str], scenes: Path, minutes: float, device, out_dir: Path) -> list[dict]:
    """`measure` of each clip's scene (scenes/<clip>.ply, fitted by `tomgs fit` when missing) against
    the clip's frames (root/<clip>/images)."""
    import subprocess
    import sys

    reports = []
    for name in names:
        frames, scene = root / name / "images", scenes / f"{name}.ply"
        if not scene.exists():
            subprocess.run([sys.executable, "-m", "tomgs.cli", "fit", str(frames), "-o", str(scene), "--budget",
                            str(60 * minutes), "--device", str(device), "-q"], check=True)
        reports.append(dict(clip=name, **measure(scene, frames, out_dir, device)))
    return reports


def clips_table(reports: list[dict]) -> str:
    """The clips' table: one row a clip."""
    head = ["clip", "Gaussians", "PLY PSNR", "tsog PSNR", "loss dB", "tsog vs PLY renders dB", "predicted loss dB",
            "bytes/Gaussian", "x smaller than PLY", "tsog / clip's JPEGs"]
    rows = [[r["clip"], f"{r['gaussians']:,}", f"{r['psnr_input']:.2f}", f"{r['psnr_output']:.2f}",
             f"{r['psnr_drop']:.3f}", f"{r['psnr_output_against_input_renders']:.1f}", f"{r['predicted_drop']:.3f}",
             f"{r['bytes_per_gaussian']:.2f}", f"{r['ratio']:.1f}",
             f"{r['output_bytes'] / r['clip_jpeg_bytes']:.2f}" if r.get("clip_jpeg_bytes") else "-"] for r in reports]
    return markdown_table(head, rows)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", help="a scene file (.ply or .tsog)")
    ap.add_argument("clip_frames", nargs="?", help="the clip the scene was fitted to (a frame folder or video)")
    ap.add_argument("--out", default=None, help="folder for the .tsog and the report (default bench_out/compress)")
    ap.add_argument("--device", default="auto", help="where to render for PSNR (auto, cpu, cuda)")
    ap.add_argument("--repeats", type=int, default=1, help="time compress and load this many times, keep the quickest")
    ap.add_argument("--means-bits", default="16", help="bits an axis of the means, or a list (16,14,12): the first is "
                    "timed, the others swept")
    ap.add_argument("--t-bits", default="16", help="bits of t_mean, or a list (swept with --means-bits)")
    ap.add_argument("--synthetic", type=int, default=None, metavar="N", help="time a synthetic scene of N Gaussians")
    ap.add_argument("--davis", type=Path, default=None, metavar="ROOT",
                    help="a folder of <clip>/images: the clips' table")
    ap.add_argument("--clips", default="blackswan,camel,car-shadow,cows,dog,goat,kite-surf,libby,motocross-jump,"
                                       "parkour")
    ap.add_argument("--scenes", type=Path, default=None, help="the clips' scenes, <clip>.ply (default: --out)")
    ap.add_argument("--minutes", type=float, default=2.0, help="the budget of a fit of a clip without a scene")
    ap.add_argument("--smoke", action="store_true", help="tiny CPU run")
    args = ap.parse_args(argv)
    if not (args.smoke or args.synthetic or args.scene or args.davis):
        ap.error("give SCENE [CLIP_FRAMES], --davis ROOT, --synthetic N or --smoke")
    out_dir = output_folder(args.out, args.smoke, "compress")
    if args.smoke or args.davis:
        device = torch.device("cpu") if args.smoke else resolve_device(args.device)
        reports = smoke(out_dir) if args.smoke else clips(args.davis, args.clips.split(","), args.scenes or out_dir,
                                                          args.minutes, device, out_dir)
        body = clips_table(reports)
        print(body)
        write_report(out_dir, "compress", "compress: each clip's PLY and .tsog against the clip",
                     environment(device, "compress", argv), body, reports)
        return reports
    if args.synthetic:
        device = torch.device("cpu")
        report = measure_synthetic(args.synthetic, out_dir, args.repeats)
    else:
        device = resolve_device(args.device)
        means, times = ([int(v) for v in text.split(",")] for text in (args.means_bits, args.t_bits))
        precisions = [(m, t) for m in means for t in times]
        report = measure(Path(args.scene), None if args.clip_frames is None else Path(args.clip_frames), out_dir,
                         device, args.repeats, precisions)
    rows = [[key, ", ".join(f"{k} {v:.2f}" for k, v in value.items()) if isinstance(value, dict) else value]
            for key, value in report.items() if key != "sweep"]
    body = markdown_table(["what", "value"], rows)
    if report.get("sweep"):
        head = list(report["sweep"][0])
        body += "\n\nPrecisions swept:\n\n" + markdown_table(head, [[row[k] for k in head] for row in report["sweep"]])
    write_report(out_dir, "compress", "compress: a .tsog's bytes, times and PSNR", environment(device, "compress", argv),
                 body, report)
    return report


if __name__ == "__main__":
    main()
