"""Training: the TOM-GS trainer, frame sampler, densification, presets, and `fit`."""

from tomgs.train.checkpoint import FitInterrupted, read_checkpoint
from tomgs.train.config import PRESETS, TrainConfig, preset
from tomgs.train.fit import check_outputs, fit, output_paths
from tomgs.train.trainer import FitResult, Trainer

__all__ = ["PRESETS", "FitInterrupted", "FitResult", "TrainConfig", "Trainer", "check_outputs", "fit", "output_paths",
           "preset", "read_checkpoint"]
