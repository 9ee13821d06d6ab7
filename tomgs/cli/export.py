"""`tomgs export`: one moment of a scene as a static splat file, and its cameras for other tools."""

from __future__ import annotations

from pathlib import Path

import click

from tomgs.cli.common import UsageError, overwrite_option, scene_cameras_option, user_errors
from tomgs.cli.params import SH_DEGREE, Number


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", type=click.Path(path_type=str), default=None,
              help="the static scene: .ply (INRIA 3DGS), .splat (antimatter15), .spz (Niantic) or .sog (PlayCanvas)")
@click.option("--frame", type=Number(0, 2**31 - 1, integer=True, what="a frame number"), default=None,
              help="the moment: a frame number of the scene (as render --frames)")
@click.option("--time", "clip_time", type=Number(0.0, 1.0, what="clip time"), default=None,
              help="the moment: clip time in [0, 1]")
@click.option("--sh-degree", type=SH_DEGREE, default=None,
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
      tomgs export scene.tsog --frame 40 -o f40.sog             # SuperSplat, PlayCanvas (SOG)
      tomgs export scene.ply --frame 40 -o f40.ply --sh-degree 3   # SIBR, INRIA's loader
      tomgs export bg.ply --layer fg.ply --frame 10 -o both.spz
      tomgs export scene.ply --cameras-out cams/                # COLMAP + transforms.json only
    """
    from tomgs.outputs import check_distinct, check_file_output, check_folder_output
    from tomgs.cli.preflight import check_scene
    from tomgs.io.kinds import CAMERA_FILES, STATIC_FORMATS

    if output is None and cameras_out is None:
        raise UsageError("give -o OUT (.ply, .splat, .spz or .sog) for the static scene, --cameras-out DIR, or both")
    check_distinct({"-o": output, "--cameras-out": cameras_out,
                    "a file --cameras-out writes": [] if cameras_out is None else
                    [str(Path(cameras_out) / name) for name in CAMERA_FILES]},
                   {"SCENE": scene, "--layer": list(layer_paths), "--cameras": cameras_path})
    if output is not None:
        if Path(output).suffix.lower() not in STATIC_FORMATS:
            raise UsageError(f"-o {output}: unknown format {Path(output).suffix or '(no extension)'!r}; the static "
                             f"scene is one of {', '.join(STATIC_FORMATS)}")
        if frame is None and clip_time is None:
            raise UsageError("give the moment to export: --frame K (a frame number of the scene) or --time T")
        check_file_output(output, overwrite, what="static scene")
    elif frame is not None or clip_time is not None or layer_paths or sh_degree is not None:
        raise UsageError("--frame, --time, --layer and --sh-degree choose what goes into -o OUT: give -o too")
    if cameras_out is not None:
        check_folder_output(cameras_out, lambda name: name in CAMERA_FILES, overwrite)
    check_scene(scene, cameras=cameras_path)
    for path in layer_paths:
        check_scene(path)

    from tomgs.edit.export import moment_with_layers, pick_moment, write_cameras
    from tomgs.io.scene import load_scene
    from tomgs.io.splats import write_static

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
