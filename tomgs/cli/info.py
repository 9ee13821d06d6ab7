"""`tomgs info`: what a scene file holds, as text, JSON or a plot."""

from __future__ import annotations

import click

from tomgs.cli.common import overwrite_option, scene_cameras_option, user_errors


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--plot", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="write a PNG histogram of temporal scales (log axis) here")
@click.option("--json", "as_json", is_flag=True, help="print the numbers as JSON instead of text")
@scene_cameras_option
@overwrite_option
@user_errors
def info(scene, plot, as_json, cameras_path, overwrite):
    """Counts, file size (bytes, bits per pixel of the clip), time coverage, temporal scales and
    opacities of SCENE (a .ply or .tsog from `tomgs fit`).

    \b
    Examples:
      tomgs info scene.ply
      tomgs info scene.ply --plot sigmas.png       # histogram of temporal scales
      tomgs info scene.ply --json | jq .gaussians
    """
    import json

    from tomgs.outputs import check_distinct, check_file_output, check_png_path
    from tomgs.cli.preflight import check_scene

    check_distinct({"--plot": plot}, {"SCENE": scene, "--cameras": cameras_path})
    if plot is not None:
        check_file_output(check_png_path(plot), overwrite, what="plot")
    check_scene(scene, cameras=cameras_path)

    from tomgs.io.scene import load_scene
    from tomgs.io.summary import format_summary, plot_temporal_scales, summarize

    loaded = load_scene(scene, cameras=cameras_path)
    summary = summarize(loaded, scene)
    if plot is not None:
        plot_temporal_scales(loaded, plot)
    click.echo(json.dumps(summary, indent=1) if as_json else format_summary(summary))
    if plot is not None and not as_json:
        click.echo(f"{plot}: histogram of temporal scales")
