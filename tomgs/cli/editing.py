"""`tomgs edit`, `tomgs tets export|import` and `tomgs simulate`: editing a scene."""

from __future__ import annotations

import click

from tomgs.cli import (
    OUTPUT_HELP,
    OVER_HELP,
    SELECT_HELP,
    UsageError,
    device_option,
    is_scene_path,
    main,
    overwrite_option,
    parse_background,
    parse_numbers,
    render_options,
    render_planned,
    user_errors,
)
from tomgs.errors import InputError
from tomgs.jobs import plan_render


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="the edited scene (.ply), or a video / PNG folder to render the edit to")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--translate", default=None, help="move the selection by dx,dy,dz")
@click.option("--rotate", default=None, help="rotate the selection by rx,ry,rz degrees (about x, then y, then z)")
@click.option("--scale", default=None, help="scale the selection by s or sx,sy,sz")
@click.option("--centre", default=None, help="x,y,z that --rotate and --scale turn about; default: the "
              "selection's bounding-box centre")
@click.option("--duplicate", default=None, help="keep the selection and add a copy offset by dx,dy,dz (moved "
              "by --translate/--rotate/--scale or --keyframes too)")
@click.option("--remove", is_flag=True, help="delete the selection")
@click.option("--keyframes", type=click.Path(path_type=str), default=None,
              help="JSON of keyframed transforms over time (README \"Editing\"); -o is then a video or folder")
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
    from tomgs.edit.transforms import edit_scene, keyframed_clouds, load_keyframes
    from tomgs.io.scene import load_scene, save_scene
    from tomgs.outputs import check_file_output

    move = dict(translate=parse_numbers(translate, "--translate"), rotate=parse_numbers(rotate, "--rotate"),
                scale=parse_numbers(scale, "--scale", (1, 3)), centre=parse_numbers(centre, "--centre"),
                duplicate=parse_numbers(duplicate, "--duplicate"))
    if move["scale"] is not None and min(move["scale"]) <= 0:
        raise UsageError(f"--scale must be positive, got {scale!r}")
    rigid = any(move[k] is not None for k in ("translate", "rotate", "scale"))
    if keyframes and (rigid or remove):
        raise UsageError("--keyframes gives the motion: leave out --translate, --rotate, --scale and --remove")
    if not (rigid or remove or keyframes or move["duplicate"]):
        raise UsageError("nothing to do: give --translate, --rotate, --scale, --duplicate, --remove or --keyframes")
    if is_scene_path(output) == bool(keyframes):
        raise UsageError(f"-o {output}: " + ("a time-varying edit (--keyframes) is rendered: give a video or a "
                                             "folder, not a .ply" if keyframes else
                                             "use a .ply to write the edited scene, or --keyframes to render"))
    if render_out and not is_scene_path(output):
        raise UsageError("--render goes with a .ply output; -o already renders")
    if over and not (render_out or keyframes):
        raise UsageError("--over is what the render goes over: give --render (or --keyframes with a video -o)")
    if not keyframes:
        check_file_output(output, overwrite, what="edited scene")
    loaded = load_scene(scene)
    video = output if keyframes else render_out
    plan = plan_render(video, loaded.cameras, frames, device, parse_background(background), overwrite, over=over,
                       name=scene) if video else None
    keys = load_keyframes(keyframes, loaded.cameras) if keyframes else None
    edited, rows = edit_scene(loaded, selectors, remove=remove, **move)
    if keys is not None:
        render_planned(edited, keyframed_clouds(edited.model, edited.cameras, rows, keys), plan, fps)
        return
    save_scene(output, edited.model, edited.cameras, edited.info)
    what = "removed" if remove else ("duplicated" if move["duplicate"] else "edited")
    click.echo(f"{output}: {edited.info['edits'][-1]['selected']:,} Gaussians {what}; {len(edited.model):,} "
               f"Gaussians, {len(edited.cameras)} frames")
    if plan is not None:
        render_planned(edited, edited.model.render_inputs(), plan, fps)


@main.group()
def tets():
    """Gaussians as tetrahedra: export them (for Blender or a simulator), import moved vertices."""


@tets.command("export")
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="tets file to write (.ply, Blender axes)")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--cage", is_flag=True, help="a connected voxel cage with the Gaussians bound into it (for soft "
              "bodies) instead of one tet per Gaussian")
@click.option("--cell", type=click.FloatRange(min=0, min_open=True), default=None,
              help="cage cell size in scene units; default: 1/8 of the selection's largest extent")
@overwrite_option
@user_errors
def tets_export(scene, output, selectors, cage, cell, overwrite):
    """Write the Gaussians of SCENE that --select picks as tetrahedra (a PLY Blender imports:
    Z up, vertex order kept; README "Editing" has the format).

    \b
    Examples:
      tomgs tets export scene.ply -o tets.ply --select sphere:0,0,3,0.5
      tomgs tets export scene.ply -o cage.ply --select mask:camel_masks/ --cage --cell 0.05
    """
    from tomgs.edit.cage import make_tets
    from tomgs.edit.selection import select
    from tomgs.io.scene import load_scene
    from tomgs.io.tets import save_tets
    from tomgs.outputs import check_file_output

    if cell is not None and not cage:
        raise UsageError("--cell sets the cage's cell size: give --cage too")
    if not is_scene_path(output):
        raise UsageError(f"-o {output}: a tets file is a .ply")
    check_file_output(output, overwrite, what="tets file")
    loaded = load_scene(scene)
    indices = select(loaded.model, loaded.cameras, selectors)
    mesh = make_tets(loaded.model, indices, "cage" if cage else "gaussian", cell)
    save_tets(output, mesh)
    click.echo(f"{output}: {len(indices):,} Gaussians as {len(mesh.tets):,} tets over {len(mesh.vertices):,} "
               f"vertices ({mesh.kind})")


@tets.command("import")
@click.argument("scene", type=click.Path(path_type=str))
@click.argument("tets_file", metavar="TETS", type=click.Path(path_type=str))
@click.argument("sequence", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help=OUTPUT_HELP + "; or a .ply scene when SEQUENCE has one frame")
@click.option("--over", type=click.Path(path_type=str), default=None, help="when rendering: " + OVER_HELP)
@render_options
@user_errors
def tets_import(scene, tets_file, sequence, output, over, frames, device, background, fps, overwrite):
    """Carry the Gaussians of SCENE bound in TETS (from `tomgs tets export`) along the moved
    vertices of SEQUENCE (an .npz with vertices [F,V,3], a folder of PLY frames, or one PLY) and
    render the result, frame f of the sequence with the scene's frame f (or the .npz's 'frames').

    \b
    Examples:
      tomgs tets import scene.ply cage.ply sim.npz -o shot.mp4
      tomgs tets import scene.ply tets.ply blender_frames/ -o shot/ --frames 0:40
      tomgs tets import scene.ply tets.ply moved.ply -o edited.ply
      tomgs tets import fg.ply cage.ply sim.npz -o shot.mp4 --over bg.ply
    """
    from tomgs.edit.transforms import (
        check_bound,
        deformed_model,
        sequence_clouds,
        sequence_rows,
    )
    from tomgs.io.scene import load_scene, save_scene
    from tomgs.io.tets import load_sequence, load_tets
    from tomgs.outputs import check_file_output

    if is_scene_path(output):
        check_file_output(output, overwrite, what="scene")
    loaded = load_scene(scene)
    mesh = load_tets(tets_file)
    check_bound(loaded.model, mesh, tets_file)
    vertices, numbers = load_sequence(sequence, mesh, max_frames=len(loaded.cameras))
    if is_scene_path(output):
        if over is not None:
            raise InputError(f"--over is what a render goes over, but -o {output} writes a scene: render "
                             f"to a video or folder, or leave --over out")
        if len(vertices) != 1:
            raise InputError(f"-o {output}: a scene holds one pose but {sequence} has {len(vertices)} frames: "
                             f"render it to a video or folder instead")
        info = {**loaded.info, "edits": [*loaded.info.get("edits", []),
                                         {"tets": str(tets_file), "sequence": str(sequence)}]}
        save_scene(output, deformed_model(loaded.model, mesh, vertices[0]), loaded.cameras, info)
        click.echo(f"{output}: {len(mesh.gaussians):,} Gaussians moved by {sequence}")
        return
    rows = sequence_rows(loaded.cameras, len(vertices), numbers)
    plan = plan_render(output, loaded.cameras, frames, device, parse_background(background), overwrite, only=rows,
                       over=over, name=scene)
    render_planned(loaded, sequence_clouds(loaded.model, mesh, vertices, rows), plan, fps)


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="vertex sequence to write (.npz); its cage is written beside it as NAME.cage.ply")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--render", "render_out", type=click.Path(path_type=str), default=None,
              help="also render the shot here (" + OUTPUT_HELP + ")")
@click.option("--over", type=click.Path(path_type=str), default=None, help="for --render: " + OVER_HELP)
@click.option("--drop", type=float, default=0.0, show_default=True,
              help="start raised this far against gravity (scene units)")
@click.option("--spin", default=None, help="initial spin wx,wy,wz in rad/s about the centre of mass (world axes)")
@click.option("--velocity", default=None, help="initial velocity vx,vy,vz in scene units per second")
@click.option("--size", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="real size in metres of the selection's largest side: gravity is scaled so it falls like that")
@click.option("--stiffness", type=click.FloatRange(min=0, min_open=True), default=None,
              help="edge stiffness, the inverse of the XPBD compliance (1000: a stiff jelly, 100: a soft one)")
@click.option("--damping", type=click.FloatRange(min=0), default=None, help="velocity damping rate, 1/s")
@click.option("--frames", "num_frames", type=click.IntRange(1), default=None,
              help="frames to simulate (default: the scene's frame count; frame f is the scene's frame f)")
@click.option("--cell", type=click.FloatRange(min=0, min_open=True), default=None,
              help="cage cell size in scene units; default: 1/8 of the selection's largest extent")
@device_option
@click.option("--background", default=None, help="r,g,b in [0, 1] for --render; default: the scene's, else black")
@click.option("--fps", type=click.FloatRange(min=0.1), default=None,
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
    from tomgs.edit.cage import shot_config, simulate_selection
    from tomgs.edit.selection import select
    from tomgs.edit.transforms import sequence_clouds
    from tomgs.io.scene import load_scene
    from tomgs.io.tets import save_sequence, save_tets
    from tomgs.jobs import render_defaults
    from tomgs.outputs import check_file_output
    from tomgs.render import resolve_device

    spin, velocity = parse_numbers(spin, "--spin"), parse_numbers(velocity, "--velocity")
    if not output.lower().endswith(".npz"):
        raise UsageError(f"-o {output}: the shot is a vertex sequence, an .npz")
    if over and not render_out:
        raise UsageError("--over is what the render goes over: give --render too")
    cage_path = output[:-4] + ".cage.ply"
    check_file_output(output, overwrite, what="vertex sequence")
    check_file_output(cage_path, overwrite, what="cage")
    dev = resolve_device(device)
    loaded = load_scene(scene)
    cams = loaded.cameras
    frames = len(cams) if num_frames is None else num_frames
    if frames > len(cams):
        raise InputError(f"--frames {frames}: the scene has {len(cams)} frames, and frame f of the shot is "
                         f"rendered with the scene's frame f; simulate at most {len(cams)}")
    plan = plan_render(render_out, cams, None, device, parse_background(background), overwrite,
                       only=set(range(frames)), over=over, name=scene) if render_out else None
    indices = select(loaded.model, cams, selectors)
    config = shot_config(loaded.model, indices, frames, fps or render_defaults(loaded.info)[1], size, drop, spin,
                         velocity, stiffness, damping)
    cage, vertices = simulate_selection(loaded.model, indices, config, cell, device=str(dev))
    save_tets(cage_path, cage)
    save_sequence(output, vertices, frames=cams.frame_indices[:frames])
    click.echo(f"{output}: {len(vertices)} frames of {len(indices):,} Gaussians on a cage of {len(cage.tets):,} "
               f"tets ({cage_path})")
    if plan is not None:
        clouds = sequence_clouds(loaded.model, cage, vertices, {k: k for k in range(frames)})
        render_planned(loaded, clouds, plan, fps)
