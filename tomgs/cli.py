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


if __name__ == "__main__":
    main()
