"""Training settings: one dataclass, a few named presets, and the paper's ablation switches."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


# Initial points per frame by device: (fewest, most, the whole start's size between them). On a GPU
# a step costs little more for more Gaussians and a denser start shortens the growth phase, after
# which the PSNR climbs fastest: 1-minute fits (H100, docs/notes/training.md) reached kite-surf 43.69 /
# 44.23 / 44.54 dB at 16,000 / 32,000 / 48,000 a frame and camel 34.00 / 34.15 at 16,000 / 32,000, and a
# 5-minute kite-surf fit ended at 52.00 dB with 48,000 against 49.61 with 16,000. Those clips (40-104
# frames) start from 2-5M Gaussians; a longer clip gets as many per frame as keep its start at 5M, never
# fewer than 16,000 (a 900-frame phone video as before, not 35M Gaussians before its first step). On a
# CPU the serial kernels' cost grows with every Gaussian, and a short fit gets fewer steps (DAVIS camel's
# background layer at 240x135, 3 minutes: 51 steps with 6480 per frame).
AUTO_POINTS_PER_FRAME = {"cuda": (16000, 48000, 5_000_000), "cpu": (2000, 2000, 0)}
# The densification threshold by device. A GPU fit under a budget of minutes is limited by how soon
# its cloud has grown (the PSNR climbs fastest once growth stops): at 1e-4 with 16,000 points a frame
# DAVIS camel reaches the 5M cap at ~37 s of training instead of ~80 s, and the first minute gained
# 1.7 dB (H100, docs/notes/training.md). A CPU fit runs hundreds of steps, where
# every added Gaussian slows each one: 3DGS's 2e-4.
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
    # a clone or split's two Gaussians share their source's opacity a: each takes 1 - sqrt(1 - a), so that where
    # they overlap they cover what it covered (Rota Bulo et al., "Revising densification in Gaussian splatting");
    # False: each keeps a (3DGS), and a clone doubles its source's cover until training brings it back. With it a
    # 1-minute fit of a 289-frame 720p phone clip (H200, docs/notes/training.md) kept its training PSNR from
    # falling 1.3 dB while densification doubled the cloud, and ended 32.97 dB against 31.30. None: on a GPU,
    # off on a CPU (not measured there: its fits of hundreds of steps densify a few times)
    share_opacity: bool | None = None
    max_gaussians: int | None = None  # None: by the clip and device (tomgs.train.plan.auto_cap)
    prune_opacity: float = 0.005
    # at the end of training, leave out the Gaussians that give no frame of the clip this many pixels'
    # worth of colour (their blend weights summed over a frame's pixels: tomgs.render.blend_weights).
    # 1-minute DAVIS fits (H100): 10% of camel's and kite-surf's 5M Gaussians, -0.001 dB, renders +8%;
    # at 0.05, 22% and -0.10 dB (docs/notes/training.md). 0: keep every Gaussian
    compact_pixels: float = 0.01
    # how many Gaussians the fit keeps (tomgs.train.sparsify): "max" grows to the cap and keeps what it grew
    # (every dB); "default" and "compact" then prune the least important Gaussians a share at a time in
    # [sparsify_start_fraction, sparsify_stop_fraction) of the run, training recovering between rounds,
    # while a prune costs less clip PSNR than the level allows (compact allows more)
    quality: str = "default"
    # after densification (densify_stop_fraction) and the few hundred steps the clip PSNR takes to settle after
    # its last split (a round measured at once priced a prune against a dip: camel on the H100, -0.5 dB)
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
    # Adam on the Gaussians in view only (tomgs/train/optim.py): the others keep their values and
    # moments. None: on a GPU, dense on a CPU. GPU fits run tens of thousands of steps, and there
    # dense Adam's stale momentum keeps moving the ~85% of Gaussians dead at the frame's time (DAVIS,
    # 7.5 min, H200: camel 34.4 -> 36.4 dB, kite-surf 43.2 -> 47.8 dB with sparse). CPU fits run
    # hundreds, where that momentum acts as extra steps (the bundled clip in 4 min: 29.57 dense,
    # 29.09 sparse; camel's background layer in 3 min: 22.44 dense, 21.99 sparse)
    sparse_adam: bool | None = None
    # each step renders only the Gaussians that may be alive at its frame (tomgs.render.alive: same images
    # and gradients, work following the ~15% alive instead of all); False renders all (ablation,
    # tests); None: where it pays (tomgs.render.alive.pays_on: on a CPU, not on a GPU)
    alive_index: bool | None = None
    # each step replayed from one CUDA graph (tomgs.train.captured_step): the host issues a launch and a
    # replay instead of ~100 operations, where a GPU step of a million Gaussians was host bound (H100, camel,
    # 1-minute fits capped at 1M: 249 -> 442 steps/s, 32.56 -> 33.74 dB; at 5M 192 -> 195 steps/s, 35.41 ->
    # 35.45 dB; benchmarks/README.md). Needs SeenAdam, no alive index, no per-pixel weights and the frames on
    # the device. None: on where the fit can have it on a GPU; True: required (InputError where it cannot be;
    # on a CPU the same step is issued from Python, as tests use it); False: the eager step
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
    # the temporal windows' width (log sigma), at twice its rate before (1e-2): with starts of one frame (below) the
    # windows of what stays in view must open fast; camel's first minute (H100, docs/notes/training.md)
    # 34.6 -> 34.8-35.0 dB at 60 s with it (4e-2: 34.7, 8e-2: 34.1)
    lr_t_scales: float = 2e-2
    ssim_weight: float = 0.2  # loss = (1 - w) L1 + w (1 - SSIM)
    # initialisation: points unprojected from every frame, alive around that frame's time; None:
    # by device, see `points_per_frame` and AUTO_POINTS_PER_FRAME
    init_points_per_frame: int | None = None
    # sigma of per-frame points, in frames. Narrower starts leave fewer Gaussians alive at a frame: camel's
    # first minute at 2 / 1 / 0.7 / 0.5 / 0.35 frames 34.4 / 34.6 / 34.85 / 34.5 / 34.05 dB at 60 s, 153 /
    # 178 / 209 / 215 / 254 steps/s (H100, docs/notes/training.md)
    init_t_scale_frames: float = 1.0
    # the share of each frame's initial points that start alive over the whole clip (temporal sigma 1 in clip time)
    # instead of around their frame: what stays in view is then trained by every frame from the first step
    init_wide_fraction: float = 0.0
    # depth of the per-frame points: "tracks", interpolated from the tracked points each frame sees (Trainer's
    # log-depth grid), so a static surface's points from every frame start on it; "median", the frame's median
    # depth of them everywhere (the rule before; an ablation)
    init_depth: str = "tracks"
    # sigma of the per-frame points' log-depth noise (a point's depth times exp(sigma * N(0, 1))). At the same
    # number of steps 0.03-0.3 end alike, but a wider spread steps faster (camel's first minute, H100: 169 /
    # 181 / 184 / 190 steps/s at 0.03 / 0.1 / 0.2 / 0.3); 0.3 against 0.1 over the six DAVIS clips' first
    # minute +0.18 dB on average (-0.39..+0.59 paired, runs of one setting ~0.1-0.4 apart); camel's 5 minutes
    # 38.88 dB (38.71 at 0.1; docs/notes/training.md). A tiny flat clip under a still camera
    # (tests/test_stiff_clips.py) starts slower with it: 40.0 / 53.6 dB at 300 / 600 steps against 43.4 / 55.2
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
    # trains for the whole budget (tomgs.train.plan.UNTIL_BUDGET), however many iterations that holds
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
