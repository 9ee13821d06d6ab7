#!/usr/bin/env python3
"""Gradient accuracy of `tomgs.rasterize` on needles (long thin Gaussians) against the float64 reference.

One Gaussian with scales (L, 1e-3, 1e-3) at depth 3 in a 64x64 image (fx = fy = 60), a fixed random
weight per pixel on image and alpha as the loss. Two families:

  in-plane  the needle lies across the view (where the renderer once failed); the 2D covariance's condition
            number then grows like L^2 (far past 1e6 at L = 100).
  tilted    the needle is tilted towards the optical axis so that the 2D covariance has a given
            condition number (1e2 .. 1e6), for each L: long in 3D, as thin on screen as asked.

For each case it prints the condition number and the relative L2 error |g - g_ref| / |g_ref| of the
gradient of every input (and the image's max abs error); `f32ref` is the float32 torch reference's
largest gradient error on the same case, the yardstick of what float32 arithmetic can do. A needle
of L >= 1e3 pointing nearly at the camera is out of float32's reach for any renderer (J W R S
cancels the needle's ~L f / z pixels down to a few; `f32ref` shows it): the summary keeps those
apart, as cases where f32ref > 1e-3.

Usage (writes check_needles.md / .json):
  python -m benchmarks.check_needles                  # CPU
  python -m benchmarks.check_needles --device cuda    # the GPU (H100 etc.)
  python -m benchmarks.check_needles --smoke          # two needles on the CPU, seconds
"""

from __future__ import annotations

import argparse
import math

import torch

import tomgs
from tomgs.runtime import resolve_device

if __package__:
    from .common import environment, markdown_table, output_folder, write_report
else:  # run as a file: Python puts this folder first on sys.path
    from common import environment, markdown_table, output_folder, write_report

NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales", "viewmat", "K", "background")
SHORT = dict(means="mean", quats="quat", scales="scale", opacities="opac", colors="color", t_means="t_mean",
             t_scales="t_scale", viewmat="view", K="K", background="bg")
WIDTH = HEIGHT = 64
FOCAL = 60.0
DEPTH = 3.0
THIN = 1e-3


def quat_from_axis_angle(axis, angle: float) -> torch.Tensor:
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), axis * math.sin(angle / 2)])


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def needle(length: float, quat: torch.Tensor, offset=(0.21, -0.13)) -> dict:
    """The one-Gaussian scene, float32-representable float64 tensors."""
    mean = torch.tensor([offset[0] * DEPTH, offset[1] * DEPTH, DEPTH], dtype=torch.float64)
    scene = dict(
        means=mean[None], quats=quat[None], scales=torch.tensor([[length, THIN, THIN]], dtype=torch.float64),
        opacities=torch.tensor([0.8], dtype=torch.float64), colors=torch.tensor([[0.9, 0.4, 0.2]], dtype=torch.float64),
        t_means=torch.tensor([0.45], dtype=torch.float64), t_scales=torch.tensor([0.3], dtype=torch.float64),
        viewmat=torch.eye(4, dtype=torch.float64),
        K=torch.tensor([[FOCAL, 0.0, WIDTH / 2 + 0.3], [0.0, FOCAL, HEIGHT / 2 - 0.2], [0.0, 0.0, 1.0]],
                       dtype=torch.float64),
        background=torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64),
    )
    return {k: v.float().double() for k, v in scene.items()}


def condition_number(scene: dict) -> float:
    """Condition number of the 2D covariance (float64, the reference's formulas)."""
    from tomgs.render.reference import quat_to_rotmat
    p = scene["viewmat"][:3, :3] @ scene["means"][0] + scene["viewmat"][:3, 3]
    fx, fy = scene["K"][0, 0], scene["K"][1, 1]
    J = torch.tensor([[fx / p[2], 0.0, -fx * p[0] / p[2] ** 2], [0.0, fy / p[2], -fy * p[1] / p[2] ** 2]],
                     dtype=torch.float64)
    M = J @ scene["viewmat"][:3, :3] @ (quat_to_rotmat(scene["quats"])[0] * scene["scales"][0])
    ev = torch.linalg.eigvalsh(M @ M.T + 0.3 * torch.eye(2, dtype=torch.float64))
    return float(ev[1] / ev[0])


def quat_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The shortest rotation (w x y z) taking unit vector a to unit vector b."""
    q = torch.cat([(1.0 + (a * b).sum()).reshape(1), torch.linalg.cross(a, b)])
    return q / q.norm()


def tilted_quat(length: float, cond: float, roll: float = 0.7) -> torch.Tensor:
    """A rotation taking the needle's long axis (x) to angle phi off the ray through its mean, phi found
    by bisection so that the 2D covariance has condition number `cond`; rolled by `roll` about itself."""
    ray = needle(length, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))["means"][0]
    ray = ray / ray.norm()
    side = torch.linalg.cross(ray, torch.tensor([0.3, 1.0, 0.0], dtype=torch.float64))
    side = side / side.norm()

    def quat(phi):
        d = math.cos(phi) * ray + math.sin(phi) * side
        return quat_mul(quat_between(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), d),
                        quat_from_axis_angle([1.0, 0.0, 0.0], roll))

    lo, hi = 0.0, math.pi / 2
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if condition_number(needle(length, quat(mid))) < cond:
            lo = mid
        else:
            hi = mid
    return quat(0.5 * (lo + hi))


def gradients(scene: dict, fn, device: str, **kw):
    tensors = [scene[k].detach().to(device).requires_grad_(True) for k in NAMES]
    named = dict(zip(NAMES, tensors))
    background = named.pop("background")
    image, alpha, _ = fn(**named, background=background, width=WIDTH, height=HEIGHT, t=0.5, **kw)
    g = torch.Generator().manual_seed(7)
    w_image = torch.rand(image.shape, generator=g, dtype=torch.float64) - 0.3
    w_alpha = torch.rand(alpha.shape, generator=g, dtype=torch.float64) - 0.3
    loss = (image * w_image.to(image)).sum() + (alpha * w_alpha.to(alpha)).sum()
    grads = torch.autograd.grad(loss, tensors)
    return image.detach().double().cpu(), [gr.detach().double().cpu() for gr in grads]


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    d = b.norm()
    return float((a - b).norm() / d) if d > 0 else float(a.norm())


def check(scene: dict, device: str) -> dict:
    ref_image, ref_grads = gradients(scene, tomgs.rasterize_reference, "cpu")
    image, grads = gradients(scene, tomgs.rasterize, device)
    _, f32_grads = gradients(scene, tomgs.rasterize_reference, "cpu", dtype=torch.float32)
    errors = {name: rel(g, r) for name, g, r in zip(NAMES, grads, ref_grads)}
    return dict(cond=condition_number(scene), image=float((image - ref_image).abs().max()), grads=errors,
                f32ref=max(rel(g, r) for g, r in zip(f32_grads, ref_grads)))


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default cpu)")
    ap.add_argument("--lengths", default="10,100,1e3,1e4", help="needle lengths L (comma-separated)")
    ap.add_argument("--conds", default="1e2,1e3,1e4,1e5,1e6", help="condition numbers of the tilted family")
    ap.add_argument("--out", default=None, help="default bench_out/check_needles")
    ap.add_argument("--smoke", action="store_true", help="L = 10 and 100, condition number 1e2, on the CPU")
    args = ap.parse_args(argv)
    if args.smoke:
        args.device, args.lengths, args.conds = "cpu", "10,100", "1e2"
    out = output_folder(args.out, args.smoke, "check_needles")
    device = str(resolve_device(args.device))
    lengths = [float(x) for x in args.lengths.split(",")]
    conds = [float(x) for x in args.conds.split(",")]

    header = f"{'case':<10} {'L':>7} {'cond':>9} {'image':>8} " + " ".join(f"{SHORT[n]:>8}" for n in NAMES) \
        + f" {'f32ref':>8}"
    print(f"tomgs.rasterize on {device} against the float64 reference: relative L2 error of each gradient")
    print(header)
    rows = []
    base = quat_mul(quat_from_axis_angle([0.0, 0.0, 1.0], 0.6), quat_from_axis_angle([1.0, 0.2, 0.0], 0.3))
    cases = [("in-plane", L, base) for L in lengths]
    cases += [("tilted", L, tilted_quat(L, c)) for L in lengths for c in conds]
    worst, worst_ratio = 0.0, 0.0
    for case, length, quat in cases:
        result = check(needle(length, quat), device)
        result.update(case=case, L=length)
        rows.append(result)
        error = max(result["grads"].values())
        if result["f32ref"] <= 1e-3:
            if result["cond"] <= 1e6 * (1 + 1e-6):
                worst = max(worst, error)
        else:
            worst_ratio = max(worst_ratio, error / result["f32ref"])
        print(f"{case:<10} {length:>7.0e} {result['cond']:>9.2e} {result['image']:>8.1e} "
              + " ".join(f"{result['grads'][n]:>8.1e}" for n in NAMES) + f" {result['f32ref']:>8.1e}", flush=True)
    table = markdown_table(["case", "L", "2D condition number", "image", *(SHORT[n] for n in NAMES), "f32ref"],
                           [[r["case"], f"{r['L']:.0e}", f"{r['cond']:.2e}", f"{r['image']:.1e}",
                             *(f"{r['grads'][n]:.1e}" for n in NAMES), f"{r['f32ref']:.1e}"] for r in rows])
    summary = f"Largest gradient error at condition numbers <= 1e6 (float32-resolvable cases): {worst:.2e}."
    if worst_ratio:
        summary += f" Where the float32 reference itself misses by > 1e-3: at most {worst_ratio:.2f} x its error."
    body = ("Relative L2 error of each gradient against the float64 reference; image: its largest absolute "
            f"error; f32ref: the float32 reference's largest gradient error.\n\n{table}\n\n{summary}")
    write_report(out, "check_needles", f"check_needles: tomgs.rasterize on {device}, needles",
                 environment(device, "check_needles", argv), body, rows)
    return rows


if __name__ == "__main__":
    main()
