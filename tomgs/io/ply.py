"""Reading PLY files safely: the header read with a byte cap and its element counts checked against
the file's size before plyfile parses anything, every parse error an InputError naming the file.
The formats built on PLY (scenes, tets files, static 3DGS exports) live beside this module.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from tomgs.errors import InputError

PLY_HEADER_CAP = 1 << 20
"""Bytes read to find a PLY header's end before any parsing: 1 MiB, about 700 times the header of a
fitted scene (1.4 kB: 70 property lines and the JSON comment with the fit's settings) and far above
a tets file's or a Blender export's; a 50 MB comment is refused at once instead of parsed."""

# bytes per value of each PLY scalar type (plyfile's names and the spec's)
_PLY_SIZES = {name: size for size, names in ((1, "char uchar int8 uint8"), (2, "short ushort int16 uint16"),
                                             (4, "int uint int32 uint32 float float32"), (8, "double float64"))
              for name in names.split()}


@dataclass
class PlyLayout:
    """What a PLY header declares: `elements` [(name, row count)] in file order, and `data_end`, the
    byte offset where their rows end when every row has a fixed size (binary, no list properties),
    else None. Bytes after `data_end` are not part of the PLY data; readers stop before them.
    `comments`: the header's comment lines, in order, without the word `comment`."""

    elements: list[tuple[str, int]]
    data_end: int | None
    comments: list[str]


def ply_layout(path: Path, what: str = "PLY file", fix: str = "") -> PlyLayout:
    """The layout of the PLY file `path`, from a header read with a byte cap (PLY_HEADER_CAP), checked
    against the file before anything is allocated: each element's rows take at least their scalar
    sizes (a list at least its count; in ASCII two characters per value), and all rows together must
    fit in the bytes after the header. InputError otherwise."""
    path = Path(path)
    fix = f": {fix}" if fix else ""
    if not path.is_file():
        raise InputError(f"{what} {path} does not exist" + (" (it is a folder)" if path.is_dir() else "") + fix)
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(min(size, PLY_HEADER_CAP))
    if not head.startswith((b"ply\n", b"ply\r")):
        raise InputError(f"{path} is not a PLY file (it does not start with 'ply'){fix}")
    end = re.search(rb"^end_header[ \t]*\r?\n", head, re.MULTILINE)
    if end is None:
        if size > PLY_HEADER_CAP:
            raise InputError(f"{path}: the PLY header is longer than {PLY_HEADER_CAP:,} bytes (no 'end_header' "
                             f"line in them); a header of that size is not one tomgs wrote or reads{fix}")
        raise InputError(f"{path} is a damaged or truncated PLY file (its header has no 'end_header' line){fix}")
    body = size - end.end()
    ascii_format = False
    elements: list[list] = []  # [name, count, least bytes per row]
    fixed_rows = True  # every row's size is known from the header alone
    comments = []
    for line in head[:end.start()].decode("latin-1").splitlines()[1:]:
        words = line.split()
        if words[:1] == ["comment"]:
            comments.append(line.split(None, 1)[1] if len(words) > 1 else "")
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            ascii_format = len(words) > 1 and words[1] == "ascii"
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isascii() or not words[2].isdigit():
                raise InputError(f"{path}: bad PLY element line {line[:80]!r} (want 'element NAME COUNT'){fix}")
            elements.append([words[1], int(words[2]), 0])
        elif words[0] == "property" and elements:
            kind = words[2] if len(words) > 2 and words[1] == "list" else words[1] if len(words) > 1 else ""
            fixed_rows = fixed_rows and not ascii_format and words[1:2] != ["list"]
            elements[-1][2] += 2 if ascii_format else _PLY_SIZES.get(kind, 1)
    for name, count, row in elements:
        least = count * max(row, 1)
        if least > body:
            raise InputError(f"{path} is a damaged or truncated PLY file: element {name!r} declares {count:,} rows, "
                             f"at least {least:,} bytes, but only {body:,} bytes are left for it{fix}")
        body -= least
    data_end = end.end() + sum(count * row for _, count, row in elements) if fixed_rows else None
    return PlyLayout([(name, count) for name, count, _ in elements], data_end, comments)


def read_ply(path, what: str = "PLY file", fix: str = "", known_list_len=None):
    """PlyData of `path` after `ply_layout`'s checks; every parse error is an InputError naming the
    file. `known_list_len` ({element: {list property: length}}) memory-maps fixed-length lists."""
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    ply_layout(path, what, fix)
    try:
        return PlyData.read(str(path), known_list_len=known_list_len or {})
    except (PlyParseError, ValueError, EOFError, OSError, IndexError, KeyError, TypeError, OverflowError) as e:
        raise InputError(f"{path} is a damaged or truncated PLY file ({str(e)[:200]})" + (f": {fix}" if fix else "")) \
            from None
