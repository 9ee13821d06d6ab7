"""`tomgs.fit`: video in, scene file out, with the error-against-run-time record beside it.

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
the clip's index, before decoding anything; a budget (config.max_seconds) is the whole fit's wall
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

import contextlib
import signal
import time

import numpy as np
import torch

from tomgs.errors import InputError
from tomgs.outputs import check_distinct, existing_path, output_lock, remove_stale_temporaries
from tomgs.outputs import check_fit_outputs as check_outputs
from tomgs.outputs import fit_output_paths as output_paths
from tomgs.train.checkpoint import FitInterrupted, StopSignals, read_checkpoint
from tomgs.train.clip import check_clip, check_options, clip_fps, clip_identity, fit_options
from tomgs.train.config import TrainConfig
from tomgs.train.phases import peak_memory, phase_text, train_ticks
from tomgs.train.log import write_csv, write_plot
from tomgs.runtime import one_cpu_thread
from tomgs.train.trainer import FitResult, Trainer


def fit(video, output, config: TrainConfig | None = None, *, masks=None, frames=None, max_side=None,
        poses="auto", focal=None, device=None, resume: bool = False, overwrite: bool = False, progress=None,
        pose_progress=None, layer: str | None = None, mask_dilation: int = 2, phases=None, on_plan=None,
        auto_budget: bool = True, started: float | None = None, gpus: int | None = None) -> FitResult:
    """Fit a TOM-GS scene to `video` (a file, a frame folder or a `tomgs.Video`) and save it to `output`.

    poses: "auto" (built-in tracker), "identity" (fixed camera, also the ablation), a cameras file,
    or anything `tomgs.estimate_cameras` takes. resume: continue from `output`'s checkpoint (with the
    options it was started with: others that change the frames are refused). overwrite: replace
    existing outputs (and start over from an interrupted fit's checkpoint); without it they are
    refused before any work. layer: None (the whole frame), "background" (the pixels outside the
    masks, dilated by `mask_dilation` pixels) or "foreground" (the masked object on a plane, no
    poses); see tomgs.render.layers. SIGINT / SIGTERM raise FitInterrupted (a KeyboardInterrupt) after
    saving the step reached.

    Before any frame is decoded the fit plans (tomgs.train.plan): `config.max_seconds` is the whole
    fit's wall-clock budget from `started` (a time.perf_counter() value, default the call), reading,
    poses and saving included; without one and with `auto_budget`, a budget is picked where the
    iterations would run longer than the device's DEFAULT_BUDGET. `on_plan(FitPlan)` hears the plan
    first; `phases(name, done, total, text)` follows each phase of tomgs.train.phases.PHASES (train
    counts iterations, or seconds of training under a budget; text: the latest log, or None);
    `progress(row)` hears each CSV row and `pose_progress(done, total)` the poses (default: through
    `phases`).

    gpus: N > 1 fits the clip in N temporal stretches, one process (GPU) each, merged into one scene
    (tomgs.train.multigpu.shards; per-rank checkpoints and CSVs beside the output); under torchrun, the ranks
    torchrun started. None or 1: this process alone.
    """
    from tomgs.runtime import resolve_device
    from tomgs.train.multigpu.pool import is_leader, wants_shards

    check_distinct({f"the fit's {what}": path for what, path in output_paths(output).items()},
                   {"the video": existing_path(video), "the masks": existing_path(masks),
                    "the poses": existing_path(poses)})
    with output_lock(output) if is_leader() else contextlib.nullcontext():  # one fit of an output at a time
        if wants_shards(gpus):
            from tomgs.train.multigpu.launch import fit_shards

            return fit_shards(video, output, config, gpus=gpus, masks=masks, frames=frames, max_side=max_side,
                              poses=poses, focal=focal, device=device, resume=resume, overwrite=overwrite,
                              progress=progress, pose_progress=pose_progress, layer=layer,
                              mask_dilation=mask_dilation, phases=phases, on_plan=on_plan, auto_budget=auto_budget,
                              started=started)

        started = time.perf_counter() if started is None else started
        config = config or TrainConfig()
        paths = check_outputs(output, resume=resume, overwrite=overwrite)
        device = resolve_device(device)
        options = fit_options(video, frames=frames, max_side=max_side, masks=masks, poses=poses, focal=focal,
                              layer=layer, mask_dilation=mask_dilation)
        saved = None
        if resume:
            saved = read_checkpoint(paths["checkpoint"])
            check_options(saved, options, config, paths["checkpoint"])
        for path in paths.values():
            remove_stale_temporaries(path)

        def existing_checkpoint():
            return paths["checkpoint"] if paths["checkpoint"].is_file() else None

        try:
            # on a CPU torch works in one thread (tomgs.runtime.one_cpu_thread): a busy machine's second
            # thread only waits
            with StopSignals(immediate=True, checkpoint=existing_checkpoint), one_cpu_thread(device):
                return _fit(video, paths, config, saved, options, masks=masks, frames=frames, max_side=max_side,
                            poses=poses, focal=focal, device=device, progress=progress, pose_progress=pose_progress,
                            layer=layer, mask_dilation=mask_dilation, phases=phases or (lambda *a: None),
                            on_plan=on_plan, auto_budget=auto_budget, started=started)
        except FitInterrupted:
            raise
        except KeyboardInterrupt:  # raised by a callback, or outside the main thread's handlers
            raise FitInterrupted(existing_checkpoint(), signal.SIGINT) from None


def _plan(video, config, device, saved, *, frames, max_side, poses, layer, auto_budget):
    """The plan of a fit (tomgs.train.plan.make_plan) from the clip's index, before decoding."""
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


def _fit(video, paths, config, saved, options, *, masks, frames, max_side, poses, focal, device, progress,
         pose_progress, layer, mask_dilation, phases, on_plan, auto_budget, started) -> FitResult:
    from tomgs.cameras import Cameras
    from tomgs.io import Video, read_video
    from tomgs.io.scene import save_scene
    from tomgs.io.video import clip_record
    from tomgs.poses import estimate_cameras
    from tomgs.runtime import mark_kernels_compiled
    from tomgs.train.warm import WarmUp, pays_on, warm_up

    plan, config = _plan(video, config, device, saved, frames=frames, max_side=max_side, poses=poses, layer=layer,
                         auto_budget=auto_budget)
    if on_plan is not None:
        on_plan(plan)
    seconds, peaks = {}, {}
    mark = time.perf_counter()

    def lap(name):
        nonlocal mark
        now = time.perf_counter()
        seconds[name] = seconds.get(name, 0.0) + now - mark
        peaks[name] = peak_memory(device)[0]  # monotone: where it rises is where the memory went
        mark = now

    # one-off costs of the first steps, paid while the CPU reads the clip and estimates its cameras
    warming = WarmUp(config, device) if pays_on(device) else None
    phases("read", 0, 1, None)
    clip = video if isinstance(video, Video) else read_video(
        video, frames=frames, max_side=max_side, masks=masks,
        progress=lambda done, total: phases("read", done, total, None))
    identity = clip_identity(clip)
    record = clip_record(clip)  # kept in the scene, for `tomgs eval` to know its video again
    if saved is not None:
        check_clip(saved["clip"], identity, options, paths["checkpoint"])
    inputs = _layer_inputs(clip, layer, config, mask_dilation, masks, device)  # checks the masks before any work
    phases("read", 1, 1, None)
    lap("read")
    point_frames, estimated = None, None
    if inputs.cameras is None and saved is not None and saved["clip"].get("cameras"):
        # resume: the cameras the checkpoint's Gaussians were fitted in, not a new estimate
        cameras = estimated = Cameras.from_dict(saved["clip"]["cameras"], source=str(paths["checkpoint"]))
        views, points, colors, pose_notes = cameras, (), (), []
    elif inputs.cameras is None:
        phases("poses", 0, 1, None)
        report_poses = pose_progress or (lambda done, total: phases("poses", done, total, None))
        cameras, points, colors, report = estimate_cameras(clip, method=poses, focal=focal, progress=report_poses)
        pose_notes = [f"poses: {report.summary()}", *report.notes]
        views, point_frames, estimated = cameras, report.point_frames, cameras
    else:  # the foreground layer's fixed cameras
        cameras, views, points, colors, pose_notes = inputs.scene_cameras, inputs.cameras, (), (), []
    lap("poses")
    pose_seconds = seconds["poses"]
    if saved is not None:
        pose_seconds = float(saved["clip"].get("pose_seconds", pose_seconds))

    phases("poses", 1, 1, None)
    if "compile" in plan.phases and warming is None:  # a first run on a CPU: the kernels compile here, said so
        phases("compile", 0, 1, "compiling kernels, first run only")
        warm_up(config, device)
        mark_kernels_compiled(device.type)
        phases("compile", 1, 1, None)
        lap("compile")
    phases("init", 0, 1, None)
    if warming is not None:
        warming.join()  # before the seed: the warm-up forked the RNG, and its steps queue on the device
    torch.manual_seed(config.seed)
    trainer = Trainer(inputs.frames, views, points, colors, config, device, point_frames=point_frames,
                      init_progress=lambda done, total: phases("init", done, total, None), **inputs.hooks)
    trainer.notes[:0] = [*clip.notes, *pose_notes, *inputs.notes]
    if saved is not None:
        trainer.load_checkpoint(saved)
        write_csv(paths["csv"], trainer.history)  # the log as of the checkpoint (a killed run wrote further)
    else:
        paths["checkpoint"].unlink(missing_ok=True)  # overwrite: the interrupted fit is replaced by this one
    trainer.clip = dict(identity, options=options, pose_seconds=round(pose_seconds, 3),
                        cameras=None if estimated is None else estimated.to_dict(),
                        source=str(getattr(video, "path", video)))
    fps = clip_fps(clip)
    if _own_copy(trainer.frames, inputs.frames):  # on a GPU: the host's frames go (1.7 GiB for 1080p x 300)
        clip = inputs = None
    phases("init", 1, 1, None)
    lap("init")
    time_limit = 0.0
    if plan.budget > 0:  # training takes what the other phases leave of the budget
        left = plan.budget - (time.perf_counter() - started) - plan.phases["save"]
        time_limit = trainer.elapsed + max(left, 1.0)
    result = trainer.run(checkpoint=paths["checkpoint"], log_csv=paths["csv"], progress=progress,
                         time_limit=time_limit, tick=train_ticks(phases, config.iterations, time_limit))
    phases("train", 1, 1, f"all {result.iterations:,} iterations" if result.iterations >= config.iterations else
           f"{result.iterations:,} of {config.iterations:,} iterations: the budget's end")
    lap("train")

    info = dict(source=str(getattr(video, "path", video)) if not isinstance(video, Video) else "<Video>",
                iterations=result.iterations, train_seconds=round(result.seconds, 2),
                pose_seconds=round(pose_seconds, 2), clip_psnr=round(result.clip_psnr, 3), extent=trainer.extent,
                fps=fps, background=[0.0, 0.0, 0.0],
                config={k: v for k, v in vars(config).items()}, notes=result.notes, clip=record)
    if layer is not None:
        info["layer"] = layer
    if result.clip_frames == trainer.num_frames:  # every view trained on (a foreground layer's: each frame and
        result.clip_frames = len(cameras)       # its mirror) is every frame of the clip
    result.cameras = cameras
    phases("save", 0, 2, None)
    try:
        save_scene(paths["scene"], result.model, cameras, info)
    except OSError as e:  # a full disk: what a resume continues from, if anything
        checkpoint = paths["checkpoint"]
        kept = f"the checkpoint {checkpoint} is kept: free some space, then run again with --resume" \
            if checkpoint.is_file() else "no checkpoint was written: free some space and run the fit again"
        raise OSError(e.errno, f"{e.strerror}; {kept}", e.filename) from None
    phases("save", 1, 2, None)
    try:
        write_plot(paths["plot"], result.history)
    except OSError as e:  # the scene and its log are written: the plot is drawn from the log
        result.notes.append(f"the PSNR plot could not be written ({e.filename}: {e.strerror}); {paths['csv']} "
                            f"holds its numbers")
    phases("save", 2, 2, None)
    paths["checkpoint"].unlink(missing_ok=True)
    mark_kernels_compiled(device.type)  # the next fit's plan counts no compilation
    for path in paths.values():  # a kill just before a resume left some too fresh to remove at its start
        remove_stale_temporaries(path)
    lap("save")
    result.plan, result.phase_seconds = plan, seconds
    result.wall_seconds = time.perf_counter() - started
    result.peak_host_mb, result.peak_gpu_mb = peak_memory(device)
    result.peak_host_mb_by_phase = peaks
    result.notes[:0] = plan.reasons
    if plan.budget > 0:
        result.notes.append(f"{'chosen ' if plan.budget_chosen else ''}budget {plan.budget:.0f} s for the whole fit: "
                            f"{result.wall_seconds:.0f} s ({phase_text(seconds)})")
    return result


def _own_copy(tensor: torch.Tensor, array: np.ndarray) -> bool:
    """Whether `tensor` holds its own copy of `array`'s data rather than sharing it."""
    return tensor.device.type != "cpu" or tensor.data_ptr() != array.__array_interface__["data"][0]


def _layer_inputs(clip, layer, config, mask_dilation, masks_path, device):
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


