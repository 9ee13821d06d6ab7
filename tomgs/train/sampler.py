"""Which frame to train on next: inverse-PSNR sampling (TOM-GS) or uniform (ablation)."""

from __future__ import annotations

import math

import torch

# A frame rendered exactly (PSNR inf: an all-black clip, a flat colour) counts as this many dB.
MAX_PSNR = 100.0


class FrameSampler:
    """p(frame k) proportional to 1 / running PSNR_k; frames not yet seen count as the worst.

    The running PSNR of a frame is updated whenever it is trained on (inf counts as MAX_PSNR, NaN
    as no measurement, so the probabilities stay finite). Sampling uses its own
    torch.Generator, so a seeded run repeats exactly and a resumed run continues the same draws.
    """

    def __init__(self, num_frames: int, mode: str = "inverse_psnr", momentum: float = 0.8, seed: int = 0):
        if mode not in ("inverse_psnr", "uniform"):
            raise ValueError(f"unknown sampling {mode!r}: use inverse_psnr or uniform")
        self.mode = mode
        self.momentum = momentum
        self.psnr = torch.zeros(num_frames, dtype=torch.float64)  # 0 = not measured yet
        # each frame's last measurement (0 = none): the fit's training PSNR as of now, a visit late at most
        self.latest = torch.zeros(num_frames, dtype=torch.float64)
        self.generator = torch.Generator().manual_seed(seed)
        # the distribution, kept until a PSNR changes: a GPU fit hears PSNRs every 8 steps, and each of
        # the ~12 small ops that rebuild it costs host time in a host-bound step
        self._probabilities: torch.Tensor | None = None

    def probabilities(self) -> torch.Tensor:
        """[T] float64 summing to 1."""
        if self._probabilities is None:
            self._probabilities = self._distribution()
        return self._probabilities

    def _distribution(self) -> torch.Tensor:
        n = self.psnr.shape[0]
        if self.mode == "uniform":
            return torch.full((n,), 1.0 / n, dtype=torch.float64)
        seen = self.psnr > 0
        floor = self.psnr[seen].min() if seen.any() else torch.tensor(1.0, dtype=torch.float64)
        weights = 1.0 / torch.where(seen, self.psnr, floor).clamp(1.0, MAX_PSNR)
        total = weights.sum()
        if not torch.isfinite(total) or total <= 0:
            return torch.full((n,), 1.0 / n, dtype=torch.float64)
        return weights / total

    def sample(self) -> int:
        return int(torch.multinomial(self.probabilities(), 1, generator=self.generator))

    def update(self, frame: int, psnr: float) -> None:
        psnr = float(psnr)
        if math.isnan(psnr):
            return  # nothing measured (no supervised pixel in the frame)
        psnr = min(psnr, MAX_PSNR)
        old = float(self.psnr[frame])
        self.psnr[frame] = psnr if old == 0 else self.momentum * old + (1 - self.momentum) * psnr
        self.latest[frame] = psnr
        self._probabilities = None

    def latest_mean(self) -> float | None:
        """The mean over the frames measured so far of each one's last PSNR (None before any). Unlike the
        running PSNR, which a frame's visits move a fifth of the way each, it follows the model within one
        visit of every frame: after a densification's dip, it shows the recovery as it happens."""
        seen = self.latest[self.latest > 0]
        return float(seen.mean()) if len(seen) else None

    def state_dict(self) -> dict:
        return dict(psnr=self.psnr.clone(), latest=self.latest.clone(), generator=self.generator.get_state())

    def load_state_dict(self, state: dict) -> None:
        self.psnr = state["psnr"].clone()
        self.latest = state["latest"].clone() if "latest" in state else self.psnr.clone()  # older: the running one
        self.generator.set_state(state["generator"])
        self._probabilities = None
