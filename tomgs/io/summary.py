"""What `tomgs info` reports about a scene: counts, time coverage, temporal scales, opacities,
and a histogram plot of the temporal scales."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.constants import ALPHA_MIN
from tomgs.io.scene import Scene, bits_per_pixel
from tomgs.io.tsog import image_sizes, is_tsog
from tomgs.outputs import check_png_path
from tomgs.temporal import alive_at, clip_time_to_frames, peak_opacity


def alive_per_frame(model, cameras: Cameras, alpha_min: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(count [T] of Gaussians whose temporal opacity at frame k's time is >= 1/255 -- those the
    renderer does not cull --, bool [N]: alive in at least one frame). Float32, as the renderer."""
    alpha_min = ALPHA_MIN if alpha_min is None else alpha_min
    with torch.no_grad():
        a, m, s = model.opacities.detach(), model.t_means.detach(), model.t_scales.detach()
        counts = np.zeros(len(cameras), dtype=np.int64)
        ever = torch.zeros(len(model), dtype=torch.bool, device=a.device)
        for k, t in enumerate(cameras.times.tolist()):
            alive = alive_at(a, m, s, torch.tensor(t, dtype=torch.float32, device=a.device), alpha_min)
            counts[k] = int(alive.sum())
            ever |= alive
    return counts, ever.cpu().numpy()


def temporal_scales_in_frames(model, cameras: Cameras) -> np.ndarray:
    """float64 [N]: sigma in frames, sigma * (T - 1) (clip units for a single-frame scene)."""
    return clip_time_to_frames(model.t_scales.detach().cpu().double().numpy(), len(cameras))


def log_histogram(values: np.ndarray, per_octave: int = 1, max_bins: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """(edges [B+1], counts [B]) of positive `values` in bins spaced by powers of two (`per_octave` per
    doubling); at most `max_bins` bins, the outer ones stretched to hold the extremes."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values) & (values > 0)]
    if len(values) == 0:
        return np.array([0.5, 1.0]), np.zeros(1, dtype=np.int64)
    lo = math.floor(math.log2(values.min()) * per_octave)
    hi = max(math.ceil(math.log2(values.max()) * per_octave), lo + 1)
    if hi - lo > max_bins:  # centre the window on the median, the rest goes into the outer bins
        mid = round(math.log2(float(np.median(values))) * per_octave)
        lo = max(lo, min(mid - max_bins // 2, hi - max_bins))
        hi = lo + max_bins
    edges = 2.0 ** (np.arange(lo, hi + 1) / per_octave)
    counts = np.histogram(np.clip(values, edges[0], edges[-1]), bins=edges)[0]
    return edges, counts


BOUNDS_SHARE = 0.98  # the inner bounds hold this share of the means on each axis (outliers left out)


def bounds(points: np.ndarray, inner: bool = True) -> dict:
    """{"min": [x, y, z], "max": [...]} of `points` [N,3] (world axes), and with `inner` the bounds of
    the middle BOUNDS_SHARE of them on each axis ("inner_min", "inner_max"): where to aim a box; None
    values for no points."""
    if len(points) == 0:
        return {"min": None, "max": None, **({"inner_min": None, "inner_max": None} if inner else {})}
    out = {"min": points.min(axis=0).tolist(), "max": points.max(axis=0).tolist()}
    if inner:
        tail = 100 * (1 - BOUNDS_SHARE) / 2
        out["inner_min"] = np.percentile(points, tail, axis=0).tolist()
        out["inner_max"] = np.percentile(points, 100 - tail, axis=0).tolist()
    return out


def _box(low, high) -> str:
    return ", ".join(f"{axis} {round(lo, 2) + 0.0:.2f}..{round(hi, 2) + 0.0:.2f}"  # + 0.0: no "-0.00"
                     for axis, lo, hi in zip("xyz", low, high))


def summarize(scene: Scene, path=None) -> dict:
    """Numbers `tomgs info` prints: counts, time coverage, temporal scales and opacities."""
    model, cams = scene.model, scene.cameras
    n, T = len(model), len(cams)
    counts, ever = alive_per_frame(model, cams)
    sigma = temporal_scales_in_frames(model, cams)
    edges, hist = log_histogram(sigma)
    opac = model.opacities.detach().cpu().double().numpy()
    m, s = model.t_means.detach().cpu().double().numpy(), model.t_scales.detach().cpu().double().numpy()
    peak = peak_opacity(opac, m, s, float(cams.times.min()), float(cams.times.max()))  # inside the clip

    def stats(x):
        if len(x) == 0:
            return {"min": None, "median": None, "mean": None, "max": None}
        return {"min": float(np.min(x)), "median": float(np.median(x)), "mean": float(np.mean(x)),
                "max": float(np.max(x))}

    nbytes = None if path is None else Path(path).stat().st_size
    out = {
        "path": None if path is None else str(path),
        "file_bytes": nbytes,
        "file_format": None if path is None else "tsog" if is_tsog(path) else "ply",
        "bits_per_pixel": None if nbytes is None else bits_per_pixel(nbytes, cams),
        "bytes_per_gaussian": None if nbytes is None or n == 0 else nbytes / n,
        "image_bytes": image_sizes(path) if path is not None and is_tsog(path) else None,
        "gaussians": n,
        "frames": T,
        "frame_numbers": [int(cams.frame_indices.min()), int(cams.frame_indices.max())],
        "width": cams.width,
        "height": cams.height,
        "focal": cams.focal,
        "sh_degree": int(model.sh_degree),
        "max_sh_degree": int(model.max_sh_degree),
        "alive_per_frame": {**stats(counts),
                            "min_frame": int(cams.frame_indices[int(np.argmin(counts))]),
                            "max_frame": int(cams.frame_indices[int(np.argmax(counts))]),
                            "counts": counts.tolist()},
        "never_alive": int(n - ever.sum()),
        "temporal_sigma_frames": {**stats(sigma), "unit": "frames" if T > 1 else "clip",
                                  "edges": edges.tolist(), "counts": hist.tolist()},
        "opacity": {**stats(opac), "below_1_255": int((opac < ALPHA_MIN).sum())},
        "peak_opacity_in_clip": {**stats(peak), "below_1_255": int((peak < ALPHA_MIN).sum())},
        "bounds": bounds(model.means.detach().cpu().double().numpy()),
        "camera_bounds": bounds(cams.c2w[:, :3, 3], inner=False),
        "info": scene.info,
    }
    return out


def format_summary(s: dict, width: int = 40) -> str:
    """Human-readable text of `summarize`'s dict, with a bar histogram of temporal scales."""
    lines = []
    lines.append(f"{s['path'] or 'scene'}: {s['gaussians']:,} Gaussians, {s['frames']} frames "
                 f"(numbers {s['frame_numbers'][0]}..{s['frame_numbers'][1]}) at {s['width']}x{s['height']}, "
                 f"focal {s['focal']:.1f} px, SH degree {s['sh_degree']} of {s['max_sh_degree']}")
    if s["file_bytes"] is not None:
        per = "" if s["bytes_per_gaussian"] is None else f", {s['bytes_per_gaussian']:.2f} bytes a Gaussian"
        lines.append(f"file: {s['file_bytes']:,} bytes ({s['file_format']}), {s['bits_per_pixel']:.3f} bits per pixel "
                     f"of the clip ({s['frames']} frames of {s['width']}x{s['height']}){per}")
    if s.get("image_bytes") and s["gaussians"]:
        lines.append("  bytes a Gaussian by image: " + ", ".join(
            f"{name} {size / s['gaussians']:.2f}" for name, size in s["image_bytes"].items()))
    a = s["alive_per_frame"]
    lines.append(f"alive per frame: min {a['min']:,.0f} (frame {a['min_frame']}), mean {a['mean']:,.0f}, median "
                 f"{a['median']:,.0f}, max {a['max']:,.0f} (frame {a['max_frame']}); never alive in any frame: "
                 f"{s['never_alive']:,}")
    b, c = s["bounds"], s["camera_bounds"]
    if s["gaussians"]:
        lines.append(f"where the Gaussians are (world axes: x right, y down, z forward): {_box(b['min'], b['max'])}; "
                     f"{BOUNDS_SHARE:.0%} of them: {_box(b['inner_min'], b['inner_max'])}")
    lines.append(f"cameras: {_box(c['min'], c['max'])}, frame 0 at the origin looking along +z")
    o, p = s["opacity"], s["peak_opacity_in_clip"]
    if s["gaussians"]:
        lines.append(f"opacity (base): min {o['min']:.3f}, median {o['median']:.3f}, mean {o['mean']:.3f}, "
                     f"max {o['max']:.3f}; below 1/255: {o['below_1_255']:,}")
        lines.append(f"peak opacity inside the clip: median {p['median']:.3f}; below 1/255: {p['below_1_255']:,}")
    h = s["temporal_sigma_frames"]
    unit = "frames" if h["unit"] == "frames" else "clip time (single frame)"
    if s["gaussians"]:
        lines.append(f"temporal sigma in {unit}: min {h['min']:.3g}, median {h['median']:.3g}, max {h['max']:.3g}")
    top = max(h["counts"]) if h["counts"] else 0
    for k, count in enumerate(h["counts"]):
        lo, hi = h["edges"][k], h["edges"][k + 1]
        bar = "#" * (round(width * count / top) if top else 0)
        lines.append(f"  {lo:>9.3g} .. {hi:<9.3g} {count:>10,} {bar}")
    return "\n".join(lines)


def plot_temporal_scales(scene: Scene, path) -> Path:
    """PNG histogram of the temporal sigmas in frames (log axis), written atomically (tomgs.io.plots)."""
    from tomgs.io.plots import histogram_png

    path = check_png_path(path)
    sigma = temporal_scales_in_frames(scene.model, scene.cameras)
    unit = "frames" if len(scene.cameras) > 1 else "clip time"
    title = f"temporal sigma of {len(sigma):,} Gaussians, {len(scene.cameras)} frames"
    return histogram_png(path, sigma, bins=40, log_x=True, xlabel=f"sigma ({unit})", title=title)
