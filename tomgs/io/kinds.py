"""What a path names, told from its name and the file system before it is opened, with nothing heavy
imported: the door (tomgs.cli.preflight) asks here before it reads a file.

    check_scene_path(path)   an existing file that is not a video: a scene file to read
    STATIC_FORMATS           the extensions of a static splat file (tomgs.io.splats writes them)
    CAMERA_FILES             the files that the cameras of a clip are exported as (tomgs.edit.export)
"""

from __future__ import annotations

from pathlib import Path

from tomgs.errors import InputError
from tomgs.io.video import VIDEO_EXTS

STATIC_FORMATS = (".ply", ".splat", ".spz", ".sog")
CAMERA_FILES = ("cameras.json", "transforms.json", "sparse/0/cameras.txt", "sparse/0/images.txt",
                "sparse/0/points3D.txt")
SCENE_FIX = "write scenes with `tomgs fit` or tomgs.save_scene"  # what to do about a file that is no scene


def check_scene_path(path) -> Path:
    """`path` as a Path once it names an existing file; InputError saying what to give otherwise (a
    video in a scene's place is named as such)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"scene file {path} does not exist" + (" (it is a folder)" if path.is_dir() else "")
                         + f": give the path of a .ply or .tsog scene ({SCENE_FIX})")
    if path.suffix.lower() in VIDEO_EXTS:
        raise InputError(f"{path} is a video, not a scene: give the .ply that `tomgs fit {path.name} -o scene.ply` "
                         f"writes")
    return path
