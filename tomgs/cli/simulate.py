"""`tomgs simulate`: a selection as a soft body dropped under gravity (XPBD on a tet cage)."""

from __future__ import annotations

import click

from tomgs.cli.common import (
    OUTPUT_HELP,
    OVER_HELP,
    SELECT_HELP,
    UsageError,
    device_option,
    overwrite_option,
    render_planned,
    selector_paths,
    user_errors,
)
from tomgs.cli.params import CELL, COORDINATES, FPS, Colour, Number, Numbers
from tomgs.errors import InputError, counted


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="vertex sequence to write (.npz); its cage is written beside it as NAME.cage.ply")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--render", "render_out", type=click.Path(path_type=str), default=None,
              help="also render the shot here (" + OUTPUT_HELP + ")")
@click.option("--over", type=click.Path(path_type=str), default=None, help="for --render: " + OVER_HELP)
@click.option("--drop", type=Number(-1e6, 1e6, what="scene units"), default=0.0, show_default=True,
              help="start raised this far against gravity (scene units)")
@click.option("--spin", type=Numbers((3,), Number(-1e4, 1e4, what="rad/s")), default=None,
              help="initial spin wx,wy,wz in rad/s about the centre of mass (world axes)")
@click.option("--velocity", type=COORDINATES, default=None, help="initial velocity vx,vy,vz in scene units per second")
@click.option("--size", type=Number(1e-6, 1e6, what="metres"), default=1.0, show_default=True,
              help="real size in metres of the selection's largest side: gravity is scaled so it falls like that")
@click.option("--stiffness", type=Number(1e-6, 1e9, what="a stiffness"), default=None,
              help="edge stiffness, the inverse of the XPBD compliance (1000: a stiff jelly, 100: a soft one)")
@click.option("--damping", type=Number(0.0, 1e6, what="per second"), default=None,
              help="velocity damping rate, 1/s")
@click.option("--frames", "num_frames", type=Number(1, 10**6, integer=True, what="frames"), default=None,
              help="frames to simulate (default: the scene's frame count; frame f is the scene's frame f)")
@click.option("--cell", type=CELL, default=None,
              help="cage cell size in scene units; default: 1/8 of the selection's largest extent")
@device_option
@click.option("--background", type=Colour(), default=None,
              help="r,g,b in [0, 1] for --render; default: the scene's, else black")
@click.option("--fps", type=FPS, default=None,
              help="frames per second of the shot and the video; default: the scene's, else 25")
@overwrite_option
@user_errors
def simulate(scene, output, selectors, render_out, over, drop, spin, velocity, size, stiffness, damping, num_frames,
             cell, device, background, fps, overwrite):
    """Drop, throw or spin the Gaussians of SCENE that --select picks as a soft body: a tet cage is
    built over them and simulated (XPBD, floor under the lowest point); frame f of the shot
    replaces the selection in the scene's frame f. Replay or re-render it with `tomgs tets import`.

    \b
    Examples:
      tomgs simulate scene.ply --select sphere:0,0,3,0.5 --drop 0.5 -o fall.npz --render fall.mp4
      tomgs simulate scene.ply --select mask:camel_masks/ --spin 0,3,0 --velocity 0,-2,0 -o toss.npz
      tomgs tets import scene.ply toss.cage.ply toss.npz -o toss.mp4
      tomgs simulate fg.ply --drop 0.25 -o drop.npz --render drop.mp4 --over bg.ply
    """
    from tomgs.outputs import check_distinct, check_file_output
    from tomgs.cli.preflight import check_device, check_render, check_scene, check_selectors

    if not output.lower().endswith(".npz"):
        raise UsageError(f"-o {output}: the shot is a vertex sequence, an .npz")
    if over and not render_out:
        raise UsageError("--over is what the render goes over: give --render too")
    cage_path = output[:-4] + ".cage.ply"
    check_distinct({"-o": output, "its cage": cage_path, "--render": render_out},
                   {"SCENE": scene, "--over": over, "--select": selector_paths(selectors)})
    check_file_output(output, overwrite, what="vertex sequence")
    check_file_output(cage_path, overwrite, what="cage")
    check_device(device)
    check_selectors(selectors)
    cameras, _ = check_scene(scene)
    if render_out:
        check_render(render_out, cameras, None, overwrite, over=over)

    from tomgs.edit.cage import shot_config, simulate_selection
    from tomgs.edit.selection import select
    from tomgs.edit.transforms import sequence_clouds
    from tomgs.io.scene import load_scene
    from tomgs.io.tets import save_sequence, save_tets
    from tomgs.render.jobs import plan_render, render_defaults
    from tomgs.runtime import resolve_device

    dev = resolve_device(device)
    loaded = load_scene(scene)
    cams = loaded.cameras
    frames = len(cams) if num_frames is None else num_frames
    if frames > len(cams):
        raise InputError(f"--frames {frames}: the scene has {len(cams)} frames, and frame f of the shot is "
                         f"rendered with the scene's frame f; simulate at most {len(cams)}")
    plan = plan_render(render_out, cams, None, device, background, overwrite,
                       only=set(range(frames)), over=over, name=scene) if render_out else None
    indices = select(loaded.model, cams, selectors)
    config = shot_config(loaded.model, indices, frames, fps or render_defaults(loaded.info)[1], size, drop, spin,
                         velocity, stiffness, damping)
    cage, vertices = simulate_selection(loaded.model, indices, config, cell, device=str(dev))
    save_tets(cage_path, cage)
    save_sequence(output, vertices, frames=cams.frame_indices[:frames])
    click.echo(f"{output}: {counted(len(vertices), 'frame')} of {len(indices):,} Gaussians on a cage of "
               f"{len(cage.tets):,} tets ({cage_path})")
    if plan is not None:
        clouds = sequence_clouds(loaded.model, cage, vertices, {k: k for k in range(frames)})
        render_planned(loaded, clouds, plan, fps)
