"""`tomgs tets export|import`: a scene to tetrahedra and back, deformed by another tool."""

from __future__ import annotations

from pathlib import Path

import click

from tomgs.cli.common import (
    OUTPUT_HELP,
    OVER_HELP,
    SELECT_HELP,
    UsageError,
    is_scene_path,
    overwrite_option,
    render_options,
    render_planned,
    selector_paths,
    user_errors,
)
from tomgs.cli.params import CELL
from tomgs.errors import InputError


@click.group()
def tets():
    """Gaussians as tetrahedra: export them (for Blender or a simulator), import moved vertices."""


@tets.command("export")
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="tets file to write (.ply, Blender axes)")
@click.option("--select", "selectors", multiple=True, help=SELECT_HELP)
@click.option("--cage", is_flag=True, help="a connected voxel cage with the Gaussians bound into it (for soft "
              "bodies) instead of one tet per Gaussian")
@click.option("--cell", type=CELL, default=None,
              help="cage cell size in scene units; default: 1/8 of the selection's largest extent")
@overwrite_option
@user_errors
def tets_export(scene, output, selectors, cage, cell, overwrite):
    """Write the Gaussians of SCENE that --select picks as tetrahedra (a PLY Blender imports:
    Z up, vertex order kept; docs/editing.md has the format).

    \b
    Examples:
      tomgs tets export scene.ply -o tets.ply --select sphere:0,0,3,0.5
      tomgs tets export scene.ply -o cage.ply --select mask:camel_masks/ --cage --cell 0.05
    """
    from tomgs.outputs import check_distinct, check_file_output
    from tomgs.cli.preflight import check_scene, check_selectors

    check_distinct({"-o": output}, {"SCENE": scene, "--select": selector_paths(selectors)})
    if cell is not None and not cage:
        raise UsageError("--cell sets the cage's cell size: give --cage too")
    if not output.lower().endswith(".ply"):
        raise UsageError(f"-o {output}: a tets file is a .ply")
    check_file_output(output, overwrite, what="tets file")
    check_selectors(selectors)
    check_scene(scene)

    from tomgs.edit.cage import make_tets
    from tomgs.edit.selection import select
    from tomgs.io.scene import load_scene
    from tomgs.io.tets import save_tets

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
              help=OUTPUT_HELP + "; or a scene (.ply or .tsog) when SEQUENCE has one frame")
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
    from tomgs.outputs import check_distinct, check_file_output
    from tomgs.cli.preflight import check_existing, check_render, check_scene

    check_distinct({"-o": output}, {"SCENE": scene, "TETS": tets_file, "SEQUENCE": sequence, "--over": over})
    check_existing(tets_file, "tets file")
    if not Path(sequence).exists():
        raise InputError(f"{sequence} does not exist: give the moved vertices (an .npz, a folder of PLY frames or one "
                         "PLY)")
    cameras, _ = check_scene(scene)
    if is_scene_path(output):
        check_file_output(output, overwrite, what="scene")
    else:
        check_render(output, cameras, frames, overwrite, over=over, device=device)

    from tomgs.edit.transforms import (
        check_bound,
        deformed_model,
        sequence_clouds,
        sequence_rows,
    )
    from tomgs.io.scene import load_scene, save_scene
    from tomgs.io.tets import load_sequence, load_tets
    from tomgs.render.jobs import plan_render

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
    plan = plan_render(output, loaded.cameras, frames, device, background, overwrite, only=rows,
                       over=over, name=scene)
    render_planned(loaded, sequence_clouds(loaded.model, mesh, vertices, rows), plan, fps)
