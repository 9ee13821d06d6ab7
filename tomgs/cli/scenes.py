"""`tomgs demo`, `tomgs example`, `tomgs render` and `tomgs info`: scenes out and about."""

from __future__ import annotations

from pathlib import Path

import click

from tomgs.cli import (
    OUTPUT_HELP,
    UsageError,
    device_option,
    main,
    overwrite_option,
    parse_background,
    progress_bar,
    render_options,
    render_planned,
    scene_cameras_option,
    user_errors,
)
from tomgs.jobs import plan_render, render_frames


def _parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 320x180, got {text!r}") from None
    from tomgs.cameras import MAX_SIDE

    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise UsageError(f"--size sides must be 1..{MAX_SIDE} pixels, got {text!r}")
    return width, height


@main.command()
@click.option("-o", "--output", default="demo.mp4", show_default=True, type=click.Path(path_type=str),
              help="an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames")
@click.option("--frames", "num_frames", default=48, show_default=True, type=click.IntRange(1, 10000))
@click.option("--size", default="320x180", show_default=True, help="WIDTHxHEIGHT in pixels")
@device_option
@overwrite_option
@user_errors
def demo(output, num_frames, size, device, overwrite):
    """Render the bundled example scene: static Gaussians whose opacity fades in and out over
    time, so a ball travels across a room although no Gaussian moves.

    \b
    Examples:
      tomgs demo                        # demo.mp4, 48 frames at 320x180
      tomgs demo -o frames/ --size 854x480 --device cuda
    """
    from tomgs.demo import demo_scene
    from tomgs.io.writer import check_output
    from tomgs.render import resolve_device

    width, height = _parse_size(size)
    check_output(output, overwrite)
    dev = resolve_device(device)
    gaussians, cams = demo_scene(num_frames, width, height)
    with progress_bar(num_frames, "render") as progress:
        report = render_frames(output, gaussians, cams, range(num_frames), background=(0.05, 0.05, 0.08),
                               device=dev, fps=24.0, what=f"at {width}x{height}", overwrite=overwrite,
                               progress=progress)
    click.echo(report.summary())


@main.command()
@click.argument("names", nargs=-1, metavar="[NAME]...")
@user_errors
def example(names):
    """Print the installed path of each bundled example file NAME; with none, list them.

    \b
    Examples:
      tomgs example                                       # what is bundled
      tomgs fit "$(tomgs example bunny.mp4)" -o bunny.ply --budget 240
    """
    from tomgs.demo import EXAMPLE_FILES, example_file

    if not names:
        for name, what in EXAMPLE_FILES.items():
            click.echo(f"{name:22s} {what}")
        return
    for name in names:
        click.echo(example_file(name))


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str), help=OUTPUT_HELP)
@click.option("--layer", "layer_paths", multiple=True, type=click.Path(path_type=str),
              help="a scene to composite over SCENE (e.g. a foreground from `fit --layer foreground`), each "
                   "with its own cameras at the same frames; repeat for more, the last in front")
@render_options
@scene_cameras_option
@user_errors
def render(scene, frames, output, device, background, fps, layer_paths, overwrite, cameras_path):
    """Render frames of SCENE (a .ply from `tomgs fit`) from its own cameras at their frame times.

    \b
    Examples:
      tomgs render scene.ply -o scene.mp4
      tomgs render scene.ply --frames 0:80 -o frames/ --device cuda
      tomgs render bg.ply --layer fg.ply -o out.mp4     # foreground over background
      tomgs render edited.ply --cameras cams/cameras.json -o out.mp4   # re-saved by SuperSplat
    """
    from tomgs.io.scene import load_scene
    from tomgs.layers import check_layers

    loaded = load_scene(scene, cameras=cameras_path)
    layers = [load_scene(path) for path in layer_paths]
    check_layers(loaded.cameras, [layer.cameras for layer in layers], list(layer_paths))
    plan = plan_render(output, loaded.cameras, frames, device, parse_background(background), overwrite)
    render_planned(loaded, loaded.model.render_inputs(), plan, fps,
                  layers=[(layer.model.render_inputs(), layer.cameras) for layer in layers])


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--plot", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="write a PNG histogram of temporal scales (log axis) here")
@click.option("--json", "as_json", is_flag=True, help="print the numbers as JSON instead of text")
@scene_cameras_option
@overwrite_option
@user_errors
def info(scene, plot, as_json, cameras_path, overwrite):
    """Counts, time coverage, temporal scales and opacities of SCENE (a .ply from `tomgs fit`).

    \b
    Examples:
      tomgs info scene.ply
      tomgs info scene.ply --plot sigmas.png       # histogram of temporal scales
      tomgs info scene.ply --json | jq .gaussians
    """
    import json

    from tomgs.io.scene import load_scene
    from tomgs.outputs import check_file_output
    from tomgs.summary import (
        check_png_path,
        format_summary,
        plot_temporal_scales,
        summarize,
    )

    if plot is not None:
        check_file_output(check_png_path(plot), overwrite, what="plot")
    loaded = load_scene(scene, cameras=cameras_path)
    summary = summarize(loaded, scene)
    if plot is not None:
        plot_temporal_scales(loaded, plot)
    click.echo(json.dumps(summary, indent=1) if as_json else format_summary(summary))
    if plot is not None and not as_json:
        click.echo(f"{plot}: histogram of temporal scales")


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help="the static scene: .ply (INRIA 3DGS), .splat (antimatter15) or .spz (Niantic)")
@click.option("--frame", type=int, default=None, help="the moment: a frame number of the scene (as render --frames)")
@click.option("--time", "clip_time", type=float, default=None, help="the moment: clip time in [0, 1]")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None,
              help="SH degree written (default the scene's; 3 pads zeros, for SIBR and INRIA's loader)")
@click.option("--layer", "layer_paths", multiple=True, type=click.Path(path_type=str),
              help="a scene composited over SCENE (as render --layer), joined into the static scene in front")
@click.option("--cameras-out", type=click.Path(path_type=str), default=None,
              help="a folder for the clip's cameras: cameras.json (tomgs), transforms.json (nerfstudio) and "
                   "sparse/0/ (COLMAP text)")
@scene_cameras_option
@overwrite_option
@user_errors
def export(scene, output, frame, clip_time, sh_degree, layer_paths, cameras_out, cameras_path, overwrite):
    """Hand one moment of SCENE to static 3DGS tools: the Gaussians alive at --frame K or --time T,
    their opacity at that moment baked in, temporal fields and cameras left out. With
    --cameras-out, also the clip's cameras, so other tools render the same views.

    \b
    Examples:
      tomgs export scene.ply --frame 40 -o frame40.ply          # SuperSplat, gsplat, open3d ...
      tomgs export scene.ply --time 0.5 -o mid.splat            # antimatter15/splat viewers
      tomgs export scene.ply --frame 40 -o f40.ply --sh-degree 3   # SIBR, INRIA's loader
      tomgs export bg.ply --layer fg.ply --frame 10 -o both.spz
      tomgs export scene.ply --cameras-out cams/                # COLMAP + transforms.json only
    """
    from tomgs.export import CAMERA_FILES, moment_with_layers, pick_moment, write_cameras
    from tomgs.io.scene import load_scene
    from tomgs.io.splats import FORMATS, write_static
    from tomgs.outputs import check_file_output, check_folder_output

    if output is None and cameras_out is None:
        raise UsageError("give -o OUT (.ply, .splat or .spz) for the static scene, --cameras-out DIR, or both")
    if output is not None:
        if Path(output).suffix.lower() not in FORMATS:
            raise UsageError(f"-o {output}: unknown format {Path(output).suffix or '(no extension)'!r}; the static "
                             f"scene is one of {', '.join(FORMATS)}")
        if frame is None and clip_time is None:
            raise UsageError("give the moment to export: --frame K (a frame number of the scene) or --time T")
        check_file_output(output, overwrite, what="static scene")
    elif frame is not None or clip_time is not None or layer_paths or sh_degree is not None:
        raise UsageError("--frame, --time, --layer and --sh-degree choose what goes into -o OUT: give -o too")
    if cameras_out is not None:
        check_folder_output(cameras_out, lambda name: name in CAMERA_FILES, overwrite)
    loaded = load_scene(scene, cameras=cameras_path)
    layers = [load_scene(path) for path in layer_paths]
    if output is not None:
        moment = pick_moment(loaded.cameras, frame, clip_time)
        gaussians = moment_with_layers(loaded, moment, layers, sh_degree)
        write_static(output, gaussians)
        total = len(loaded.model) + sum(len(layer.model) for layer in layers)
        click.echo(f"{output}: {len(gaussians):,} of {total:,} Gaussians alive at {moment.describe()}, "
                   f"opacity baked, SH degree {gaussians.sh_degree}")
    if cameras_out is not None:
        write_cameras(cameras_out, loaded.cameras)
        click.echo(f"{cameras_out}: {len(loaded.cameras)} cameras as cameras.json, transforms.json and sparse/0/ "
                   f"(COLMAP text), images named NNNNN.png as `tomgs render -o folder/` writes them")
