"""The project-wide error for bad user input.

`InputError` is a ValueError whose message names the file or value and the fix. Library code
raises it for anything a caller passed or a file held; the CLI turns it into exit code 2.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (missing file, corrupt video, mismatched masks, ...): message says the fix."""
