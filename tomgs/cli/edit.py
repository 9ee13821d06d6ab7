"""`tomgs edit`: move, rotate, scale, duplicate or remove a selection, optionally keyframed."""

from __future__ import annotations

import click

from tomgs.cli.common import (
    OUTPUT_HELP,
    OVER_HELP,
    SELECT_HELP,
    UsageError,
    is_scene_path,
    render_options,
    render_planned,
    selector_paths,
    user_errors,
)
from tomgs.cli.params import COORDINATES, SCALES, Number, Numbers
from tomgs.errors import counted


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="the edited scene (.ply, or .tsog compressed), or a video / PNG folder to render the edit to")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--translate", type=COORDINATES, default=None, help="move the selection by dx,dy,dz")
@click.option("--rotate", type=Numbers((3,), Number(-1e6, 1e6, what="degrees")), default=None,
              help="rotate the selection by rx,ry,rz degrees (about x, then y, then z)")
@click.option("--scale", type=SCALES, default=None, help="scale the selection by s or sx,sy,sz")
@click.option("--centre", type=COORDINATES, default=None,
              help="x,y,z that --rotate and --scale turn about; default: the "
              "selection's bounding-box centre")
@click.option("--duplicate", type=COORDINATES, default=None,
              help="keep the selection and add a copy offset by dx,dy,dz (moved "
              "by --translate/--rotate/--scale or --keyframes too)")
@click.option("--remove", is_flag=True, help="delete the selection")
@click.option("--keyframes", type=click.Path(path_type=str), default=None,
              help="JSON of keyframed transforms over time (docs/editing.md has the format); -o is then a video "
                   "or folder")
@click.option("--render", "render_out", type=click.Path(path_type=str), default=None,
              help="also render the edited scene here (" + OUTPUT_HELP + ")")
@click.option("--over", type=click.Path(path_type=str), default=None, help="when rendering: " + OVER_HELP)
@render_options
@user_errors
def edit(scene, output, selectors, translate, rotate, scale, centre, duplicate, remove, keyframes, render_out, over,
         frames, device, background, fps, overwrite):
    """Edit the Gaussians of SCENE that --select picks: move, rotate, scale, duplicate or remove
    them, or move them over time with --keyframes. Edits move each Gaussian's tetrahedron and
    rebuild the Gaussian from it; timing, opacity and colour are kept.

    \b
    Examples:
      tomgs edit scene.ply -o moved.ply --select box:-1,-1,2,1,1,4 --translate 0.5,0,0
      tomgs edit scene.ply -o two.ply --select sphere:0,0,3,0.5 --duplicate 1,0,0 --render two.mp4
      tomgs edit scene.ply -o clean.ply --select mask:camel_masks/ --remove
      tomgs edit scene.ply -o spin.mp4 --select sphere:0,0,3,0.5 --keyframes spin.json
      tomgs edit fg.ply -o big.ply --scale 1.3 --render big.mp4 --over bg.ply
    """
    from tomgs.outputs import check_distinct, check_file_output
    from tomgs.cli.preflight import check_existing, check_render, check_scene, check_selectors

    check_distinct({"-o": output, "--render": render_out},
                   {"SCENE": scene, "--keyframes": keyframes, "--over": over, "--select": selector_paths(selectors)})
    move = dict(translate=translate, rotate=rotate, scale=scale, centre=centre, duplicate=duplicate)
    rigid = any(move[k] is not None for k in ("translate", "rotate", "scale"))
    if keyframes and (rigid or remove):
        raise UsageError("--keyframes gives the motion: leave out --translate, --rotate, --scale and --remove")
    if not (rigid or remove or keyframes or move["duplicate"]):
        raise UsageError("nothing to do: give --translate, --rotate, --scale, --duplicate, --remove or --keyframes")
    if is_scene_path(output) == bool(keyframes):
        raise UsageError(f"-o {output}: " + ("a time-varying edit (--keyframes) is rendered: give a video or a "
                                             "folder, not a scene file" if keyframes else
                                             "use a .ply or .tsog to write the edited scene, or --keyframes to "
                                             "render"))
    if render_out and not is_scene_path(output):
        raise UsageError("--render goes with a scene output (.ply or .tsog); -o already renders")
    if over and not (render_out or keyframes):
        raise UsageError("--over is what the render goes over: give --render (or --keyframes with a video -o)")
    check_selectors(selectors)  # the arguments' mistakes before the scene is read
    cameras, _ = check_scene(scene)
    if keyframes:
        check_existing(keyframes, "--keyframes: file")
    else:
        check_file_output(output, overwrite, what="edited scene")
    video = output if keyframes else render_out
    if video:
        check_render(video, cameras, frames, overwrite, over=over, device=device)

    from tomgs.edit.transforms import edit_scene, keyframed_clouds, load_keyframes
    from tomgs.io.scene import load_scene, save_scene
    from tomgs.render.jobs import plan_render

    loaded = load_scene(scene)
    plan = plan_render(video, loaded.cameras, frames, device, background, overwrite, over=over,
                       name=scene) if video else None
    keys = load_keyframes(keyframes, loaded.cameras) if keyframes else None
    edited, rows = edit_scene(loaded, selectors, remove=remove, **move)
    if keys is not None:
        render_planned(edited, keyframed_clouds(edited.model, edited.cameras, rows, keys), plan, fps)
        return
    save_scene(output, edited.model, edited.cameras, edited.info)
    what = "removed" if remove else ("duplicated" if move["duplicate"] else "edited")
    click.echo(f"{output}: {edited.info['edits'][-1]['selected']:,} Gaussians {what}; {len(edited.model):,} "
               f"Gaussians, {counted(len(edited.cameras), 'frame')}")
    if plan is not None:
        render_planned(edited, edited.model.render_inputs(), plan, fps)
