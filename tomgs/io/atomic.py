"""Publishing a finished temporary file or folder under its final name.

Outputs are written under a private temporary name (tempfile's 0600/0700 modes) and renamed when
complete; before the rename they get the modes a plain `open`/`mkdir` would have given them.
"""

from __future__ import annotations

import os
from pathlib import Path


def publish(tmp, path) -> Path:
    """chmod `tmp` to the process's default mode for a new file or folder, then rename it to `path`."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, (0o777 if os.path.isdir(tmp) else 0o666) & ~umask)
    os.replace(tmp, path)
    return Path(path)
