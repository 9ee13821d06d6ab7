"""Training: the TOM-GS trainer, frame sampler, densification, presets, and `fit`.

    api         `fit`: checks the inputs and outputs, then runs the pipeline here or in shards (multigpu)
    pipeline    a fit in one process, its phases in order (Pipeline): a clip in, a scene file out
    budget      a fit's time: the one reader of max_seconds and of the iteration stop
    clip        what a checkpoint records of the clip and options, a resume's checks; phases: the
                phases' names, ticks, start and peak memory
    init        the Gaussians a fit starts from
    trainer     the Trainer (its step, measurements, checkpoints; FitResult); loop: its run, the cadences
                around the steps; log: its CSV and plot; captured_step: a step as one CUDA graph
    config      TrainConfig and its presets; plan: the budget's plan of a fit
    densify     the densification strategy; growth: how far it grows (stages priced per Gaussian);
                sparsify: the quality levels and their prune rounds; optim: Adam; sampler: which
                frame trains next
    checkpoint  checkpoints, stop signals, resume; warm: the kernels' warm-up beside the poses
    multigpu/   the sharded fit over several GPUs (pool, launch, rank, shards)

Public names are resolved lazily, as in `tomgs`: importing the package (and so
tomgs.train.multigpu.pool) loads no torch.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {
    "FitInterrupted": "tomgs.train.checkpoint",
    "read_checkpoint": "tomgs.train.checkpoint",
    "PRESETS": "tomgs.train.config",
    "TrainConfig": "tomgs.train.config",
    "preset": "tomgs.train.config",
    "check_outputs": "tomgs.train.api",
    "fit": "tomgs.train.api",
    "output_paths": "tomgs.train.api",
    "FitResult": "tomgs.train.trainer",
    "Trainer": "tomgs.train.trainer",
}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
