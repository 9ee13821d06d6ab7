"""`tomgs render`: a scene (and its layers) to a video or PNG frames."""

from __future__ import annotations

import click

from tomgs.cli.common import OUTPUT_HELP, render_options, render_planned, scene_cameras_option, user_errors


@click.command()
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
    from tomgs.outputs import check_distinct
    from tomgs.cli.preflight import check_render, check_render_output, check_scene

    check_distinct({"-o": output}, {"SCENE": scene, "--layer": list(layer_paths), "--cameras": cameras_path})
    check_render_output(output, overwrite, device)  # the arguments' mistakes before the scene is read
    cameras, _ = check_scene(scene, cameras=cameras_path)
    for path in layer_paths:
        check_scene(path)
    check_render(output, cameras, frames, overwrite, device=device)

    from tomgs.io.scene import load_scene
    from tomgs.render.jobs import plan_render
    from tomgs.render.layers import check_layers

    loaded = load_scene(scene, cameras=cameras_path)
    layers = [load_scene(path) for path in layer_paths]
    check_layers(loaded.cameras, [layer.cameras for layer in layers], list(layer_paths))
    plan = plan_render(output, loaded.cameras, frames, device, background, overwrite)
    render_planned(loaded, loaded.model.render_inputs(), plan, fps,
                  layers=[(layer.model.render_inputs(), layer.cameras) for layer in layers])
