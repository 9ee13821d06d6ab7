"""A fit in one process, its phases in order (Pipeline): video in, scene file out, with the
error-against-run-time record beside it (`tomgs.fit`, tomgs.train.api, checks the inputs and outputs and runs it).

    scene.ply         the Gaussians, cameras and frame times (tomgs.load_scene reads it); scene.tsog
                      for the same compressed (tomgs.io.tsog)
    scene.csv         iteration, wall seconds of training, training PSNR (running, of the frames
                      trained on), clip PSNR and clip_frames, the frames it covers, Gaussians, memory
                      (peak MiB: GPU allocated, or host resident). The clip PSNR (frames rendered at
                      their times) is measured every eval_interval_s, never within densify_interval /
                      2 steps after a densification, prune or opacity reset (it dips by 2-3 dB right
                      after one), and at the end over every frame; before the end, over evenly spaced
                      frames while every frame would cost more than 10% of the run so far (a long
                      clip's curve starts in its first minute); rows without one leave both empty
    scene.psnr.png    PSNR against wall-clock time
    scene.ckpt        the checkpoint while training runs (removed when the fit completes)

A fit first plans (tomgs.train.plan: frames, size, device, iterations or budget, cap, ETA) from
the clip's index, before decoding anything; its budget (tomgs.train.budget) is the whole fit's wall
time, and training takes what reading, poses and saving leave of it.

Every output is checked before the video is read: an existing scene, log or plot is replaced only
with overwrite=True, and a checkpoint left by an interrupted fit means resume=True (continue it) or
overwrite=True (start over). A checkpoint records what identifies its clip (source frame numbers,
frame size, a 4x4 thumbnail of every frame and mask, the layer and pose options, the cameras), so a
resume with options that change the frames is refused naming the option, and it reuses the
checkpoint's cameras instead of estimating them again. SIGINT and SIGTERM stop a fit with
FitInterrupted (tomgs.train.checkpoint), whose `checkpoint` is the file a resume continues from, or
None when there is none yet.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from tomgs.errors import InputError
from tomgs.outputs import remove_stale_temporaries
from tomgs.train.clip import check_clip, clip_fps, clip_identity
from tomgs.train.config import TrainConfig
from tomgs.train.loop import RunHooks
from tomgs.train.phases import peak_memory, phase_text, train_ticks
from tomgs.train.log import write_csv, write_plot
from tomgs.train.trainer import FitResult, Trainer


@dataclass
class FitRequest:
    """What a fit was asked (tomgs.train.api.fit's arguments, checked): `device` a torch.device, `started`
    the time.perf_counter() value the budget counts from, `options` what a checkpoint records of them
    (tomgs.train.clip.fit_options); the callbacks as `fit` documents them."""

    video: object
    output: object
    config: TrainConfig
    device: torch.device
    started: float
    options: dict
    masks: object = None
    frames: object = None
    max_side: int | None = None
    poses: object = "auto"
    focal: float | None = None
    layer: str | None = None
    mask_dilation: int = 2
    auto_budget: bool = True
    progress: object = None
    pose_progress: object = None
    phases: object = None
    on_plan: object = None


@dataclass
class FitState:
    """What the phases hand on: the plan and its budget, the clip and its record, the cameras (those the scene
    keeps; `views`: those trained on) and the tracker's points, the trainer, the result, the seconds and
    peak host memory of each phase."""

    plan: object = None
    budget: object = None
    clip: object = None
    inputs: object = None  # tomgs.render.layers.LayerInputs
    identity: dict | None = None
    record: dict | None = None
    cameras: object = None
    views: object = None
    estimated: object = None  # the cameras a checkpoint keeps (None: a layer's fixed ones)
    points: object = ()
    colors: object = ()
    point_frames: object = None
    notes: list = field(default_factory=list)
    pose_seconds: float = 0.0
    fps: float | None = None
    trainer: object = None
    result: object = None
    seconds: dict = field(default_factory=dict)
    peaks: dict = field(default_factory=dict)


class Pipeline:
    """One fit, its phases as methods in the order `run` calls them: plan, read, cameras, compile, init,
    train, after_training, save, result. `paths` are the fit's outputs (tomgs.outputs.fit_output_paths),
    `saved` a checkpoint's state to resume from (checked against the options) or None. A sharded rank
    (tomgs.train.multigpu.rank.ShardedPipeline) overrides the hooks: where the cameras come from, the
    frames it trains on, what follows training (the merge and joint refinement) and who saves."""

    def __init__(self, request: FitRequest, paths: dict, saved: dict | None):
        self.request, self.paths, self.saved = request, paths, saved
        self.config, self.device = request.config, request.device
        self.say = request.phases or (lambda *a: None)
        self.state = FitState()
        self.warming = None  # a GPU's warm-up (tomgs.train.warm.WarmUp), joined before the Trainer
        self._mark = time.perf_counter()

    def run(self) -> FitResult:
        self.plan()
        self.read()
        self.cameras()
        self.compile()
        self.init()
        self.train()
        self.after_training()
        self.save()
        return self.result()

    def lap(self, name: str) -> None:
        """The phase `name` ends now: its seconds, and the peak host memory so far (monotone: where it rises is
        where the memory went)."""
        now = time.perf_counter()
        self.state.seconds[name] = self.state.seconds.get(name, 0.0) + now - self._mark
        self.state.peaks[name] = peak_memory(self.device)[0]
        self._mark = now

    # -- the phases ----------------------------------------------------------------------------

    def plan(self) -> None:
        """The plan (tomgs.train.plan.make_plan) from the clip's index, before decoding; its budget; on a GPU,
        the first steps' one-off costs paid while the CPU reads the clip and estimates its cameras."""
        from tomgs.train.warm import WarmUp, pays_on

        r = self.request
        plan, self.config = plan_fit(r.video, r.config, self.device, self.saved, frames=r.frames,
                                     max_side=r.max_side, poses=r.poses, layer=r.layer, auto_budget=r.auto_budget)
        self.state.plan, self.state.budget = plan, plan.budget_from(r.started)
        if r.on_plan is not None:
            r.on_plan(plan)
        self._mark = time.perf_counter()
        self.warming = WarmUp(self.config, self.device) if pays_on(self.device) else None

    def read(self) -> None:
        """The clip decoded, checked against a resumed checkpoint, and the layer's inputs made (which checks
        the masks before any work)."""
        from tomgs.io import Video, read_video
        from tomgs.io.video import clip_record

        r, state = self.request, self.state
        self.say("read", 0, 1, None)
        state.clip = r.video if isinstance(r.video, Video) else read_video(
            r.video, frames=r.frames, max_side=r.max_side, masks=r.masks,
            progress=lambda done, total: self.say("read", done, total, None))
        state.identity = clip_identity(state.clip)
        state.record = clip_record(state.clip)  # kept in the scene, for `tomgs eval` to know its video again
        if self.saved is not None:
            check_clip(self.saved["clip"], state.identity, r.options, self.paths["checkpoint"])
        state.inputs = layer_inputs(state.clip, r.layer, self.config, r.mask_dilation, r.masks, self.device)
        self.say("read", 1, 1, None)
        self.lap("read")

    def cameras(self) -> None:
        """The cameras: a resumed checkpoint's (those its Gaussians were fitted in), the tracker's estimate with
        its points, or a layer's fixed cameras."""
        from tomgs.cameras import Cameras
        from tomgs.poses import estimate_cameras

        r, state = self.request, self.state
        saved = self.saved_cameras()
        if state.inputs.cameras is None and saved:
            cameras = Cameras.from_dict(saved, source=str(self.paths["checkpoint"]))
            state.cameras = state.views = state.estimated = cameras
        elif state.inputs.cameras is None:
            self.say("poses", 0, 1, None)
            report_poses = r.pose_progress or (lambda done, total: self.say("poses", done, total, None))
            cameras, state.points, state.colors, report = estimate_cameras(state.clip, method=r.poses, focal=r.focal,
                                                                           progress=report_poses)
            state.notes = [f"poses: {report.summary()}", *report.notes]
            state.cameras = state.views = state.estimated = cameras
            state.point_frames = report.point_frames
        else:  # the foreground layer's fixed cameras
            state.cameras, state.views = state.inputs.scene_cameras, state.inputs.cameras
        self.lap("poses")
        state.pose_seconds = state.seconds["poses"]
        if self.saved is not None:
            state.pose_seconds = float(self.saved["clip"].get("pose_seconds", state.pose_seconds))
        self.say("poses", 1, 1, None)

    def saved_cameras(self) -> dict | None:
        """The cameras (Cameras.to_dict) a resumed checkpoint's Gaussians were fitted in, or None."""
        return self.saved["clip"].get("cameras") if self.saved is not None else None

    def compile(self) -> None:
        """A first run on a CPU: the kernels compile here, said so (a GPU's compile in the warm-up)."""
        from tomgs.runtime import mark_kernels_compiled
        from tomgs.train.warm import warm_up

        if "compile" in self.state.plan.phases and self.warming is None:
            self.say("compile", 0, 1, "compiling kernels, first run only")
            warm_up(self.config, self.device)
            mark_kernels_compiled(self.device.type)
            self.say("compile", 1, 1, None)
            self.lap("compile")

    def init(self) -> None:
        """The Trainer: seeded, its initial Gaussians, resumed from the checkpoint or starting over, with what
        identifies its clip for its checkpoints."""
        r, state = self.request, self.state
        self.say("init", 0, 1, None)
        if self.warming is not None:
            self.warming.join()  # before the seed: the warm-up forked the RNG, and its steps queue on the device
        torch.manual_seed(self.config.seed)
        inputs = state.inputs
        trainer = Trainer(inputs.frames, state.views, state.points, state.colors, self.config, self.device,
                          point_frames=state.point_frames,
                          init_progress=lambda done, total: self.say("init", done, total, None), **inputs.hooks)
        trainer.notes[:0] = [*state.clip.notes, *state.notes, *inputs.notes]
        self.resume_or_start_over(trainer)
        trainer.clip = dict(state.identity, options=r.options, pose_seconds=round(state.pose_seconds, 3),
                            cameras=None if state.estimated is None else state.estimated.to_dict(),
                            source=str(getattr(r.video, "path", r.video)))
        state.fps = clip_fps(state.clip)
        if _own_copy(trainer.frames, inputs.frames):  # on a GPU: the host's frames go (1.7 GiB for 1080p x 300)
            state.clip = state.inputs = None
        state.trainer = trainer
        self.say("init", 1, 1, None)
        self.lap("init")

    def resume_or_start_over(self, trainer: Trainer) -> None:
        """The checkpoint's state into `trainer` and its log as of then (a killed run wrote further); without
        one, an interrupted fit's checkpoint goes (overwrite: this fit replaces it)."""
        if self.saved is not None:
            trainer.load_checkpoint(self.saved)
            write_csv(self.paths["csv"], trainer.history)
        else:
            self.paths["checkpoint"].unlink(missing_ok=True)
        self.saved = None

    def train(self) -> None:
        """Training under `training_budget`, with its checkpoints and log at the fit's paths."""
        trainer, budget = self.state.trainer, self.training_budget()
        hooks = RunHooks(checkpoint=self.paths["checkpoint"], log_csv=self.paths["csv"],
                         progress=self.request.progress, tick=train_ticks(self.say, budget))
        self.state.result = result = trainer.run(budget, hooks)
        self.say("train", 1, 1, f"all {result.iterations:,} iterations" if result.iterations >= budget.iterations
                 else f"{result.iterations:,} of {budget.iterations:,} iterations: the budget's end")
        self.lap("train")

    def training_budget(self):
        """The Budget training runs under: the fit's, less what saving takes (plan.phases["save"])."""
        state = self.state
        state.budget.train_for(state.trainer.elapsed, state.plan.phases["save"])
        return state.budget

    def after_training(self) -> None:
        """What follows training before the scene is saved: nothing in one process."""

    def save(self) -> None:
        """The scene, its plot; the checkpoint removed once the scene is written."""
        from tomgs.io.scene import save_scene
        from tomgs.runtime import mark_kernels_compiled

        state, result = self.state, self.state.result
        info = self.scene_info()
        if result.clip_frames == state.trainer.num_frames:  # every view trained on (a foreground layer's: each
            result.clip_frames = len(state.cameras)        # frame and its mirror) is every frame of the clip
        result.cameras = state.cameras
        self.say("save", 0, 2, None)
        try:
            save_scene(self.paths["scene"], result.model, state.cameras, info)
        except OSError as e:  # a full disk: what a resume continues from, if anything
            checkpoint = self.paths["checkpoint"]
            kept = f"the checkpoint {checkpoint} is kept: free some space, then run again with --resume" \
                if checkpoint.is_file() else "no checkpoint was written: free some space and run the fit again"
            raise OSError(e.errno, f"{e.strerror}; {kept}", e.filename) from None
        self.say("save", 1, 2, None)
        try:
            write_plot(self.paths["plot"], result.history)
        except OSError as e:  # the scene and its log are written: the plot is drawn from the log
            result.notes.append(f"the PSNR plot could not be written ({e.filename}: {e.strerror}); "
                                f"{self.paths['csv']} holds its numbers")
        self.say("save", 2, 2, None)
        self.paths["checkpoint"].unlink(missing_ok=True)
        mark_kernels_compiled(self.device.type)  # the next fit's plan counts no compilation
        for path in self.paths.values():  # a kill just before a resume left some too fresh to remove at its start
            remove_stale_temporaries(path)
        self.lap("save")

    def scene_info(self) -> dict:
        """The scene's header: where it came from, how it was trained, its notes and clip record."""
        from tomgs.io import Video

        r, state, result = self.request, self.state, self.state.result
        info = dict(source=str(getattr(r.video, "path", r.video)) if not isinstance(r.video, Video) else "<Video>",
                    iterations=result.iterations, train_seconds=round(result.seconds, 2),
                    pose_seconds=round(state.pose_seconds, 2), clip_psnr=round(result.clip_psnr, 3),
                    extent=state.trainer.extent, fps=state.fps, background=[0.0, 0.0, 0.0],
                    config={k: v for k, v in vars(self.config).items()}, notes=result.notes, clip=state.record)
        if r.layer is not None:
            info["layer"] = r.layer
        return info

    def result(self) -> FitResult:
        """The FitResult with the plan, the phases' seconds and memory, and the budget's account."""
        state, result, plan = self.state, self.state.result, self.state.plan
        result.plan, result.phase_seconds = plan, state.seconds
        result.wall_seconds = time.perf_counter() - self.request.started
        result.peak_host_mb, result.peak_gpu_mb = peak_memory(self.device)
        result.peak_host_mb_by_phase = state.peaks
        result.notes[:0] = plan.reasons
        if plan.budget > 0:
            result.notes.append(f"{'chosen ' if plan.budget_chosen else ''}budget {plan.budget:.0f} s for the whole "
                                f"fit: {result.wall_seconds:.0f} s ({phase_text(state.seconds)})")
        return result


def plan_fit(video, config, device, saved, *, frames, max_side, poses, layer, auto_budget):
    """(FitPlan, the config to train with) of a fit (tomgs.train.plan.make_plan) from the clip's index, before
    decoding."""
    from tomgs.io import Video
    from tomgs.io.video import probe_clip, probe_source
    from tomgs.runtime import kernels_compiled
    from tomgs.train.plan import make_plan

    facts = ""
    if isinstance(video, Video):
        count, height, width = video.frames.shape[:3]
        source = height * width
    else:
        probed = probe_source(video)
        count, height, width, source = probe_clip(video, frames, max_side, probed)
        facts = probed.facts()
    views = 2 * count if layer == "foreground" else count  # the foreground trains two views of each frame
    free = None
    if device.type == "cuda":
        free = torch.cuda.mem_get_info(device)[0] - views * height * width * 3
    estimated = layer != "foreground" and str(poses) == "auto" and not (saved and saved["clip"].get("cameras"))
    plan, config = make_plan(config, views, height, width, source * views // max(count, 1), device.type,
                             poses_estimated=estimated, auto_budget=auto_budget, free_bytes=free,
                             compiles=not kernels_compiled(device.type))
    plan.source = facts
    return plan, config


def _own_copy(tensor: torch.Tensor, array: np.ndarray) -> bool:
    """Whether `tensor` holds its own copy of `array`'s data rather than sharing it."""
    return tensor.device.type != "cpu" or tensor.data_ptr() != array.__array_interface__["data"][0]


def layer_inputs(clip, layer, config, mask_dilation, masks_path, device):
    """tomgs.render.layers.LayerInputs for `layer`; for None, the whole clip with estimated cameras."""
    if layer is None:
        from tomgs.render.layers import LayerInputs

        return LayerInputs(clip.frames, None, {})
    from tomgs.render.layers import background_inputs, foreground_inputs

    if layer == "background":
        return background_inputs(clip, mask_dilation, masks_path)
    if layer == "foreground":
        return foreground_inputs(clip, config, masks_path, device.type)
    raise InputError(f"unknown layer {layer!r}: use background or foreground")


