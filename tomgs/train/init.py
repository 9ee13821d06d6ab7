"""The init stage: the Gaussians a fit starts from.

The tracked points (alive over the frames that saw them, or the whole clip) plus points drawn from
every frame, alive around its time (`wide_fraction` of them over the whole clip), placed along their
pixels' rays at the depth a grid over that frame gives, interpolated from the tracked points it sees
(`TrainConfig.init_depth`; a frame with too few takes their median), spread around it by a log-normal
factor (`init_depth_jitter`). The cloud is built a frame at a time in float32 arrays on the training
device: the host never holds the whole of it.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from tomgs.cameras import Cameras
from tomgs.model import GaussianModel, nearest_neighbour_distance
from tomgs.temporal import frames_to_clip_time
from tomgs.train.config import TrainConfig

# the initial per-frame points' depth (config.init_depth "tracks"): a grid of about this many nodes a frame,
# each the mean log depth of its nearest tracked points (tracks are sparse: camel's 937 for 854x480 frames);
# a frame with fewer in view takes its median depth
DEPTH_GRID_NODES = 2048
DEPTH_NEIGHBOURS = 4
MIN_DEPTH_POINTS = 3
DEPTH_GRID_CHUNK = 1 << 22  # node-point pairs of the frames computed at once (their [c,G,P,2] float32: 32 MB)
STATIC_T_SCALE = 1e3  # temporal sigma of every Gaussian of a static fit (clip time: alive throughout)


def initial_model(frames: torch.Tensor, cameras: Cameras, config: TrainConfig, device: torch.device, points, colors, *,
                  weights: torch.Tensor | None = None, point_frames=None, wide_fraction: float = 0.0,
                  progress=None) -> tuple[GaussianModel, float, list[str]]:
    """(model on `device`, extent: the median depth of the tracked points, notes). frames: uint8 [T,H,W,3]
    (the trainer's, on the host or the device); points [P,3], colors [P,3] in [0,1]: the tracker's cloud
    (may be empty); weights: None, or uint8 [T,H,W] (0: a pixel no Gaussian starts from); point_frames:
    None, or int [P,2] (the first and last frame that saw each point); wide_fraction and
    progress(done, total) as the Trainer takes them."""
    c = config
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.asarray(colors, dtype=np.float32).reshape(-1, 3)
    point_frames = None if point_frames is None else np.asarray(point_frames, dtype=np.int64).reshape(-1, 2)
    progress = progress or (lambda done, total: None)
    num_frames, height, width = frames.shape[:3]
    times = [float(t) for t in cameras.times]
    notes = []
    g = torch.Generator().manual_seed(c.seed)
    w2c = cameras.viewmats()
    depth = median_depth(points, w2c)
    per_frame = c.points_per_frame(width * height, num_frames, device.type)
    frame_sigma = frames_to_clip_time(c.init_t_scale_frames, num_frames)
    wide = int(round(wide_fraction * per_frame))  # the first `wide` of each frame's points (random)
    tracked_means, tracked_sigma = tracked_windows(point_frames, times, len(points), frame_sigma)
    # sizes: tracked points from their neighbours (few), per-frame points from one sample's
    # share of the image at their depth (many: a neighbour search over them would be quadratic)
    sample_pixels = math.sqrt(width * height / per_frame) / float(cameras.K[0, 0])
    pixel_size = max(float(np.median(depth)) * sample_pixels, 1e-6)
    total = len(points) + num_frames * per_frame
    all_points, all_colors, t_means, start_t_scales, sizes = _cloud_with_tracked_points(
        points, colors, tracked_means, tracked_sigma, total, pixel_size, device)
    if c.init_depth == "tracks":
        grids, known = log_depth_grids(points, w2c, cameras, point_frames, device)
    else:
        grids, known = None, torch.zeros(num_frames, dtype=torch.bool)
    n = len(points)
    for k in range(num_frames):
        u, v = initial_pixels(weights, k, per_frame, width, height, g)
        z = _frame_depths(grids[k] if known[k] else None, depth[k], u, v, width, height, c.init_depth_jitter, g)
        m = len(u)
        all_points[n:n + m], all_colors[n:n + m] = _frame_points(frames, cameras, k, u, v, z, device)
        if known[k]:
            sizes[n:n + m] = (z * sample_pixels).clamp_min(1e-6).float().to(device)
        early = torch.arange(m, device=device) < wide
        t_means[n:n + m] = torch.where(early, 0.5, float(np.float32(times[k])))
        start_t_scales[n:n + m] = torch.where(early, 1.0, float(np.float32(frame_sigma)))
        n += m
        progress(k + 1, num_frames)
    if n < total:  # frames with no allowed pixel gave none
        all_points, all_colors, t_means, start_t_scales, sizes = (
            a[:n].clone() for a in (all_points, all_colors, t_means, start_t_scales, sizes))
    if n > c.max_gaussians:  # the tracked points and a point a frame outnumber a small cap: a random share
        keep = torch.randperm(n, generator=g)[:c.max_gaussians].sort().values.to(device)
        all_points, all_colors, t_means, start_t_scales, sizes = (
            a[keep] for a in (all_points, all_colors, t_means, start_t_scales, sizes))
        notes.append(f"{c.max_gaussians:,} of the {n:,} starting points kept: the cap")
    t_scales = start_t_scales if c.temporal else STATIC_T_SCALE
    del start_t_scales
    model = GaussianModel.from_points(all_points, all_colors, t_means, t_scales, max_sh_degree=c.sh_degree,
                                      sizes=sizes)
    del all_points, all_colors, t_means, t_scales, sizes
    if c.sh_degree > 0:
        model.sh_degree = c.sh_degree
    else:
        notes.append("SH degree 0: view-dependent colour left out (--sh-degree 1..3 fits it; Python: "
                     "sh_degree=)")
    return model.to(device), float(np.median(depth)), notes


def _cloud_with_tracked_points(points: np.ndarray, colors: np.ndarray, t_means: np.ndarray, t_scales: np.ndarray,
                               total: int, pixel_size: float, device: torch.device) -> tuple[torch.Tensor, ...]:
    """The starting cloud's float32 arrays on the training device, room for `total` points: positions and
    colours [total,3], t_means, temporal sigmas and sizes [total]. The first P rows hold the tracked
    points (points, colors [P,3]; t_means, t_scales [P]; sized by their nearest neighbour); the rest
    (sizes `pixel_size` until then) are filled a frame at a time, so the host holds one frame's points,
    never the whole cloud (7.2M points, ~1.8 GB with their SH, for 900 frames on a GPU)."""
    P = len(points)
    dev = dict(dtype=torch.float32, device=device)
    all_points, all_colors = torch.empty(total, 3, **dev), torch.empty(total, 3, **dev)
    all_t_means, all_t_scales = torch.empty(total, **dev), torch.empty(total, **dev)
    sizes = torch.full((total,), pixel_size, **dev)
    if P:
        all_points[:P] = torch.as_tensor(points, dtype=torch.float32)
        all_colors[:P] = torch.as_tensor(colors, dtype=torch.float32)
        all_t_means[:P] = torch.as_tensor(t_means, dtype=torch.float32)
        all_t_scales[:P] = torch.as_tensor(t_scales, dtype=torch.float32)
        sizes[:P] = nearest_neighbour_distance(torch.as_tensor(points, dtype=torch.float32)).to(device)
    return all_points, all_colors, all_t_means, all_t_scales, sizes


def _frame_depths(grid: torch.Tensor | None, median: float, u: torch.Tensor, v: torch.Tensor, width: int,
                  height: int, jitter: float, g: torch.Generator) -> torch.Tensor:
    """Depths float64 [n] of one frame's new points at pixels u, v [n] of its width x height image: its
    log-depth `grid` [gh, gw] sampled there (None: the frame's `median` tracked depth), times a
    log-normal factor of sigma `jitter` (one draw of n normals from `g`)."""
    if grid is not None:
        z = torch.exp(sample_grid(grid, u, v, width, height))
    else:
        z = torch.full_like(u, median)
    return z * torch.exp(jitter * torch.randn(len(u), generator=g, dtype=torch.float64))


def _frame_points(frames: torch.Tensor, cameras: Cameras, k: int, u: torch.Tensor, v: torch.Tensor, z: torch.Tensor,
                  device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(world positions float32 [n,3] on the host, colours in [0,1] float32 [n,3] on `device`) of frame
    k's new points: pixels u, v [n] at depths z [n] (float64) through its camera, coloured by the pixel
    of frames [T,H,W,3] they fall in."""
    height, width = frames.shape[1:3]
    fx, fy, cx, cy = cameras.K[0, 0], cameras.K[1, 1], cameras.K[0, 2], cameras.K[1, 2]
    cam = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], -1).numpy()
    c2w = cameras.c2w[k]
    world = torch.from_numpy(cam @ c2w[:3, :3].T + c2w[:3, 3]).float()
    pix = frames[k, v.long().clamp(max=height - 1).to(frames.device),
                 u.long().clamp(max=width - 1).to(frames.device)]
    return world, pix.float().to(device) / 255.0


def tracked_windows(point_frames, times, count: int, min_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """(t_means [P], t_scales [P]) of the tracked points: centred on the frames that saw each one,
    sigma half their time span (at least `min_sigma`); the whole clip without `point_frames`."""
    if point_frames is None or len(point_frames) != count:
        return np.full(count, 0.5), np.full(count, 1.0)
    times = np.asarray(times)
    first, last = times[point_frames[:, 0]], times[point_frames[:, 1]]
    return (first + last) / 2, np.maximum((last - first) / 2, min_sigma)

def initial_pixels(weights, k: int, n: int, width: int, height: int, g: torch.Generator
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """n pixel positions (u, v) float64 [n] in frame k: uniform, or only where `weights` [T,H,W] is > 0."""
    if weights is None:
        return (torch.rand(n, generator=g, dtype=torch.float64) * width,
                torch.rand(n, generator=g, dtype=torch.float64) * height)
    allowed = (weights[k] > 0).flatten().double().cpu()
    if not allowed.any():
        return torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.float64)
    pixel = torch.multinomial(allowed, n, replacement=True, generator=g)
    jitter = torch.rand(2, n, generator=g, dtype=torch.float64)
    return (pixel % width).double() + jitter[0], (pixel // width).double() + jitter[1]

def log_depth_grids(points: np.ndarray, w2c: np.ndarray, cameras: Cameras, point_frames, device: torch.device
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each frame's log depth at grid nodes spread evenly over the image (corners included, about
    DEPTH_GRID_NODES): (float64 [T, gh, gw], bool [T] whether frame k's grid is known), on the host. A
    node's value is the inverse-squared-distance mean of the log depths of the DEPTH_NEIGHBOURS nearest
    tracked points seen in the frame (`point_frames`; without it, every point in front of the camera) as
    they project into the image; a frame with fewer than MIN_DEPTH_POINTS there has none. The frames go
    a chunk at a time through the training device, which copies the grids back once. points: float64
    [P,3] world; w2c: [T,4,4]."""
    T, width, height = len(cameras), cameras.width, cameras.height
    cell = math.sqrt(width * height / DEPTH_GRID_NODES)
    gw, gh = math.ceil(width / cell) + 1, math.ceil(height / cell) + 1
    if len(points) == 0:
        return torch.zeros(T, gh, gw, dtype=torch.float64), torch.zeros(T, dtype=torch.bool)
    dev = device
    ys, xs = torch.meshgrid(torch.linspace(0, height, gh, device=dev),
                            torch.linspace(0, width, gw, device=dev), indexing="ij")
    nodes = torch.stack([xs.flatten(), ys.flatten()], -1)  # [G,2] pixels
    world = torch.as_tensor(points, dtype=torch.float64, device=dev)
    w2c = torch.as_tensor(w2c, dtype=torch.float64, device=dev)
    K = torch.as_tensor(cameras.K, dtype=torch.float64, device=dev)
    size = torch.tensor([width, height], dtype=torch.float64, device=dev)
    frames = torch.arange(T, device=dev)
    if point_frames is not None and len(point_frames) == len(points):
        spans = torch.as_tensor(point_frames, device=dev)
        seen = (spans[:, 0] <= frames[:, None]) & (frames[:, None] <= spans[:, 1])  # [T,P]
    else:
        seen = torch.ones(T, len(points), dtype=torch.bool, device=dev)
    near = min(DEPTH_NEIGHBOURS, len(points))
    grids = torch.empty(T, gh * gw, dtype=torch.float64, device=dev)
    known = torch.empty(T, dtype=torch.bool, device=dev)
    chunk = max(1, DEPTH_GRID_CHUNK // (len(nodes) * len(points)))
    for a in range(0, T, chunk):
        b = min(a + chunk, T)
        cam = torch.einsum("tij,pj->tpi", w2c[a:b, :3, :3], world) + w2c[a:b, None, :3, 3]  # [c,P,3]
        z = cam[..., 2]
        uv = cam[..., :2] / z.clamp_min(1e-12)[..., None] * K.diagonal()[:2] + K[:2, 2]
        ok = seen[a:b] & (z > 1e-6) & ((uv >= 0) & (uv <= size)).all(-1)
        d2 = ((nodes[None, :, None, :] - uv[:, None].float()) ** 2).sum(-1)  # [c,G,P]
        d2, nearest = d2.masked_fill(~ok[:, None], float("inf")).topk(near, dim=-1, largest=False)
        # 0 for the points not seen; the cell's square keeps a node on a point from taking only its depth
        weights = 1.0 / (d2.double() + cell * cell)
        log_z = z.clamp_min(1e-12).log()[:, None].expand(-1, len(nodes), -1)
        grids[a:b] = (weights * log_z.gather(-1, nearest)).sum(-1) / weights.sum(-1).clamp_min(1e-300)
        known[a:b] = ok.sum(-1) >= MIN_DEPTH_POINTS
    return grids.reshape(T, gh, gw).cpu(), known.cpu()

def median_depth(points: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """Median depth [T] of the tracked points in each camera (1.0 where none is in front)."""
    out = np.ones(len(w2c))
    if len(points) == 0:
        return out
    for k, m in enumerate(w2c):
        z = points @ m[2, :3] + m[2, 3]
        z = z[z > 1e-6]
        if len(z):
            out[k] = float(np.median(z))
    return out


def sample_grid(grid: torch.Tensor, u: torch.Tensor, v: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Bilinear samples [n] of `grid` [gh, gw], whose nodes span the image (node (0, 0) at pixel (0, 0),
    (gh-1, gw-1) at (width, height)), at pixel positions u, v [n] (clamped to the image)."""
    gh, gw = grid.shape
    x = (u * ((gw - 1) / width)).clamp(0, gw - 1)
    y = (v * ((gh - 1) / height)).clamp(0, gh - 1)
    x0, y0 = x.floor().long().clamp(max=gw - 2), y.floor().long().clamp(max=gh - 2)
    a, b = (x - x0).to(grid.dtype), (y - y0).to(grid.dtype)
    top = grid[y0, x0] * (1 - a) + grid[y0, x0 + 1] * a
    bottom = grid[y0 + 1, x0] * (1 - a) + grid[y0 + 1, x0 + 1] * a
    return top * (1 - b) + bottom * b
