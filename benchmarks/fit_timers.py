"""benchmarks/davis.py with timers patched in: each training step's host time, each clip PSNR's time
(a device sync on each side) and its peak memory above what was allocated before it, each checkpoint's
host time and the host time lost in the 400 steps after it, the save phase's parts. Prints one line
'PROBE {json}' at the end. RESULTS.md "Session 36" measured where a checkpoint's cost goes with it.

    PROBE=time python benchmarks/fit_timers.py <clips> --clips camel --minutes 1 \
        --set max_gaussians=5000000 --set checkpoint_interval_s=13

PROBE: time (as tomgs runs), nowrite (the state copied to the host, no file), cloneonly (the clones,
no copies), none (no checkpoints), pinned (the session-36 trial: the copies through one 64 MB pinned
buffer, then torch.save of host tensors).
"""
import json
import os
import runpy
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import tomgs.io.scene as scene_mod
import tomgs.train.checkpoint as ck
import tomgs.train.pipeline as fit_mod
import tomgs.train.trainer as tr

MODES = ("time", "nowrite", "cloneonly", "none", "pinned")
mode = os.environ.get("PROBE", "time")
if mode not in MODES:
    sys.exit(f"PROBE={mode!r}: one of {', '.join(MODES)}")
steps, evals, ckpts, save = [], [], [], {}

step = tr.Trainer.step
def timed_step(self):
    t = time.perf_counter(); step(self); steps.append((t, time.perf_counter() - t))
tr.Trainer.step = timed_step

clip_psnr = tr.Trainer.clip_psnr
def timed_eval(self, *a, **k):
    gpu = torch.cuda.is_available()
    if gpu:
        torch.cuda.synchronize(); base = torch.cuda.memory_allocated(); torch.cuda.reset_peak_memory_stats()
    t = time.perf_counter(); out = clip_psnr(self, *a, **k)
    if gpu:
        torch.cuda.synchronize()
    peak = round((torch.cuda.max_memory_allocated() - base) / 2**20) if gpu else None
    evals.append(dict(at=t, s=round(time.perf_counter() - t, 4), frames=len(out), peak_over_mb=peak, N=len(self.model)))
    return out
tr.Trainer.clip_psnr = timed_eval

bg = tr.Trainer._checkpoint_in_background
def timed_bg(self, path, writer):
    t = time.perf_counter()
    if mode != "none":
        bg(self, path, writer)
    ckpts.append(dict(at=t, host_s=round(time.perf_counter() - t, 4), it=self.iteration))
tr.Trainer._checkpoint_in_background = timed_bg
if mode == "nowrite":
    def copies_only(path, state):
        for tensor in ck._tensors(state):
            tensor.cpu()
        return path
    ck.write_checkpoint = copies_only
    tr.write_checkpoint = copies_only

# fit imports save_scene from tomgs.io.scene when it runs: patched there
if mode == "cloneonly":
    ck.write_checkpoint = tr.write_checkpoint = lambda path, state: path
if mode == "pinned":  # the device's copies through one pinned buffer, then torch.save of host tensors
    write = ck.write_checkpoint
    staging = {}
    def via_pinned(path, state):
        def host(v):
            if isinstance(v, torch.Tensor) and v.is_cuda:
                if "buf" not in staging:
                    staging["buf"] = torch.empty(64 << 20, dtype=torch.uint8, pin_memory=True)
                buf = staging["buf"]; out = torch.empty(v.shape, dtype=v.dtype)
                src = v.contiguous().view(-1).view(torch.uint8); dst = out.view(-1).view(torch.uint8)
                for i in range(0, src.numel(), buf.numel()):
                    n = min(buf.numel(), src.numel() - i)
                    buf[:n].copy_(src[i:i + n], non_blocking=True)
                    torch.cuda.current_stream().synchronize()
                    dst[i:i + n].copy_(buf[:n])
                return out
            if isinstance(v, dict): return {k: host(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)): return type(v)(host(x) for x in v)
            return v
        return write(path, host(state))
    ck.write_checkpoint = tr.write_checkpoint = via_pinned
for mod, name in ((scene_mod, "save_scene"), (fit_mod, "_plot")):
    f = getattr(mod, name)
    def timed(*a, _f=f, _n=name, **k):
        t = time.perf_counter(); r = _f(*a, **k); save[_n] = round(time.perf_counter() - t, 3); return r
    setattr(mod, name, timed)

sys.argv = ["davis.py", *sys.argv[1:]]
try:
    runpy.run_path(str(Path(__file__).with_name("davis.py")), run_name="__main__")
finally:
    t0 = steps[0][0] if steps else 0
    dt = np.array([s for _, s in steps]); at = np.array([t for t, _ in steps])
    med = float(np.median(dt[len(dt) // 2:])) if len(dt) else 0
    def lost(t, n=400):  # extra host time of the n steps after t, over the median step time of the window before
        i = int(np.searchsorted(at, t)); before = dt[max(0, i - n):i]
        ref = float(np.median(before)) if len(before) else med
        return round(float(dt[i:i + n].sum() - ref * len(dt[i:i + n])), 3), round(ref * 1e3, 3)
    for c in ckpts: c["lost_s"], c["step_ms_before"] = lost(c["at"]); c["at"] = round(c["at"] - t0, 2)
    for e in evals: e["lost_after_s"], _ = lost(e["at"] + e["s"]); e["at"] = round(e["at"] - t0, 2)
    print("PROBE " + json.dumps(dict(mode=mode, steps=len(dt), step_ms_median=round(med * 1e3, 3),
                                     checkpoints=ckpts, evals=evals, save=save)), flush=True)
