"""The `tomgs` group: the commands, one module each, gathered under one click group."""

from __future__ import annotations

import click

from tomgs import __version__
from tomgs.cli.common import Group, set_verbosity, verbosity_options
from tomgs.cli.compress import compress
from tomgs.cli.demo import demo, example
from tomgs.cli.edit import edit
from tomgs.cli.eval import evaluate_command
from tomgs.cli.export import export
from tomgs.cli.fit import fit
from tomgs.cli.info import info
from tomgs.cli.poses import poses
from tomgs.cli.render import render
from tomgs.cli.simulate import simulate
from tomgs.cli.tets import tets
from tomgs.cli.view import view


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="tomgs")
@click.option("-q", "--quiet", is_flag=True, help="no progress bars or notes on stderr: results and errors only")
@click.option("-v", "--verbose", is_flag=True, help="also every training log row of `fit` on stderr")
def main(quiet: bool, verbose: bool) -> None:
    """Editable video as static 3D Gaussians with temporal opacity (TOM-GS).

    Results go to stdout (`--json -` makes it pure JSON); progress bars and notes go to stderr.
    """
    set_verbosity(quiet, verbose)


for command in (poses, fit, evaluate_command, render, info, export, compress, edit, tets, simulate, view, demo,
                example):
    main.add_command(command)
verbosity_options(main)
