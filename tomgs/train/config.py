"""Training settings: one dataclass, a few named presets, and the paper's ablation switches.

The measurements behind the defaults are in docs/notes/training.md, "Why the defaults are what they are"."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


# Initial points per frame by device: (fewest, most, the whole start's size, which a longer clip keeps to within
# them). On a GPU a denser start costs a step little and shortens the growth phase, after which the PSNR climbs
# fastest; on a CPU every Gaussian slows the serial kernels, and a short fit gets fewer steps.
AUTO_POINTS_PER_FRAME = {"cuda": (16000, 48000, 5_000_000), "cpu": (2000, 2000, 0)}
# The densification threshold by device: a GPU fit of minutes is limited by how soon its cloud has grown
# (+1.7 dB in DAVIS camel's first minute at 1e-4); a CPU fit's every added Gaussian slows each step: 3DGS's 2e-4.
AUTO_GRAD_THRESHOLD = {"cuda": 1e-4, "cpu": 2e-4}
INIT_DEPTHS = ("tracks", "median")  # TrainConfig.init_depth
QUALITIES = ("compact", "default", "max")  # TrainConfig.quality (tomgs.train.sparsify.QUALITY_RULES)
# A GPU fit at a quality below "max" grows in stages from at most this share of its cap (tomgs.train.growth);
# a CPU fit's cap is already what its time allows, three times its start (tomgs.train.plan.auto_cap).
START_SHARE = 1 / 32


@dataclass
class TrainConfig:
    iterations: int = 12_000
    # densification (3DGS defaults) inside a window of the run's progress (the
    # iteration fraction or the wall-clock fraction of a budget, whichever is further), so a run
    # under a time budget densifies however few iterations fit; it also stops at the cap
    densify_start_fraction: float = 0.04  # 3DGS: from iteration 500 of 12k
    densify_stop_fraction: float = 0.5  # refinement after the last split is worth more than more splits
    densify_interval: int = 100
    # view-space positional gradient, NDC units as in 3DGS; None: by device (AUTO_GRAD_THRESHOLD)
    grad_threshold: float | None = None
    percent_dense: float = 0.01  # clone below this fraction of the scene extent, split above
    # a clone or split's two Gaussians take 1 - sqrt(1 - a) each of their source's opacity a, so that together they
    # cover what it covered (Rota Bulo et al., "Revising densification in Gaussian splatting"); False: each keeps a
    # (3DGS), doubling the cover until training brings it back. None: on a GPU, off on a CPU (few densifications)
    share_opacity: bool | None = None
    max_gaussians: int | None = None  # None: by the clip and device (tomgs.train.plan.auto_cap)
    prune_opacity: float = 0.005
    # at the end of training, leave out the Gaussians that give no frame this many pixels' worth of colour (blend
    # weights summed over a frame: tomgs.render.blend_weights): ~10% of a DAVIS fit for -0.001 dB. 0: keep them all
    compact_pixels: float = 0.01
    # how many Gaussians the fit keeps (tomgs.train.sparsify): "max" grows to the cap and keeps what it grew
    # (every dB); "default" and "compact" then prune the least important Gaussians a share at a time in
    # [sparsify_start_fraction, sparsify_stop_fraction) of the run, training recovering between rounds,
    # while a prune costs less clip PSNR than the level allows (compact allows more)
    quality: str = "default"
    # after densification (densify_stop_fraction) and the few hundred steps the clip PSNR takes to settle after
    # its last split: a round taken at once would price a prune against that dip
    sparsify_start_fraction: float = 0.55
    sparsify_stop_fraction: float = 0.85  # the rest of the run recovers from the last prune
    sparsify_rounds: int = 8  # rounds spread evenly over the window (each: two passes over every frame)
    sparsify_share: float = 0.3  # of the Gaussians a round offers to remove at first (halved when refused)
    opacity_reset_interval: int = 0  # 0: off (TOM-GS); 3000 reproduces the 3DGS heuristic (ablation)
    # sampling of training frames: "inverse_psnr" (TOM-GS) or "uniform" (ablation)
    sampling: str = "inverse_psnr"
    psnr_momentum: float = 0.8  # running per-frame PSNR: new = m * old + (1 - m) * measured
    temporal: bool = True  # False: static 3DGS, no temporal opacity (ablation)
    sh_degree: int = 0  # view-dependent colour is rare in video: left out unless asked
    # Adam on the Gaussians in view only (tomgs/train/optim.py): the others keep their values and moments. None:
    # on a GPU, where dense Adam's stale momentum keeps moving the ~85% of Gaussians dead at the frame's time over
    # tens of thousands of steps; dense on a CPU, where over a few hundred that momentum acts as extra steps
    sparse_adam: bool | None = None
    # each step renders only the Gaussians that may be alive at its frame (tomgs.render.alive: same images
    # and gradients, work following the ~15% alive instead of all); False renders all (ablation,
    # tests); None: where it pays (tomgs.render.alive.pays_on: on a CPU, not on a GPU)
    alive_index: bool | None = None
    # each step replayed from one CUDA graph (tomgs.train.captured_step): the host issues a launch and a replay
    # instead of ~100 operations, since a GPU step of a million Gaussians is host bound. Needs SeenAdam, no alive
    # index, no per-pixel weights and the frames on the device. None: on where a GPU fit can have it; True:
    # required (InputError where it cannot be; a CPU issues the same step from Python, as tests use it); False: eager
    captured_step: bool | None = None
    # learning rates (3DGS; means scaled by the scene extent and decayed exponentially)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_sh_dc: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_opacity: float = 5e-2
    lr_scales: float = 5e-3
    lr_quats: float = 1e-3
    lr_t_means: float = 1e-3
    # the temporal windows' width (log sigma), fast: with starts of one frame (init_t_scale_frames) the windows of
    # what stays in view must open quickly
    lr_t_scales: float = 2e-2
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w (1 - SSIM)
    # initialisation: points unprojected from every frame, alive around that frame's time; None:
    # by device, see `points_per_frame` and AUTO_POINTS_PER_FRAME
    init_points_per_frame: int | None = None
    # sigma of per-frame points, in frames: a narrower start leaves fewer Gaussians alive at a frame, so each step
    # is faster, but too narrow a one ends the first minute lower
    init_t_scale_frames: float = 1.0
    # the share of each frame's initial points that start alive over the whole clip (temporal sigma 1 in clip time)
    # instead of around their frame: what stays in view is then trained by every frame from the first step
    init_wide_fraction: float = 0.0
    # depth of the per-frame points: "tracks", interpolated from the tracked points each frame sees (Trainer's
    # log-depth grid), so a static surface's points from every frame start on it; "median", the frame's median
    # depth of them everywhere (the rule before; an ablation)
    init_depth: str = "tracks"
    # sigma of the per-frame points' log-depth noise (a point's depth times exp(sigma * N(0, 1))): at the same
    # number of steps the spreads end alike, and a wider one steps faster
    init_depth_jitter: float = 0.3
    # logging
    log_interval: int = 50  # iterations between CSV rows
    # seconds between full-clip PSNR measurements (further apart where one costs more than 10% of
    # that, and never right after a densification: Trainer.run)
    eval_interval_s: float = 30.0
    # seconds of training between checkpoints: what a crash (kill -9, power loss) can lose at most;
    # spaced further only when a save is slow (trainer.CHECKPOINT_OVERHEAD). SIGINT and SIGTERM save
    # at once. A CPU save takes ~10 ms, a GPU scene of millions of Gaussians a few seconds.
    checkpoint_interval_s: float = 30.0
    # the whole fit's wall-clock budget, reading, poses and saving included (0: none; `fit` may pick
    # one where the iterations would take longer than tomgs.train.plan.DEFAULT_BUDGET); a Trainer
    # used alone stops its training after this long
    max_seconds: float = 0.0
    # under a budget (max_seconds) asked for, stop at `iterations` too, whichever comes first; False: `fit`
    # trains for the whole budget (tomgs.train.budget.UNTIL_BUDGET), however many iterations that holds
    stop_at_iterations: bool = False
    seed: int = 0

    def __post_init__(self):
        if self.init_depth not in INIT_DEPTHS:
            raise ValueError(f"init_depth must be one of {', '.join(INIT_DEPTHS)}, not {self.init_depth!r}")
        if self.quality not in QUALITIES:
            raise ValueError(f"quality must be one of {', '.join(QUALITIES)}, not {self.quality!r}")
        if not 0 < self.sparsify_share < 1:  # NaN fails too
            raise ValueError(f"sparsify_share must be between 0 and 1, not {self.sparsify_share!r}")
        if self.sparsify_rounds < 0:
            raise ValueError(f"sparsify_rounds must be 0 or more, not {self.sparsify_rounds!r}")
        if not 0 <= self.init_wide_fraction <= 1:  # NaN fails too
            raise ValueError(f"init_wide_fraction must be between 0 and 1, not {self.init_wide_fraction!r}")
        if not 0 <= self.init_depth_jitter <= 1:  # NaN fails too; exp(N(0, 1)) past 1 spans e^2 around the depth
            raise ValueError(f"init_depth_jitter must be between 0 and 1, not {self.init_depth_jitter!r}")

    def points_per_frame(self, pixels: int, frames: int, device_type: str = "cpu") -> int:
        """Initial Gaussians per frame of `pixels` pixels in a clip of `frames` frames, trained on a
        `device_type` device: `init_points_per_frame`, or when it is None AUTO_POINTS_PER_FRAME's
        count for the device and clip length, at most one per 5 pixels, and on a GPU at a quality below "max" at
        most START_SHARE of the cap over the whole clip (growth in stages starts small); never more than half of
        the cap (`cap`) over the whole clip, so that densification always has room to work."""
        if self.init_points_per_frame is None:
            fewest, most, start = AUTO_POINTS_PER_FRAME.get(device_type, AUTO_POINTS_PER_FRAME["cpu"])
            wanted = min(max(fewest, min(most, start // max(frames, 1))), pixels // 5)
            if device_type == "cuda" and self.quality != "max":
                wanted = min(wanted, int(self.cap(frames, pixels, device_type) * START_SHARE) // max(frames, 1))
        else:
            wanted = int(self.init_points_per_frame)
        return max(min(wanted, self.cap(frames, pixels, device_type) // (2 * max(frames, 1))), 1)

    def shares_opacity(self, device_type: str = "cpu") -> bool:
        """`share_opacity`, or when it is None: on a GPU, not on a CPU."""
        return device_type == "cuda" if self.share_opacity is None else bool(self.share_opacity)

    def threshold(self, device_type: str = "cpu") -> float:
        """`grad_threshold`, or when it is None AUTO_GRAD_THRESHOLD's for a `device_type` device."""
        if self.grad_threshold is not None:
            return float(self.grad_threshold)
        return AUTO_GRAD_THRESHOLD.get(device_type, AUTO_GRAD_THRESHOLD["cpu"])

    def cap(self, frames: int, pixels: int, device_type: str = "cpu") -> int:
        """`max_gaussians`, or when it is None the cap tomgs.train.plan.auto_cap picks for the clip."""
        if self.max_gaussians is not None:
            return int(self.max_gaussians)
        from tomgs.train.plan import auto_cap

        return auto_cap(frames, pixels, device_type)[0]

    def replace(self, **changes) -> "TrainConfig":
        return dataclasses.replace(self, **changes)


PRESETS = {
    # tuned to reach the paper's quality sooner: fewer iterations, earlier densification stop
    "default": TrainConfig(),
    # the paper's schedule: 80k iterations, densification until 60k, cap 10M
    "paper": TrainConfig(iterations=80_000, densify_start_fraction=500 / 80_000, densify_stop_fraction=0.75,
                         max_gaussians=10_000_000, grad_threshold=2e-4),
    # a few hundred iterations: smoke tests and CPU demos
    "quick": TrainConfig(iterations=600, densify_start_fraction=1 / 6, densify_stop_fraction=0.75, densify_interval=50,
                         init_points_per_frame=400, eval_interval_s=5.0),
}


def preset(name: str, **overrides) -> TrainConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}: use one of {', '.join(PRESETS)}")
    unknown = set(overrides) - {f.name for f in dataclasses.fields(TrainConfig)}
    if unknown:
        raise ValueError(f"unknown training settings: {', '.join(sorted(unknown))}")
    return PRESETS[name].replace(**overrides)
