"""`tomgs.fit`: the inputs and every output checked once, then the fit run in this process
(tomgs.train.pipeline.Pipeline) or handed, with the same arguments, to the ranks of a sharded fit
(tomgs.train.multigpu.launch)."""

from __future__ import annotations

import contextlib
import signal
import time

from tomgs.outputs import check_distinct, existing_path, output_lock, remove_stale_temporaries
from tomgs.outputs import check_fit_outputs as check_outputs
from tomgs.outputs import fit_output_paths as output_paths
from tomgs.runtime import one_cpu_thread
from tomgs.train.budget import asked_iterations
from tomgs.train.checkpoint import FitInterrupted, StopSignals, read_checkpoint
from tomgs.train.clip import check_options, fit_options
from tomgs.train.config import TrainConfig
from tomgs.train.pipeline import FitRequest, Pipeline
from tomgs.train.trainer import FitResult


def fit(video, output, config: TrainConfig | None = None, *, masks=None, frames=None, max_side=None,
        poses="auto", focal=None, device=None, resume: bool = False, overwrite: bool = False, progress=None,
        pose_progress=None, layer: str | None = None, mask_dilation: int = 2, phases=None, on_plan=None,
        auto_budget: bool | None = None, started: float | None = None, gpus: int | None = None) -> FitResult:
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
    poses and saving included (tomgs.train.budget); without one and with `auto_budget` (None: unless
    the config's iterations were asked for, TrainConfig.stop_at_iterations), a budget is picked where
    the iterations would run longer than the device's DEFAULT_BUDGET. `on_plan(FitPlan)` hears the plan
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

    if auto_budget is None:
        auto_budget = not asked_iterations(config or TrainConfig())
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

        config = config or TrainConfig()
        paths = check_outputs(output, resume=resume, overwrite=overwrite)
        options = fit_options(video, frames=frames, max_side=max_side, masks=masks, poses=poses, focal=focal,
                              layer=layer, mask_dilation=mask_dilation)
        request = FitRequest(video, output, config, resolve_device(device),
                             time.perf_counter() if started is None else started, options, masks=masks, frames=frames,
                             max_side=max_side, poses=poses, focal=focal, layer=layer, mask_dilation=mask_dilation,
                             auto_budget=auto_budget, progress=progress, pose_progress=pose_progress, phases=phases,
                             on_plan=on_plan)
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
            with StopSignals(immediate=True, checkpoint=existing_checkpoint), one_cpu_thread(request.device):
                return Pipeline(request, paths, saved).run()
        except FitInterrupted:
            raise
        except KeyboardInterrupt:  # raised by a callback, or outside the main thread's handlers
            raise FitInterrupted(existing_checkpoint(), signal.SIGINT) from None


__all__ = ["check_outputs", "fit", "output_paths"]
