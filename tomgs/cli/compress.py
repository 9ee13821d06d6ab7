"""`tomgs compress`: a scene file written compressed (.tsog), or back as a PLY scene."""

from __future__ import annotations

import time
from pathlib import Path

import click

from tomgs.cli.common import UsageError, is_scene_path, overwrite_option, scene_cameras_option, user_errors
from tomgs.cli.params import Number


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="the compressed scene (.tsog); a .ply writes a PLY scene back")
@click.option("--means-bits", type=Number(1, 16, integer=True, what="bits"), default=16, show_default=True,
              help="bits an axis of the positions (after a log transform); fewer: a smaller file, coarser positions")
@click.option("--t-bits", type=Number(1, 16, integer=True, what="bits"), default=16, show_default=True,
              help="bits of each Gaussian's temporal centre (t_mean)")
@scene_cameras_option
@overwrite_option
@user_errors
def compress(scene, output, means_bits, t_bits, cameras_path, overwrite):
    """Write SCENE compressed: its Gaussians quantised onto sorted grids of lossless WebP images,
    cameras, frame times and settings as they were (docs/scene-format.md). Every command that
    reads a scene reads a .tsog.

    \b
    Examples:
      tomgs compress scene.ply -o scene.tsog
      tomgs compress scene.ply -o small.tsog --means-bits 14     # coarser positions, ~0.75 bytes less a Gaussian
      tomgs render scene.tsog -o scene.mp4
      tomgs compress scene.tsog -o back.ply          # a PLY scene again, for 3DGS tools
    """
    from tomgs.outputs import check_distinct, check_file_output
    from tomgs.cli.preflight import check_scene

    check_distinct({"-o": output}, {"SCENE": scene, "--cameras": cameras_path})
    if not is_scene_path(output):
        raise UsageError(f"-o {output}: a compressed scene is a .tsog (a .ply writes a PLY scene)")
    if output.lower().endswith(".ply") and (means_bits, t_bits) != (16, 16):
        raise UsageError("--means-bits and --t-bits set a .tsog's precision; a .ply scene is exact")
    check_file_output(output, overwrite, what="scene")
    check_scene(scene, cameras=cameras_path)

    from tomgs.io.scene import bits_per_pixel, load_scene, save_scene

    loaded = load_scene(scene, cameras=cameras_path)
    before = Path(scene).stat().st_size
    started = time.perf_counter()
    save_scene(output, loaded.model, loaded.cameras, loaded.info, means_bits=means_bits, t_bits=t_bits)
    seconds = time.perf_counter() - started
    after = Path(output).stat().st_size
    n, cams = len(loaded.model), loaded.cameras
    per = f", {after / n:.2f} bytes a Gaussian" if n else ""
    click.echo(f"{output}: {n:,} Gaussians, {after:,} bytes ({before / max(after, 1):.1f}x smaller than "
               f"{Path(scene).name}){per}, {bits_per_pixel(after, cams):.3f} bits per pixel of the clip "
               f"({len(cams)} frames of {cams.width}x{cams.height}); written in {seconds:.1f} s")
