"""`tomgs compress`: a scene file written compressed (.tsog), or back as a PLY scene."""

from __future__ import annotations

import time
from pathlib import Path

import click

from tomgs.cli.common import (UsageError, device_option, is_scene_path, overwrite_option, scene_cameras_option,
                              user_errors)
from tomgs.cli.params import Number

ASSUMED_PSNR = 40.0  # a scene's PSNR against its clip when its info does not record one (a fit's does)


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="the compressed scene (.tsog); a .ply writes a PLY scene back")
@click.option("--means-bits", type=Number(1, 16, integer=True, what="bits"), default=16, show_default=True,
              help="bits an axis of the positions (after a log transform); fewer: a smaller file, coarser positions")
@click.option("--t-bits", type=Number(1, 16, integer=True, what="bits"), default=16, show_default=True,
              help="bits of each Gaussian's temporal centre (t_mean)")
@click.option("--max-loss", type=Number(0.0, 100.0, low_open=True, what="dB"), default=0.2, show_default=True,
              help="most dB of the scene's PSNR the .tsog may lose; a .tsog that would lose more is not written")
@click.option("--check-frames", type=Number(0, 1000, integer=True, what="frames"), default=4, show_default=True,
              help="frames rendered from both to measure the loss (0: no check)")
@device_option
@scene_cameras_option
@overwrite_option
@user_errors
def compress(scene, output, means_bits, t_bits, max_loss, check_frames, device, cameras_path, overwrite):
    """Write SCENE compressed: its Gaussians quantised onto sorted grids of lossless WebP images,
    cameras, frame times and settings as they were (docs/scene-format.md). Every command that
    reads a scene reads a .tsog.

    The .tsog is checked before it is kept: a few frames rendered from both, and the dB of the
    scene's PSNR against its clip (its info's clip_psnr, which a fit records; else 40 dB) that the
    difference costs. Past --max-loss nothing is written.

    \b
    Examples:
      tomgs compress scene.ply -o scene.tsog
      tomgs compress scene.ply -o small.tsog --means-bits 14     # coarser positions, ~0.75 bytes less a Gaussian
      tomgs render scene.tsog -o scene.mp4
      tomgs compress scene.tsog -o back.ply          # a PLY scene again, for 3DGS tools
    """
    from tomgs.outputs import check_distinct, check_file_output, discard, publish, temporary
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
    check = output.lower().endswith(".tsog") and check_frames > 0 and len(loaded.model) > 0
    # a checked .tsog is staged as out.tsog in a temporary folder of this process (removed on every exit
    # path, and by a later writer if this process dies) and published once it has passed
    stage = temporary(output, folder=True) if check else None
    written = stage / "out.tsog" if check else Path(output)
    try:
        save_scene(written, loaded.model, loaded.cameras, loaded.info, means_bits=means_bits, t_bits=t_bits)
        seconds = time.perf_counter() - started
        verdict = _checked(loaded, written, output, max_loss, check_frames, device) if check else ""
        if check:
            publish(written, output)
    finally:
        if check:
            discard(stage)
    after = Path(output).stat().st_size
    n, cams = len(loaded.model), loaded.cameras
    per = f", {after / n:.2f} bytes a Gaussian" if n else ""
    click.echo(f"{output}: {n:,} Gaussians, {after:,} bytes ({before / max(after, 1):.1f}x smaller than "
               f"{Path(scene).name}){per}, {bits_per_pixel(after, cams):.3f} bits per pixel of the clip "
               f"({len(cams)} frames of {cams.width}x{cams.height}); written in {seconds:.1f} s{verdict}")


def _checked(loaded, written: Path, output: str, max_loss: float, frames: int, device) -> str:
    """What the .tsog `written` loses against the scene `loaded`, as a clause of the command's line;
    UsageError (nothing kept) past `max_loss` dB."""
    import math

    from tomgs.io.scene import load_scene
    from tomgs.metrics import copy_psnr, loss_db, required_copy_psnr
    from tomgs.runtime import resolve_device

    recorded = loaded.info.get("clip_psnr") if isinstance(loaded.info, dict) else None
    known = isinstance(recorded, (int, float)) and not isinstance(recorded, bool) and math.isfinite(recorded)
    scene_psnr = float(recorded) if known else ASSUMED_PSNR
    where = resolve_device(device)
    psnr = copy_psnr(loaded.model.to(where), load_scene(written, device=where).model, loaded.cameras, frames,
                     device=where)
    lost = loss_db(scene_psnr, psnr)
    said = f"the scene's {scene_psnr:.2f} dB" + ("" if known else " (not recorded: assumed)")
    if lost > max_loss:
        raise UsageError(f"-o {output} would lose {lost:.2f} dB of {said}: its renders are {psnr:.1f} dB against "
                         f"the scene's, {required_copy_psnr(scene_psnr, max_loss):.1f} dB needed for --max-loss "
                         f"{max_loss:g}; nothing written (raise --means-bits / --t-bits, or --max-loss)")
    return f"; renders {psnr:.1f} dB against the scene's over {frames} frames: {lost:.3f} dB of {said}"
