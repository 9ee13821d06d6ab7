"""How many Gaussians a fit keeps: the quality levels and the rule that applies them.

A fit grows its cloud by densification (tomgs.train.densify), then, unless its quality is "max", takes
it down by importance a share at a time: `TrainConfig.sparsify_rounds` rounds spread evenly over
[sparsify_start_fraction, sparsify_stop_fraction) of the run. A round measures, in one pass over
every training frame (`importance`), the clip PSNR and each Gaussian's importance, the
pixels' worth of colour it gives the clip (its blend weights alpha * T summed over every supervised
pixel of every frame; its temporal opacity is inside alpha, so a Gaussian alive at three frames is
judged on those three). It proposes the least important share of the cloud (`sparsify_share`), and
a second pass renders the clip without them (`Trainer.clip_psnr(hidden=...)`): the prune is taken
when what it costs right away, before any training recovers from it, is within the level's price
(`QualityRule.per_halving` dB for each halving of the count, and the PSNR no further than
`QualityRule.in_all` below the best the rounds measured). A prune that costs more is not taken, and
the share halves for the rounds that follow, down to MIN_SHARE, where the rounds stop. Training
recovers between rounds: prune, recover, prune. Pricing a prune before training hides its cost keeps
the rule's reading the same however fast the fit still climbs. A clip that loses little when thinned
goes on down, one that loses much stops early; on DAVIS in 2 minutes the first 30% of camel's and cows'
10M went for ~0.1 dB and the next 30% cost 1-2 dB, and kite-surf's least important 30% cost 4 dB, so
all three stopped near 6M (benchmarks/README.md, "How many Gaussians a fit keeps").

Where growth stops is decided earlier, while the cloud grows, at the level's `per_gaussian` price
(tomgs.train.growth).

Decisions are taken at those rounds only (`take_round`, which the trainer's loop calls), on the host,
from numbers the passes already brought back: nothing here runs at a training step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from tomgs.render.sh import fused_sh_to_colors

# A round never takes the cloud below this many Gaussians per pixel of one frame.
MIN_PER_PIXEL = 1 / 8
# The share of the cloud below which a round proposes nothing: the rounds stop.
MIN_SHARE = 1 / 32


@dataclass(frozen=True)
class QualityRule:
    """What a quality level lets a prune cost in clip PSNR (dB), measured right after it: `per_halving`
    for each halving of the count, and at most `in_all` below the best PSNR the rounds measured; and the
    least squared error a Gaussian grown must take away from the clip, `per_gaussian` (tomgs.train.growth)."""

    per_halving: float
    in_all: float
    per_gaussian: float


QUALITY_RULES = {
    # prunes: from the DAVIS prices (benchmarks/README.md); growth: estimated from camel's 1-minute fits capped
    # at 1-5M (~1-2e-3 per Gaussian around 1-2M, ~8e-4 around 2-4M; docs/notes/compact.md), not yet measured
    "compact": QualityRule(per_halving=2.0, in_all=2.5, per_gaussian=4e-3),
    "default": QualityRule(per_halving=1.0, in_all=1.0, per_gaussian=1e-3),
    "max": None,  # no rounds: the cloud densification grew, less what the end's compaction leaves out
}


class Sparsifier:
    """The rounds of a fit with TrainConfig `config` on frames of `pixels` pixels: `due(progress)`
    says when one is taken, `propose(count, psnr)` how many Gaussians it offers to remove, and
    `judge(count, remove, psnr, without)` whether their removal is taken."""

    def __init__(self, config, pixels: int):
        self.rule = QUALITY_RULES[config.quality]
        self.start, self.stop = config.sparsify_start_fraction, config.sparsify_stop_fraction
        self.rounds, self.share = int(config.sparsify_rounds), float(config.sparsify_share)
        self.floor = max(1, int(pixels * MIN_PER_PIXEL))
        self.taken = 0  # rounds begun (a round's slot passed while it ran counts as taken)
        self.measured: list[tuple[int, float]] = []  # (count, clip PSNR) at each round, before its prune
        self.priced: list[tuple] = []  # (count, proposed, clip PSNR with and without them, taken) of each prune
        self.stopped = ""  # why the rounds ended early ("" while they go on)
        self.seconds = 0.0  # what the rounds taken have cost (the trainer times them)

    @property
    def active(self) -> bool:
        return self.rule is not None and self.rounds > 0 and self.stop > self.start

    def due(self, progress: float) -> bool:
        """Whether a round is due at `progress` (the run's fraction done): its slot has come, no round
        has taken it, and the rule has not stopped them. Slots passed while a round ran are skipped,
        so training always recovers between two prunes."""
        if not self.active or self.stopped or progress >= self.stop:
            return False
        slot = math.floor((progress - self.start) / (self.stop - self.start) * self.rounds + 1e-9)  # 0.6 of [0.5, 0.9)
        if slot < self.taken:
            return False
        self.taken = slot + 1
        return True

    def propose(self, count: int, psnr: float) -> int:
        """How many of the `count` Gaussians, the least important first, this round offers to remove,
        given the clip PSNR `psnr` it measured with all of them; 0 once the rounds have stopped (the
        share fell below MIN_SHARE, or the floor is reached)."""
        self.measured.append((int(count), float(psnr)))
        if self.stopped:
            return 0
        remove = min(int(count * self.share), count - self.floor)
        if remove <= 0:
            self.stopped = f"{count:,} Gaussians: the floor of {self.floor:,}"
            return 0
        return remove

    def judge(self, count: int, remove: int, psnr: float, without: float) -> bool:
        """Whether removing the `remove` proposed of `count` Gaussians is taken, given the clip PSNR with
        them (`psnr`) and without them (`without`): its cost within `per_halving` dB a halving and the
        PSNR within `in_all` of the best round's. A prune not taken halves the share of later rounds."""
        halvings = math.log2(count / (count - remove))
        best = max(p for _, p in self.measured)
        taken = psnr - without <= self.rule.per_halving * halvings and best - without <= self.rule.in_all
        self.priced.append((int(count), int(remove), float(psnr), float(without), taken))
        if taken:
            return True
        self.share /= 2
        if self.share < MIN_SHARE:
            self.stopped = (f"removing {remove:,} of {count:,} would cost {psnr - without:.2f} dB of clip PSNR "
                            f"({best - without:.2f} below the best round's)")
        return False

    def summary(self, quality: str) -> str:
        """One line: the rounds taken, the count they went from and to, each prune priced, why they ended."""
        priced = ", ".join(f"{remove / count:.0%} of {count:,} {without - psnr:+.2f} dB" + ("" if taken else " refused")
                           for count, remove, psnr, without, taken in self.priced)
        return (f"quality {quality}: {len(self.measured)} rounds from {self.measured[0][0]:,} Gaussians; prunes "
                f"priced: {priced or 'none'}" + (f"; stopped: {self.stopped}" if self.stopped else ""))

    def state_dict(self) -> dict:
        return dict(taken=self.taken, share=self.share, measured=[[c, p] for c, p in self.measured],
                    priced=[list(p) for p in self.priced], stopped=self.stopped, seconds=self.seconds)

    def load_state_dict(self, state: dict) -> None:
        self.taken, self.share = int(state["taken"]), float(state["share"])
        self.measured = [(int(c), float(p)) for c, p in state["measured"]]
        self.priced = [(int(c), int(r), float(p), float(w), bool(t)) for c, r, p, w, t in state["priced"]]
        self.stopped = str(state["stopped"])
        self.seconds = float(state.get("seconds", 0.0))  # checkpoints before it: none counted


def importance(trainer, tick=None) -> tuple[torch.Tensor, list[float]]:
    """(float32 [N]: each Gaussian of `trainer`'s model's importance, the pixels' worth of colour it gives
    the clip: its blend weights alpha * T, temporal opacity inside, summed over every supervised pixel
    (times its loss weight) of every training frame; the PSNR of each frame, floats [T]), from one pass
    over the frames, each rendered with its RGB colours [N,3] as a leaf, whose gradient of the weighted
    red channel's sum is that sum (as `tomgs.render.blend_weights`). tick(text) after each frame."""
    model = trainer.model
    inputs = {k: v.detach() for k, v in model.render_inputs().items()}
    sh = inputs.pop("colors")
    total = torch.zeros(len(model), device=trainer.device)
    psnrs, colors = [], None
    for k in range(trainer.num_frames):
        if colors is None or model.sh_degree > 0:  # degree 0: one colour for every view
            colors = fused_sh_to_colors(sh, inputs["means"], trainer.viewmats[k]).detach().requires_grad_(True)
        with torch.enable_grad():
            image, _, _ = trainer.render(k, inputs=dict(inputs, colors=colors))
            red = image[..., 0] if trainer.weights is None else image[..., 0] * trainer.weight(k)[..., 0]
            (grad,) = torch.autograd.grad(red.sum(), colors)
        total += grad[:, 0]
        psnrs.append(trainer.frame_psnr(k, image))
        if tick is not None:
            tick(f"importance {k + 1}/{trainer.num_frames}")
    return total, torch.stack(psnrs).tolist() if psnrs else []


def take_round(trainer, sparsifier: Sparsifier, tick=None) -> tuple[float, int] | None:
    """A round of `sparsifier`'s rule on `trainer` (a tomgs.train.Trainer, of which it uses the model, the
    frames' renders and PSNRs (`importance`), `clip_psnr`, `remove` and `mark_changed`): the clip PSNR and
    the importance in one pass; the least important Gaussians the rule proposes priced by a second pass
    without them (`trainer.clip_psnr(hidden=)`), and removed when the rule takes the prune. Returns (the clip
    PSNR before the prune, the frames it covers), or None for an empty cloud."""
    model = trainer.model
    if len(model) == 0:
        return None
    scores, psnrs = importance(trainer, tick)
    measured = float(np.mean(psnrs))
    remove = sparsifier.propose(len(model), measured)
    if remove:
        least = torch.zeros(len(model), dtype=torch.bool, device=trainer.device)
        least[torch.argsort(scores)[:remove]] = True
        without = float(np.mean(trainer.clip_psnr(tick, hidden=least)))
        if sparsifier.judge(len(model), remove, measured, without):
            trainer.remove(least)
    trainer.mark_changed()
    return measured, trainer.num_frames
