"""Growth that follows the scene: how far densification grows the cloud, decided while it grows.

At a quality other than "max" a fit grows in stages. Densification (tomgs.train.densify) grows the
cloud up to the stage's limit, twice the cloud the fit started from; once there, training goes on
until the training PSNR settles (it gains less than SETTLE_DB over SETTLE_INTERVALS densification
intervals and is not below its best since by more, or the stage has lasted its share of the densification
window, 1 / MAX_STAGES), and the stage is priced by its *worth*: the clip's squared error its new Gaussians took away, per new
Gaussian (colours in [0, 1], summed over every supervised pixel of every training frame). The next
stage doubles the limit while the worth expected of it (this stage's, shrunk by the ratio of this
stage's worth to the last one's, a ratio in [0, 1]) is at least the quality's price
(`QualityRule.per_gaussian`); otherwise densification stops, and the cloud keeps what it has. A worth
of zero or less is no price: the stage is still inside the dip its splits made, and waits; one whose
share runs out before it has won its PSNR back stops the growth, said so.

The training PSNR the stages read is the mean of each frame's last measurement (tomgs.train.sampler's
`latest_mean`): a frame's running PSNR moves a fifth of the way at each visit, and on a 300-frame clip
it lagged the model by a few hundred steps, so a stage read it inside its own dip.

The price is a rate-distortion slope, the lambda of a video encoder at constant quality: one number
for every clip. A Gaussian earns its place when it takes at least that much error away. At a high
PSNR each takes little away, so a clean clip stops small; a busy clip at a lower PSNR grows on. A
quality's `per_halving` prices the later prunes (tomgs.train.sparsify) in dB of clip PSNR.

On a GPU the cloud of a staged fit starts at tomgs.train.config.START_SHARE of the cap (1/32);
a CPU fit's cap is already set by what its time allows (tomgs.train.plan.auto_cap), and its first
stage is twice what it starts from. Decisions are taken on the host, every densification interval,
from the training PSNR the sampler already holds: nothing here runs inside a training step.
"""

from __future__ import annotations

import math

from tomgs.train.sparsify import QUALITY_RULES

# A stage ends once the training PSNR gained less than SETTLE_DB over the last SETTLE_INTERVALS
# densification intervals at its limit ...
SETTLE_DB, SETTLE_INTERVALS = 0.05, 5
# ... or after 1 / MAX_STAGES of the densification window at its limit.
MAX_STAGES = 6


def squared_error(psnr: float) -> float:
    """The mean squared error (colours in [0, 1]) of a PSNR in dB."""
    return 10.0 ** (-psnr / 10.0)


class Growth:
    """The stages of a fit with TrainConfig `config` (its cap resolved) that starts from `start`
    Gaussians on frames whose supervised pixels number `pixels` in all (frames x pixels a frame, or the
    loss weights' sum). `limit` is the most Gaussians densification may have now (the cap at "max");
    `update` moves it on, `stopped` says why growth ended ("" while it goes on)."""

    def __init__(self, config, start: int, pixels: float):
        rule = QUALITY_RULES[config.quality]
        self.price = None if rule is None else rule.per_gaussian
        self.cap = int(config.max_gaussians)
        self.pixels = float(pixels)
        self.window = (config.densify_stop_fraction - config.densify_start_fraction) / MAX_STAGES
        self.limit = self.cap if self.price is None else min(self.cap, 2 * max(int(start), 1))
        self.stages: list[tuple[int, float, float]] = [(int(start), math.nan, math.nan)]  # (count, PSNR, worth)
        self.full_since: float | None = None  # the progress at which the limit was reached
        self.heard: list[float] = []  # the training PSNR at each interval since
        self.stopped = ""

    @property
    def staged(self) -> bool:
        return self.price is not None and not self.stopped and self.limit < self.cap

    def update(self, progress: float, count: int, full: bool, psnr: float | None) -> str | None:
        """At a densification interval, `progress` into the run, with `count` Gaussians, `full` when
        densification has reached the limit, `psnr` the training PSNR (None before any): ends the
        stage once it has settled, and returns what happened ("grow": the limit doubled; "stop":
        growth ends here), else None."""
        if not self.staged or not full or psnr is None:
            return None
        if self.full_since is None:
            self.full_since, self.heard = progress, []
        self.heard.append(float(psnr))
        out_of_time = progress - self.full_since >= self.window
        if not (self.settled() or out_of_time):
            return None
        was_count, was_psnr, was_worth = self.stages[-1]
        worth = math.inf if math.isnan(was_psnr) else \
            (squared_error(was_psnr) - squared_error(psnr)) * self.pixels / max(count - was_count, 1)
        if worth <= 0 and not out_of_time:  # still inside the dip its splits made: no price to read yet
            return None
        self.full_since = None
        self.stages.append((int(count), float(psnr), float(worth)))
        if worth <= 0:
            self.stopped = (f"at {count:,} Gaussians: the last stage had not won back its training PSNR "
                            f"({was_psnr:.2f} -> {psnr:.2f} dB) when its share of the densification window ran out")
            return "stop"
        # the worth shrinks from stage to stage at most as it did last (the first two stages have no ratio to go
        # by: the start's worth is NaN, the first stage's infinite)
        ratio = min(1.0, worth / was_worth) if 0 < was_worth < math.inf else 1.0
        expected = worth * ratio
        if expected >= self.price:
            self.limit = min(self.cap, 2 * self.limit)
            return "grow"
        self.stopped = (f"at {count:,} Gaussians the last stage took away {worth:.2g} of the clip's squared error "
                        f"per new Gaussian, and the next would take about {expected:.2g}: under the price of "
                        f"{self.price:.2g}")
        return "stop"

    def settled(self) -> bool:
        """Whether the training PSNR heard since the stage reached its limit has settled: it gained less than
        SETTLE_DB over the last SETTLE_INTERVALS intervals and is within SETTLE_DB of the best heard since,
        so a PSNR still falling (the dip right after splits) is not taken as settled."""
        if len(self.heard) <= SETTLE_INTERVALS:
            return False
        latest = self.heard[-1]
        return latest - self.heard[-1 - SETTLE_INTERVALS] < SETTLE_DB and latest >= max(self.heard) - SETTLE_DB

    def summary(self) -> str:
        """One line: the stages' counts and training PSNRs, and why growth ended."""
        stages = ", ".join(f"{count:,} ({psnr:.2f} dB)" for count, psnr, _ in self.stages[1:])
        return f"growth in stages: {stages or 'none ended'}" + (f"; stopped {self.stopped}" if self.stopped else "")

    def state_dict(self) -> dict:
        return dict(limit=self.limit, stages=[list(s) for s in self.stages], full_since=self.full_since,
                    heard=list(self.heard), stopped=self.stopped)

    def load_state_dict(self, state: dict) -> None:
        self.limit = int(state["limit"])
        self.stages = [(int(c), float(p), float(w)) for c, p, w in state["stages"]]
        self.full_since = None if state["full_since"] is None else float(state["full_since"])
        self.heard, self.stopped = [float(p) for p in state["heard"]], str(state["stopped"])
