"""`tomgs fit`: a clip in, a scene file out (one process, or shards over several GPUs)."""

from __future__ import annotations

import os
from pathlib import Path

import click

from tomgs.cli.common import (
    check_json,
    clip_options,
    device_option,
    json_option,
    overwrite_option,
    phase_bars,
    say,
    user_errors,
    write_json,
)
from tomgs.cli.params import SEED, SH_DEGREE, Number
from tomgs.errors import counted


@click.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="scene file to write (.ply, or .tsog compressed); a .csv log and a .psnr.png plot are written "
                   "beside it")
@click.option("--preset", default="default", show_default=True, type=click.Choice(["default", "paper", "quick"]),
              help="default: tuned for speed; paper: 80k iterations, densify to 60k; quick: a few hundred")
@click.option("--iterations", type=Number(1, 10**7, integer=True, what="iterations"), default=None,
              help="override the preset's iteration count (with --budget: stop at whichever comes first)")
@click.option("--quality", type=click.Choice(["compact", "default", "max"]), default=None,
              help="how many Gaussians the fit keeps: default grows the cloud while new Gaussians still take "
                   "enough error away and prunes the least important while that costs little PSNR, compact stops "
                   "and prunes sooner, max grows to the cap and keeps it all (every dB)")
@click.option("--poses", default="auto", show_default=True,
              help="auto, identity, or a cameras .json / AnyCam .npy / COLMAP folder / .onnx model")
@clip_options
@device_option
@click.option("--cap", "max_gaussians", type=Number(1, 10**9, integer=True, what="Gaussians"), default=None,
              help="most Gaussians (default: by the clip's frames x pixels and the device, see the plan line)")
@click.option("--budget", "max_seconds", type=Number(1.0, 1e7, what="seconds"), default=None,
              help="the whole command's wall time in seconds, reading, poses and saving included: training takes "
                   "what the rest leaves, and a longer budget trains longer; default: none on a GPU, chosen where "
                   "the iterations would take longer (10 min on a CPU)")
@click.option("--sampling", type=click.Choice(["inverse_psnr", "uniform"]), default=None,
              help="how training picks its next frame: inverse_psnr (default) favours the frames it renders worst; "
                   "uniform picks any alike (ablation)")
@click.option("--static", "static_3dgs", is_flag=True, help="ablation: no temporal opacity (static 3DGS)")
@click.option("--opacity-reset", type=Number(0, 10**7, integer=True, what="iterations"), default=None,
              help="ablation: reset opacities every N")
@click.option("--sh-degree", type=SH_DEGREE, default=None, help="view-dependent colour (default 0)")
@click.option("--compact", "compact_pixels", type=Number(0.0, 1e6, what="pixels"), default=None,
              help="at the end, leave out the Gaussians that give no frame this many pixels' worth of colour "
                   "(default 0.01; 0 keeps every Gaussian)")
@click.option("--seed", type=SEED, default=None,
              help="seed of the random start and frame choices (default 0): a CPU fit of set --iterations with "
                   "the same seed repeats exactly")
@click.option("--resume", is_flag=True, help="continue from the checkpoint beside OUTPUT")
@click.option("--layer", type=click.Choice(["background", "foreground"]), default=None,
              help="fit one layer (needs --masks): the pixels outside the masks, or the masked object on a plane")
@click.option("--mask-dilation", type=Number(0, 1024, integer=True, what="pixels"), default=2, show_default=True,
              help="background layer: grow the masks by this many pixels before leaving them out")
@click.option("--gpus", type=Number(1, 1024, integer=True, what="processes"), default=None,
              help="fit N stretches of the clip side by side, one process per GPU (--device cpu: N CPU processes), "
                   "merged into one scene; default 1, or under torchrun its ranks (docs/multi-gpu.md)")
@json_option("the fit's summary")
@overwrite_option
@user_errors
def fit(video, output, preset, iterations, quality, frames, max_side, masks, poses, focal, device, max_gaussians, max_seconds,
        sampling, static_3dgs, opacity_reset, sh_degree, compact_pixels, seed, resume, layer, mask_dilation, gpus,
        json_out, overwrite):
    """Fit a TOM-GS scene to VIDEO (a video file or a folder of frames).

    \b
    Examples:
      tomgs fit clip.mp4 -o scene.ply
      tomgs fit frames/ -o scene.ply --masks masks/ --frames 0:80 --max-side 854 --device cuda
      tomgs fit clip.mp4 -o scene.ply --resume          # after Ctrl-C, SIGTERM or a crash
      tomgs fit clip.mp4 -o scene.ply -y                # start over, replacing scene.* files
      tomgs fit frames/ --masks masks/ --layer background -o bg.ply
      tomgs fit frames/ --masks masks/ --layer foreground -o fg.ply
      tomgs fit long.mp4 -o scene.ply --gpus 2          # two GPUs, one stretch of the clip each
      torchrun --nproc_per_node 8 -m tomgs.cli fit long.mp4 -o scene.ply
    """
    from tomgs.outputs import check_distinct, check_fit_outputs, check_unlocked, existing_path, fit_output_paths
    from tomgs.cli.preflight import check_clip, check_device, check_poses
    from tomgs.train.multigpu import pool as rank_pool

    if gpus is not None and gpus > 1 and not rank_pool.under_torchrun():  # a host that cannot run them starts none
        rank_pool.check_world(gpus, device, rank_pool.visible_gpus(), cores=os.cpu_count())
    if gpus in (None, 1) and not rank_pool.under_torchrun():  # a sharded fit checks its ranks' files itself
        check_fit_outputs(output, resume=resume, overwrite=overwrite)
        check_unlocked(output)
    to_stdout = check_json(json_out, overwrite)
    beside = {f"the fit's {what}": path for what, path in fit_output_paths(output).items() if what != "scene"}
    check_distinct({"-o": output, **beside, "--json": json_out},
                   {"VIDEO": video, "--masks": masks, "--poses": existing_path(poses)})
    check_device(device)
    check_clip(video, frames, max_side, masks, layer)
    check_poses(poses)
    if gpus is not None:  # the ranks import while this process does (tomgs.train.multigpu.pool)
        rank_pool.start(gpus)
    with phase_bars() as bars:  # torch and Warp take seconds to import on a busy machine: a log hears of them
        bars("load", 0, 1, "torch and Warp")
        from tomgs.io.scene import bits_per_pixel
        from tomgs.train import FitInterrupted
        from tomgs.train import fit as fit_scene
        from tomgs.train import preset as make_config
        from tomgs.train.multigpu.launch import ShardFailed
        from tomgs.train.multigpu.pool import is_leader
        from tomgs.train.phases import phase_text, tomgs_started

    started = tomgs_started()
    overrides = dict(iterations=iterations, max_gaussians=max_gaussians, max_seconds=max_seconds, sampling=sampling,
                     opacity_reset_interval=opacity_reset, sh_degree=sh_degree, compact_pixels=compact_pixels,
                     seed=seed, quality=quality, stop_at_iterations=iterations is not None or None)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if static_3dgs:
        overrides["temporal"] = False
    config = make_config(preset, **overrides)

    def on_row(row):
        psnr = f"{row['train_psnr']} dB" if row["train_psnr"] != "" else "-"  # none heard yet: the first steps
        covers = f" over {row['clip_frames']} frames" if row.get("clip_frames") else ""
        clip = f"{row['clip_psnr']} dB{covers}" if row["clip_psnr"] != "" else "-"
        say(f"  iteration {row['iteration']}: {row['wall_s']:.1f} s, PSNR {psnr}, {row['gaussians']:,} Gaussians, "
            f"{row['iteration'] / max(row['wall_s'], 1e-9):.1f} it/s, clip PSNR {clip}", level=2)

    try:
        with phase_bars() as bars:
            result = fit_scene(video, output, config, masks=masks, frames=frames, max_side=max_side, poses=poses,
                               focal=focal, device=device, resume=resume, overwrite=overwrite, progress=on_row,
                               layer=layer, mask_dilation=mask_dilation, phases=bars,
                               on_plan=lambda plan: say(plan.summary()), started=started, gpus=gpus)
    except FitInterrupted as e:
        click.echo(f"\n{e.message()}", err=True)
        raise SystemExit(e.exit_code) from None
    except ShardFailed as e:
        click.echo(f"\n{e}", err=True)
        raise SystemExit(1) from None
    finally:
        rank_pool.dismiss()  # ranks the fit did not take (it refused its inputs first)
    if not is_leader():  # a torchrun rank other than 0: rank 0 reports the run
        return
    paths = fit_output_paths(output)
    memory = f"peak memory {result.peak_host_mb / 1024:.2f} GiB host" + (
        "" if result.peak_gpu_mb is None else f", {result.peak_gpu_mb / 1024:.2f} GiB GPU")
    nbytes = Path(output).stat().st_size
    bpp = bits_per_pixel(nbytes, result.cameras)
    if not to_stdout:
        frames = len(result.cameras)
        covered = "full-clip PSNR" if result.clip_frames in (0, frames) else \
            f"clip PSNR over {result.clip_frames} of {frames} frames"
        click.echo(f"{output}: {len(result.model):,} Gaussians, {result.iterations:,} iterations in "
                   f"{result.seconds:.1f} s, {covered} {result.clip_psnr:.2f} dB")
        click.echo(f"  {nbytes:,} bytes, {bpp:.3f} bits per pixel of the clip ({counted(frames, 'frame')} of "
                   f"{result.cameras.width}x{result.cameras.height})")
        click.echo(f"  {result.wall_seconds:.1f} s in all ({phase_text(result.phase_seconds)}), {memory}")
        click.echo(f"  error against run time: {paths['csv']} and {paths['plot']}")
    for note in result.notes:
        say(f"  note: {note}")
    write_json(json_out, dict(output=str(output), gaussians=len(result.model), iterations=result.iterations,
                               seconds=result.seconds, wall_seconds=result.wall_seconds,
                               phase_seconds=result.phase_seconds, eta_seconds=result.plan.eta,
                               peak_host_mb=result.peak_host_mb, peak_gpu_mb=result.peak_gpu_mb,
                               peak_host_mb_by_phase=result.peak_host_mb_by_phase,
                               clip_psnr=result.clip_psnr, clip_frames=result.clip_frames or len(result.cameras),
                               scene_bytes=nbytes, bits_per_pixel=bpp,
                               csv=str(paths["csv"]), plot=str(paths["plot"]),
                               notes=list(result.notes), shards=result.shards))
