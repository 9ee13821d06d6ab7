"""What the benchmark scripts share: where a run's table goes and what it says about the run (command,
commit, device), timing helpers, the random scene of the rasterizer's benchmarks, tiny synthetic clips
for the `--smoke` modes, the arguments of the benchmarks over DAVIS clips, reading a fit's CSV log,
and the paper's DAVIS figures.

Every script of the suite imports this module and no other script of the suite.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]

# ----------------------------------------------------------------------------- a run's report


def git_commit() -> str | None:
    """The checkout's short commit, '+dirty' when tracked files differ from it; None outside git."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                                timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return (commit + "+dirty" if dirty else commit) or None


def environment(device, name: str, argv=None) -> dict:
    """What a table needs to be read again later: the command (`python -m benchmarks.<name>` and `argv`, by
    default this process's arguments), commit, device and library versions."""
    device = torch.device(device)
    args = sys.argv[1:] if argv is None else list(argv)
    now = datetime.datetime.now(datetime.timezone.utc)
    env = dict(command=shlex.join(["python", "-m", f"benchmarks.{name}", *map(str, args)]), commit=git_commit(),
               device=str(device), torch=torch.__version__, python=platform.python_version(), host=platform.node(),
               date_utc=now.isoformat(timespec="seconds"))
    if device.type == "cuda":
        env["gpu"] = torch.cuda.get_device_name(device)
    else:
        env["cpu"] = platform.processor() or platform.machine()
    try:
        import warp

        env["warp"] = warp.__version__
    except ImportError:
        env["warp"] = None
    return env


def output_folder(out, smoke: bool, name: str) -> Path:
    """The folder a run writes to: `out`; without it a fresh temporary folder for a smoke run, else
    bench_out/<name> (git ignores bench_out/)."""
    if out is None and smoke:
        return Path(tempfile.mkdtemp(prefix=f"tomgs-bench-{name}-"))
    folder = Path("bench_out") / name if out is None else Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def markdown_table(head: list[str], rows: list[list]) -> str:
    """A markdown table; floats at two decimals (three below 1), None as '-'."""
    def cell(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1 else f"{v:.2f}"
        return str(v)

    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def write_report(folder: Path, name: str, title: str, env: dict, body: str, data) -> Path:
    """`<folder>/<name>.md` (the title, command, commit and device, then `body`) and `<name>.json` (`env`
    and `data`); returns the markdown's path and prints it."""
    device = env.get("gpu") or env.get("cpu") or env["device"]
    text = (f"### {title}\n\ncommand: `{env['command']}`  \ncommit: {env['commit']}  \n"
            f"device: {device} ({env['device']}), torch {env['torch']}, warp {env['warp']}  \n"
            f"date: {env['date_utc']}\n\n{body.rstrip()}\n")
    path = folder / f"{name}.md"
    path.write_text(text)
    (folder / f"{name}.json").write_text(json.dumps(dict(env=env, results=data), indent=1, default=str) + "\n")
    print(text, flush=True)
    print(f"written to {path} and {path.with_suffix('.json')}", flush=True)
    return path


# ----------------------------------------------------------------------------- timing


def sync(device) -> None:
    """Wait for `device`'s queued work (nothing to wait for on a CPU)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def fastest(modes: dict, repeats: int, device) -> dict[str, float]:
    """Seconds of each mode's quickest call over `repeats` turns, the modes taking turns (a shared
    machine's load hits all alike; on a GPU machine one pass of a ~1 ms frame moves +-20% with the
    host), after one untimed turn (kernels loaded, buffers and bounds set)."""
    best = {name: math.inf for name in modes}
    for turn in range(repeats + 1):
        for name, run in modes.items():
            sync(device)
            start = time.perf_counter()
            run()
            sync(device)
            if turn:
                best[name] = min(best[name], time.perf_counter() - start)
    return best


# a kernel's name as reported: long enough to tell cub's sort kernels apart (their first 80
# characters are the same namespace)
KERNEL_NAME_CHARS = 140


def kernel_times(step, iters: int) -> dict[str, float]:
    """GPU milliseconds per call of `step`, by kernel name (torch profiler, which sees Warp's kernels
    too); empty on a machine without CUDA."""
    if not torch.cuda.is_available():
        return {}
    acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    with torch.profiler.profile(activities=acts) as prof:
        for _ in range(iters):
            step()
        torch.cuda.synchronize()
    per_kernel = defaultdict(float)
    events = prof.key_averages()
    # a record_function range also shows as a GPU range spanning its kernels: counted once, by its kernels
    host_ranges = {evt.key for evt in events if evt.device_type == torch.autograd.DeviceType.CPU}
    for evt in events:
        if evt.device_type == torch.autograd.DeviceType.CUDA and evt.device_time_total > 0 \
                and evt.key not in host_ranges:
            per_kernel[evt.key[:KERNEL_NAME_CHARS]] += evt.device_time_total / iters / 1e3
    return dict(per_kernel)


def render_modes(inputs: dict, cams, device: torch.device) -> tuple[dict, "tomgs.ClipRenderer"]:
    """(mode name -> a callable rendering every frame of `cams` from `inputs` (rasterize's keyword
    arguments of one cloud, on `device`), images left there, and the kept renderer that replays):
    - rasterize: frame by frame, each waiting for its counts;
    - sequence waiting: render_sequence, frames waiting for their counts;
    - sequence eager / sequence: a whole call (index and, from REPLAY_FRAMES frames, capture made by the
      call), its frames issued from Python / as render_sequence issues them;
    - kept eager / kept: a ClipRenderer kept across calls (index made once, in the untimed turn, and
      captured once it has rendered REPLAY_FRAMES frames), issued from Python / replayed."""
    import tomgs

    frames = list(range(len(cams)))
    viewmats, Ks = cams.viewmats(device), cams.Ks(device)

    def each_frame():
        for k in frames:
            tomgs.rasterize(**inputs, viewmat=viewmats[k], K=Ks[k], width=cams.width, height=cams.height,
                            t=float(cams.times[k]))

    def run(renderer_of):
        def go():
            for _ in renderer_of().frames(frames, to_cpu=False):
                pass
        return go

    def waiting():
        for _ in tomgs.render_sequence(inputs, cams, frames, device=device, to_cpu=False, pipelined=False):
            pass

    kept_eager = tomgs.ClipRenderer(inputs, cams, device=device, replay=False)
    kept = tomgs.ClipRenderer(inputs, cams, device=device)
    return {"rasterize": each_frame, "sequence waiting": waiting,
            "sequence eager": run(lambda: tomgs.ClipRenderer(inputs, cams, device=device, replay=False)),
            "sequence": run(lambda: tomgs.ClipRenderer(inputs, cams, device=device)),
            "kept eager": run(lambda: kept_eager), "kept": run(lambda: kept)}, kept


def scene_fps(scene_path: Path, device, repeats: int = 5) -> dict:
    """Frames per second over a scene file's clip, images left on the device, the quickest of `repeats`
    passes: `fps`, a ClipRenderer kept across passes (its alive index and captured frame made once, in
    the untimed first turn); `fps_call`, whole render_sequence calls (each building its own)."""
    import tomgs

    scene = tomgs.load_scene(scene_path, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    frames = list(range(len(scene.cameras)))
    kept = tomgs.ClipRenderer(inputs, scene.cameras, device=device)

    def each(frames_of):
        return lambda: [None for _ in frames_of()]

    modes = {"fps": each(lambda: kept.frames(frames, to_cpu=False)),
             "fps_call": each(lambda: tomgs.render_sequence(inputs, scene.cameras, frames, device=device,
                                                            to_cpu=False))}
    with torch.no_grad():
        best = fastest(modes, repeats, device)
    return {name: len(frames) / seconds for name, seconds in best.items()}


def host_profile(step, iters: int, device, top: int = 25) -> None:
    """Print the Python functions that cost host time over `iters` calls of `step` (cProfile; a wait for
    the device shows up as the time of the call that waited, e.g. `tolist`)."""
    import cProfile
    import pstats

    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(iters):
        step()
    sync(device)
    profiler.disable()
    pstats.Stats(profiler).sort_stats("tottime").print_stats(top)


# ----------------------------------------------------------------------------- the random scene

# Camera at the origin looking down +z (OpenCV), fx = fy = FOCAL_RATIO W, principal point at the centre;
# means z ~ U(3, 5), x = z TAN_X u, y = z TAN_Y v (u, v ~ U(-1, 1)): every centre inside the 16:9 frustum,
# the scene depending only on N and the seed. Scales U(0.002, 0.02), quaternions normalised Gaussian
# draws, opacity U(0, 1), RGB U(0, 1), t_means U(0, 1) (REFERENCES.md, "Speed anchors").
FOCAL_RATIO = 0.9
TAN_X = 0.5 / FOCAL_RATIO
TAN_Y = TAN_X * 9.0 / 16.0
STATIC_T_SCALE = 1e3  # a temporal sigma that keeps every Gaussian alive at every time of [0, 1]


def parse_count(text: str) -> int:
    """'5M', '250k', '2000' -> an int."""
    text = text.strip().lower()
    mult = {"k": 1_000, "m": 1_000_000}.get(text[-1:], 1)
    return int(round(float(text[:-1] if mult > 1 else text) * mult))


def parse_size(text: str) -> tuple[int, int]:
    """'854x480' -> (854, 480)."""
    w, h = text.lower().split("x")
    return int(w), int(h)


def random_scene(n: int, seed: int, device) -> dict[str, torch.Tensor]:
    """The random scene's means [n,3], quats [n,4], scales [n,3], opacities [n], colors [n,3], t_means [n]
    (no t_scales: `temporal_scales` or STATIC_T_SCALE give them), drawn on the CPU with a seeded generator
    so that every device sees the same scene."""
    g = torch.Generator().manual_seed(seed)

    def u(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float32)

    z = 3.0 + 2.0 * u(n)
    means = torch.stack([z * TAN_X * (2.0 * u(n) - 1.0), z * TAN_Y * (2.0 * u(n) - 1.0), z], -1)
    scales = 0.002 + 0.018 * u(n, 3)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float32)
    quats = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    scene = dict(means=means, quats=quats, scales=scales, opacities=u(n), colors=u(n, 3), t_means=u(n))
    return {k: v.to(device) for k, v in scene.items()}


def temporal_scales(opacities: torch.Tensor, alive_frac: float) -> torch.Tensor:
    """sigma [n] such that a exp(-d^2 / (2 sigma^2)) >= 1/255 exactly for |d| <= alive_frac / 2: each
    Gaussian alive over `alive_frac` of the clip (those with a <= 1/255 are dead at every time)."""
    log_ratio = torch.log(255.0 * opacities.double()).clamp_min(1e-6)
    return ((0.5 * alive_frac) / torch.sqrt(2.0 * log_ratio)).float()


def camera(width: int, height: int, device) -> tuple[torch.Tensor, torch.Tensor]:
    """(viewmat [4,4] identity, K [3,3]) of the random scene's camera."""
    f = FOCAL_RATIO * width
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], device=device)
    return torch.eye(4, device=device), K


# ----------------------------------------------------------------------------- tiny clips for --smoke


def demo_frames(frames: int, width: int, height: int, device="cpu"):
    """Yield `frames` frames of the demo scene (a room and a ball travelling across it, a camera that
    moves), uint8 [H, W, 3] each, rendered on `device`."""
    import tomgs
    from tomgs.demo import demo_scene

    gaussians, cams = demo_scene(num_frames=frames, width=width, height=height)
    with torch.no_grad():
        for _, image, _ in tomgs.render_sequence(gaussians, cams, background=(0.05, 0.05, 0.08), device=device):
            yield (image.numpy() * 255 + 0.5).astype(np.uint8)


def smoke_clip_folder(root: Path, name: str = "smoke", frames: int = 6, width: int = 48, height: int = 27) -> Path:
    """A clip in the DAVIS layout under `root`: `<name>/images/00000.png ...` and `<name>/masks/` (black:
    nothing moves on its own). Returns the clip's folder."""
    from PIL import Image

    clip = Path(root) / name
    (clip / "images").mkdir(parents=True, exist_ok=True)
    (clip / "masks").mkdir(exist_ok=True)
    for k, image in enumerate(demo_frames(frames, width, height)):
        Image.fromarray(image).save(clip / "images" / f"{k:05d}.png")
        Image.fromarray(np.zeros(image.shape[:2], np.uint8)).save(clip / "masks" / f"{k:05d}.png")
    return clip


def demo_model(frames: int, width: int, height: int):
    """(GaussianModel, Cameras) of the demo scene, SH degree 0."""
    import tomgs
    from tomgs.demo import demo_scene
    from tomgs.model import rgb_to_sh_dc

    g, cams = demo_scene(num_frames=frames, width=width, height=height)
    model = tomgs.GaussianModel(g["means"], g["quats"], torch.log(g["scales"]), torch.logit(g["opacities"]),
                                rgb_to_sh_dc(g["colors"]), torch.zeros(len(g["means"]), 0, 3), g["t_means"],
                                torch.log(g["t_scales"]), sh_degree=0)
    return model, cams


def smoke_scene(path: Path, frames: int = 8, width: int = 48, height: int = 27) -> Path:
    """The demo scene saved as a tomgs scene file at `path`."""
    import tomgs

    return Path(tomgs.save_scene(path, *demo_model(frames, width, height), {"fps": 24.0}))


def demo_video(path: Path, frames: int = 6, width: int = 48, height: int = 28, device="cpu") -> Path:
    """The demo scene as an H.264 MP4 at `path` (even sides), its frames rendered on `device` and
    streamed to the file."""
    from tomgs.io.writer import write_frames

    write_frames(demo_frames(frames, width, height, device), path, fps=24.0, overwrite=True)
    return Path(path)


# ----------------------------------------------------------------------------- benchmarks over DAVIS clips


def clip_parser(doc: str, name: str, minutes: float, smoke: str) -> argparse.ArgumentParser:
    """The arguments of a benchmark that fits DAVIS clips (davis, compact): the folder of clips, --clips,
    --minutes, --out, --set, --poses, --tag, --lpips, --device and --smoke (`smoke` says what it runs)."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", type=Path, nargs="?", help="folder holding <clip>/images and <clip>/masks")
    ap.add_argument("--clips", default="camel,cows,kite-surf")
    ap.add_argument("--minutes", type=float, default=minutes, help="wall-clock budget of each fit, poses included")
    ap.add_argument("--out", type=Path, default=None, help=f"default bench_out/{name}")
    ap.add_argument("--set", action="append", default=[], help="a TrainConfig override (JSON value), e.g. "
                                                               "--set max_gaussians=2000000")
    ap.add_argument("--poses", default="auto", help="auto (tracker with the DAVIS masks) or identity (ablation)")
    ap.add_argument("--tag", default="", help="a name for this run's files (ablations, sweeps)")
    ap.add_argument("--lpips", type=Path, help="LPIPS weights (alexnet-lpips-v0.1.npz or its folder)")
    ap.add_argument("--device", default="cuda", help="cuda; cpu for a dry run")
    ap.add_argument("--smoke", action="store_true",
                    help=f"a 6-frame synthetic clip at 48x27 on the CPU, {smoke}, identity poses; the table in a "
                         "temporary folder unless --out")
    return ap


def parse_clip_args(ap: argparse.ArgumentParser, argv, smoke_minutes: float) -> argparse.Namespace:
    """`ap`'s arguments; --smoke sets the CPU, identity poses, the smoke clip and `smoke_minutes`."""
    args = ap.parse_args(argv)
    if args.smoke:
        args.device, args.poses, args.clips, args.minutes = "cpu", "identity", "smoke", smoke_minutes
    elif args.root is None:
        ap.error("the folder of clips is required (or --smoke)")
    return args


def start_clip_run(args: argparse.Namespace, name: str, argv) -> tuple[Path, torch.device, dict, object, dict]:
    """(the output folder, the device, the TrainConfig overrides of --set, the LPIPS network or None, the
    run's environment) of a benchmark over clips; a smoke run's clip is made in the output folder."""
    import tomgs

    out = output_folder(args.out, args.smoke, name)
    if args.smoke:
        args.root = out / "clips"
        smoke_clip_folder(args.root, "smoke")
    device = torch.device(args.device)
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    lpips = tomgs.LPIPS(args.lpips, device=device) if args.lpips else None
    return out, device, overrides, lpips, environment(device, name, argv)


# ----------------------------------------------------------------------------- a fit's CSV log


# The paper's figures for the DAVIS clips (../shared/data/README.md): Table 2 at 480p for camel, cows and
# kite-surf, with SSIM and LPIPS from its training statistics; Table 3 (DNeRV protocol, 1920x960, so not
# directly comparable at 480p) for the other three, which give no LPIPS.
PAPER = {
    "camel": dict(psnr=35.28, ssim=0.967, lpips=0.035),
    "cows": dict(psnr=30.28, ssim=0.932, lpips=0.094),
    "kite-surf": dict(psnr=43.90, ssim=0.987, lpips=0.012),
    "blackswan": dict(psnr=38.38, ssim=0.968, lpips=None),
    "dog": dict(psnr=39.84, ssim=0.977, lpips=None),
    "car-shadow": dict(psnr=36.10, ssim=0.947, lpips=None),
}


def log_rows(path: Path) -> list[dict]:
    """The rows of a fit's CSV log (`tomgs fit`'s scene.csv)."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def psnr_at(rows: list[dict], seconds: float, offset: float = 0.0):
    """(the full-clip PSNR measured last at or before `seconds` of the whole fit, the frames it covers),
    the log's training seconds shifted by `offset` (what ran before training); (None, None) if none was
    measured by then."""
    best = (None, None)
    for row in rows:
        if row["clip_psnr"] and offset + float(row["wall_s"]) <= seconds:
            best = (float(row["clip_psnr"]), int(row["clip_frames"]) if row.get("clip_frames") else None)
    return best


def time_to(rows: list[dict], target: float, offset: float = 0.0):
    """Seconds of the whole fit at the first full-clip PSNR at or above `target` (None if never)."""
    for row in rows:
        if row["clip_psnr"] and float(row["clip_psnr"]) >= target:
            return offset + float(row["wall_s"])
    return None
