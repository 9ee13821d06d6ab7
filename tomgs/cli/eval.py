"""`tomgs eval`: a scene rendered at its frames against the clip, PSNR, SSIM and LPIPS."""

from __future__ import annotations

import click

from tomgs.cli.common import check_json, device_option, overwrite_option, say, user_errors, write_json


@click.command("eval")
@click.argument("scene", type=click.Path(path_type=str))
@click.argument("video", type=click.Path(path_type=str))
@click.option("--lpips", "lpips_weights", type=click.Path(path_type=str), default=None,
              help="LPIPS v0.1 AlexNet weights as one .npz, made from torchvision's AlexNet and the lpips "
                   "package's alex.pth (docs/fitting.md shows how); default $TOMGS_LPIPS_WEIGHTS, else LPIPS is "
                   "left out")
@click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
              help="also write per-frame and mean metrics as JSON to this file ('-' for stdout)")
@click.option("--force", is_flag=True,
              help="compare even when VIDEO is not the clip SCENE was fitted on (another picture, frame count or "
                   "size): the frames both have, resized to the scene's size, saying what differs")
@device_option
@overwrite_option
@user_errors
def evaluate_command(scene, video, lpips_weights, json_out, force, device, overwrite):
    """Compare SCENE, rendered at every frame it was fitted on, with VIDEO: PSNR and SSIM per frame
    and on average, as the peers compute them (float renders, 11x11 Gaussian SSIM); LPIPS when its
    weights are given.

    \b
    Examples:
      tomgs eval scene.ply clip.mp4
      tomgs eval scene.ply frames/ --lpips alexnet-lpips-v0.1.npz --json metrics.json
      tomgs eval scene.ply clip.mp4 --json - | jq .psnr     # the mean PSNR (JSON alone on stdout)
      tomgs eval scene.ply other.mp4 --force                # another clip, deliberately
    """
    from tomgs.outputs import check_distinct
    from tomgs.cli.preflight import check_device, check_eval_video, check_existing, check_scene, refuse_or_note
    from tomgs.io.video import probe_source

    check_distinct({"--json": json_out}, {"SCENE": scene, "VIDEO": video, "--lpips": lpips_weights})
    to_stdout = check_json(json_out, overwrite)
    check_device(device)
    probe_source(video)  # a missing video or a file of another kind, before the scene's header is read (numpy)
    cameras, info = check_scene(scene)
    notes, partial = check_eval_video(video, scene, cameras, info, force)
    if lpips_weights is not None:
        check_existing(lpips_weights, "--lpips: weights file")

    from tomgs.io.scene import load_scene
    from tomgs.io.video import frame_differences, read_video_against, read_video_for
    from tomgs.metrics import LPIPS, default_lpips_weights, evaluate
    from tomgs.runtime import resolve_device

    dev = resolve_device(device)
    loaded = load_scene(scene, device=dev)
    cameras = loaded.cameras
    if partial:  # forced: the frames both have, resized
        frames, keep, done = read_video_against(video, cameras)
        cameras, notes = cameras[keep], notes + done
    else:
        frames = read_video_for(video, cameras)
        notes += refuse_or_note(video, scene, frame_differences(video, frames, loaded.info.get("clip")), force)
    weights = lpips_weights or default_lpips_weights()
    lpips = LPIPS(weights, device=dev) if weights else None
    report = evaluate(loaded.model, cameras, frames, lpips=lpips, device=dev)
    show = say if to_stdout else click.echo  # notes on stderr (-q silences them) when stdout carries the JSON
    for k, p, s in zip(report.frames, report.psnr, report.ssim):
        show(f"  frame {int(cameras.frame_indices[k]):5d}: PSNR {p:6.2f} dB  SSIM {s:.4f}")
    show(f"{scene}: {report.summary()}" + ("" if lpips else " (LPIPS left out: no weights given)"))
    for note in notes:
        say(f"  note: {note}")
    write_json(json_out, report.to_dict())  # a perfect frame's PSNR is inf: null
