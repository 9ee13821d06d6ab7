"""The `tomgs` command line: a thin click layer that parses, calls the library, and prints."""

from __future__ import annotations

import contextlib
import functools
import sys

import click

from tomgs import __version__
from tomgs.errors import InputError, RenderError
from tomgs.jobs import parse_floats, plan_render, render_frames, run_render


class UsageError(click.ClickException):
    """A bad input: clear message, exit code 2, nothing written."""

    exit_code = 2


def _user_errors(command):
    """Bad input found by the library (InputError, RenderError): exit 2 with its message. An OS
    error while reading or writing (disk full, a file removed under us): exit 1 naming the file.
    Never a traceback."""
    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except (InputError, RenderError) as e:
            raise UsageError(str(e)) from None
        except OSError as e:
            where = f"{e.filename}: " if e.filename else ""
            raise click.ClickException(f"{where}{e.strerror or e}") from None
    return wrapper


_OUTPUT_HELP = "an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames"


def _clip_options(f):
    """--frames, --max-side, --masks and --focal, as `poses` and `fit` read a clip."""
    for option in reversed([
        click.option("--frames", default=None, help="frame range start:stop:step of the source, e.g. 0:80 or ::2"),
        click.option("--max-side", type=click.IntRange(16), default=None, help="resize frames so that max(W, H) <= N"),
        click.option("--masks", type=click.Path(path_type=str), default=None,
                     help="folder of masks, one per source frame, white on the moving object (left out of poses)"),
        click.option("--focal", type=float, default=None, help="focal length in pixels of the (resized) frames"),
    ]):
        f = option(f)
    return f


_device_option = click.option("--device", default="auto", show_default=True, help="auto, cpu, cuda or cuda:N")
_overwrite_option = click.option(
    "-y", "--overwrite", is_flag=True,
    help="replace existing outputs (in a folder of frames only its numbered PNGs; other files are kept)")


def _render_options(f):
    """--frames, --device, --background, --fps and --overwrite, as `tomgs render` has them."""
    for option in reversed([
        click.option("--frames", default=None, help="frame range start:stop:step in the scene's frame numbers"),
        _device_option,
        click.option("--background", default=None, help="r,g,b in [0, 1]; default: the scene's, else black"),
        click.option("--fps", type=click.FloatRange(min=0.1), default=None,
                     help="frame rate of a video output; default: the scene's, else 25"),
        _overwrite_option,
    ]):
        f = option(f)
    return f


_VERBOSITY = {"level": 1}  # 0: -q, 1: default, 2: -v (set by `main` for the command it runs)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tomgs")
@click.option("-q", "--quiet", is_flag=True, help="no progress bars or notes on stderr: results and errors only")
@click.option("-v", "--verbose", is_flag=True, help="also every training log row on stderr")
def main(quiet: bool, verbose: bool) -> None:
    """Editable video as static 3D Gaussians with temporal opacity (TOM-GS).

    Results go to stdout (`--json -` makes it pure JSON); progress bars and notes go to stderr.
    """
    if quiet and verbose:
        raise UsageError("-q and -v contradict each other: give one")
    _VERBOSITY["level"] = 0 if quiet else 2 if verbose else 1


def _note(text: str, level: int = 1) -> None:
    """A note on stderr, shown from verbosity `level` up."""
    if _VERBOSITY["level"] >= level:
        click.echo(text, err=True)


def _json_option(what: str):
    return click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
                        help=f"also write {what} as JSON to this file ('-' for stdout, then nothing else is printed)")


def _write_json(json_out: str | None, value) -> None:
    """`value` as JSON to `json_out` ('-': stdout), non-finite floats as null."""
    from tomgs.outputs import json_text, write_text

    if json_out == "-":
        click.echo(json_text(value))
    elif json_out:
        write_text(json_out, json_text(value))


def _check_json(json_out: str | None, overwrite: bool) -> bool:
    """Check a --json file before any work; True when the JSON goes to stdout (print nothing else)."""
    from tomgs.outputs import check_file_output

    if json_out and json_out != "-":
        check_file_output(json_out, overwrite, what="JSON report")
    return json_out == "-"


@main.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="cameras JSON to write (schema in tomgs.cameras)")
@click.option("--method", default="auto", show_default=True,
              help="auto, identity, a cameras .json / AnyCam c2w .npy / COLMAP text folder, or an .onnx model")
@_clip_options
@_json_option("the pose report")
@_overwrite_option
@_user_errors
def poses(video, output, masks, frames, method, focal, max_side, json_out, overwrite):
    """Estimate per-frame cameras of VIDEO (a video file or a folder of frames).

    \b
    Examples:
      tomgs poses clip.mp4 -o cameras.json
      tomgs poses frames/ -o cameras.json --masks masks/ --frames 0:80 --max-side 854
      tomgs poses clip.mp4 -o cameras.json --method colmap_model/      # convert known cameras
      tomgs fit clip.mp4 -o scene.ply --poses cameras.json
    """
    from tomgs.io import read_video
    from tomgs.outputs import check_file_output
    from tomgs.poses import estimate_cameras

    check_file_output(output, overwrite, what="cameras file")
    to_stdout = _check_json(json_out, overwrite)
    clip = read_video(video, frames=frames, max_side=max_side, masks=masks)
    with _bar(2 * len(clip), "poses") as progress:
        cams, _, _, report = estimate_cameras(clip, method=method, focal=focal,
                                              progress=lambda done, total: progress(done))
    cams.save(output)
    for note in report.notes:
        _note(f"  note: {note}")
    if not to_stdout:
        click.echo(f"{output}: {report.summary()}")
    _write_json(json_out, dict(output=str(output), summary=report.summary(), method=report.method, mode=report.mode,
                               frames=report.frames, focal=report.focal, focal_estimated=report.focal_estimated,
                               reprojection_px=report.reproj_px, points=report.points, seconds=report.seconds,
                               notes=list(report.notes)))


@main.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="scene file to write (.ply); a .csv log and a .psnr.png plot are written beside it")
@click.option("--preset", default="default", show_default=True, type=click.Choice(["default", "paper", "quick"]),
              help="default: tuned for speed; paper: 80k iterations, densify to 60k; quick: a few hundred")
@click.option("--iterations", type=click.IntRange(1), default=None, help="override the preset's iteration count")
@click.option("--poses", default="auto", show_default=True,
              help="auto, identity, or a cameras .json / AnyCam .npy / COLMAP folder / .onnx model")
@_clip_options
@_device_option
@click.option("--cap", "max_gaussians", type=click.IntRange(1), default=None, help="most Gaussians (default 10M)")
@click.option("--budget", "max_seconds", type=click.FloatRange(min=1.0), default=None,
              help="stop after this many seconds of training (schedules follow the budget)")
@click.option("--sampling", type=click.Choice(["inverse_psnr", "uniform"]), default=None)
@click.option("--static", "static_3dgs", is_flag=True, help="ablation: no temporal opacity (static 3DGS)")
@click.option("--opacity-reset", type=click.IntRange(0), default=None, help="ablation: reset opacities every N")
@click.option("--sh-degree", type=click.IntRange(0, 3), default=None, help="view-dependent colour (default 0)")
@click.option("--seed", type=int, default=None)
@click.option("--resume", is_flag=True, help="continue from the checkpoint beside OUTPUT")
@click.option("--layer", type=click.Choice(["background", "foreground"]), default=None,
              help="fit one layer (needs --masks): the pixels outside the masks, or the masked object on a plane")
@click.option("--mask-dilation", type=click.IntRange(0), default=2, show_default=True,
              help="background layer: grow the masks by this many pixels before leaving them out")
@_json_option("the fit's summary")
@_overwrite_option
@_user_errors
def fit(video, output, preset, iterations, frames, max_side, masks, poses, focal, device, max_gaussians, max_seconds,
        sampling, static_3dgs, opacity_reset, sh_degree, seed, resume, layer, mask_dilation, json_out, overwrite):
    """Fit a TOM-GS scene to VIDEO (a video file or a folder of frames).

    \b
    Examples:
      tomgs fit clip.mp4 -o scene.ply
      tomgs fit frames/ -o scene.ply --masks masks/ --frames 0:80 --max-side 854 --device cuda
      tomgs fit clip.mp4 -o scene.ply --resume          # after Ctrl-C, SIGTERM or a crash
      tomgs fit clip.mp4 -o scene.ply -y                # start over, replacing scene.* files
      tomgs fit frames/ --masks masks/ --layer background -o bg.ply
      tomgs fit frames/ --masks masks/ --layer foreground -o fg.ply
    """
    from tomgs.train import FitInterrupted, output_paths
    from tomgs.train import fit as fit_scene
    from tomgs.train import preset as make_config

    overrides = dict(iterations=iterations, max_gaussians=max_gaussians, max_seconds=max_seconds, sampling=sampling,
                     opacity_reset_interval=opacity_reset, sh_degree=sh_degree, seed=seed)
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if static_3dgs:
        overrides["temporal"] = False
    config = make_config(preset, **overrides)
    to_stdout = _check_json(json_out, overwrite)

    def row_text(row):
        return row and (f"PSNR {row['train_psnr']} dB, {row['gaussians']:,} Gaussians, "
                        f"{row['iteration'] / max(row['wall_s'], 1e-9):.0f} it/s")
    try:
        with _bar(config.iterations, "fit", item_show_func=row_text) as progress:
            def on_row(row):
                progress(row["iteration"], row)
                _note(f"  iteration {row['iteration']}: {row['wall_s']:.1f} s, {row_text(row)}, full-clip PSNR "
                      f"{row['clip_psnr'] or '-'}", level=2)

            result = fit_scene(video, output, config, masks=masks, frames=frames, max_side=max_side, poses=poses,
                               focal=focal, device=device, resume=resume, overwrite=overwrite, progress=on_row,
                               layer=layer, mask_dilation=mask_dilation)
    except FitInterrupted as e:
        click.echo(f"\n{e.message()}", err=True)
        raise SystemExit(e.exit_code) from None
    paths = output_paths(output)
    if not to_stdout:
        click.echo(f"{output}: {len(result.model):,} Gaussians, {result.iterations} iterations in "
                   f"{result.seconds:.1f} s, full-clip PSNR {result.clip_psnr:.2f} dB")
        click.echo(f"  error against run time: {paths['csv']} and {paths['plot']}")
    for note in result.notes:
        _note(f"  note: {note}")
    _write_json(json_out, dict(output=str(output), gaussians=len(result.model), iterations=result.iterations,
                               seconds=result.seconds, clip_psnr=result.clip_psnr, csv=str(paths["csv"]),
                               plot=str(paths["plot"]), notes=list(result.notes)))


@main.command("eval")
@click.argument("scene", type=click.Path(path_type=str))
@click.argument("video", type=click.Path(path_type=str))
@click.option("--lpips", "lpips_weights", type=click.Path(path_type=str), default=None,
              help="LPIPS AlexNet weights (.npz); default $TOMGS_LPIPS_WEIGHTS, else LPIPS is left out")
@click.option("--json", "json_out", type=click.Path(path_type=str), default=None,
              help="also write per-frame and mean metrics as JSON to this file ('-' for stdout)")
@_device_option
@_overwrite_option
@_user_errors
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
    from tomgs.render import resolve_device

    to_stdout = _check_json(json_out, overwrite)
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
    _write_json(json_out, report.to_dict())  # a perfect frame's PSNR is inf: null


def _parse_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UsageError(f"--size must look like 320x180, got {text!r}") from None
    from tomgs.cameras import MAX_SIDE

    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise UsageError(f"--size sides must be 1..{MAX_SIDE} pixels, got {text!r}")
    return width, height


@main.command()
@click.option("-o", "--output", default="demo.mp4", show_default=True, type=click.Path(path_type=str),
              help="an .mp4/.avi/.mov/.mkv file, or a folder (no suffix) for PNG frames")
@click.option("--frames", "num_frames", default=48, show_default=True, type=click.IntRange(1, 10000))
@click.option("--size", default="320x180", show_default=True, help="WIDTHxHEIGHT in pixels")
@_device_option
@_overwrite_option
@_user_errors
def demo(output, num_frames, size, device, overwrite):
    """Render the bundled example scene: static Gaussians whose opacity fades in and out over
    time, so a ball travels across a room although no Gaussian moves.

    \b
    Examples:
      tomgs demo                        # demo.mp4, 48 frames at 320x180
      tomgs demo -o frames/ --size 854x480 --device cuda
    """
    from tomgs.demo import demo_scene
    from tomgs.io.writer import check_output
    from tomgs.render import resolve_device

    width, height = _parse_size(size)
    check_output(output, overwrite)
    dev = resolve_device(device)
    gaussians, cams = demo_scene(num_frames, width, height)
    with _bar(num_frames, "render") as progress:
        report = render_frames(output, gaussians, cams, range(num_frames), background=(0.05, 0.05, 0.08),
                               device=dev, fps=24.0, what=f"at {width}x{height}", overwrite=overwrite,
                               progress=progress)
    click.echo(report.summary())


@main.command()
@click.argument("names", nargs=-1, metavar="[NAME]...")
@_user_errors
def example(names):
    """Print the installed path of each bundled example file NAME; with none, list them.

    \b
    Examples:
      tomgs example                                       # what is bundled
      tomgs fit "$(tomgs example bunny.mp4)" -o bunny.ply --budget 240
    """
    from tomgs.demo import EXAMPLE_FILES, example_file

    if not names:
        for name, what in EXAMPLE_FILES.items():
            click.echo(f"{name:22s} {what}")
        return
    for name in names:
        click.echo(example_file(name))


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str), help=_OUTPUT_HELP)
@click.option("--layer", "layer_paths", multiple=True, type=click.Path(path_type=str),
              help="a scene to composite over SCENE (e.g. a foreground from `fit --layer foreground`), each "
                   "with its own cameras at the same frames; repeat for more, the last in front")
@_render_options
@_user_errors
def render(scene, frames, output, device, background, fps, layer_paths, overwrite):
    """Render frames of SCENE (a .ply from `tomgs fit`) from its own cameras at their frame times.

    \b
    Examples:
      tomgs render scene.ply -o scene.mp4
      tomgs render scene.ply --frames 0:80 -o frames/ --device cuda
      tomgs render bg.ply --layer fg.ply -o out.mp4     # foreground over background
    """
    from tomgs.io.scene import load_scene
    from tomgs.layers import check_layers

    loaded = load_scene(scene)
    layers = [load_scene(path) for path in layer_paths]
    check_layers(loaded.cameras, [layer.cameras for layer in layers], list(layer_paths))
    plan = plan_render(output, loaded.cameras, frames, device, _background(background), overwrite)
    _render(loaded, loaded.model.render_inputs(), plan, fps,
                  layers=[(layer.model.render_inputs(), layer.cameras) for layer in layers])


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--plot", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="write a PNG histogram of temporal scales (log axis) here")
@click.option("--json", "as_json", is_flag=True, help="print the numbers as JSON instead of text")
@_overwrite_option
@_user_errors
def info(scene, plot, as_json, overwrite):
    """Counts, time coverage, temporal scales and opacities of SCENE (a .ply from `tomgs fit`).

    \b
    Examples:
      tomgs info scene.ply
      tomgs info scene.ply --plot sigmas.png       # histogram of temporal scales
      tomgs info scene.ply --json | jq .gaussians
    """
    import json

    from tomgs.io.scene import load_scene
    from tomgs.summary import check_png_path, format_summary, plot_temporal_scales, summarize
    from tomgs.outputs import check_file_output

    if plot is not None:
        check_file_output(check_png_path(plot), overwrite, what="plot")
    loaded = load_scene(scene)
    summary = summarize(loaded, scene)
    if plot is not None:
        plot_temporal_scales(loaded, plot)
    click.echo(json.dumps(summary, indent=1) if as_json else format_summary(summary))
    if plot is not None and not as_json:
        click.echo(f"{plot}: histogram of temporal scales")


def _background(text: str | None):
    """--background 'r,g,b' in [0, 1] -> tuple, or None."""
    rgb = None if text is None else parse_floats(text)
    if rgb is not None and (len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb)):
        raise UsageError(f"--background must be three numbers in [0, 1] like 0,0,0 or 1,1,1, got {text!r}")
    return rgb


def _floats(text: str | None, option: str, counts=(3,)):
    """'a,b,c' -> tuple of floats (one of `counts` many), or None; UsageError naming `option` otherwise."""
    if text is None:
        return None
    values = parse_floats(text)
    if len(values) not in counts:
        shape = " or ".join(",".join("xyz"[:n] if n > 1 else "s") for n in counts)
        raise UsageError(f"{option} takes {' or '.join(map(str, counts))} comma-separated numbers ({shape}), got {text!r}")
    return values


_SELECT_HELP = ("pick Gaussians (repeat to intersect): box:x0,y0,z0,x1,y1,z1 | sphere:x,y,z,r | time:t0,t1 (clip "
                "time 0..1) | index:FILE.txt | mask:FOLDER (world axes: x right, y down, z forward)")


_OVER_HELP = ("a scene to render behind (e.g. a background from `fit --layer background`), with its own cameras "
              "at the same frames; the rendered scene is composited over it as `render --layer` does")


@contextlib.contextmanager
def _bar(length: int, label: str, **options):
    """A progress bar with rate and ETA on stderr (stdout carries results only), none with -q;
    yields progress(done, item=None)."""
    if _VERBOSITY["level"] == 0:
        yield lambda done, item=None: None
        return
    with click.progressbar(length=length, label=label, file=sys.stderr, show_eta=True, show_percent=True,
                           **options) as bar:
        yield lambda done, item=None: bar.update(done - bar.pos, item)


def _render(scene, gaussians, plan, fps, layers=()) -> None:
    """Run a planned render (tomgs.jobs) with a progress bar and print its report."""
    with _bar(len(plan.positions), "render") as progress:
        report = run_render(plan, scene, gaussians, fps, layers, progress=progress)
    click.echo(report.summary())


def _is_scene_path(path: str) -> bool:
    return path.lower().endswith(".ply")


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(path_type=str),
              help="the edited scene (.ply), or a video / PNG folder to render the edit to")
@click.option("--select", "selectors", multiple=True, help=_SELECT_HELP)
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
              help="also render the edited scene here (" + _OUTPUT_HELP + ")")
@click.option("--over", type=click.Path(path_type=str), default=None, help="when rendering: " + _OVER_HELP)
@_render_options
@_user_errors
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

    move = dict(translate=_floats(translate, "--translate"), rotate=_floats(rotate, "--rotate"),
                scale=_floats(scale, "--scale", (1, 3)), centre=_floats(centre, "--centre"),
                duplicate=_floats(duplicate, "--duplicate"))
    if move["scale"] is not None and min(move["scale"]) <= 0:
        raise UsageError(f"--scale must be positive, got {scale!r}")
    rigid = any(move[k] is not None for k in ("translate", "rotate", "scale"))
    if keyframes and (rigid or remove):
        raise UsageError("--keyframes gives the motion: leave out --translate, --rotate, --scale and --remove")
    if not (rigid or remove or keyframes or move["duplicate"]):
        raise UsageError("nothing to do: give --translate, --rotate, --scale, --duplicate, --remove or --keyframes")
    if _is_scene_path(output) == bool(keyframes):
        raise UsageError(f"-o {output}: " + ("a time-varying edit (--keyframes) is rendered: give a video or a "
                                             "folder, not a .ply" if keyframes else
                                             "use a .ply to write the edited scene, or --keyframes to render"))
    if render_out and not _is_scene_path(output):
        raise UsageError("--render goes with a .ply output; -o already renders")
    if over and not (render_out or keyframes):
        raise UsageError("--over is what the render goes over: give --render (or --keyframes with a video -o)")
    if not keyframes:
        check_file_output(output, overwrite, what="edited scene")
    loaded = load_scene(scene)
    video = output if keyframes else render_out
    plan = plan_render(video, loaded.cameras, frames, device, _background(background), overwrite, over=over,
                       name=scene) if video else None
    keys = load_keyframes(keyframes, loaded.cameras) if keyframes else None
    edited, rows = edit_scene(loaded, selectors, remove=remove, **move)
    if keys is not None:
        _render(edited, keyframed_clouds(edited.model, edited.cameras, rows, keys), plan, fps)
        return
    save_scene(output, edited.model, edited.cameras, edited.info)
    what = "removed" if remove else ("duplicated" if move["duplicate"] else "edited")
    click.echo(f"{output}: {edited.info['edits'][-1]['selected']:,} Gaussians {what}; {len(edited.model):,} "
               f"Gaussians, {len(edited.cameras)} frames")
    if plan is not None:
        _render(edited, edited.model.render_inputs(), plan, fps)


@main.group()
def tets():
    """Gaussians as tetrahedra: export them (for Blender or a simulator), import moved vertices."""


@tets.command("export")
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="tets file to write (.ply, Blender axes)")
@click.option("--select", "selectors", multiple=True, help=_SELECT_HELP)
@click.option("--cage", is_flag=True, help="a connected voxel cage with the Gaussians bound into it (for soft "
              "bodies) instead of one tet per Gaussian")
@click.option("--cell", type=click.FloatRange(min=0, min_open=True), default=None,
              help="cage cell size in scene units; default: 1/8 of the selection's largest extent")
@_overwrite_option
@_user_errors
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
    if not _is_scene_path(output):
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
              help=_OUTPUT_HELP + "; or a .ply scene when SEQUENCE has one frame")
@click.option("--over", type=click.Path(path_type=str), default=None, help="when rendering: " + _OVER_HELP)
@_render_options
@_user_errors
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
    from tomgs.edit.transforms import check_bound, deformed_model, sequence_clouds, sequence_rows
    from tomgs.io.scene import load_scene, save_scene
    from tomgs.io.tets import load_sequence, load_tets
    from tomgs.outputs import check_file_output

    if _is_scene_path(output):
        check_file_output(output, overwrite, what="scene")
    loaded = load_scene(scene)
    mesh = load_tets(tets_file)
    check_bound(loaded.model, mesh, tets_file)
    vertices, numbers = load_sequence(sequence, mesh, max_frames=len(loaded.cameras))
    if _is_scene_path(output):
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
    plan = plan_render(output, loaded.cameras, frames, device, _background(background), overwrite, only=rows,
                       over=over, name=scene)
    _render(loaded, sequence_clouds(loaded.model, mesh, vertices, rows), plan, fps)


@main.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="vertex sequence to write (.npz); its cage is written beside it as NAME.cage.ply")
@click.option("--select", "selectors", multiple=True, help=_SELECT_HELP)
@click.option("--render", "render_out", type=click.Path(path_type=str), default=None,
              help="also render the shot here (" + _OUTPUT_HELP + ")")
@click.option("--over", type=click.Path(path_type=str), default=None, help="for --render: " + _OVER_HELP)
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
@_device_option
@click.option("--background", default=None, help="r,g,b in [0, 1] for --render; default: the scene's, else black")
@click.option("--fps", type=click.FloatRange(min=0.1), default=None,
              help="frames per second of the shot and the video; default: the scene's, else 25")
@_overwrite_option
@_user_errors
def simulate(scene, output, selectors, render_out, over, drop, spin, velocity, size, stiffness, damping, num_frames, cell,
             device, background, fps, overwrite):
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
    from tomgs.jobs import render_defaults
    from tomgs.io.tets import save_sequence, save_tets
    from tomgs.outputs import check_file_output
    from tomgs.render import resolve_device

    spin, velocity = _floats(spin, "--spin"), _floats(velocity, "--velocity")
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
    plan = plan_render(render_out, cams, None, device, _background(background), overwrite,
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
        _render(loaded, clouds, plan, fps)


def _set_verbosity(ctx, param, value) -> None:
    if not value:
        return
    if ctx.meta.setdefault("tomgs.verbosity", param.name) != param.name:
        raise UsageError("-q and -v contradict each other: give one")
    _VERBOSITY["level"] = 0 if param.name == "quiet" else 2


def _verbosity_options(group: click.Group) -> None:
    """-q and -v after the command too (`tomgs render ... -q` as well as `tomgs -q render ...`)."""
    for command in group.commands.values():
        if isinstance(command, click.Group):
            _verbosity_options(command)
            continue
        command.params += [
            click.Option(["-q", "--quiet"], is_flag=True, expose_value=False, callback=_set_verbosity,
                         help="no progress bars or notes on stderr: results and errors only"),
            click.Option(["-v", "--verbose"], is_flag=True, expose_value=False, callback=_set_verbosity,
                         help="also every training log row on stderr")]


_verbosity_options(main)

if __name__ == "__main__":
    main()
