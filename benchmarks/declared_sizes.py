"""How much memory does each loader take for a file that declares at least 100 times what its bytes
can hold? A loader checks the sizes a file declares against its bytes before it allocates, so the
answer should be nothing beyond the process's own.

Every case is a small valid file of its kind, patched to declare more: images whose header claims a
16000x16000 (or 16384-wide) frame, a Motion JPEG whose frames do, an MP4 cut to 1% of its bytes under
an index of all its frames, a scene or tets file whose element count is 100x, a .tsog of 100,000
random Gaussians (its images most of its bytes, checksums intact) declaring 100x as many, a checkpoint of
stride-0 views declaring 200M rows, .npy / .npz arrays whose header shape is 100x. Each is loaded in a
child process by the public loader a command uses; the child reports its resident memory after its
imports and its peak during the load (Linux: VmHWM, reset before the load), and what the loader said.

    python -m benchmarks.declared_sizes [--cases png,jpeg_progressive,...]
    python -m benchmarks.declared_sizes --smoke        # three cases
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

if __package__:
    from .common import ROOT, demo_frames, environment, markdown_table, output_folder, smoke_scene, write_report
else:  # run as a file (the children are)
    from common import ROOT, demo_frames, environment, markdown_table, output_folder, smoke_scene, write_report

SIDE = 16000


def _frames(count: int = 3, width: int = 64, height: int = 48) -> list[np.ndarray]:
    return list(demo_frames(count, width, height))


def declare_jpeg(data: bytes, sof: bytes, width: int, height: int) -> bytes:
    """`data` with every JPEG frame header `sof` (FFC0 baseline, FFC2 progressive) declaring `width` x `height`."""
    out, at = bytearray(data), 0
    while (at := data.find(sof, at)) >= 0:
        out[at + 5:at + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
        at += 2
    return bytes(out)


def _image_folder(root: Path, name: str, encode) -> Path:
    folder = root / name
    folder.mkdir()
    for k, frame in enumerate(_frames()):
        (folder / f"{k:05d}.{name.split('_')[0]}").write_bytes(encode(frame))
    return folder


def _png(frame) -> bytes:
    import cv2

    data = bytearray(cv2.imencode(".png", frame[..., ::-1])[1].tobytes())
    data[16:24] = SIDE.to_bytes(4, "big") + SIDE.to_bytes(4, "big")  # IHDR width, height (the CRC no longer holds)
    return bytes(data)


def _jpeg(progressive: bool):
    def encode(frame) -> bytes:
        import cv2

        data = cv2.imencode(".jpg", frame[..., ::-1], [cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)])[1].tobytes()
        return declare_jpeg(data, b"\xff\xc2" if progressive else b"\xff\xc0", SIDE, SIDE)
    return encode


def _bmp(frame) -> bytes:
    import cv2

    data = bytearray(cv2.imencode(".bmp", frame[..., ::-1])[1].tobytes())
    data[18:26] = SIDE.to_bytes(4, "little") + SIDE.to_bytes(4, "little")
    return bytes(data)


def _tiff(frame) -> bytes:
    import cv2

    data = bytearray(cv2.imencode(".tiff", frame[..., ::-1], [cv2.IMWRITE_TIFF_COMPRESSION, 1])[1].tobytes())
    ifd = int.from_bytes(data[4:8], "little")
    for k in range(int.from_bytes(data[ifd:ifd + 2], "little")):
        entry = ifd + 2 + 12 * k
        if int.from_bytes(data[entry:entry + 2], "little") in (256, 257):  # ImageWidth, ImageLength
            width = 2 if data[entry + 2] == 3 else 4
            data[entry + 8:entry + 8 + width] = SIDE.to_bytes(width, "little")
    return bytes(data)


def _random_model(n: int):
    """A GaussianModel of `n` Gaussians of random attributes in front of the demo's cameras: a .tsog of
    it is mostly images, ~16 bytes a Gaussian as a fitted scene's."""
    import torch

    from tomgs.model import GaussianModel

    g = torch.Generator().manual_seed(0)
    means = torch.rand(n, 3, generator=g) * torch.tensor([4.0, 2.0, 4.0]) - torch.tensor([2.0, 1.0, -2.0])
    return GaussianModel(means, torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g) * 0.5 - 4.0,
                         torch.randn(n, generator=g), torch.randn(n, 1, 3, generator=g), torch.zeros(n, 0, 3),
                         torch.rand(n, generator=g), torch.randn(n, generator=g) * 0.3 - 1.5)


def _npy(array: np.ndarray, shape: tuple) -> bytes:
    """`array`'s bytes under an .npy header that declares `shape`."""
    import io

    from numpy.lib import format as npy

    header = io.BytesIO()
    npy.write_array_header_1_0(header, dict(descr=npy.dtype_to_descr(array.dtype), fortran_order=False,
                                            shape=shape))
    return header.getvalue() + array.tobytes()


def _checkpoint_of_views(rows: int) -> dict:
    """A tiny fit's checkpoint state whose per-Gaussian tensors are stride-0 views of `rows` rows."""
    import torch

    from tomgs.demo import demo_scene
    from tomgs.train import Trainer, preset

    gaussians, cams = demo_scene(num_frames=2, width=24, height=14)
    images = np.stack(_frames(2, 24, 14))
    points = gaussians["means"][::7].double().numpy()
    config = preset("quick", iterations=5, init_points_per_frame=50, max_gaussians=400)
    state = Trainer(images, cams, points, np.full((len(points), 3), 0.5, np.float32), config,
                    torch.device("cpu")).state_dict()
    return views_declaring(state, rows)


def views_declaring(state: dict, rows: int) -> dict:
    """A trainer's checkpoint state whose per-Gaussian tensors (parameters, Adam moments, densifier
    statistics) are stride-0 views of `rows` rows over their first row: a few KB saved."""

    def declared(t):
        return t.detach()[:1].expand(rows, *t.shape[1:])

    state["params"] = {k: declared(v) for k, v in state["params"].items()}
    for entry in state["optimizer"]["state"].values():
        entry["exp_avg"], entry["exp_avg_sq"] = declared(entry["exp_avg"]), declared(entry["exp_avg_sq"])
    state["densifier"]["grad_sum"] = declared(state["densifier"]["grad_sum"])
    state["densifier"]["seen"] = declared(state["densifier"]["seen"])
    return state


def _scaled_count(path: Path, element: bytes, factor: int = 100) -> None:
    """Multiply the count of PLY `element` in the header of `path` by `factor`."""
    data = path.read_bytes()
    end = data.index(b"end_header")
    head = data[:end]
    at = head.index(b"element " + element + b" ") + len(element) + 9
    stop = head.index(b"\n", at)
    count = int(head[at:stop])
    path.write_bytes(head[:at] + str(count * factor).encode() + head[stop:] + data[end:])


def make_cases(root: Path, names: list[str]) -> dict[str, tuple[str, str]]:
    """{case: (loader, path)} of crafted files under `root`."""
    import torch

    from tomgs.io.writer import write_frames

    cases = {}
    scene = smoke_scene(root / "scene.ply", frames=4, width=32, height=18)
    for name in names:
        path = root / name
        if name == "png":
            cases[name] = ("read_video", str(_image_folder(root, "png", _png)))
        elif name == "jpeg_baseline":
            cases[name] = ("read_video", str(_image_folder(root, "jpg_baseline", _jpeg(False))))
        elif name == "jpeg_progressive":
            cases[name] = ("read_video", str(_image_folder(root, "jpg_progressive", _jpeg(True))))
        elif name == "bmp":
            cases[name] = ("read_video", str(_image_folder(root, "bmp", _bmp)))
        elif name == "tiff":
            cases[name] = ("read_video", str(_image_folder(root, "tiff", _tiff)))
        elif name == "mjpeg_avi":
            write_frames(_frames(8), root / "small.avi")
            path = root / "mjpeg.avi"
            path.write_bytes(declare_jpeg((root / "small.avi").read_bytes(), b"\xff\xc0", SIDE, SIDE))
            cases[name] = ("read_video", str(path))
        elif name == "mp4_cut":
            write_frames(_frames(100), root / "whole.mp4")
            data = (root / "whole.mp4").read_bytes()
            media = data.index(b"mdat") + 4  # the index (moov) comes first: keep it and 1% of the frames' bytes
            path = root / "cut.mp4"
            path.write_bytes(data[:media + (len(data) - media) // 100])
            cases[name] = ("read_video", str(path))
        elif name == "scene_ply":
            path = root / "scene_count.ply"
            path.write_bytes(scene.read_bytes())
            _scaled_count(path, b"vertex")
            cases[name] = ("load_scene", str(path))
        elif name in ("tsog", "tsog_bomb"):
            import struct
            import zlib

            import tomgs
            from tomgs.io.quantise import grid_shape
            from tomgs.io.tsog import MAGIC

            small = tomgs.save_scene(root / "small.tsog", _random_model(100_000), tomgs.load_scene(scene).cameras, {})
            data = small.read_bytes()  # ~1.6 MB, its images most of it
            (length,) = struct.unpack("<Q", data[len(MAGIC):len(MAGIC) + 8])
            start = len(MAGIC) + 8
            header = json.loads(data[start:start + length])
            header["count"] *= 100
            header["grid"] = list(grid_shape(header["count"]))
            rest = data[start + length + 4:]
            if name == "tsog_bomb":  # each image one colour on the declared grid: a few kB of 10M pixels
                from tomgs.io.quantise import QUAT_TAG, encode_webp

                width, height = header["grid"]
                records = rest[sum(entry["bytes"] for entry in header["images"]):]
                images = []
                for entry in header["images"]:
                    pixels = np.zeros((height, width, entry["channels"]), np.uint8)
                    pixels[..., 3:] = QUAT_TAG  # quaternions' tags valid: the bomb is a well-formed file
                    images.append(encode_webp(pixels))
                    entry.update(bytes=len(images[-1]), crc32=zlib.crc32(images[-1]))
                rest = b"".join(images) + records
                header["padding"] = " " * (header["count"] // 64)  # as big as 64 Gaussians a byte lets it be
            text = json.dumps(header).encode()
            path = root / f"{name}.tsog"
            path.write_bytes(MAGIC + struct.pack("<Q", len(text)) + text + struct.pack("<I", zlib.crc32(text)) + rest)
            cases[name] = ("load_scene", str(path))
        elif name == "tets_ply":
            from tomgs.edit.cage import make_tets
            from tomgs.io.tets import save_tets

            loaded = __import__("tomgs").load_scene(scene)
            save_tets(root / "small_tets.ply", make_tets(loaded.model, np.arange(len(loaded.model))))
            path = root / "tets.ply"
            path.write_bytes((root / "small_tets.ply").read_bytes())
            _scaled_count(path, b"vertex")
            cases[name] = ("load_tets", str(path))
        elif name == "checkpoint":
            path = root / "views.ckpt"
            torch.save(_checkpoint_of_views(200_000_000), path)
            cases[name] = ("read_checkpoint", str(path))
        elif name == "npy":
            path = root / "c2w.npy"
            path.write_bytes(_npy(np.tile(np.eye(4), (4, 1, 1)), (400, 4, 4)))
            cases[name] = ("load_array", str(path))
        elif name == "npz_sequence":
            import zipfile

            path = root / "seq.npz"
            with zipfile.ZipFile(path, "w") as z:
                z.writestr("vertices.npy", _npy(np.zeros((3, 8, 3), np.float32), (300, 8, 3)))
            cases[name] = ("load_sequence_header", str(path))
        else:
            raise SystemExit(f"unknown case {name!r}")
    return cases


CASES = ["png", "jpeg_baseline", "jpeg_progressive", "bmp", "tiff", "mjpeg_avi", "mp4_cut", "scene_ply", "tsog",
         "tsog_bomb", "tets_ply", "checkpoint", "npy", "npz_sequence"]


def child(loader: str, path: str) -> None:
    """Load `path` with `loader` in this process; print {"imports_mib", "peak_mib", "said"} as JSON."""
    import resource

    import av  # noqa: F401 - the decoders' own imports, before the peak is measured
    import cv2  # noqa: F401

    from tomgs.errors import InputError
    from tomgs.io import read_video
    from tomgs.io.cameras import load_array
    from tomgs.io.scene import load_scene
    from tomgs.io.tets import load_tets
    from tomgs.train import read_checkpoint

    def status(field: str) -> float:
        """MiB of /proc/self/status's `field` (VmHWM: the peak since the last reset, VmRSS: now)."""
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith(field + ":")) / 1024

    try:  # the peak from here on (Linux: writing 5 to clear_refs resets VmHWM to the current size)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        before = status("VmRSS")

        def peak():
            return status("VmHWM")
    except OSError:  # elsewhere: the process's peak so far, which may hide a smaller load
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

        def peak():
            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    loaders = dict(read_video=read_video, load_scene=load_scene, load_tets=load_tets, read_checkpoint=read_checkpoint,
                   load_array=lambda p: load_array(p, "c2w"), load_sequence_header=_sequence_header)
    try:
        loaders[loader](path)
        said = "loaded"
    except InputError as e:
        said = f"refused: {str(e)[:140]}"
    except Exception as e:  # noqa: BLE001 - what a loader must not do, reported
        said = f"{type(e).__name__}: {str(e)[:140]}"
    print(json.dumps(dict(imports_mib=round(before, 1), peak_mib=round(peak(), 1), said=said)))


def _sequence_header(path):
    """What `tomgs tets import` does first with an .npz: its arrays' headers against their bytes."""
    from tomgs.io.tets import Tets, load_sequence

    like = Tets("gaussian", np.zeros((8, 3)), np.zeros((0, 4), np.int64), np.zeros(0, np.int64))
    return load_sequence(path, like)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--out", default=None)
    parser.add_argument("--smoke", action="store_true", help="three cases")
    parser.add_argument("--child", nargs=2, metavar=("LOADER", "PATH"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(*args.child)
        return
    names = ["png", "jpeg_progressive", "checkpoint"] if args.smoke else args.cases.split(",")
    folder = output_folder(args.out, args.smoke, "declared_sizes")
    env = environment("cpu", "declared_sizes", argv)
    results = []
    with tempfile.TemporaryDirectory(prefix="tomgs-declared-") as tmp:
        cases = make_cases(Path(tmp), names)
        for name, (loader, path) in cases.items():
            held = sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file()) if Path(path).is_dir() \
                else Path(path).stat().st_size
            out = subprocess.run([sys.executable, "-m", "benchmarks.declared_sizes", "--child", loader, path],
                                 cwd=ROOT, capture_output=True, text=True, timeout=600,
                                 env=dict(os.environ, PYTHONPATH=str(ROOT)))
            try:
                found = json.loads(out.stdout.strip().splitlines()[-1])
            except (IndexError, ValueError):
                found = dict(imports_mib=None, peak_mib=None, said=f"child failed: {out.stderr.strip()[-200:]}")
            grew = None if found["peak_mib"] is None else round(found["peak_mib"] - found["imports_mib"], 1)
            results.append(dict(case=name, loader=loader, file_bytes=held, **found, grew_mib=grew))
    table = markdown_table(["file", "loader", "bytes", "resident after imports (MiB)", "peak during the load (MiB)",
                            "grew (MiB)", "what the loader said"],
                           [[r["case"], r["loader"], r["file_bytes"], r["imports_mib"], r["peak_mib"], r["grew_mib"],
                             r["said"][:90]] for r in results])
    write_report(folder, "declared_sizes", "Peak memory of each loader on files declaring 100x what they hold", env,
                 table, results)


if __name__ == "__main__":
    main()
