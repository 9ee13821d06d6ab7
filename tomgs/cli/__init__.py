"""The `tomgs` command line: a thin click layer that parses, calls the library, and prints.

    app       the group `main`, which gathers the commands
    common    what the commands share: the error decorator, shared options, verbosity, progress bars
    poses fit eval render info export edit tets simulate view demo
              one module per command, named after it (demo also holds `example`)

`main` is resolved lazily, as the package's other public names are.
"""

from __future__ import annotations

from tomgs._lazy import lazy_exports

_EXPORTS = {"main": "tomgs.cli.app"}

__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, globals(), _EXPORTS)
