"""The optimiser of the trainer's sparse mode: Adam that updates only the Gaussians a step saw (and,
over every row, the CPU's dense Adam: make_adam).

`SeenAdam.step(seen)` runs torch.optim.Adam's update on the rows whose Gaussian was in view
(`seen`, bool [N]) and leaves the other rows and their moments alone (tomgs/kernels/adam.py says
why), all parameters in one launch; `step()` updates every row. Its state has Adam's layout
(step, exp_avg, exp_avg_sq per parameter), so densification's moment surgery and checkpoints treat
both optimisers alike.
"""

from __future__ import annotations

import collections
import math

import torch


def uses_seen_adam(config, device: torch.device) -> bool:
    """`config.sparse_adam`, or when it is None: SeenAdam on a GPU, dense Adam on a CPU (TrainConfig says why)."""
    return device.type == "cuda" if config.sparse_adam is None else bool(config.sparse_adam)


def make_adam(params: dict[str, torch.nn.Parameter], lr: dict[str, float], sparse: bool,
              device: torch.device) -> torch.optim.Optimizer | SeenAdam:
    """One group per parameter (named, with its learning rate `lr[name]`): SeenAdam when `sparse`;
    else dense Adam: on a GPU torch's, fused (one kernel for all groups; the foreach path took 2 ms at
    4.5M Gaussians), on a CPU SeenAdam over every row (`step()`: the same update), since torch's
    Adam imports torch._dynamo when it is made (1.5 s of an idle 2-core CPU, 5.6 s of a busy one)."""
    groups = [dict(params=[p], lr=lr[name], name=name) for name, p in params.items()]
    if sparse or device.type == "cpu":
        return SeenAdam(groups, lr=0.0, eps=1e-15)
    return torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)


class SeenAdam:
    """Adam on the seen rows. Learning rates may differ by group; betas and eps are the optimiser's.

    torch.optim.Optimizer's interface as the trainer, densification and checkpoints use it
    (`param_groups`, `state` keyed by parameter, `zero_grad`, `state_dict` / `load_state_dict` in
    its layout, so a checkpoint moves between SeenAdam and torch's Adam), without deriving from it:
    that class's first add_param_group imports torch._dynamo, 1.5-5 s of every fit's first minute
    (tomgs/train/warm.py)."""

    def __init__(self, params, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.defaults = dict(lr=lr, betas=tuple(betas), eps=eps)
        self.param_groups: list[dict] = []
        self.state: collections.defaultdict = collections.defaultdict(dict)  # parameter -> its Adam state
        for group in params:
            group = {**self.defaults, **group, "params": list(group["params"])}
            if tuple(group["betas"]) != self.defaults["betas"] or group["eps"] != eps:
                raise ValueError("SeenAdam takes betas and eps for all groups at once, not per group")
            self.param_groups.append(group)
        self._empty: dict[torch.device, torch.Tensor] = {}  # the stand-in of an unused slot, per device
        self._every: dict[torch.device, torch.Tensor] = {}  # a dense step's `seen`, per device

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if set_to_none:
                    p.grad = None
                elif p.grad is not None:
                    p.grad.zero_()

    def state_dict(self) -> dict:
        """torch.optim.Optimizer.state_dict's layout: parameters numbered in group order."""
        numbers: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            for p in group["params"]:
                numbers.setdefault(id(p), len(numbers))
            groups.append({**{k: v for k, v in group.items() if k != "params"},
                           "params": [numbers[id(p)] for p in group["params"]]})
        state = {numbers[id(p)]: dict(s) for p, s in self.state.items() if id(p) in numbers and s}
        return dict(state=state, param_groups=groups)

    def load_state_dict(self, saved: dict) -> None:
        """Groups and moments from `state_dict()` (SeenAdam's or torch's Adam's): each group's
        settings as saved, moments in their parameter's dtype and device, the step count on the host
        (where step() reads it without waiting for the device)."""
        groups = saved["param_groups"]
        if len(groups) != len(self.param_groups) or any(
                len(g["params"]) != len(own["params"]) for g, own in zip(groups, self.param_groups)):
            raise ValueError("the saved optimizer state has groups of other sizes than this optimizer's")
        for g in groups:
            if tuple(g.get("betas", self.defaults["betas"])) != self.defaults["betas"] \
                    or g.get("eps", self.defaults["eps"]) != self.defaults["eps"]:
                raise ValueError(f"the saved optimizer state has betas {g.get('betas')} and eps {g.get('eps')}; "
                                 f"this SeenAdam's are {self.defaults['betas']} and {self.defaults['eps']}")
        params = {}
        for g, own in zip(groups, self.param_groups):
            params.update(zip(g["params"], own["params"]))
        self.state = collections.defaultdict(dict)
        for number, entry in saved["state"].items():
            p = params[number]
            self.state[p] = {key: (torch.tensor(float(value)) if key == "step"
                                   else value.to(p.device, p.dtype) if torch.is_tensor(value) else value)
                             for key, value in entry.items()}
        self.param_groups = [{**{k: v for k, v in g.items() if k != "params"}, "params": own["params"]}
                             for g, own in zip(groups, self.param_groups)]

    def state_of(self, p: torch.Tensor) -> dict:
        """`p`'s Adam state (step, exp_avg, exp_avg_sq), made at zero when it has none."""
        state = self.state[p]
        if not state:
            state["step"] = torch.tensor(0.0)
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
        return state

    def advance(self, group: dict, p: torch.Tensor) -> tuple[float, float, float]:
        """Count one more step of `p` (of `group`): (lr, 1 - beta1^step, sqrt(1 - beta2^step)), its update's
        rates. `step` calls it for every parameter it updates; a captured training step
        (tomgs.train.captured_step), whose graph runs the update, for the parameters it updates."""
        beta1, beta2 = self.defaults["betas"]
        state = self.state_of(p)
        state["step"] += 1
        step = float(state["step"])  # a CPU tensor: no wait for the device
        return group["lr"], 1.0 - beta1 ** step, math.sqrt(1.0 - beta2 ** step)

    @torch.no_grad()
    def step(self, seen: torch.Tensor | None = None) -> None:
        """One Adam step on the rows where `seen` (bool [N], N = every parameter's first axis) is True;
        None: on every row (dense Adam, as torch.optim.Adam steps)."""
        from tomgs.kernels import adam
        from tomgs.runtime import launch, scope, wrap, wrap_rows

        slots = []  # (param, grad, exp_avg, exp_avg_sq, lr, bias1, bias2_sqrt) of every parameter with a gradient
        beta1, beta2 = self.defaults["betas"]
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None or p.numel() == 0:
                    continue
                if seen is None:
                    seen = self._every_row(p.shape[0], p.device)
                if p.shape[0] != seen.shape[0]:
                    raise ValueError(f"seen has {seen.shape[0]} rows but the parameter has {p.shape[0]}")
                state = self.state_of(p)
                slots.append((p, p.grad.contiguous(), state["exp_avg"], state["exp_avg_sq"], *self.advance(group, p)))
        if not slots:
            return
        seen = seen.contiguous()  # held until the launches are queued: a descriptor does not own its tensor
        empty = self._empty.get(seen.device)
        if empty is None:
            empty = self._empty[seen.device] = torch.empty(0, 1, device=seen.device)
        with scope(seen.device) as device:
            for first in range(0, len(slots), adam.SLOTS):
                chunk = slots[first:first + adam.SLOTS]
                unused = adam.SLOTS - len(chunk)
                arrays = [wrap_rows(t) for slot in chunk for t in slot[:4]]  # param, grad, exp_avg, exp_avg_sq
                arrays += [wrap(empty)] * (4 * unused)
                lr, bias1, bias2_sqrt = ([s[i] for s in chunk] + [1.0] * unused for i in (4, 5, 6))
                launch(adam.adam_seen_rows, seen.shape[0], device=device, args=[
                    *arrays, wrap(seen), adam.vec_slots(*lr), adam.vec_slots(*bias1), adam.vec_slots(*bias2_sqrt),
                    beta1, beta2, self.defaults["eps"]])


    def _every_row(self, rows: int, device: torch.device) -> torch.Tensor:
        """bool [rows] of True on `device`, kept while the row count holds (dense steps)."""
        every = self._every.get(device)
        if every is None or every.shape[0] != rows:
            every = self._every[device] = torch.ones(rows, dtype=torch.bool, device=device)
        return every


def adam_estimates(optimizer: torch.optim.Optimizer) -> dict[str, tuple[torch.Tensor, torch.Tensor, int]]:
    """Per named group (make_adam's): its parameter's Adam moment estimates, bias-corrected
    (exp_avg / (1 - beta1^step), exp_avg_sq / (1 - beta2^step): what its next update starts from,
    whatever number of steps made them; zeros where it has no state yet), and its step count."""
    out = {}
    for group in optimizer.param_groups:
        (p,) = group["params"]
        beta1, beta2 = group["betas"]
        state = optimizer.state.get(p, {})
        step = int(float(state["step"])) if "step" in state else 0
        if step == 0:
            out[group["name"]] = (torch.zeros_like(p.detach()), torch.zeros_like(p.detach()), 0)
            continue
        out[group["name"]] = (state["exp_avg"].detach() / (1.0 - beta1 ** step),
                              state["exp_avg_sq"].detach() / (1.0 - beta2 ** step), step)
    return out


def prime_adam(optimizer: torch.optim.Optimizer, estimates: dict[str, tuple[torch.Tensor, torch.Tensor]],
               steps: dict[str, int]) -> None:
    """Start `optimizer` (make_adam's, no step taken) from moment estimates (`adam_estimates`' first
    two, rows matching its parameters): each named group's state as if `steps[name]` steps had ended
    at them (the moments biased again by that count), so that its next update is the one the
    optimiser that made them would have taken after as many steps. Groups not named, or with no
    steps, start fresh. Through load_state_dict: the state takes the layout the optimiser's device
    and mode want (fused Adam's step on the GPU, SeenAdam's on the host)."""
    saved = optimizer.state_dict()
    for index, group in enumerate(optimizer.param_groups):
        name, (p,) = group["name"], group["params"]
        step = int(steps.get(name, 0))
        if name not in estimates or step <= 0:
            continue
        first, second = estimates[name]
        if first.shape != p.shape or second.shape != p.shape:
            raise ValueError(f"{name}: estimates of shape {tuple(first.shape)} for a parameter of {tuple(p.shape)}")
        beta1, beta2 = group["betas"]
        (position,) = saved["param_groups"][index]["params"]
        saved["state"][position] = dict(step=torch.tensor(float(step)),
                                        exp_avg=(first * (1.0 - beta1 ** step)).to(p.device, p.dtype),
                                        exp_avg_sq=(second * (1.0 - beta2 ** step)).to(p.device, p.dtype))
    optimizer.load_state_dict(saved)
