#!/usr/bin/env python3
"""Time tomgs.rasterize against gsplat 1.5.3 in one process on one GPU: forward, backward and memory.

What it measures, per case (image size x N x variant), for each library, in the same run:
  fwd ms        forward with requires_grad inputs (the training path), CUDA events, median
  bwd ms        loss.backward() alone, CUDA events, median
  fwd+bwd ms    median of (fwd + bwd) over the same iterations
  step ms       one unsynchronised fwd -> loss -> bwd, CUDA events around the whole (pipelined)
  peak GB       torch.cuda.max_memory_allocated() over one fwd+bwd minus the memory held by the inputs
                at the start of the case (grads, outputs and every buffer count); for tomgs also the
                peak of Warp's CUDA mempool (Warp arrays and radix-sort scratch live outside torch)
and the ratios tomgs / gsplat. Host wall-clock times (with device syncs) are kept in the JSON as a
cross-check: a wall time far above the event time means host overhead or work on another stream.

The random scene (REFERENCES.md, "Speed anchors"; benchmarks.common.random_scene): camera at the origin
looking down +z (OpenCV), fx = fy = 0.9 W, cx = W/2, cy = H/2 (horizontal FOV 2 atan(1/1.8) = 58.1 deg,
vertical 34.7 deg at 16:9). Means: z ~ U(3, 5) (around z = 4), x = z tan_x u, y = z tan_y v with
u, v ~ U(-1, 1), where tan_x = 0.5 / 0.9 and tan_y = tan_x * 9 / 16: every centre lies inside the 16:9
frustum, and the scene depends only on N and the seed (the same scene at 854x480 and 1920x1080).
scales ~ U(0.002, 0.02) per axis, quaternions (w,x,y,z) normalised Gaussian draws, opacity a ~ U(0, 1),
RGB ~ U(0, 1).

Variants:
  static    t_means ~ U(0,1), t_scales = 1e3, t = 0.5: o(t) = a (1 - O(1e-7)), every Gaussian alive;
            gsplat gets the opacities as they are.
  temporal  t_means m ~ U(0,1); o(t) = a exp(-(t-m)^2 / (2 s^2)) >= 1/255 holds for
            |t - m| <= s sqrt(2 ln(255 a)), a window of width 2 s sqrt(2 ln(255 a)). Setting it to
            f = 0.10 of the clip gives s = (f/2) / sqrt(2 ln(255 a)) per Gaussian (ln clamped at 1e-6
            for a <= 1/255, which are dead in every variant). Timed at t_k = (k + 0.5) / n_t,
            k = 0..n_t-1 (n_t = 8): every t_k is >= 1/16 > f/2 from the clip ends, so at each t_k the
            expected alive fraction is exactly f (of the Gaussians with a > 1/255). Times are the mean
            over t_k of the per-t medians. gsplat gets the time-modulated opacities
            a * exp(-0.5 ((t - m) / s)^2), computed in torch inside the timed forward (gradients flow
            to m and s, as they would for a torch user of gsplat).

Loss: (image * Wimg).sum() + (alpha * Walpha).sum() with fixed random weights (seeded).
gsplat call: rasterization(..., viewmats[None], Ks[None], W, H, near_plane=0.01, far_plane=1e10,
packed=False) with its defaults radius_clip=0.0, eps2d=0.3, rasterize_mode="classic", sh_degree=None
(colours are post-activation RGB), backgrounds=None.

Usage (`python -m benchmarks.bench_raster` runs the same; the history: docs/notes/rasterizer.md):
  python benchmarks/bench_raster.py --sizes 854x480,1920x1080 --tomgs-graph
  python benchmarks/bench_raster.py --sizes 854x480 --n 1M,5M --variants static,temporal
  python benchmarks/bench_raster.py --smoke     # --device cpu --tiny, tomgs against the float64 reference
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import statistics
import sys
import time
import traceback
from pathlib import Path

import torch

if __package__:
    from .common import FOCAL_RATIO, STATIC_T_SCALE, TAN_X, TAN_Y, camera, environment, kernel_times, \
        output_folder, parse_count, parse_size, random_scene, temporal_scales
else:  # run as a file (python benchmarks/bench_raster.py): Python puts this folder first on sys.path
    from common import FOCAL_RATIO, STATIC_T_SCALE, TAN_X, TAN_Y, camera, environment, kernel_times, \
        output_folder, parse_count, parse_size, random_scene, temporal_scales

T0 = time.perf_counter()
LIBS = ("tomgs", "gsplat")


def log(msg: str) -> None:
    print(f"[{time.perf_counter() - T0:7.1f}s] {msg}", flush=True)


# ----------------------------------------------------------------------------- arguments


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    p.add_argument("--tiny", action="store_true",
                   help="smoke mode: N=2000, 64x48, few repeats (gsplat only on cuda and if importable)")
    p.add_argument("--sizes", default="854x480,1920x1080", help="comma list of WxH")
    p.add_argument("--n", default="1M,5M", help="comma list of Gaussian counts (1M, 5M, 250k, 2000)")
    p.add_argument("--variants", default="static,temporal", help="comma list of static,temporal")
    p.add_argument("--libs", default="tomgs,gsplat", help="comma list of tomgs,gsplat")
    p.add_argument("--repeats", type=int, default=20, help="timed iterations per case (per t value)")
    p.add_argument("--warmup", type=int, default=3, help="untimed iterations per library per case")
    p.add_argument("--n-t", type=int, default=8, help="t values for the temporal variant")
    p.add_argument("--alive-frac", type=float, default=0.10,
                   help="temporal variant: fraction of the clip each Gaussian is alive (o(t) >= 1/255)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--budget-s", type=float, default=540.0,
                   help="wall-clock budget for the whole run; cases that would not fit are skipped")
    p.add_argument("--min-case-s", type=float, default=25.0,
                   help="skip a case when fewer seconds than this remain of --budget-s")
    p.add_argument("--tomgs-impl", default="tomgs:rasterize",
                   help="module:function timed as 'tomgs' (same signature as tomgs.rasterize)")
    p.add_argument("--tomgs-defer", action="store_true",
                   help="time tomgs as its training loop runs it (tomgs.render.render_frame(defer=True)): the forward "
                        "does not wait for its counts, read after the backward (a frame past its keys' bound fails "
                        "the run)")
    p.add_argument("--tomgs-graph", action="store_true",
                   help="time tomgs replayed from CUDA graphs (tomgs.FrameGraph, one per scene, captured at "
                        "its first frame): camera and time written per call, counts read after the backward")
    p.add_argument("--no-sanity", action="store_true", help="skip the tomgs vs gsplat image comparison")
    p.add_argument("--stages", action="store_true",
                   help="also profile each library's fwd+bwd (torch profiler, CUDA only) and report GPU time by stage "
                        "beside the time the GPU idles waiting for the host: where a ratio above 0.9 goes")
    p.add_argument("--out", default=os.environ.get("OUT") or None,
                   help="output folder for JSON + markdown (default $OUT, else bench_out/; a temporary folder "
                        "with --smoke)")
    p.add_argument("--smoke", action="store_true", help="--device cpu --tiny, tomgs only, the tables in a temporary "
                   "folder unless --out: seconds on a CPU")
    a = p.parse_args(argv)
    if a.smoke:
        a.device, a.tiny, a.libs = "cpu", True, "tomgs"
    a.out = str(output_folder(a.out if a.out or a.smoke else "bench_out", a.smoke, "bench_raster"))
    if a.tiny:
        if a.sizes == p.get_default("sizes"):
            a.sizes = "64x48"
        if a.n == p.get_default("n"):
            a.n = "2000"
        if a.repeats == p.get_default("repeats"):
            a.repeats = 3
        if a.warmup == p.get_default("warmup"):
            a.warmup = 1
        if a.n_t == p.get_default("n_t"):
            a.n_t = 2
    a.size_list = [parse_size(s) for s in a.sizes.split(",") if s.strip()]
    a.n_list = [parse_count(s) for s in a.n.split(",") if s.strip()]
    a.variant_list = [v.strip() for v in a.variants.split(",") if v.strip()]
    a.lib_list = [v.strip() for v in a.libs.split(",") if v.strip()]
    for v in a.variant_list:
        if v not in ("static", "temporal"):
            p.error(f"unknown variant {v!r}")
    for v in a.lib_list:
        if v not in LIBS:
            p.error(f"unknown library {v!r}")
    if not 0.0 < a.alive_frac < 1.0:
        p.error("--alive-frac must lie in (0, 1)")
    return a


# ----------------------------------------------------------------------------- scene


def t_values(variant: str, n_t: int) -> list[float]:
    if variant == "static":
        return [0.5]
    return [(k + 0.5) / n_t for k in range(n_t)]


# ----------------------------------------------------------------------------- libraries


def load_tomgs(spec: str = "tomgs:rasterize"):
    import importlib

    module, _, attr = spec.partition(":")
    return getattr(importlib.import_module(module), attr or "rasterize")


def deferred(fn):
    """`fn` (tomgs.render.render_frame) as the training loop calls it: rasterize's signature and
    returns, meta['counts'] the frame's FrameCounts (read by `iteration` after the backward)."""
    def run(*args, **kw):
        image, alpha, meta, counts = fn(*args, defer=True, **kw)
        meta["counts"] = counts
        return image, alpha, meta
    return run


def graphed():
    """tomgs.FrameGraph behind rasterize's signature, as `deferred` returns: the graph of the
    latest cloud and size (captured at its first frame; a new scene replaces it, so an old scene's
    tensors are not kept), meta['counts'] each frame's FrameCounts."""
    from tomgs import FrameGraph

    held = {}

    def run(means, quats, scales, opacities, colors, t_means, t_scales, viewmat, K, width, height, t, **kw):
        cloud = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, t_means=t_means,
                     t_scales=t_scales)
        key = (tuple(id(x) for x in cloud.values()), tuple(x.requires_grad for x in cloud.values()), width, height)
        if held.get("key") != key:
            held.clear()  # the last scene's graph and tensors go before this one is captured
            held.update(key=key, graph=FrameGraph(**cloud, width=width, height=height, **kw))
        image, alpha, counts = held["graph"](viewmat, K, t)
        return image, alpha, dict(counts=counts)
    run.release = held.clear
    return run


class Overflowed(Exception):
    """A deferred tomgs frame's keys overflowed their bound: its image lacked entries (the bound has
    grown since), so its timing is void; the training loop renders such a frame again."""


def read_counts(meta) -> None:
    """Read a deferred tomgs frame's counts, as the training loop does after the backward."""
    counts = meta.get("counts") if isinstance(meta, dict) else None
    if counts is not None and counts.overflowed:
        raise Overflowed()


def load_gsplat(device: torch.device):
    """gsplat.rasterization, with its CUDA extension built/loaded now (JIT ~2 min on a cold machine)."""
    import gsplat
    from gsplat import rasterization

    ver = getattr(gsplat, "__version__", "?")
    if ver != "1.5.3":
        log(f"WARNING: gsplat {ver} imported; the figures are against 1.5.3")
    if device.type == "cuda":
        t = time.perf_counter()
        from gsplat.cuda._backend import _C

        if _C is None:
            raise RuntimeError("gsplat CUDA extension unavailable (no CUDA toolkit?)")
        log(f"gsplat {ver} CUDA extension ready in {time.perf_counter() - t:.1f}s")
    return rasterization, ver


class Runner:
    """One library's forward: (params, t) -> (image[H,W,3], alpha[H,W,1], meta)."""

    def __init__(self, name, fn, width, height, viewmat, K, variant):
        self.name, self.fn = name, fn
        self.width, self.height, self.viewmat, self.K, self.variant = width, height, viewmat, K, variant

    def params(self, P: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        keys = ["means", "quats", "scales", "opacities", "colors"]
        if self.name == "tomgs" or self.variant == "temporal":
            keys += ["t_means", "t_scales"]
        return [P[k] for k in keys]

    def __call__(self, P: dict[str, torch.Tensor], t: float):
        if self.name == "tomgs":
            return self.fn(P["means"], P["quats"], P["scales"], P["opacities"], P["colors"],
                           P["t_means"], P["t_scales"], self.viewmat, self.K, self.width, self.height, t,
                           background=None, near=0.01, far=1e10)
        op = P["opacities"]
        if self.variant == "temporal":
            op = op * torch.exp(-0.5 * ((t - P["t_means"]) / P["t_scales"]) ** 2)
        img, alpha, meta = self.fn(P["means"], P["quats"], P["scales"], op, P["colors"],
                                   self.viewmat[None], self.K[None], self.width, self.height,
                                   near_plane=0.01, far_plane=1e10, packed=False)
        return img[0], alpha[0], meta


# ----------------------------------------------------------------------------- device helpers


class Clock:
    """CUDA events on cuda, perf_counter on cpu; sync() waits for the whole device."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"

    def sync(self):
        if self.cuda:
            torch.cuda.synchronize()

    def mark(self):
        if self.cuda:
            e = torch.cuda.Event(enable_timing=True)
            e.record()
            return e
        return time.perf_counter()

    def ms(self, a, b) -> float:
        if self.cuda:
            return a.elapsed_time(b)
        return (b - a) * 1e3


class WarpPool:
    """Warp's CUDA mempool usage (Warp arrays, radix-sort scratch), with a high-water reset via libcuda."""

    def __init__(self, device: torch.device):
        self.ok = False
        self.reset_ok = False
        self.info: dict = {}
        if device.type != "cuda":
            return
        try:
            import warp as wp

            self.wp = wp
            self.dev = f"cuda:{device.index or 0}"
            self.ordinal = device.index or 0
            self.info["warp_version"] = wp.__version__
            self.info["mempool_enabled"] = bool(wp.is_mempool_enabled(self.dev))
            wp.get_mempool_used_mem_current(self.dev)
            self.ok = True
        except Exception as e:  # noqa: BLE001
            self.info["error"] = f"{type(e).__name__}: {e}"
            return
        try:
            self.cu = ctypes.CDLL("libcuda.so.1")
            self.pool = ctypes.c_void_p()
            dev = ctypes.c_int()
            if self.cu.cuDeviceGet(ctypes.byref(dev), ctypes.c_int(self.ordinal)) != 0:
                raise RuntimeError("cuDeviceGet failed")
            self.cu.cuMemPoolSetAttribute.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
            if self.cu.cuDeviceGetMemPool(ctypes.byref(self.pool), dev) != 0:
                raise RuntimeError("cuDeviceGetMemPool failed")
            self.reset_ok = True
        except Exception as e:  # noqa: BLE001
            self.info["reset_error"] = f"{type(e).__name__}: {e}"

    def current(self):
        return self.wp.get_mempool_used_mem_current(self.dev) if self.ok else None

    def high(self):
        return self.wp.get_mempool_used_mem_high(self.dev) if self.ok else None

    def reset_high(self) -> bool:
        """CU_MEMPOOL_ATTR_USED_MEM_HIGH = 8; it can only be set to zero (meaning: to the current use)."""
        if not (self.ok and self.reset_ok):
            return False
        zero = ctypes.c_uint64(0)
        rc = self.cu.cuMemPoolSetAttribute(self.pool, 8, ctypes.byref(zero))
        if rc != 0:
            self.info["reset_error"] = f"cuMemPoolSetAttribute rc={rc}"
            self.reset_ok = False
            return False
        return self.high() <= self.current() + (1 << 20)


def gb(x) -> float | None:
    return None if x is None else x / 1e9


# ----------------------------------------------------------------------------- one case


def _drop_grads(params):
    for p in params:
        p.grad = None


def iteration(run: Runner, P, params, t, Wimg, Walpha, clock: Clock, synced: bool) -> dict:
    """One fwd + loss + bwd. synced: device syncs between phases (clean fwd / bwd split, wall times);
    not synced: events around the whole step only (pipelined, as in a training loop). A deferred
    frame that overflowed its keys' bound is timed again (the bound grew: once per new total)."""
    try:
        return _iteration(run, P, params, t, Wimg, Walpha, clock, synced)
    except Overflowed:
        log(f"  {run.name}: t={t} overflowed its keys' bound, timed again")
        return _iteration(run, P, params, t, Wimg, Walpha, clock, synced)


def _iteration(run: Runner, P, params, t, Wimg, Walpha, clock: Clock, synced: bool) -> dict:
    _drop_grads(P.values())
    clock.sync()
    w0 = time.perf_counter()
    e0 = clock.mark()
    img, alpha, meta = run(P, t)
    if not synced:
        loss = (img * Wimg).sum() + (alpha * Walpha).sum()
        loss.backward()
        read_counts(meta)
        e3 = clock.mark()
        clock.sync()
        return dict(step=clock.ms(e0, e3), step_wall=(time.perf_counter() - w0) * 1e3)
    e1 = clock.mark()
    clock.sync()
    w1 = time.perf_counter()
    loss = (img * Wimg).sum() + (alpha * Walpha).sum()
    clock.sync()
    w2 = time.perf_counter()
    e2 = clock.mark()
    loss.backward()
    e3 = clock.mark()
    clock.sync()
    w3 = time.perf_counter()
    read_counts(meta)
    fwd, bwd = clock.ms(e0, e1), clock.ms(e2, e3)
    return dict(fwd=fwd, bwd=bwd, fb=fwd + bwd, fwd_wall=(w1 - w0) * 1e3, bwd_wall=(w3 - w2) * 1e3,
                fb_wall=(w1 - w0 + w3 - w2) * 1e3)


def memory_probe(run: Runner, P, params, t, Wimg, Walpha, clock: Clock, base_inputs: int,
                 pool: WarpPool) -> dict:
    _drop_grads(P.values())
    gc.collect()
    clock.sync()
    held_before = torch.cuda.memory_allocated()
    torch.cuda.reset_peak_memory_stats()
    pool_reset = pool.reset_high()
    pool_before = pool.current()
    img, alpha, _ = run(P, t)
    loss = (img * Wimg).sum() + (alpha * Walpha).sum()
    loss.backward()
    clock.sync()
    peak = torch.cuda.max_memory_allocated()
    out = dict(peak_gb=gb(peak - base_inputs), peak_delta_gb=gb(peak - held_before),
               held_before_gb=gb(held_before - base_inputs))
    if pool.ok:
        high = pool.high()
        out.update(warp_pool_high_raw_gb=gb(high), warp_pool_before_gb=gb(pool_before),
                   warp_pool_reset=pool_reset,
                   warp_pool_peak_gb=gb(high - pool_before) if pool_reset else None)
    del img, alpha, loss
    _drop_grads(P.values())
    return out


def image_diff(a_img, a_alpha, b_img, b_alpha) -> dict:
    d = (a_img.double() - b_img.double()).abs()
    da = (a_alpha.double() - b_alpha.double()).abs()
    return dict(img_max_abs=float(d.max()), img_mean_abs=float(d.mean()),
                img_frac_gt_1em2=float((d > 1e-2).double().mean()),
                alpha_max_abs=float(da.max()), alpha_mean_abs=float(da.mean()),
                finite=bool(torch.isfinite(a_img).all() and torch.isfinite(b_img).all()))


def scalar_meta(meta) -> dict:
    out = {}
    for k, v in (meta or {}).items():
        if isinstance(v, (int, float, bool)):
            out[k] = v
        elif isinstance(v, torch.Tensor) and v.numel() == 1:
            out[k] = v.item()
    return out


def visible_count(name: str, meta) -> int | None:
    try:
        if name == "gsplat":
            return int((meta["radii"] > 0).all(dim=-1).sum())
        for key in ("n_visible", "visible_count", "num_visible", "n_vis"):
            if key in meta:
                v = meta[key]
                return int(v.item() if isinstance(v, torch.Tensor) else v)
        r = meta.get("radii")
        if isinstance(r, torch.Tensor):
            return int((r > 0).all(dim=-1).sum()) if r.dim() == 2 else int((r > 0).sum())
        if meta.get("counts") is not None:  # a replayed frame's meta: its counts alone
            return int(meta["counts"].read()["n_visible"])
    except Exception:  # noqa: BLE001
        pass
    return None


def med(xs):
    return statistics.median(xs) if xs else None


# Stages of a frame, and the kernel-name fragments (lower case) that put a kernel in one: tomgs's Warp
# kernels and gsplat 1.5.3's CUDA kernels (projection_ewa_3dgs_fused_*, intersect_tile/offset,
# rasterize_to_pixels_3dgs_*); the first match wins, anything else (fills, the loss, the gradients'
# accumulation, gsplat's torch-side opacity) is "other".
STAGES = (
    ("project fwd", ("project_forward", "project_listed", "projection_ewa_3dgs_fused_fwd", "fused_projection_fwd")),
    ("project bwd", ("project_backward", "projection_ewa_3dgs_fused_bwd", "fused_projection_bwd")),
    ("sort", ("radix",)),
    ("binning", ("write_tile_keys", "pad_tile_keys", "tile_ranges", "frame_stats", "scan", "intersect", "isect")),
    ("raster fwd", ("raster_forward", "rasterize_to_pixels_3dgs_fwd", "rasterize_to_pixels_fwd")),
    ("raster bwd", ("raster_backward", "rasterize_to_pixels_3dgs_bwd", "rasterize_to_pixels_bwd")),
)
STAGE_NAMES = tuple(name for name, _ in STAGES) + ("other",)


def stage_of(kernel: str) -> str:
    low = kernel.lower()
    return next((name for name, parts in STAGES if any(p in low for p in parts)), "other")


def stage_profile(run: Runner, P, params, ts, Wimg, Walpha, clock: Clock, iters: int = 10) -> dict:
    """GPU ms per synced fwd+loss+bwd by stage (torch profiler, mean over `ts` and `iters`), the kernels
    by name, and the events' f+b time in the same calls: f+b minus the kernels is the time the GPU
    waited for the host."""
    fb = []

    def step():
        for t in ts:
            fb.append(iteration(run, P, params, t, Wimg, Walpha, clock, synced=True)["fb"])

    kernels = {k: v / len(ts) for k, v in kernel_times(step, iters).items()}
    stages = dict.fromkeys(STAGE_NAMES, 0.0)
    for name, ms in kernels.items():
        stages[stage_of(name)] += ms
    events = sum(fb) / len(fb)
    return dict(stages_ms=stages, kernels_ms=dict(sorted(kernels.items(), key=lambda kv: -kv[1])[:16]),
                kernels_total_ms=sum(kernels.values()), profiled_fb_ms=events,
                host_wait_ms=events - sum(kernels.values()))


def run_case(args, fns, width, height, n, variant, device, clock, pool, deadline) -> dict:
    case = dict(width=width, height=height, n=n, variant=variant, libs={}, sanity={}, skipped=None)
    for fn in fns.values():  # what a library keeps between calls (tomgs's captured graph) goes before a case
        getattr(fn, "release", lambda: None)()
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()
        case["torch_allocated_at_start_gb"] = gb(torch.cuda.memory_allocated())

    scene = random_scene(n, args.seed, device)
    if variant == "static":
        scene["t_scales"] = torch.full_like(scene["opacities"], STATIC_T_SCALE)
    else:
        scene["t_scales"] = temporal_scales(scene["opacities"], args.alive_frac)
        case["alive_frac_expected"] = args.alive_frac * float((scene["opacities"] > 1.0 / 255).float().mean())
    P = {k: v.detach().requires_grad_(True) for k, v in scene.items()}
    del scene
    viewmat, K = camera(width, height, device)
    g = torch.Generator().manual_seed(args.seed + 1)
    Wimg = torch.rand(height, width, 3, generator=g).to(device)
    Walpha = torch.rand(height, width, 1, generator=g).to(device)
    base_inputs = torch.cuda.memory_allocated() if device.type == "cuda" else 0
    ts = t_values(variant, args.n_t)
    t_mid = ts[len(ts) // 2]

    runners = {name: Runner(name, fn, width, height, viewmat, K, variant) for name, fn in fns.items()}
    params = {name: r.params(P) for name, r in runners.items()}
    alive = [name for name in runners]

    # --- warm-up (the first call compiles Warp kernels / loads gsplat's extension)
    for name in list(alive):
        res = case["libs"].setdefault(name, {})
        try:
            tic = time.perf_counter()
            iteration(runners[name], P, params[name], ts[0], Wimg, Walpha, clock, synced=True)
            res["first_call_s"] = time.perf_counter() - tic
            last = None
            for _ in range(max(args.warmup - 1, 0)):
                for t in (ts if variant == "temporal" else [ts[0]])[:2]:
                    last = iteration(runners[name], P, params[name], t, Wimg, Walpha, clock, synced=True)
            if last is None:
                last = iteration(runners[name], P, params[name], ts[0], Wimg, Walpha, clock, synced=True)
            res["iter_s_estimate"] = max(last["fb_wall"], last["fb"]) / 1e3
            log(f"  {name}: first call {res['first_call_s']:.2f}s, warm fwd {last['fwd']:.3f} ms, "
                f"bwd {last['bwd']:.3f} ms")
        except Exception as e:  # noqa: BLE001
            res["error"] = f"{type(e).__name__}: {e}"
            res["traceback"] = traceback.format_exc()
            log(f"  {name}: ERROR in warm-up: {res['error']}")
            alive.remove(name)
            _drop_grads(P.values())
            if device.type == "cuda":
                torch.cuda.empty_cache()

    # --- sanity: same scene, same t, both libraries (no grad)
    if not args.no_sanity and alive:
        try:
            with torch.no_grad():
                outs = {name: runners[name](P, t_mid) for name in alive}
            for name, (_, _, meta) in outs.items():
                case["libs"][name]["visible"] = visible_count(name, meta)
                case["libs"][name]["meta_scalars"] = scalar_meta(meta)
            if "tomgs" in outs and "gsplat" in outs:
                case["sanity"] = dict(t=t_mid, vs="gsplat", **image_diff(outs["tomgs"][0], outs["tomgs"][1],
                                                                        outs["gsplat"][0], outs["gsplat"][1]))
            elif "tomgs" in outs and args.tiny:
                case["sanity"] = reference_diff(P, viewmat, K, width, height, t_mid, outs["tomgs"])
            if case["sanity"]:
                s = case["sanity"]
                log(f"  sanity tomgs vs {s.get('vs')}: image max {s.get('img_max_abs', float('nan')):.3g} "
                    f"mean {s.get('img_mean_abs', float('nan')):.3g}, alpha max "
                    f"{s.get('alpha_max_abs', float('nan')):.3g}")
            del outs
        except Exception as e:  # noqa: BLE001
            case["sanity"] = dict(error=f"{type(e).__name__}: {e}")
            log(f"  sanity ERROR: {case['sanity']['error']}")

    # --- repeats, shrunk to fit the budget (2 iterations per repeat and t: synced + pipelined)
    reserve = 5.0 + 2.0 * sum(case["libs"][n_]["iter_s_estimate"] for n_ in alive)
    per_repeat = 2.0 * len(ts) * sum(case["libs"][n_]["iter_s_estimate"] for n_ in alive) + 1e-3 * len(ts)
    left = deadline - time.perf_counter() - reserve
    repeats = args.repeats
    if per_repeat * repeats > left:
        repeats = max(3, int(left / per_repeat))
        log(f"  budget: repeats cut from {args.repeats} to {repeats}")
    case["repeats"] = repeats

    samples = {name: {t: [] for t in ts} for name in alive}

    def timed(name, t, record=True):
        try:
            s = iteration(runners[name], P, params[name], t, Wimg, Walpha, clock, synced=True)
            if record:
                s.update(iteration(runners[name], P, params[name], t, Wimg, Walpha, clock, synced=False))
                samples[name][t].append(s)
        except Exception as e:  # noqa: BLE001
            case["libs"][name]["error"] = f"{type(e).__name__}: {e}"
            case["libs"][name]["traceback"] = traceback.format_exc()
            log(f"  {name}: ERROR while timing at t={t}: {case['libs'][name]['error']}")
            alive.remove(name)
            _drop_grads(P.values())

    for t in ts:
        if variant == "temporal":  # one untimed iteration per new t (the alive set changes with t)
            for name in list(alive):
                timed(name, t, record=False)
        for r in range(repeats):
            for name in list(alive if r % 2 == 0 else alive[::-1]):  # alternate: drift hits both alike
                if name in alive:
                    timed(name, t)

    for name, per_t in samples.items():
        res = case["libs"][name]
        keys = ("fwd", "bwd", "fb", "step", "fwd_wall", "bwd_wall", "fb_wall", "step_wall")
        per_t_med = {t: {k: med([s[k] for s in ss]) for k in keys} for t, ss in per_t.items() if ss}
        if not per_t_med:
            continue
        res["per_t_ms"] = {f"{t:.4f}": v for t, v in per_t_med.items()}
        for k in keys:
            vals = [v[k] for v in per_t_med.values() if v[k] is not None]
            res[f"{k}_ms"] = sum(vals) / len(vals) if vals else None
        res["n_samples_per_t"] = min(len(ss) for ss in per_t.values())

    # --- where the time goes, by stage (after the timed repeats: the profiler slows the host)
    if args.stages and device.type == "cuda":
        for name in alive:
            try:
                case["libs"][name]["profile"] = stage_profile(runners[name], P, params[name], ts, Wimg, Walpha, clock)
            except Overflowed:  # the profiled frames' bound grew: once more, as the training loop renders
                case["libs"][name]["profile"] = stage_profile(runners[name], P, params[name], ts, Wimg, Walpha, clock)
            except Exception as e:  # noqa: BLE001
                case["libs"][name]["profile_error"] = f"{type(e).__name__}: {e}"
                log(f"  {name}: ERROR in the stage profile: {case['libs'][name]['profile_error']}")

    # --- peak memory, one fwd+bwd per library, at the middle t
    if device.type == "cuda":
        for name in alive:
            for other, fn in fns.items():  # what another library keeps (tomgs's graph) is not this one's peak
                if other != name:
                    getattr(fn, "release", lambda: None)()
            try:
                case["libs"][name].update(memory_probe(runners[name], P, params[name], t_mid, Wimg, Walpha,
                                                       clock, base_inputs, pool))
            except Exception as e:  # noqa: BLE001
                case["libs"][name]["mem_error"] = f"{type(e).__name__}: {e}"
                log(f"  {name}: ERROR in memory probe: {case['libs'][name]['mem_error']}")
        for res in case["libs"].values():  # Warp's pool is ~0 for gsplat; added for both alike
            if res.get("peak_gb") is not None:
                res["total_peak_gb"] = res["peak_gb"] + (res.get("warp_pool_peak_gb") or 0.0)

    # --- ratios tomgs / gsplat
    tm, gs = case["libs"].get("tomgs", {}), case["libs"].get("gsplat", {})
    ratios = {}
    for k in ("fwd_ms", "bwd_ms", "fb_ms", "step_ms"):
        if tm.get(k) and gs.get(k):
            ratios[k.replace("_ms", "")] = tm[k] / gs[k]
    if tm.get("peak_gb") and gs.get("peak_gb"):
        ratios["mem_torch"] = tm["peak_gb"] / gs["peak_gb"]
        ratios["mem_total"] = tm["total_peak_gb"] / gs["total_peak_gb"]
    case["ratios"] = ratios

    _drop_grads(P.values())
    return case


def reference_diff(P, viewmat, K, width, height, t, tomgs_out) -> dict:
    """Tiny mode without gsplat: compare with the float64 torch reference, if it is there."""
    from tomgs import rasterize_reference

    with torch.no_grad():
        img, alpha, _ = rasterize_reference(P["means"], P["quats"], P["scales"], P["opacities"], P["colors"],
                                            P["t_means"], P["t_scales"], viewmat, K, width, height, t,
                                            dtype=torch.float64)
    return dict(t=t, vs="reference(float64)", **image_diff(tomgs_out[0], tomgs_out[1], img, alpha))


# ----------------------------------------------------------------------------- report


def fmt(x, nd=3):
    if x is None:
        return "-"
    if isinstance(x, float):
        return f"{x:.{nd}f}"
    return str(x)


def markdown(results: dict) -> str:
    env = results["env"]
    lines = [
        f"### bench_raster: {env.get('gpu', env['device'])}, torch {env['torch']}, warp {env.get('warp')}, "
        f"gsplat {env.get('gsplat')}, commit {env.get('commit')}",
        "",
        f"command: `{env['command']}`",
        "",
        f"Times in ms ({'CUDA events' if env['device'].startswith('cuda') else 'perf_counter'}, median over "
        "repeats; temporal = mean over t of per-t medians). "
        "f+b = fwd + bwd; step = one pipelined fwd+loss+bwd. Memory: peak GB above the inputs "
        "(torch allocator; tomgs 'tot' adds Warp's mempool peak). Ratio = tomgs / gsplat.",
        "",
        "| size | N | variant | tomgs fwd | tomgs bwd | tomgs f+b | tomgs step | gsplat fwd | gsplat bwd "
        "| gsplat f+b | gsplat step | ratio f+b | ratio step | tomgs GB (torch/tot) | gsplat GB | ratio mem (tot) "
        "| f+b <= 1.5x |",
        "|---|---|---|" + "---|" * 14,
    ]
    for c in results["cases"]:
        size = f"{c['width']}x{c['height']}"
        n = f"{c['n'] / 1e6:g}M" if c["n"] >= 100_000 else str(c["n"])
        if c.get("skipped"):
            lines.append(f"| {size} | {n} | {c['variant']} | skipped: {c['skipped']} |" + " |" * 13)
            continue
        tm, gs, r = c["libs"].get("tomgs", {}), c["libs"].get("gsplat", {}), c.get("ratios", {})

        def cell(d, k):
            if d.get("error") and d.get(k) is None:
                return "ERR"
            return fmt(d.get(k))

        mem_t = f"{fmt(tm.get('peak_gb'))} / {fmt(tm.get('total_peak_gb'))}" if tm else "-"
        ok = "-" if r.get("fb") is None else ("yes" if r["fb"] <= 1.5 else "NO")
        lines.append(
            f"| {size} | {n} | {c['variant']} | {cell(tm, 'fwd_ms')} | {cell(tm, 'bwd_ms')} | {cell(tm, 'fb_ms')} "
            f"| {cell(tm, 'step_ms')} | {cell(gs, 'fwd_ms')} | {cell(gs, 'bwd_ms')} | {cell(gs, 'fb_ms')} "
            f"| {cell(gs, 'step_ms')} | {fmt(r.get('fb'), 2)} | {fmt(r.get('step'), 2)} | {mem_t} "
            f"| {fmt(gs.get('peak_gb'))} | {fmt(r.get('mem_total'), 2)} | {ok} |")
    lines += ["", "| size | N | variant | compared with | t | image max abs | image mean abs | px > 1e-2 "
                  "| alpha max abs | visible tomgs | visible gsplat |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in results["cases"]:
        s = c.get("sanity") or {}
        if c.get("skipped") or not s:
            continue
        size = f"{c['width']}x{c['height']}"
        if "error" in s:
            lines.append(f"| {size} | {c['n']} | {c['variant']} | {s.get('vs', '-')} | error: {s['error']} |" + " |" * 5)
            continue
        lines.append(
            f"| {size} | {c['n']} | {c['variant']} | {s.get('vs')} | {fmt(s.get('t'), 4)} | {s['img_max_abs']:.3g} "
            f"| {s['img_mean_abs']:.3g} | {s['img_frac_gt_1em2']:.3g} | {s['alpha_max_abs']:.3g} "
            f"| {fmt(c['libs'].get('tomgs', {}).get('visible'))} | {fmt(c['libs'].get('gsplat', {}).get('visible'))} |")
    lines += ["", "Host wall-clock cross-check (device synced around each phase), ms: a wall time far above the "
                  "event time means host overhead (Python, launches, host syncs) the GPU waits for.", "",
              "| size | N | variant | tomgs fwd wall | tomgs f+b wall | tomgs step wall | gsplat fwd wall "
              "| gsplat f+b wall | gsplat step wall | tomgs isect | tomgs alive |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in results["cases"]:
        if c.get("skipped"):
            continue
        tm, gs = c["libs"].get("tomgs", {}), c["libs"].get("gsplat", {})
        ms = tm.get("meta_scalars", {})
        lines.append(f"| {c['width']}x{c['height']} | {c['n']} | {c['variant']} | {fmt(tm.get('fwd_wall_ms'))} "
                     f"| {fmt(tm.get('fb_wall_ms'))} | {fmt(tm.get('step_wall_ms'))} | {fmt(gs.get('fwd_wall_ms'))} "
                     f"| {fmt(gs.get('fb_wall_ms'))} | {fmt(gs.get('step_wall_ms'))} | {fmt(ms.get('n_intersections'))} "
                     f"| {fmt(ms.get('n_alive'))} |")
    profiled = [c for c in results["cases"] if any("profile" in d for d in c.get("libs", {}).values())]
    if profiled:
        lines += ["", "Where the time goes (`--stages`): GPU ms per fwd+bwd by stage (torch profiler, mean over t), "
                      "the events' f+b of the same calls, and the GPU's wait for the host (f+b minus kernels).", "",
                  "| size | N | variant | library | " + " | ".join(STAGE_NAMES) + " | kernels | f+b | host wait |",
                  "|---|---|---|---|" + "---|" * (len(STAGE_NAMES) + 3)]
        for c in profiled:
            for name, d in c["libs"].items():
                if "profile" not in d:
                    continue
                pr = d["profile"]
                cells = " | ".join(fmt(pr["stages_ms"][k]) for k in STAGE_NAMES)
                totals = " | ".join(fmt(pr[k]) for k in ("kernels_total_ms", "profiled_fb_ms", "host_wait_ms"))
                case = f"{c['width']}x{c['height']} | {c['n']} | {c['variant']}"
                lines.append(f"| {case} | {name} | {cells} | {totals} |")
    errs = [(c, name, d["error"]) for c in results["cases"] for name, d in c.get("libs", {}).items() if d.get("error")]
    if errs:
        lines += ["", "Errors:"]
        lines += [f"- {c['width']}x{c['height']} N={c['n']} {c['variant']} {name}: {e}" for c, name, e in errs]
    notes = results.get("notes") or []
    if notes:
        lines += ["", "Notes:"] + [f"- {x}" for x in notes]
    return "\n".join(lines) + "\n"


def run_environment(device: torch.device, argv) -> dict:
    """common.environment plus what a GPU run of this script needs to be compared with another."""
    env = environment(device, "bench_raster", argv)
    if device.type == "cuda":
        env["cuda_runtime"] = torch.version.cuda
        env["gpu_mem_gb"] = torch.cuda.get_device_properties(device).total_memory / 1e9
    env["env_vars"] = {k: os.environ[k] for k in ("WARP_CACHE_PATH", "TORCH_EXTENSIONS_DIR", "MAX_JOBS",
                                                  "TORCH_CUDA_ARCH_LIST", "PYTHONPATH") if k in os.environ}
    return env


def write_outputs(out_dir: Path, results: dict) -> str:
    out_dir.mkdir(parents=True, exist_ok=True)
    md = markdown(results)
    stamp = results["env"]["date_utc"].replace(":", "").replace("-", "")[:15]
    tag = results["args"]["sizes"].replace(",", "_")
    for name, text in ((f"bench_raster_{tag}_{stamp}.json", json.dumps(results, indent=2, default=str)),
                       (f"bench_raster_{tag}_{stamp}.md", md)):
        tmp = out_dir / (name + ".tmp")
        tmp.write_text(text)
        tmp.replace(out_dir / name)
    return md


# ----------------------------------------------------------------------------- main


def main(argv=None) -> int:
    args = parse_args(argv)
    deadline = T0 + args.budget_s
    if args.device == "cuda" and not torch.cuda.is_available():
        print("error: --device cuda but torch sees no GPU; use --device cpu --tiny for a smoke test",
              file=sys.stderr)
        return 2
    device = torch.device("cuda", torch.cuda.current_device()) if args.device == "cuda" else torch.device("cpu")
    clock = Clock(device)
    env = run_environment(device, argv)
    results = dict(env=env, args={k: v for k, v in vars(args).items() if not k.endswith("_list")},
                   scene=dict(focal_ratio=FOCAL_RATIO, tan_x=TAN_X, tan_y=TAN_Y, z_range=[3.0, 5.0],
                              scale_range=[0.002, 0.02], static_t_scale=STATIC_T_SCALE,
                              alive_frac=args.alive_frac),
                   cases=[], notes=[])
    log(f"bench_raster on {env.get('gpu', device)}; torch {env['torch']}, warp {env['warp']}, "
        f"commit {env.get('commit')}; budget {args.budget_s:.0f}s")

    fns = {}
    if "tomgs" in args.lib_list:
        try:
            fns["tomgs"] = (graphed() if args.tomgs_graph else deferred(load_tomgs("tomgs.render:render_frame"))
                            if args.tomgs_defer else load_tomgs(args.tomgs_impl))
            if args.tomgs_graph:
                results["notes"].append("tomgs timed replayed from CUDA graphs (tomgs.FrameGraph, captured "
                                        "at a scene's first frame, warm-up): camera and time written per call, the "
                                        "counts read after the backward")
            elif args.tomgs_defer:
                results["notes"].append("tomgs timed as its training loop runs it: render_frame(defer=True), the "
                                        "counts read after the backward")
        except Exception as e:  # noqa: BLE001
            results["notes"].append(f"tomgs unavailable: {type(e).__name__}: {e}")
            log(f"tomgs unavailable: {e}")
    if "gsplat" in args.lib_list:
        if device.type != "cuda":
            results["notes"].append("gsplat skipped: it needs a CUDA device")
        else:
            try:
                fns["gsplat"], env["gsplat"] = load_gsplat(device)
            except Exception as e:  # noqa: BLE001
                results["notes"].append(f"gsplat unavailable: {type(e).__name__}: {e}")
                log(f"gsplat unavailable: {type(e).__name__}: {e}")
    if not fns:
        print("error: neither tomgs nor gsplat could be loaded", file=sys.stderr)
        write_outputs(Path(args.out), results)
        return 1

    pool = WarpPool(device)
    results["warp_pool"] = pool.info
    if device.type == "cuda" and not pool.reset_ok:
        results["notes"].append("Warp mempool high-water mark could not be reset: warp_pool_peak_gb not reported")

    cases = [(w, h, n, v) for (w, h) in args.size_list for n in args.n_list for v in args.variant_list]
    for i, (w, h, n, v) in enumerate(cases):
        left = deadline - time.perf_counter()
        label = f"case {i + 1}/{len(cases)}: {w}x{h} N={n:,} {v}"
        if left < args.min_case_s:
            log(f"{label}: SKIPPED, {left:.0f}s of budget left (< --min-case-s {args.min_case_s:.0f})")
            results["cases"].append(dict(width=w, height=h, n=n, variant=v, skipped=f"budget ({left:.0f}s left)",
                                         libs={}, sanity={}))
            continue
        log(f"{label} ({left:.0f}s of budget left)")
        try:
            case = run_case(args, fns, w, h, n, v, device, clock, pool, deadline)
        except Exception as e:  # noqa: BLE001 (e.g. OOM while building the scene)
            case = dict(width=w, height=h, n=n, variant=v, skipped=f"{type(e).__name__}: {e}", libs={}, sanity={},
                        traceback=traceback.format_exc())
            log(f"{label}: FAILED {case['skipped']}")
        results["cases"].append(case)
        r = case.get("ratios", {})
        tm, gs = case["libs"].get("tomgs", {}), case["libs"].get("gsplat", {})
        log(f"  done: tomgs f+b {fmt(tm.get('fb_ms'))} ms, gsplat f+b {fmt(gs.get('fb_ms'))} ms, "
            f"ratio {fmt(r.get('fb'), 2)}; mem tomgs {fmt(tm.get('total_peak_gb'))} GB, "
            f"gsplat {fmt(gs.get('peak_gb'))} GB")
        write_outputs(Path(args.out), results)  # partial results survive a timeout
        gc.collect()
        if device.type == "cuda":
            torch.cuda.empty_cache()

    results["total_s"] = time.perf_counter() - T0
    md = write_outputs(Path(args.out), results)
    log(f"wrote JSON + markdown to {Path(args.out).resolve()} (total {results['total_s']:.0f}s)")
    print()
    print(md, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
