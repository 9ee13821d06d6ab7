"""`tomgs view`: a scene in the browser (tomgs.viewer.server; needs the optional extra `[view]`)."""

from __future__ import annotations

import click

from tomgs.cli.common import device_option, user_errors
from tomgs.cli.params import Number


@click.command()
@click.argument("scene", type=click.Path(path_type=str))
@click.option("--layer", "layer_paths", multiple=True, type=click.Path(path_type=str),
              help="a scene shown over SCENE as `tomgs render --layer` composites it; repeat for more, the last "
                   "in front")
@click.option("--host", default="127.0.0.1", show_default=True,
              help="address to serve on (0.0.0.0: every network of this machine)")
@click.option("--port", type=Number(0, 65535, integer=True, what="a port"), default=8080, show_default=True,
              help="port to serve on (busy: the next free one; 0: any free one)")
@device_option
@user_errors
def view(scene, layer_paths, host, port, device):
    """Look at SCENE in the browser: scrub its time, see it from the clip's camera or orbit freely,
    and place a box or sphere to get the `tomgs edit --select` options that pick what it holds.
    Ctrl-C stops it.

    \b
    Examples:
      tomgs view scene.ply                     # then open the printed URL
      tomgs view bg.ply --layer fg.ply --port 8081
    """
    from tomgs.cli.preflight import check_device, check_scene

    check_device(device)
    for path in (scene, *layer_paths):
        check_scene(path)

    from tomgs.viewer.server import open_viewer

    viewer = open_viewer(scene, layer_paths, host=host, port=port, device=device, echo=click.echo)
    click.echo(f"tomgs view: {viewer.url}  (Ctrl-C stops)")
    viewer.serve_forever()
    click.echo("tomgs view: stopped")
