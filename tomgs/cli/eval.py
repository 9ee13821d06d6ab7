"""`tomgs eval`: a scene rendered at its frames against the clip, PSNR, SSIM and LPIPS."""

from __future__ import annotations

import click

from tomgs.cli import check_json, device_option, main, overwrite_option, user_errors, write_json


@main.command("eval")
@click.argument("scene", type=click.Path(path_type=str))
@click.argument("video", type=click.Path(path_type=str))
@click.option("--lpips", "lpips_weights", type=click.Path(path_type=str), default=None,
              help="LPIPS AlexNet weights (.npz); default $TOMGS_LPIPS_WEIGHTS, else LPIPS is left out")
@click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
              help="also write per-frame and mean metrics as JSON to this file ('-' for stdout)")
@device_option
@overwrite_option
@user_errors
def evaluate_command(scene, video, lpips_weights, json_out, device, overwrite):
    """Compare SCENE, rendered at every frame it was fitted on, with VIDEO: PSNR and SSIM per frame
    and on average, as the peers compute them (float renders, 11x11 Gaussian SSIM); LPIPS when its
    weights are given.

    \b
    Examples:
      tomgs eval scene.ply clip.mp4
      tomgs eval scene.ply frames/ --lpips alexnet-lpips-v0.1.npz --json metrics.json
      tomgs eval scene.ply clip.mp4 --json - | jq .mean     # JSON alone on stdout
    """

    from tomgs.io.scene import load_scene
    from tomgs.io.video import read_video_for
    from tomgs.metrics import LPIPS, default_lpips_weights, evaluate
    from tomgs.outputs import check_distinct
    from tomgs.runtime import resolve_device

    check_distinct({"--json": json_out}, {"SCENE": scene, "VIDEO": video, "--lpips": lpips_weights})
    to_stdout = check_json(json_out, overwrite)
    dev = resolve_device(device)
    loaded = load_scene(scene, device=dev)
    frames = read_video_for(video, loaded.cameras)
    weights = lpips_weights or default_lpips_weights()
    lpips = LPIPS(weights, device=dev) if weights else None
    report = evaluate(loaded.model, loaded.cameras, frames, lpips=lpips, device=dev)
    for k, p, s in zip(report.frames, report.psnr, report.ssim):  # on stderr when stdout carries the JSON
        click.echo(f"  frame {int(loaded.cameras.frame_indices[k]):5d}: PSNR {p:6.2f} dB  SSIM {s:.4f}",
                   err=to_stdout)
    click.echo(f"{scene}: {report.summary()}" + ("" if lpips else " (LPIPS left out: no weights given)"),
               err=to_stdout)
    write_json(json_out, report.to_dict())  # a perfect frame's PSNR is inf: null
