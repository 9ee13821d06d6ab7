"""`tomgs demo` and `tomgs example`: a synthetic scene, and the example files that ship with tomgs."""

from __future__ import annotations

import click

from tomgs.cli.common import device_option, overwrite_option, progress_bar, user_errors
from tomgs.cli.params import Number, Size


@click.command()
@click.option("-o", "--output", default="demo.mp4", show_default=True, type=click.Path(path_type=str),
              help="an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames")
@click.option("--frames", "num_frames", default=48, show_default=True,
              type=Number(1, 10000, integer=True, what="frames"), help="how many frames to render")
@click.option("--size", type=Size(), default="320x180", show_default=True, help="WIDTHxHEIGHT in pixels")
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
    from tomgs.io.writer import check_output
    from tomgs.cli.preflight import check_device

    width, height = size
    check_device(device)
    check_output(output, overwrite)

    from tomgs.demo import demo_scene
    from tomgs.render.jobs import render_frames
    from tomgs.runtime import resolve_device

    dev = resolve_device(device)
    gaussians, cams = demo_scene(num_frames, width, height)
    with progress_bar(num_frames, "render") as progress:
        report = render_frames(output, gaussians, cams, range(num_frames), background=(0.05, 0.05, 0.08),
                               device=dev, fps=24.0, what=f"at {width}x{height}", overwrite=overwrite,
                               progress=progress)
    click.echo(report.summary())


@click.command()
@click.argument("names", nargs=-1, metavar="[NAME]...")
@user_errors
def example(names):
    """Print the installed path of each bundled example file NAME; with none, list them.

    \b
    Examples:
      tomgs example                                       # what is bundled
      tomgs fit "$(tomgs example ball.mp4)" -o ball.ply --budget 240
    """
    from tomgs.data import EXAMPLE_FILES, example_file

    if not names:
        for name, what in EXAMPLE_FILES.items():
            click.echo(f"{name:22s} {what}")
        return
    for name in names:
        click.echo(example_file(name))
