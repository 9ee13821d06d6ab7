"""Temporal shards: several processes (one per GPU) fit one clip, each a stretch of it, into one scene.

TOM-GS shards in time: every Gaussian is static in one world frame and alive in a temporal window,
so Gaussians fitted for different stretches of a clip live side by side in one scene file.

    tomgs fit clip.mp4 -o scene.ply --gpus 2                               # N processes on this host
    torchrun --nproc_per_node 2 -m tomgs.cli fit clip.mp4 -o scene.ply     # the same under torchrun

A run (docs/multi-gpu.md; the processes and their faults: tomgs.train.multigpu.rank):

1. Rank 0 reads the clip and estimates the cameras once (a resume takes them from a checkpoint) and
   broadcasts them; every other rank then reads its own stretch (`plan_stretches`: equal runs of
   frames, `overlap` frames into each neighbour).
2. Phase 1, no communication: each rank is an ordinary Trainer on its stretch, in the stretch's own
   clip time (t in [0, 1] over its frames, so learning rates and initial windows mean what they mean
   in a fit of that many frames), with its own checkpoint and CSV beside the output
   (scene.rank1.ckpt, scene.rank1.csv), for 1 - `refine_fraction` of the training time.
3. Merge: each rank keeps the Gaussians whose temporal centre lies in its own stretch (an overlap's
   copies belong to the rank that owns those frames), maps them to clip time (t -> t0 + span t, an
   affine map under which o(t) is unchanged), and every rank gathers the union.
4. Joint refinement, data-parallel, for `refine_fraction` of the training time: a long-lived Gaussian
   of one stretch is alive in the next, where that rank fitted its own (the union alone double-draws
   them: 4-5 dB lost on the CPU benchmark, 2-2.5 more at the boundary). Each rank trains its part of the
   union (its Halo: the Gaussians that may be alive in its stretch) on its own frames; the gradients
   of the Gaussians in more than one part are summed over the ranks at each step (one all_reduce), so
   each is fitted to every frame it is alive in, and all replicas take the same step; a Gaussian
   alive in one stretch only is its rank's alone. No densification. A checkpoint is not written
   here: an interrupted refinement resumes from the ranks' last phase-1 checkpoints.
5. Each rank measures its own frames with the assembled scene; rank 0 writes the scene (an ordinary
   scene file), the merged CSV and its plot; the checkpoints are removed, the per-rank CSVs kept.

Error against run time: scene.rankR.csv is rank R's log (its Trainer's rows in phase 1, then the
refinement's); scene.csv merges them: until the merge, the frame-weighted mean of the ranks' latest
rows, then the union's refinement and, last, the full-clip PSNR of the scene written.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tomgs.errors import InputError
from tomgs.io import Video, read_video
from tomgs.io.video import parse_frames, probe_clip, read_video_for
from tomgs.model import PARAM_NAMES, GaussianModel
from tomgs.outputs import check_file_output, fit_output_paths, remove_stale_temporaries
from tomgs.train.checkpoint import START_OVER

MIN_STRETCH = 2  # frames per rank: a stretch's own clip time needs two
REFINE_FRACTION = 0.15  # of the training time, for the joint refinement of the union
# a Gaussian takes part in a rank's refinement when its alive window, widened by this share of its
# radius and REFINE_SLACK_FRAMES frames, meets the rank's stretch: the windows move while refining
REFINE_SLACK = 0.25
REFINE_SLACK_FRAMES = 2.0
RANK_FILE = "rank{}"  # scene.rank0.ckpt, scene.rank0.csv beside scene.ply


# -- the plan: which frames each rank fits ---------------------------------------------------------


@dataclass(frozen=True)
class Stretch:
    """Rank `rank`'s frames, as positions of the clip: it trains on [lo, hi) and owns [own_lo, own_hi)
    (its own frames; the rest of [lo, hi) is overlap with a neighbour)."""

    rank: int
    lo: int
    hi: int
    own_lo: int
    own_hi: int

    @property
    def frames(self) -> int:
        return self.hi - self.lo

    def describe(self, frame_numbers=None) -> str:
        """'frames 300..599' (source frame numbers when given), with the overlap when there is one."""
        name = (lambda k: int(frame_numbers[k])) if frame_numbers is not None else (lambda k: k)
        text = f"frames {name(self.own_lo)}..{name(self.own_hi - 1)}"
        extra = (self.own_lo - self.lo) + (self.hi - self.own_hi)
        return text + (f" (+{extra} overlap)" if extra else "")


def plan_stretches(count: int, world: int, overlap: int = 0) -> list[Stretch]:
    """`world` stretches of a `count`-frame clip: equal runs of positions (sizes differ by at most
    one), each reaching `overlap` frames into its neighbours. InputError when a rank would get fewer
    than MIN_STRETCH frames of its own."""
    if world < 1:
        raise InputError(f"--gpus {world}: give 1 or more")
    if overlap < 0:
        raise InputError(f"overlap {overlap}: give 0 or more frames")
    if count < MIN_STRETCH * world:
        raise InputError(f"--gpus {world} splits the clip's {count} frames into {world} stretches, but each rank "
                         f"needs at least {MIN_STRETCH} frames of its own: use --gpus "
                         f"{max(count // MIN_STRETCH, 1)} or fewer, or select more frames (--frames)")
    bounds = [round(r * count / world) for r in range(world + 1)]
    return [Stretch(r, max(bounds[r] - overlap, 0), min(bounds[r + 1] + overlap, count), bounds[r], bounds[r + 1])
            for r in range(world)]


def rank_paths(output, world: int) -> list[dict[str, Path]]:
    """Per rank: its checkpoint and CSV beside the scene (scene.rank0.ckpt, scene.rank0.csv)."""
    stem = Path(output).with_suffix("")
    return [dict(checkpoint=Path(f"{stem}.{RANK_FILE.format(r)}.ckpt"), csv=Path(f"{stem}.{RANK_FILE.format(r)}.csv"))
            for r in range(world)]


def default_overlap(count: int, world: int) -> int:
    """Frames each stretch reaches into its neighbours when not asked: none (measured on the CPU test,
    docs/multi-gpu.md: the refinement fits the boundary, and overlap frames are frames a rank does
    not own)."""
    return 0


# -- clip time and stretch time ---------------------------------------------------------------------


def stretch_span(times, stretch: Stretch) -> tuple[float, float]:
    """(t0, span): the stretch's first frame time and the clip time its frames cover; its own clip
    time is (t - t0) / span."""
    t0, t1 = float(times[stretch.lo]), float(times[stretch.hi - 1])
    if not t1 > t0:
        raise InputError(f"frames {stretch.lo}..{stretch.hi - 1} of the clip share one time ({t0}): a stretch's "
                         "frames must have increasing times")
    return t0, t1 - t0


def local_cameras(cameras, stretch: Stretch):
    """The cameras of the stretch's frames with the stretch's own times (first 0, last 1)."""
    from tomgs.cameras import Cameras

    t0, span = stretch_span(cameras.times, stretch)
    sub = cameras[stretch.lo:stretch.hi]
    return Cameras(sub.c2w, sub.K, sub.width, sub.height, (sub.times - t0) / span, sub.frame_indices)


def to_clip_time(params: dict, t0: float, span: float) -> dict:
    """Stored parameters (PARAM_NAMES: tensors [N, ...]) fitted in a stretch's own time, in clip time:
    t_means -> t0 + span t_means, log_t_scales -> log_t_scales + log(span). o(t) at corresponding
    times is unchanged (z = (t - m) / sigma is invariant); float64 inside."""
    out = dict(params)
    out["t_means"] = (t0 + span * params["t_means"].double()).float()
    out["log_t_scales"] = (params["log_t_scales"].double() + math.log(span)).float()
    return out


def moments_to_clip_time(first: dict, second: dict, span: float) -> tuple[dict, dict]:
    """Adam's moment estimates ({name: tensor [N, ...]} of a stretch's parameters, `adam_estimates`)
    for the same Gaussians in clip time (`to_clip_time`): they follow the gradient, and
    d/dt_means in clip time is d/dt_means in the stretch's time over `span` (the first moment over
    span, the second over span^2); log_t_scales only moves by a constant, the rest not at all. With
    the rates of `clip_rates`, an Adam step in clip time is the stretch's step mapped."""
    first, second = dict(first), dict(second)
    first["t_means"] = first["t_means"] / span
    second["t_means"] = second["t_means"] / (span * span)
    return first, second


def clip_rates(rates: dict[str, float], span: float) -> dict[str, float]:
    """A stretch's learning rates ({group name: lr}, its optimiser's) in clip time: t_means' times
    `span` (a step of t in the stretch's time is span times one in clip time), the others as they are."""
    return {name: lr * span if name == "t_means" else lr for name, lr in rates.items()}


def own_cut(times, stretch: Stretch) -> tuple[float, float]:
    """The clip-time interval [lo, hi) whose Gaussians the stretch's rank keeps at the merge: from
    half way between its first own frame and the one before, to half way after its last (open at the
    clip's ends)."""
    n = len(times)
    lo = -math.inf if stretch.own_lo == 0 else 0.5 * (times[stretch.own_lo - 1] + times[stretch.own_lo])
    hi = math.inf if stretch.own_hi >= n else 0.5 * (times[stretch.own_hi - 1] + times[stretch.own_hi])
    return float(lo), float(hi)


def stretch_points(points, colors, point_frames, stretch: Stretch):
    """The tracker's points for a stretch: those seen in its frames, with their first and last frame as
    positions of the stretch (clipped to it). point_frames int [P,2] (clip positions) or None."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    colors = np.asarray(colors, dtype=np.float32).reshape(-1, 3)
    if point_frames is None or len(points) == 0:
        return points, colors, None
    frames = np.asarray(point_frames, dtype=np.int64).reshape(-1, 2)
    seen = (frames[:, 1] >= stretch.lo) & (frames[:, 0] < stretch.hi)
    local = np.clip(frames[seen] - stretch.lo, 0, stretch.frames - 1)
    return points[seen], colors[seen], local


# -- rows: a model's parameters as one float32 row per Gaussian --------------------------------------


def row_widths(max_sh_degree: int) -> dict[str, int]:
    rest = 3 * ((max_sh_degree + 1) ** 2 - 1)
    return dict(means=3, quats=4, log_scales=3, opacity_logits=1, sh_dc=3, sh_rest=rest, t_means=1, log_t_scales=1)


def pack(params: dict) -> torch.Tensor:
    """float32 [N, D]: the stored parameters (PARAM_NAMES) of each Gaussian side by side."""
    n = params["means"].shape[0]
    return torch.cat([params[name].detach().reshape(n, -1).float() for name in PARAM_NAMES], dim=1)


def unpack(rows: torch.Tensor, max_sh_degree: int) -> dict[str, torch.Tensor]:
    """`pack`'s inverse: {name: tensor [N, ...]} of rows [N, D]."""
    widths, n, at, out = row_widths(max_sh_degree), rows.shape[0], 0, {}
    shapes = dict(means=(3,), quats=(4,), log_scales=(3,), opacity_logits=(), sh_dc=(1, 3),
                  sh_rest=((max_sh_degree + 1) ** 2 - 1, 3), t_means=(), log_t_scales=())
    for name in PARAM_NAMES:
        out[name] = rows[:, at:at + widths[name]].reshape(n, *shapes[name]).contiguous()
        at += widths[name]
    if at != rows.shape[1]:
        raise ValueError(f"rows of width {rows.shape[1]} are not SH degree {max_sh_degree}'s {at}")
    return out


def model_of(rows: torch.Tensor, max_sh_degree: int, sh_degree: int) -> GaussianModel:
    return GaussianModel(**unpack(rows, max_sh_degree), sh_degree=sh_degree)


def owned_rows(model: GaussianModel, times, stretch: Stretch, estimates: dict | None = None) -> torch.Tensor:
    """float32 [M, D]: the Gaussians of a rank's model (fitted in its stretch's time) whose temporal
    centre lies in the stretch's own cut (`own_cut`), in clip time. With `estimates` (its optimiser's
    `adam_estimates`), [M, 3 D]: each row followed by its Adam moment estimates in clip time (first,
    then second, each in `pack`'s layout)."""
    t0, span = stretch_span(times, stretch)
    params = to_clip_time({k: v.detach() for k, v in model.parameters_by_name().items()}, t0, span)
    lo, hi = own_cut(times, stretch)
    keep = (params["t_means"].double() >= lo) & (params["t_means"].double() < hi)
    if estimates is None:
        return pack(params)[keep]
    first, second = moments_to_clip_time({k: v[0] for k, v in estimates.items()},
                                         {k: v[1] for k, v in estimates.items()}, span)
    return torch.cat([pack(params), pack(first), pack(second)], dim=1)[keep]


@dataclass
class Union:
    """Every rank's owned Gaussians (`owned_rows`), gathered on every rank, with what phase 1 hands the
    refinement (the same on every rank, so that replicas of a shared Gaussian start alike).

    rows      float32 [N, D]: the Gaussians, in clip time, rank 0's first
    moments   float32 [N, 2 D] or None: each row's Adam moment estimates from the rank that fitted it
              (first | second, `pack`'s layout, clip time); None: not carried
    steps     {group: Adam steps}: the refinement's step counts, the ranks' largest ({}: not carried)
    rates     {group: lr}: the learning rates phase 1 ended with, in clip time (`clip_rates`), the
              ranks' mean
    gather_s  seconds the rows' all_gather took (the assembly's is as large)"""

    rows: torch.Tensor
    moments: torch.Tensor | None
    steps: dict
    rates: dict
    gather_s: float


def gather_union(model: GaussianModel, optimizer, times, stretch: Stretch, carry: bool = True) -> Union:
    """The Union of every rank's phase-1 model and optimiser (make_adam's: one named group per
    parameter), gathered over the default process group (every rank calls it; rows on the model's
    device). `carry`: also the Adam moment estimates of every row, for `refine` to go on from."""
    from tomgs.train.optim import adam_estimates

    device = model.means.device
    estimates = adam_estimates(optimizer) if carry else None
    rows = owned_rows(model, times, stretch, estimates).to(device)
    width = sum(row_widths(model.max_sh_degree).values())
    began = time.perf_counter()
    union = torch.cat(all_gather_rows(rows[:, :width].contiguous()))
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    gather_s = time.perf_counter() - began
    moments = torch.cat(all_gather_rows(rows[:, width:].contiguous())) if carry else None
    del rows
    # each rank's step counts and rates, one float64 row: the ranks' largest counts, their mean rates
    names = [g["name"] for g in optimizer.param_groups]
    span = stretch_span(times, stretch)[1]
    rates = clip_rates({g["name"]: float(g["lr"]) for g in optimizer.param_groups}, span)
    steps = {name: estimates[name][2] if carry else 0 for name in names}
    mine = torch.tensor([[steps[n] for n in names] + [rates[n] for n in names]], dtype=torch.float64, device=device)
    every = torch.cat(all_gather_rows(mine)).cpu()
    k = len(names)
    return Union(union, moments, {n: int(every[:, i].max()) for i, n in enumerate(names)} if carry else {},
                 {n: float(every[:, k + i].mean()) for i, n in enumerate(names)}, gather_s)


def reach(model: GaussianModel, times, stretches: list[Stretch]) -> torch.Tensor:
    """bool [S, N]: whether Gaussian i may be alive in stretch s's own frames while refining (its alive
    window widened by REFINE_SLACK and REFINE_SLACK_FRAMES frames meets [first, last] own frame time)."""
    from tomgs import temporal

    with torch.no_grad():
        first, last = temporal.alive_window(model.opacities.double(), model.t_means.double(),
                                            model.t_scales.double())
        radius = (last - first) / 2
        margin = REFINE_SLACK * radius.clamp_min(0) + REFINE_SLACK_FRAMES / max(len(times) - 1, 1)
        first, last = first - margin, last + margin
        dead = ~(radius >= 0)  # alive at no time (a < 1/255): in no stretch
        rows = []
        for s in stretches:
            t0, t1 = float(times[s.own_lo]), float(times[s.own_hi - 1])
            rows.append((last >= t0) & (first <= t1) & ~dead)
        return torch.stack(rows) if rows else torch.zeros(0, len(model), dtype=torch.bool)


# -- the merged curve -----------------------------------------------------------------------------


def log_row(**values) -> dict:
    """A row of a fit's CSV log with every field it has (tomgs.train.checkpoint.LOG_FIELDS), "" for
    those not given."""
    from tomgs.train.checkpoint import LOG_FIELDS

    return {name: values.get(name, "") for name in LOG_FIELDS}


def merged_history(histories: list[list[dict]], weights: list[float]) -> list[dict]:
    """One CSV log (tomgs.train.checkpoint.LOG_FIELDS rows) of ranks that trained side by side: at
    every time a rank logged (wall_s: each rank's training seconds), each rank's latest row so far
    combined: iterations and Gaussians summed, memory the largest, PSNRs the `weights`-weighted mean
    (frames per rank). A full-clip PSNR is given where a rank measured one and every rank has one by
    then (each rank's latest)."""
    events = sorted({(float(row["wall_s"]), r, i) for r, rows in enumerate(histories) for i, row in enumerate(rows)})
    latest: list[dict | None] = [None] * len(histories)
    clip: list[float | None] = [None] * len(histories)
    frames: list[int | None] = [None] * len(histories)  # the frames each rank's latest clip PSNR covers
    out = []
    for wall, r, i in events:
        row = histories[r][i]
        latest[r] = row
        measured = row["clip_psnr"] != ""
        if measured:
            clip[r] = float(row["clip_psnr"])
            frames[r] = int(row["clip_frames"]) if row.get("clip_frames") not in ("", None) else None
        if any(x is None for x in latest):
            continue

        def mean(values):
            pairs = [(w, float(v)) for w, v in zip(weights, values) if v not in ("", None)]
            total = sum(w for w, _ in pairs)
            return round(sum(w * v for w, v in pairs) / total, 3) if total > 0 else ""

        complete = measured and all(c is not None for c in clip)
        covered = [frames[r] for r in range(len(histories))]
        merged = log_row(iteration=sum(int(x["iteration"]) for x in latest), wall_s=round(wall, 3),
                         train_psnr=mean([x["train_psnr"] for x in latest]),
                         clip_psnr=mean(clip) if complete else "",
                         clip_frames=sum(covered) if complete and None not in covered else "",
                         gaussians=sum(int(x["gaussians"]) for x in latest),
                         scene_bytes=sum(int(x["scene_bytes"]) for x in latest)
                         if all(x.get("scene_bytes") not in ("", None) for x in latest) else "",
                         memory_mb=max(float(x["memory_mb"]) for x in latest))
        if out and out[-1]["wall_s"] == merged["wall_s"]:
            if merged["clip_psnr"] == "" and out[-1]["clip_psnr"] != "":
                merged["clip_psnr"], merged["clip_frames"] = out[-1]["clip_psnr"], out[-1].get("clip_frames", "")
            out[-1] = merged
        else:
            out.append(merged)
    return out


def boundary_psnr(frame_psnr, stretches: list[Stretch], near: int = 2) -> dict:
    """Per-frame PSNRs [T] of a scene split by `stretches`: the mean of the frames within `near` frames
    of each boundary between two stretches ('boundaries': one per boundary, 'boundary': all of them)
    and of the others ('interior')."""
    psnr = np.asarray(frame_psnr, dtype=np.float64)
    close = np.zeros(len(psnr), dtype=bool)
    per = []
    for s in stretches[1:]:
        lo, hi = max(s.own_lo - near, 0), min(s.own_lo + near, len(psnr))
        close[lo:hi] = True
        per.append(dict(frame=int(s.own_lo), psnr=round(float(psnr[lo:hi].mean()), 3)))
    return dict(boundaries=per, boundary=round(float(psnr[close].mean()), 3) if close.any() else None,
                interior=round(float(psnr[~close].mean()), 3) if (~close).any() else None, near=near)


# -- the joint refinement ---------------------------------------------------------------------------


@dataclass
class Halo:
    """Rank `rank`'s part of the union (N Gaussians, in the same order on every rank): the Gaussians
    that may be alive in its stretch (`reach`), which it alone refines, with the others that share
    them.

    rows      int64 [M]: their rows of the union, ascending
    shared    int64 [K]: the positions in `rows` of those alive in another stretch too
    slots     int64 [K]: their places in the union's list of shared Gaussians (the all_reduce buffer)
    total     the union's shared Gaussians (the buffer's rows)
    holder    int64 [N]: the rank whose copy of each Gaussian goes to the scene (the first whose
              stretch it may be alive in; -1: alive in none, left out)"""

    rank: int
    rows: torch.Tensor
    shared: torch.Tensor
    slots: torch.Tensor
    total: int
    holder: torch.Tensor


def halo(union: torch.Tensor, max_sh_degree: int, times, stretches: list[Stretch], rank: int) -> Halo:
    """The Halo of rank `rank` in the union's rows [N, D] (every rank computes every rank's the same)."""
    with torch.no_grad():
        reaches = reach(model_of(union, max_sh_degree, 0), times, stretches)  # [S, N]
    count = reaches.sum(0)
    is_shared = count > 1
    slot_of = torch.cumsum(is_shared.long(), 0) - 1  # [N]: a shared Gaussian's place in the buffer
    rows = reaches[rank].nonzero()[:, 0]
    shared = is_shared[rows].nonzero()[:, 0]
    holder = torch.where(count > 0, reaches.long().argmax(0), torch.full_like(count, -1))
    return Halo(rank, rows, shared, slot_of[rows[shared]], int(is_shared.sum()), holder)


# -- the outputs -----------------------------------------------------------------------------------


def check_shard_outputs(output, world: int, resume: bool, overwrite: bool, tidy: bool = False) -> dict:
    """The outputs of a sharded fit (tomgs.outputs.fit_output_paths plus each rank's checkpoint and CSV)
    once every one can be written, else InputError saying how to proceed. Resume expects the ranks'
    checkpoints (at least one) and refuses those of another number of ranks, or a one-GPU fit's
    checkpoint; without resume, any checkpoint is refused unless `overwrite`. `tidy`: remove, with
    overwrite, the checkpoints that this run replaces (a one-GPU fit's, other ranks'), and stale
    temporaries."""
    import re

    paths = fit_output_paths(output)
    if paths["scene"].suffix.lower() != ".ply":
        raise InputError(f"{output}: a scene is written as .ply; name the output like scene.ply")
    ranks = rank_paths(output, world)
    check_file_output(paths["scene"], overwrite, "scene")
    check_file_output(paths["plot"], overwrite, "PSNR plot")
    check_file_output(paths["csv"], overwrite or resume, "log")
    stem = paths["scene"].with_suffix("").name
    pattern = re.compile(re.escape(stem) + r"\.rank(\d+)\.ckpt$")
    others = sorted((int(m.group(1)), p) for p in paths["scene"].parent.glob(f"{stem}.rank*.ckpt")
                    if (m := pattern.match(p.name)) and int(m.group(1)) >= world)
    single = paths["checkpoint"]
    have = [r["checkpoint"] for r in ranks if r["checkpoint"].is_file()]
    if resume:
        if single.is_file():
            raise InputError(f"{single} holds an interrupted one-GPU fit of {paths['scene'].name}: resume it without "
                             f"--gpus, or {START_OVER}")
        if others:
            raise InputError(f"{others[0][1]} belongs to a fit of {others[-1][0] + 1} or more ranks: resume with the "
                             f"--gpus it was started with, or {START_OVER}")
        if not have:
            names = ", ".join(str(r["checkpoint"].name) for r in ranks)
            raise InputError(f"no checkpoint of a {world}-rank fit beside {output} ({names}) to resume from; run "
                             f"without --resume")
    elif (have or others or single.is_file()) and not overwrite:
        found = (have + [p for _, p in others] + ([single] if single.is_file() else []))[0]
        raise InputError(f"{found} holds an interrupted fit of {paths['scene'].name}: pass --resume to continue it "
                         f"(with the --gpus it was started with), or --overwrite (-y) to start over (Python: "
                         f"resume=True or overwrite=True)")
    for r in ranks:
        check_file_output(r["checkpoint"], True, "checkpoint")
        check_file_output(r["csv"], overwrite or resume, "log")
    if tidy:
        if overwrite and not resume:
            for path in [p for _, p in others] + [single]:
                path.unlink(missing_ok=True)
        for path in [*paths.values(), *(p for r in ranks for p in r.values())]:
            remove_stale_temporaries(path)
    return dict(paths, ranks=ranks)


# -- a rank's frames -------------------------------------------------------------------------------


def read_early(job, rank: int):
    """A rank's frames (a tomgs.io.Video) read before rank 0's cameras arrive, when the selection (--frames) names their
    source frame numbers without the source's length (a range from a start >= 0); None otherwise. The
    clip's frame count comes from its index (tomgs.io.video.probe_clip)."""
    if isinstance(job.video, Video):
        return None
    sel = parse_frames(job.frames)
    if sel.start is not None and sel.start < 0:
        return None
    count = probe_clip(job.video, job.frames, job.max_side)[0]
    overlap = default_overlap(count, job.world) if job.overlap is None else job.overlap
    stretch = plan_stretches(count, job.world, overlap)[rank]
    start, step = sel.start or 0, sel.step or 1
    numbers = slice(start + stretch.lo * step, start + (stretch.hi - 1) * step + 1, step)
    return read_video(job.video, frames=numbers, max_side=job.max_side)


def read_stretch(job, cameras, stretch: Stretch) -> np.ndarray:
    """uint8 [F,H,W,3]: a rank's frames, read from the clip by their source frame numbers."""
    if isinstance(job.video, Video):
        return np.ascontiguousarray(job.video.frames[stretch.lo:stretch.hi])
    return read_video_for(job.video, cameras[stretch.lo:stretch.hi])


def stretch_frames(job, cameras, stretch: Stretch, clip=None, early=None, early_identity: dict | None = None):
    """(uint8 [F,H,W,3] of `stretch`, what identifies them for a checkpoint): from rank 0's `clip`, a rank's
    `early` read (`read_early`; `early_identity` its identity when worked out already) when it holds the
    stretch's frames at the cameras' size, or read now."""
    numbers = cameras.frame_indices[stretch.lo:stretch.hi]
    if clip is not None:
        frames = np.ascontiguousarray(clip.frames[stretch.lo:stretch.hi]).copy()
    elif early is not None and np.array_equal(early.indices, numbers) \
            and early.frames.shape[1:3] == (cameras.height, cameras.width):
        if early_identity is not None:
            return early.frames, early_identity
        frames = early.frames
    else:
        frames = read_stretch(job, cameras, stretch)
    return frames, identity_of(numbers, frames)


def identity_of(indices, frames) -> dict:
    """tomgs.train.clip.clip_identity of a stretch's frames (uint8 [F,H,W,3], source frame numbers `indices`),
    read without masks: what its checkpoint identifies them by."""
    from types import SimpleNamespace

    from tomgs.train.clip import clip_identity

    return clip_identity(SimpleNamespace(indices=indices, frames=frames, masks=None))


def check_shard(shard, stretch, world: int, checkpoint) -> None:
    """A rank's checkpoint must be of this run's ranks and stretch."""
    if not isinstance(shard, dict):
        raise InputError(f"{checkpoint} is not a checkpoint of a sharded fit: {START_OVER}")
    if shard.get("world") != world:
        raise InputError(f"{checkpoint} was fitted with --gpus {shard.get('world')}, this run asks for --gpus {world}: "
                         f"resume with the --gpus it was started with, or {START_OVER}")
    if [shard.get(k) for k in ("lo", "hi", "own_lo", "own_hi")] != [stretch.lo, stretch.hi, stretch.own_lo,
                                                                     stretch.own_hi]:
        raise InputError(f"{checkpoint} was fitted on positions {shard.get('lo')}..{shard.get('hi')} of the clip, "
                         f"this run gives rank {stretch.rank} {stretch.lo}..{stretch.hi}: resume with the options it "
                         f"was started with, or {START_OVER}")


# -- collectives on rows -----------------------------------------------------------------------------


def all_gather_rows(rows: torch.Tensor) -> list[torch.Tensor]:
    """Every rank's rows [n_r, D] (n_r may differ), on every rank, in rank order (default group:
    `rows` on its device, CUDA under NCCL)."""
    import torch.distributed as dist

    world = dist.get_world_size()
    size = torch.tensor([rows.shape[0]], dtype=torch.int64, device=rows.device)
    sizes = [torch.zeros_like(size) for _ in range(world)]
    dist.all_gather(sizes, size)
    sizes = [int(s) for s in sizes]
    padded = torch.zeros(max(max(sizes), 1), rows.shape[1], dtype=rows.dtype, device=rows.device)  # never empty
    padded[:rows.shape[0]] = rows
    gathered = [torch.empty_like(padded) for _ in range(world)]
    dist.all_gather(gathered, padded)
    return [g[:s] for g, s in zip(gathered, sizes)]


def assemble(model: GaussianModel, part: Halo) -> torch.Tensor:
    """The refined union as rows [M, D], the same on every rank: each Gaussian as its holder has it
    (`Halo.holder`; replicas of a shared one took the same steps), in the union's order, those alive
    in no stretch left out. `model`: this rank's Halo after refining."""
    device = model.means.device
    holder = part.holder.to(device)
    mine = holder.index_select(0, part.rows.to(device)) == part.rank
    received = all_gather_rows(pack(model.parameters_by_name())[mine])
    kept = holder >= 0
    position = torch.cumsum(kept.long(), 0) - 1  # a kept Gaussian's row of the scene
    out = torch.empty(int(kept.sum()), received[part.rank].shape[1], device=device)
    for r, rows in enumerate(received):
        out[position[holder == r]] = rows
    return out


__all__ = ["Halo", "MIN_STRETCH", "REFINE_FRACTION", "Stretch", "Union", "all_gather_rows", "assemble",
           "boundary_psnr", "check_shard", "check_shard_outputs", "clip_rates", "gather_union", "halo",
           "identity_of", "local_cameras", "log_row", "merged_history", "model_of", "moments_to_clip_time",
           "own_cut", "owned_rows", "pack", "plan_stretches", "rank_paths", "reach", "read_early", "read_stretch",
           "stretch_frames", "stretch_points", "stretch_span", "to_clip_time", "unpack"]
