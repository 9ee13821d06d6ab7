"""The `tomgs` command line: a thin click layer that parses, calls the library, and prints."""

from __future__ import annotations

import click

from tomgs import __version__


class UsageError(click.ClickException):
    """A bad input: clear message, exit code 2, nothing written."""

    exit_code = 2


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tomgs")
def main() -> None:
    """Editable video as static 3D Gaussians with temporal opacity (TOM-GS)."""


@main.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="cameras JSON to write (schema in tomgs.cameras)")
@click.option("--masks", type=click.Path(path_type=str), default=None,
              help="folder of masks, one per source frame (white = moving, ignored for poses)")
@click.option("--frames", default=None, help="frame range start:stop:step, e.g. 0:80 or ::2")
@click.option("--method", default="auto", show_default=True,
              help="auto, identity, a cameras .json / AnyCam c2w .npy / COLMAP text folder, or an .onnx model")
@click.option("--focal", type=float, default=None, help="focal length in pixels of the (resized) frames")
@click.option("--max-side", type=int, default=None, help="resize frames so that max(W, H) <= N")
def poses(video, output, masks, frames, method, focal, max_side):
    """Estimate per-frame cameras of VIDEO (a video file or a folder of frames)."""
    from tomgs.io import InputError, read_video
    from tomgs.poses import estimate_cameras

    try:
        clip = read_video(video, frames=frames, max_side=max_side, masks=masks)
        with click.progressbar(length=2 * len(clip), label="poses", show_eta=True, show_percent=True) as bar:
            def progress(done, total):
                bar.update(done - bar.pos)

            cams, _, _, report = estimate_cameras(clip, method=method, focal=focal, progress=progress)
        cams.save(output)
    except InputError as e:
        raise UsageError(str(e)) from None
    for note in report.notes:
        click.echo(f"  note: {note}")
    click.echo(f"{output}: {report.summary()}")


@main.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="scene file to write (.ply); a .csv log and a .psnr.png plot are written beside it")
@click.option("--preset", default="default", show_default=True, type=click.Choice(["default", "paper", "quick"]),
              help="default: tuned for speed; paper: 80k iterations, densify to 60k; quick: a few hundred")
@click.option("--iterations", type=click.IntRange(1), default=None, help="override the preset's iteration count")
@click.option("--frames", default=None, help="frame range start:stop:step, e.g. 0:80")
@click.option("--max-side", type=click.IntRange(16), default=None, help="resize frames so that max(W, H) <= N")
@click.option("--masks", type=click.Path(path_type=str), default=None, help="folder of masks (moving content)")
@click.option("--poses", default="auto", show_default=True,
              help="auto, identity, or a cameras .json / AnyCam .npy / COLMAP folder / .onnx model")
@click.option("--focal", type=float, default=None, help="focal length in pixels, if known")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
@click.option("--cap", "max_gaussians", type=click.IntRange(1), default=None, help="most Gaussians (default 10M)")
@click.option("--budget", "max_seconds", type=click.FloatRange(min=1.0), default=None,
              help="stop after this many seconds of training (schedules follow the budget)")
@click.option("--sampling", type=click.Choice(["inverse_psnr", "uniform"]), default=None)
@click.option("--static", "static_3dgs", is_flag=True, help="ablation: no temporal opacity (static 3DGS)")
@click.option("--opacity-reset", type=click.IntRange(0), default=None, help="ablation: reset opacities every N")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None, help="view-dependent colour (default 0)")
@click.option("--seed", type=int, default=None)
@click.option("--resume", is_flag=True, help="continue from the checkpoint beside OUTPUT")
@click.option("--layer", type=click.Choice(["background", "foreground"]), default=None,
              help="fit one layer (needs --masks): the pixels outside the masks, or the masked object on a plane")
@click.option("--mask-dilation", type=click.IntRange(0), default=2, show_default=True,
              help="background layer: grow the masks by this many pixels before leaving them out")
def fit(video, output, preset, iterations, frames, max_side, masks, poses, focal, device, max_gaussians, max_seconds,
        sampling, static_3dgs, opacity_reset, sh_degree, seed, resume, layer, mask_dilation):
    """Fit a TOM-GS scene to VIDEO (a video file or a folder of frames).

    \b
    Examples:
      tomgs fit clip.mp4 -o scene.ply
      tomgs fit frames/ -o scene.ply --masks masks/ --frames 0:80 --max-side 854 --device cuda
      tomgs fit clip.mp4 -o scene.ply --resume          # after Ctrl-C
      tomgs fit frames/ --masks masks/ --layer background -o bg.ply
      tomgs fit frames/ --masks masks/ --layer foreground -o fg.ply
    """
    from tomgs.io import InputError
    from tomgs.render import RenderError
    from tomgs.train import fit as fit_scene
    from tomgs.train import output_paths
    from tomgs.train import preset as make_config

    overrides = dict(iterations=iterations, max_gaussians=max_gaussians, max_seconds=max_seconds, sampling=sampling,
                     opacity_reset_interval=opacity_reset, sh_degree=sh_degree, seed=seed)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if static_3dgs:
        overrides["temporal"] = False
    config = make_config(preset, **overrides)
    bar = click.progressbar(length=config.iterations, label="fit", show_eta=True, show_percent=True,
                            item_show_func=lambda row: row and (
                                f"PSNR {row['train_psnr']} dB, {row['gaussians']:,} Gaussians, "
                                f"{row['iteration'] / max(row['wall_s'], 1e-9):.0f} it/s"))
    try:
        with bar:
            def progress(row):
                bar.update(row["iteration"] - bar.pos, row)

            result = fit_scene(video, output, config, masks=masks, frames=frames, max_side=max_side, poses=poses,
                               focal=focal, device=device, resume=resume, progress=progress, layer=layer,
                               mask_dilation=mask_dilation)
    except (InputError, RenderError) as e:
        raise UsageError(str(e)) from None
    except KeyboardInterrupt:
        click.echo(f"\ninterrupted: checkpoint kept at {output_paths(output)['checkpoint']}; "
                   f"continue with --resume", err=True)
        raise SystemExit(130) from None
    paths = output_paths(output)
    click.echo(f"{output}: {len(result.model):,} Gaussians, {result.iterations} iterations in {result.seconds:.1f} s, "
               f"full-clip PSNR {result.clip_psnr:.2f} dB")
    click.echo(f"  error against run time: {paths['csv']} and {paths['plot']}")
    for note in result.notes:
        click.echo(f"  note: {note}")


@main.command("eval")
@click.argument("scene", type=click.Path(path_type=str))
@click.argument("video", type=click.Path(path_type=str))
@click.option("--lpips", "lpips_weights", type=click.Path(path_type=str), default=None,
              help="LPIPS AlexNet weights (.npz); default $TOMGS_LPIPS_WEIGHTS, else LPIPS is left out")
@click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
              help="also write per-frame and mean metrics as JSON to this file ('-' for stdout)")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
def evaluate_command(scene, video, lpips_weights, json_out, device):
    """Compare SCENE, rendered at every frame it was fitted on, with VIDEO: PSNR and SSIM per frame
    and on average, as the peers compute them (float renders, 11x11 Gaussian SSIM); LPIPS when its
    weights are given.

    \b
    Examples:
      tomgs eval scene.ply clip.mp4
      tomgs eval scene.ply frames/ --lpips alexnet-lpips-v0.1.npz --json metrics.json
    """
    import json

    from tomgs.io import InputError
    from tomgs.io.scene import load_scene
    from tomgs.io.video import read_video_for
    from tomgs.metrics import LPIPS, default_lpips_weights, evaluate
    from tomgs.render import RenderError, resolve_device

    try:
        dev = resolve_device(device)
        loaded = load_scene(scene, device=dev)
        frames = read_video_for(video, loaded.cameras)
        weights = lpips_weights or default_lpips_weights()
        lpips = LPIPS(weights, device=dev) if weights else None
        report = evaluate(loaded.model, loaded.cameras, frames, lpips=lpips, device=dev)
    except (InputError, RenderError) as e:
        raise UsageError(str(e)) from None
    except ValueError as e:  # LPIPS weights that do not load
        raise UsageError(str(e)) from None
    for k, p, s in zip(report.frames, report.psnr, report.ssim):
        click.echo(f"  frame {int(loaded.cameras.frame_indices[k]):5d}: PSNR {p:6.2f} dB  SSIM {s:.4f}")
    click.echo(f"{scene}: {report.summary()}" + ("" if lpips else " (LPIPS left out: no weights given)"))
    if json_out:
        text = json.dumps(_finite_or_null(report.to_dict()), indent=1)  # a perfect frame's PSNR is inf
        if json_out == "-":
            click.echo(text)
        else:
            with open(json_out, "w") as f:
                f.write(text)


def _finite_or_null(value):
    """JSON has no infinity: non-finite floats become null, recursively."""
    import math

    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(v) for v in value]
    return value


def _parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 320x180, got {text!r}") from None
    if width < 1 or height < 1:
        raise UsageError(f"--size must be positive, got {text!r}")
    return width, height


@main.command()
@click.option("-o", "--output", default="demo.mp4", show_default=True, type=click.Path(path_type=str),
              help="an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames")
@click.option("--frames", "num_frames", default=48, show_default=True, type=click.IntRange(1, 10000))
@click.option("--size", default="320x180", show_default=True, help="WIDTHxHEIGHT in pixels")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
def demo(output, num_frames, size, device):
    """Render the bundled example scene: static Gaussians whose opacity fades in and out over
    time, so a ball travels across a room although no Gaussian moves.

    \b
    Examples:
      tomgs demo                        # demo.mp4, 48 frames at 320x180
      tomgs demo -o frames/ --size 854x480 --device cuda
    """
    from tomgs.demo import demo_scene
    from tomgs.io import InputError
    from tomgs.render import RenderError, resolve_device

    width, height = _parse_size(size)
    try:
        dev = resolve_device(device)
        gaussians, cams = demo_scene(num_frames, width, height)
        _render_to(output, gaussians, cams, range(num_frames), background=(0.05, 0.05, 0.08), device=dev, fps=24.0,
                   what=f"at {width}x{height}")
    except (InputError, RenderError) as e:
        raise UsageError(str(e)) from None


def _render_to(output, gaussians, cams, positions, background, device, fps: float, what: str, layers=()) -> None:
    """Render frames `positions` of `cams` to `output` (video or PNG folder) with a progress bar,
    `layers` ((gaussians, cameras) pairs) composited over them, then report the frame rate and how
    many Gaussians each frame skipped as dead."""
    import time

    import numpy as np

    from tomgs.io import write_frames
    from tomgs.layers import render_layers

    positions = list(positions)
    alive = []
    start = time.perf_counter()

    def images():
        sequence = render_layers(gaussians, cams, positions, layers, background=background, device=device)
        with click.progressbar(sequence, length=len(positions), label="render") as bar:
            for _, image, meta in bar:
                alive.append(int(meta["n_alive"]))
                yield (image.numpy() * 255.0 + 0.5).astype(np.uint8)

    count = write_frames(images(), output, fps=fps)
    seconds = time.perf_counter() - start
    total = sum(g["means"].shape[0] for g in [gaussians, *(g for g, _ in layers)])
    click.echo(f"{output}: {count} frames {what} on {device} in {seconds:.1f} s ({count / seconds:.1f} fps)")
    click.echo(f"  {total:,} Gaussians; alive per frame {min(alive):,}..{max(alive):,}: only those alive near "
               f"each frame's time were projected")


def _parse_background(text: str | None):
    """'r,g,b' in [0, 1] -> tuple, or None."""
    if text is None:
        return None
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise UsageError(f"--background must be three numbers in [0, 1] like 0,0,0 or 1,1,1, got {text!r}")
    return rgb


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--frames", default=None, help="frame range start:stop:step in the scene's frame numbers, e.g. 0:80")
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames")
@click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
@click.option("--background", default=None,
              help="r,g,b in [0, 1]; default: the scene's (info \"background\"), else black")
@click.option("--fps", type=click.FloatRange(min=0.1), default=None,
              help="frame rate of a video output; default: the scene's (info \"fps\"), else 25")
@click.option("--layer", "layer_paths", multiple=True, type=click.Path(path_type=str),
              help="a scene to composite over SCENE (e.g. a foreground from `fit --layer foreground`), each "
                   "with its own cameras at the same frames; repeat for more, the last in front")
def render(scene, frames, output, device, background, fps, layer_paths):
    """Render frames of SCENE (a .ply from `tomgs fit`) from its own cameras at their frame times.

    \b
    Examples:
      tomgs render scene.ply -o scene.mp4
      tomgs render scene.ply --frames 0:80 -o frames/ --device cuda
      tomgs render bg.ply --layer fg.ply -o out.mp4     # foreground over background
    """
    from tomgs.io import InputError
    from tomgs.io.scene import load_scene, render_defaults, select_frames
    from tomgs.layers import check_layers
    from tomgs.render import RenderError, resolve_device

    rgb = _parse_background(background)
    try:
        dev = resolve_device(device)
        loaded = load_scene(scene)
        cams = loaded.cameras
        layers = [load_scene(path) for path in layer_paths]
        check_layers(cams, [layer.cameras for layer in layers], list(layer_paths))
        positions = select_frames(cams, frames)
        numbers = cams.frame_indices[positions]
        default_rgb, default_fps = render_defaults(loaded.info)
        _render_to(output, loaded.model.render_inputs(), cams, positions.tolist(), background=rgb or default_rgb,
                   device=dev, fps=fps or default_fps, what=f"({numbers[0]}..{numbers[-1]}) at {cams.width}x{cams.height}",
                   layers=[(layer.model.render_inputs(), layer.cameras) for layer in layers])
    except (InputError, RenderError) as e:
        raise UsageError(str(e)) from None


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--plot", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="write a PNG histogram of temporal scales (log axis) here")
@click.option("--json", "as_json", is_flag=True, help="print the numbers as JSON instead of text")
def info(scene, plot, as_json):
    """Counts, time coverage, temporal scales and opacities of SCENE (a .ply from `tomgs fit`)."""
    import json

    from tomgs.io import InputError
    from tomgs.io.scene import check_png_path, format_summary, load_scene, plot_temporal_scales, summarize

    try:
        if plot is not None:
            check_png_path(plot)
        loaded = load_scene(scene)
        summary = summarize(loaded, scene)
        if plot is not None:
            plot_temporal_scales(loaded, plot)
    except InputError as e:
        raise UsageError(str(e)) from None
    click.echo(json.dumps(summary, indent=1) if as_json else format_summary(summary))
    if plot is not None and not as_json:
        click.echo(f"{plot}: histogram of temporal scales")


if __name__ == "__main__":
    main()
