"""What a fit will do, decided before any frame is decoded: frames, size, device, iterations or a time
budget, the Gaussian cap and the initial points, and when it will end (ETA). `fit` prints it first,
so a user knows from the first second what to expect, and follows it.

Time comes from a cost model per device (seconds per training step: a + b Gaussians + c pixels;
the same for a frame's render; decoding and poses per pixel), and a fit's training is its steps and
what the trainer measures beside them: the clip PSNRs (at most EVAL_OVERHEAD of the steps), the
quality rule's rounds (ROUND_PASSES renders of every frame each; under a budget at most ROUND_OVERHEAD of
the training) and the end (the compaction and the
last clip PSNR). The CPU's is CPU time with torch in one thread (what an idle machine's wall time is;
tomgs.runtime.one_cpu_thread), measured on the bundled clip at 160x96 and 80x48 with 4k-128k Gaussians on the
2-core machine of the workplace; a machine that other work keeps busy takes longer in wall time, by
its load. The GPU's is a first guess for the benchmarks to correct. A plan with a budget ends at the
budget whatever the model says, since training takes the time the other phases leave.

Capacity follows the clip and the device. The cap on Gaussians grows with the square root of the
clip's pixels (frames x width x height; 10M for a DAVIS clip, 90 frames of 854x480, where the paper
used 10M), bounded on a GPU by its free memory. On a CPU, where every step costs ~2.7 us per
Gaussian (the Warp kernels run serially), the starting cloud is at most what the time left can step
MIN_STEPS times, and the cap CAP_OVER_START times that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tomgs.errors import counted
from tomgs.train.budget import UNTIL_BUDGET, Budget, asked_seconds, budget_iterations

# seconds per training step (render, loss, backward, Adam): a + b * Gaussians + c * pixels (cpu: CPU seconds of
# the bundled clip's steps, 0.135-0.497 s at 160x96 with 4k-128k Gaussians, 0.054-0.182 s at 80x48 with 4k-64k;
# cuda: the H100's, from benchmarks/results/phone_*.json and camel_fit.json: 10-16 ms a step at 0.4-2 Mpx)
STEP_COST = {"cpu": (0.023, 2.7e-6, 7.5e-6), "cuda": (6e-3, 0.6e-9, 2.5e-9)}
# seconds per forward render of one frame (clip PSNR; cpu: 0.050-0.200 s at 160x96, 0.021-0.062 s at 80x48)
RENDER_COST = {"cpu": (0.002, 1.1e-6, 3.5e-6), "cuda": (1e-3, 0.5e-9, 2e-9)}
DECODE_COST = 10e-9  # seconds per source pixel decoded and converted (H.264, 2 cores)
# seconds per fitted pixel of the built-in tracker (cpu: the bundled clip without masks, 3.0 CPU seconds for 40
# frames of 160x96; H100: 900 x 1080p in 12.7 s)
POSE_COST = {"cpu": 4e-6, "cuda": 7e-9}
# seconds of a first run's kernel compilation (Warp compiles each module at its first launch and caches it; a
# fresh 2-core CPU spent ~54 s; the GPU's is a first guess)
COMPILE_COST = {"cpu": 60.0, "cuda": 30.0}
SETUP_COST = {"cpu": 0.5, "cuda": 5.0}  # seconds each for the tracker's and the trainer's start (H100: kernels load)
# seconds to write the scene and plot: a + b * Gaussians (H100, DAVIS fits: 0.7-1.5 s for 4.0-4.8M; the
# 0.3e-6 before left ~0.8 s of every 1-minute fit unused)
SAVE_COST = (0.5, 0.2e-6)
# when the preset would run longer than this on the device, the fit stops at this budget instead
DEFAULT_BUDGET = {"cpu": 600.0, "cuda": 3600.0}
MIN_STEPS = 500  # a CPU fit must be able to step its starting cloud this many times
# What the trainer (tomgs.train.trainer) spends beside its steps, which it and the estimates here share:
# Clip PSNR measurements may cost at most this fraction of the run (a long clip's takes seconds).
EVAL_OVERHEAD = 0.1
# the compaction at a run's end costs per frame what this many frames of a clip PSNR cost (a forward and
# a backward: camel's 1-minute scene on the H100, 0.5 s for 90 frames, ~5.6 ms a frame against ~2)
COMPACT_SHARE = 3.0
# a round of the quality rule (tomgs.train.sparsify) costs what this many clip PSNRs cost: its importance pass
# (a render and its backward a frame) and the pass without the Gaussians it proposes; under a time limit a
# round is taken only where it and the run's end fit in the time left (a busy 2-core CPU's round on the
# bundled clip took 15 s of a 40-s budget's last 8 and ran the fit over by as much)
ROUND_PASSES = 3.0
# Under a time limit the rounds may take at most this fraction of the training time so far (1-minute fits of
# 289-frame 720p clips, H200: eight rounds took ~15 s of 49 s of training, the PSNR flat meanwhile)
ROUND_OVERHEAD = 0.15
CAP_OVER_START = 3  # time-bound cap: this many times the starting cloud
REFERENCE_CAP, REFERENCE_PIXELS = 10_000_000, 90 * 854 * 480  # DAVIS clip: the paper's 10M cap
MIN_CAP = 100_000
GAUSSIAN_BYTES = 1500  # GPU memory per Gaussian while training (parameters, Adam, gradients, sorting)
GPU_MEMORY_SHARE = 0.6  # of the free GPU memory after the frames, for Gaussians


def _cost(table: dict, device_type: str, gaussians: float, pixels: float) -> float:
    a, b, c = table.get(device_type, table["cpu"])
    return a + b * gaussians + c * pixels


def step_seconds(device_type: str, gaussians: float, pixels: float) -> float:
    return _cost(STEP_COST, device_type, gaussians, pixels)


def render_seconds(device_type: str, gaussians: float, pixels: float) -> float:
    return _cost(RENDER_COST, device_type, gaussians, pixels)


@dataclass
class FitPlan:
    """A fit's plan: clip (frames x height x width) on `device`; `iterations`, and `budget` (seconds
    of the whole fit, 0: none) with `budget_chosen` when the plan picked it; `cap` and
    `points_per_frame` with the reason for each; estimated seconds per phase (`phases`) and `eta`;
    `source`, what the video file says of itself (tomgs.io.video.Source.facts)."""

    frames: int
    height: int
    width: int
    device: str
    iterations: int
    budget: float
    budget_chosen: bool
    cap: int
    points_per_frame: int
    phases: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)
    source: str = ""  # what the clip's file says of itself: its frame rate, a display rotation

    def budget_from(self, started: float) -> Budget:
        """The fit's Budget: this plan's seconds from `started` (a time.perf_counter() value) and iterations."""
        return Budget(self.budget, self.iterations, started, self.budget_chosen)

    @property
    def eta(self) -> float:
        """Seconds from the start to the scene file: the phases' estimates, at most the budget."""
        total = round(sum(self.phases.values()), 6)  # training fills a budget to the float's last bits
        return min(self.budget, total) if self.budget > 0 else total

    def summary(self) -> str:
        """One line: what the fit will do and when it ends."""
        work = (f"training for {duration(self.budget)} in all" if self.iterations >= UNTIL_BUDGET else
                f"{self.iterations:,} iterations or {duration(self.budget)}, whichever comes first"
                if self.budget > 0 else f"{self.iterations:,} iterations")
        chosen = " (budget chosen for this device: --budget or --iterations to change)" if self.budget_chosen else ""
        eta = duration(self.eta) if self.budget > 0 else f"~{duration(self.eta)} (estimated)"
        compiling = (f"; compiling kernels first (first run only, ~{duration(self.phases['compile'])})"
                     if self.phases.get("compile") else "")
        source = f" ({self.source})" if self.source else ""
        return (f"plan: {counted(self.frames, 'frame')} of {self.width}x{self.height}{source} on {self.device}, "
                f"{work}{chosen}{compiling}; "
                f"start from {self.points_per_frame * self.frames:,} Gaussians, cap {self.cap:,}; ETA {eta}")


def duration(seconds: float) -> str:
    """A duration as a plan prints it: '45 s', '12.5 min', '3.2 h'."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.1f} h"


def auto_cap(frames: int, pixels: int, device_type: str, free_bytes: int | None = None) -> tuple[int, str]:
    """(cap, why): REFERENCE_CAP scaled by the square root of the clip's pixels, at least MIN_CAP;
    on a GPU at most what `free_bytes` (after the frames) holds."""
    cap = max(MIN_CAP, int(REFERENCE_CAP * math.sqrt(frames * pixels / REFERENCE_PIXELS)))
    why = (f"at most {cap:,} Gaussians for {frames} frame{'s' if frames != 1 else ''} of {pixels:,} pixels (10M for "
           f"90 frames at 854x480, by the square root of the pixels; --cap to change)")
    if free_bytes is not None:
        fits = int(GPU_MEMORY_SHARE * max(free_bytes, 0) / GAUSSIAN_BYTES)
        if fits < cap:
            cap = max(fits, MIN_CAP)
            why = (f"at most {cap:,} Gaussians: what {free_bytes / 2**30:.1f} GiB of free GPU memory holds (--cap to "
                   "change)")
    return cap, why


def make_plan(config, frames: int, height: int, width: int, source_pixels: int, device_type: str, *,
              poses_estimated: bool = True, auto_budget: bool = True,
              free_bytes: int | None = None, compiles: bool = False) -> tuple[FitPlan, object]:
    """(FitPlan, the TrainConfig to train with: its cap and initial points resolved).

    config: TrainConfig (max_seconds: the whole fit's budget, 0: none; max_gaussians and
    init_points_per_frame None: chosen here). source_pixels: pixels of a frame as decoded.
    poses_estimated: the built-in tracker will run. auto_budget: pick DEFAULT_BUDGET where the
    iterations would take longer on this device. free_bytes: a GPU's free memory after the frames.
    compiles: the kernels are not compiled yet for this device (tomgs.runtime.kernels_compiled):
    the first steps will compile them, a phase of its own in the estimates and the budget.
    A budget asked for (max_seconds) is the time training takes: the iterations become UNTIL_BUDGET
    unless they were asked for too (tomgs.train.budget.budget_iterations)."""
    pixels = height * width
    setup = SETUP_COST.get(device_type, SETUP_COST["cpu"])
    phases = dict(read=DECODE_COST * frames * source_pixels,
                  poses=setup + POSE_COST.get(device_type, POSE_COST["cpu"]) * frames * pixels if poses_estimated
                  else 0.0,
                  init=setup + 2e-4 * frames)
    if compiles:
        phases["compile"] = COMPILE_COST.get(device_type, COMPILE_COST["cpu"])
    budget, chosen = asked_seconds(config), False
    reasons = []
    if budget_iterations(config) != config.iterations:  # a longer budget trains longer
        config = config.replace(iterations=budget_iterations(config))
    cap, cap_why = (config.max_gaussians, f"cap {config.max_gaussians:,} as asked") \
        if config.max_gaussians is not None else auto_cap(frames, pixels, device_type, free_bytes)
    per_frame = config.replace(max_gaussians=cap).points_per_frame(pixels, frames, device_type)
    start = per_frame * frames

    def train_estimate(n0: int) -> float:  # the steps, the measurements and rounds beside them, the end
        grown = min(cap, 2 * n0)  # the cloud grows while it densifies: its mean size, roughly
        clip = frames * render_seconds(device_type, grown, pixels)  # one clip PSNR
        rounds = config.sparsify_rounds * ROUND_PASSES * clip if config.quality != "max" else 0.0
        end = (COMPACT_SHARE * clip if config.compact_pixels > 0 else 0.0) + clip
        steps = config.iterations * step_seconds(device_type, grown, pixels)
        if asked_seconds(config) > 0:  # under a limit the rounds take at most ROUND_OVERHEAD of the training
            rounds = min(rounds, ROUND_OVERHEAD * steps)
        return steps * (1 + EVAL_OVERHEAD) + rounds + end

    def save(n: int) -> float:
        return SAVE_COST[0] + SAVE_COST[1] * min(cap, 2 * n)

    if budget <= 0 and auto_budget:
        needed = sum(phases.values()) + train_estimate(start) + save(start)
        limit = DEFAULT_BUDGET.get(device_type, DEFAULT_BUDGET["cpu"])
        if needed > limit:
            budget, chosen = limit, True
            reasons.append(f"budget {duration(limit)}: {config.iterations:,} iterations would take about "
                           f"{duration(needed)} on {device_type}")
    if budget > 0:
        before = sum(phases.values()) + save(start)
        train = max(budget - before, 0.1 * budget)
        if before > 0.5 * budget:
            reasons.append(f"reading, poses and saving are estimated at {duration(before)} of the "
                           f"{duration(budget)} budget: training gets what they leave (the fit may run over)")
        if device_type == "cpu" and config.init_points_per_frame is None:
            a, b, c = STEP_COST["cpu"]
            # never below the cloud whose cost matches a step's fixed cost: fewer saves little time
            steppable = max(int((train / MIN_STEPS - a - c * pixels) / b), int(a / b), frames)
            if start > steppable:
                per_frame = max(steppable // frames, 1)
                reasons.append(f"starts from {per_frame * frames:,} Gaussians ({per_frame} per frame): more would "
                               f"slow each CPU step so much that {duration(train)} of training takes fewer than "
                               f"{MIN_STEPS} steps")
                start = per_frame * frames
            if config.max_gaussians is None and cap > CAP_OVER_START * max(start, steppable):
                cap = CAP_OVER_START * max(start, steppable)
                cap_why = (f"at most {cap:,} Gaussians, {CAP_OVER_START} times the start: a CPU step slows with every "
                           f"Gaussian, and {duration(train)} of training should take {MIN_STEPS} steps or more "
                           f"(--cap to change)")
        train = max(budget - sum(phases.values()) - save(start), 0.1 * budget)  # the cloud may have shrunk
        phases["train"] = min(train, train_estimate(start))  # the iterations may end first
    else:
        phases["train"] = train_estimate(start)
    phases["save"] = save(start)
    reasons.insert(0, cap_why)
    plan = FitPlan(frames, height, width, device_type, config.iterations, budget, chosen, cap, per_frame, phases,
                   reasons)
    return plan, config.replace(max_gaussians=cap, init_points_per_frame=per_frame)
