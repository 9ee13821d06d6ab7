"""Training: the TOM-GS trainer, frame sampler, densification, presets, and `fit`."""

from tomgs.train.config import PRESETS, TrainConfig, preset
from tomgs.train.fit import fit, output_paths
from tomgs.train.trainer import FitResult, Trainer

__all__ = ["PRESETS", "FitResult", "TrainConfig", "Trainer", "fit", "output_paths", "preset"]
