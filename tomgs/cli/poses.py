"""`tomgs poses`: a clip's cameras, from its frames or a pose file."""

from __future__ import annotations

import click

from tomgs.cli.common import (
    UsageError,
    check_json,
    clip_options,
    json_option,
    overwrite_option,
    phase_bars,
    say,
    user_errors,
    write_json,
)


@click.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str, allow_dash=True),
              help="cameras JSON to write (schema in tomgs.cameras); '-' for stdout")
@click.option("--method", default="auto", show_default=True,
              help="auto, identity, a cameras .json / AnyCam c2w .npy / COLMAP text folder, or an .onnx model")
@clip_options
@json_option("the pose report")
@overwrite_option
@user_errors
def poses(video, output, masks, frames, method, focal, max_side, json_out, overwrite):
    """Estimate per-frame cameras of VIDEO (a video file or a folder of frames).

    \b
    Examples:
      tomgs poses clip.mp4 -o cameras.json
      tomgs poses frames/ -o cameras.json --masks masks/ --frames 0:80 --max-side 854
      tomgs poses clip.mp4 -o cameras.json --method colmap_model/      # convert known cameras
      tomgs poses clip.mp4 -o - | jq .K                                 # the JSON on stdout
      tomgs fit clip.mp4 -o scene.ply --poses cameras.json
    """
    from tomgs.outputs import check_distinct, check_file_output, existing_path
    from tomgs.cli.preflight import check_clip, check_poses

    check_distinct({"-o": None if output == "-" else output, "--json": json_out},
                   {"VIDEO": video, "--masks": masks, "--method": existing_path(method)})
    if output == "-" and json_out == "-":
        raise UsageError("-o - and --json - both write to stdout: send one of them to a file")
    if output != "-":
        check_file_output(output, overwrite, what="cameras file")
    to_stdout = check_json(json_out, overwrite) or output == "-"
    check_clip(video, frames, max_side, masks)
    check_poses(method, "--method")

    from tomgs.io import read_video
    from tomgs.poses import estimate_cameras

    with phase_bars() as bars:
        clip = read_video(video, frames=frames, max_side=max_side, masks=masks,
                          progress=lambda done, total: bars("read", done, total))
        bars("poses", 0, 1)
        cams, _, _, report = estimate_cameras(clip, method=method, focal=focal,
                                              progress=lambda done, total: bars("poses", done, total))
        bars("poses", 1, 1)
    if output == "-":
        click.echo(cams.to_json())
    else:
        cams.save(output)
    for note in [*clip.notes, *report.notes]:
        say(f"  note: {note}")
    click.echo(f"{'cameras' if output == '-' else output}: {report.summary()}", err=to_stdout)
    write_json(json_out, dict(output=str(output), summary=report.summary(), method=report.method, mode=report.mode,
                               frames=report.frames, focal=report.focal, focal_estimated=report.focal_estimated,
                               reprojection_px=report.reproj_px, points=report.points, seconds=report.seconds,
                               notes=[*clip.notes, *report.notes]))
