"""The optimiser of the trainer's sparse mode: Adam that updates only the Gaussians a step saw.

`SeenAdam.step(seen)` runs torch.optim.Adam's update on the rows whose Gaussian was in view
(`seen`, bool [N]) and leaves the other rows and their moments alone (tomgs/kernels/adam.py says
why). Its state has Adam's layout (step, exp_avg, exp_avg_sq per parameter), so densification's
moment surgery and checkpoints treat both optimisers alike.
"""

from __future__ import annotations

import math

import torch


class SeenAdam(torch.optim.Optimizer):
    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        super().__init__(params, dict(lr=lr, betas=betas, eps=eps))

    @torch.no_grad()
    def step(self, seen: torch.Tensor) -> None:
        """One Adam step on the rows where `seen` (bool [N], N = every parameter's first axis) is True."""
        from tomgs.kernels import adam
        from tomgs.runtime import launch, scope, wrap

        seen_bytes = seen.to(torch.uint8)  # held until the launches are queued: the descriptor does not own it
        seen_d = wrap(seen_bytes)
        with scope(seen.device) as device:
            for group in self.param_groups:
                beta1, beta2 = group["betas"]
                for p in group["params"]:
                    if p.grad is None or p.numel() == 0:
                        continue
                    if p.shape[0] != seen.shape[0]:
                        raise ValueError(f"seen has {seen.shape[0]} rows but the parameter has {p.shape[0]}")
                    state = self.state[p]
                    if not state:
                        state["step"] = torch.tensor(0.0)
                        state["exp_avg"] = torch.zeros_like(p)
                        state["exp_avg_sq"] = torch.zeros_like(p)
                    state["step"] += 1
                    step = float(state["step"])  # a CPU tensor: no wait for the device
                    rows = p.shape[0]
                    grad = p.grad.contiguous()
                    views = [wrap(t.view(rows, -1)) for t in (p, grad, state["exp_avg"], state["exp_avg_sq"])]
                    launch(adam.adam_seen_rows, p.numel(), device=device, args=[
                        *views, seen_d, group["lr"], beta1, beta2, group["eps"], 1.0 - beta1 ** step,
                        math.sqrt(1.0 - beta2 ** step)])
