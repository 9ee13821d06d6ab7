"""Torch operations per training step, by phase: the host work of `Trainer.step` as a GPU runs it.

Each dispatched aten operation costs the host a few microseconds on a GPU machine (and most queue a
kernel), so their count per step is the host's bill for everything that is not a Warp launch. The
step runs here on the CPU at a tiny size with a GPU's settings (SeenAdam, pipelined, no alive index),
which issues the same operations a GPU step does; each is attributed to the phase of the step that
issued it (the render's forward, the loss, the backward, Adam, the densifier's statistics...).

    python benchmarks/step_ops.py                 # the demo scene, 4 frames of 32x18
    python benchmarks/step_ops.py --json ops.json
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import sys
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_train import CPU, small_config, synthetic_clip  # noqa: E402  (the tests' tiny clip)

from tomgs.train import Trainer  # noqa: E402


class Census(TorchDispatchMode):
    """Counts dispatched aten operations under the innermost phase named by `phase(...)`."""

    def __init__(self):
        super().__init__()
        self.phases = ["other"]
        self.counts: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.counts[self.phases[-1]][str(func.overloadpacket).rsplit(".", 1)[-1]] += 1
        return func(*args, **(kwargs or {}))

    @contextlib.contextmanager
    def phase(self, name: str):
        self.phases.append(name)
        try:
            yield
        finally:
            self.phases.pop()

    def label(self, owner, attribute: str, name: str) -> None:
        """Count what owner.attribute(...) issues under `name`."""
        method = getattr(owner, attribute)

        def labelled(*args, **kwargs):
            with self.phase(name):
                return method(*args, **kwargs)

        setattr(owner, attribute, labelled)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20, help="steps counted, after 30 untimed ones")
    ap.add_argument("--json", type=Path, help="also write the counts per step to this file")
    args = ap.parse_args()
    images, cams, points, colors = synthetic_clip(4, 32, 18)
    trainer = Trainer(images, cams, points, colors, small_config(10_000, sparse_adam=True, alive_index=False), CPU)
    trainer.pipelined = True  # as on a GPU: counts read after the backward, PSNRs a flush late
    for _ in range(30):
        trainer.step()

    census = Census()
    for owner, attribute, name in ((trainer, "render", "render forward"), (trainer, "target", "target"),
                                   (trainer, "loss", "loss forward"), (trainer, "_psnr", "PSNR"),
                                   (trainer, "flush_measurements", "sampler"), (trainer.sampler, "sample", "sampler"),
                                   (trainer.densifier, "step_pre_backward", "densifier"),
                                   (trainer.densifier, "step_post_backward", "densifier"),
                                   (trainer.optimizer, "step", "Adam"), (trainer.optimizer, "zero_grad", "Adam")):
        census.label(owner, attribute, name)
    tensor_backward = torch.Tensor.backward

    def backward(tensor, *a, **k):
        with census.phase("backward"):
            return tensor_backward(tensor, *a, **k)

    torch.Tensor.backward = backward
    try:
        with census:
            for _ in range(args.steps):
                trainer.step()
    finally:
        torch.Tensor.backward = tensor_backward

    per_step = {name: {op: c / args.steps for op, c in ops.most_common()} for name, ops in census.counts.items()}
    totals = {name: sum(ops.values()) for name, ops in per_step.items()}
    print(f"torch operations per step: {sum(totals.values()):.1f} ({len(trainer.model):,} Gaussians, "
          f"{trainer.width}x{trainer.height})")
    for name in sorted(totals, key=totals.get, reverse=True):
        ops = ", ".join(f"{op} {c:g}" for op, c in list(per_step[name].items())[:10])
        print(f"  {totals[name]:6.1f}  {name:15s} {ops}")
    if args.json:
        args.json.write_text(json.dumps(dict(per_step=per_step, totals=totals), indent=1))


if __name__ == "__main__":
    main()
