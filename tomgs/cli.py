"""The `tomgs` command line: a thin click layer that parses, calls the library, and prints."""

from __future__ import annotations

import click

from tomgs import __version__


class UsageError(click.ClickException):
    """A bad input: clear message, exit code 2, nothing written."""

    exit_code = 2


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tomgs")
def main() -> None:
    """Editable video as static 3D Gaussians with temporal opacity (TOM-GS)."""


@main.command()
@click.argument("video", type=click.Path(path_type=str))
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="cameras JSON to write (schema in tomgs.cameras)")
@click.option("--masks", type=click.Path(path_type=str), default=None,
              help="folder of masks, one per source frame (white = moving, ignored for poses)")
@click.option("--frames", default=None, help="frame range start:stop:step, e.g. 0:80 or ::2")
@click.option("--method", default="auto", show_default=True,
              help="auto, identity, a cameras .json / AnyCam c2w .npy / COLMAP text folder, or an .onnx model")
@click.option("--focal", type=float, default=None, help="focal length in pixels of the (resized) frames")
@click.option("--max-side", type=int, default=None, help="resize frames so that max(W, H) <= N")
def poses(video, output, masks, frames, method, focal, max_side):
    """Estimate per-frame cameras of VIDEO (a video file or a folder of frames)."""
    from tomgs.io import InputError, read_video
    from tomgs.poses import estimate_cameras

    try:
        clip = read_video(video, frames=frames, max_side=max_side, masks=masks)
        with click.progressbar(length=2 * len(clip), label="poses", show_eta=True, show_percent=True) as bar:
            def progress(done, total):
                bar.update(done - bar.pos)

            cams, _, _, report = estimate_cameras(clip, method=method, focal=focal, progress=progress)
        cams.save(output)
    except InputError as e:
        raise UsageError(str(e)) from None
    for note in report.notes:
        click.echo(f"  note: {note}")
    click.echo(f"{output}: {report.summary()}")


if __name__ == "__main__":
    main()
