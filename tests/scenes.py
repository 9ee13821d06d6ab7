"""Random Gaussian scenes for rasterizer tests, with the awkward cases mixed in on purpose."""

from __future__ import annotations

import os

import numpy as np
import torch
import warp as wp

from tomgs import cameras

# Seeds are fixed so CI is repeatable; set TOMGS_TEST_SEED to draw a different family of scenes.
SEED_BASE = int(os.environ.get("TOMGS_TEST_SEED", "0"))

INPUT_NAMES = ("means", "quats", "scales", "opacities", "colors", "t_means", "t_scales", "viewmat", "K", "background")


def devices() -> list[str]:
    """CPU always; CUDA too when both torch and Warp can use a GPU."""
    found = ["cpu"]
    if torch.cuda.is_available():
        wp.init()
        if wp.is_cuda_available():
            found.append("cuda")
    return found


def look_at(eye, target, dtype=torch.float64) -> torch.Tensor:
    """World->camera [4,4] (OpenCV axes) for a camera at `eye` looking at `target`, y down."""
    return torch.linalg.inv(torch.as_tensor(cameras.look_at(torch.as_tensor(eye).tolist(),
                                                            torch.as_tensor(target).tolist()), dtype=dtype))


def random_scene(seed: int, n: int = 120, width: int = 45, height: int = 37, sh_degree: int | None = None,
                 dtype=torch.float64) -> dict:
    """A small scene seen by a tilted camera: a dense overlapping cluster, Gaussians off screen,
    behind the camera and near the near plane, random temporal windows, and a background."""
    g = torch.Generator().manual_seed(SEED_BASE * 1000 + seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=dtype)

    def randn(*shape):
        return torch.randn(*shape, generator=g, dtype=dtype)

    view = look_at(randn(3) * 0.3 + torch.tensor([0.2, -0.1, -3.0], dtype=dtype), randn(3) * 0.1, dtype)
    c2w = torch.linalg.inv(view)
    # points in camera space, then to world
    kind = torch.randint(0, 10, (n,), generator=g)
    cam = torch.stack([randn(n) * 0.6, randn(n) * 0.5, 1.0 + rand(n) * 5.0], -1)
    cam[kind == 0] = torch.stack([randn(n) * 0.1, randn(n) * 0.1, 2.5 + rand(n) * 0.2], -1)[kind == 0]  # overlap
    cam[kind == 1, 0] += 6.0 * torch.sign(randn(n))[kind == 1]  # off screen to the side
    cam[kind == 2, 2] = -rand(n)[kind == 2] * 3.0  # behind the camera
    cam[kind == 3, 2] = 0.011 + rand(n)[kind == 3] * 0.05  # hugging the near plane
    means = cam @ c2w[:3, :3].T + c2w[:3, 3]
    fx = width * (0.7 + 0.6 * rand(1)).item()
    K = torch.tensor([[fx, 0.0, width / 2 + randn(1).item()], [0.0, fx * (0.9 + 0.2 * rand(1)).item(),
                                                                  height / 2 + randn(1).item()], [0.0, 0.0, 1.0]], dtype=dtype)
    colors = rand(n, 3) if sh_degree is None else randn(n, (sh_degree + 1) ** 2, 3) * 0.5
    return dict(
        means=means,
        quats=randn(n, 4) * (0.2 + 2.0 * rand(n, 1)),
        scales=torch.exp(randn(n, 3) * 0.6 - 2.3),
        opacities=0.05 + 0.9 * rand(n),
        colors=colors,
        t_means=rand(n),
        t_scales=torch.exp(randn(n) * 0.8 - 1.5),
        viewmat=view,
        K=K,
        background=rand(3),
        width=width,
        height=height,
        t=rand(1).item(),
    )


def split(scene: dict, device: str, requires_grad: bool = True) -> tuple[list[torch.Tensor], dict]:
    """(tensor inputs in INPUT_NAMES order on `device`, the remaining keyword arguments)."""
    tensors = [scene[k].detach().to(device).requires_grad_(requires_grad) for k in INPUT_NAMES]
    rest = {k: v for k, v in scene.items() if k not in INPUT_NAMES}
    return tensors, rest


def render_both(scene: dict, device: str, **kw):
    """Render with the Warp rasterizer on `device` and with the float64 reference on the CPU.
    Returns (outputs, reference outputs, input tensors of each, weights) where a shared random
    loss sum(image * w_img) + sum(alpha * w_alpha) can be differentiated."""
    import tomgs

    # both sides see the same float32-representable values, so the comparison measures arithmetic only
    scene = {k: (v.float().double() if isinstance(v, torch.Tensor) else v) for k, v in scene.items()}
    scene["t"] = float(torch.tensor(scene["t"], dtype=torch.float32))
    ours_in, rest = split(scene, device)
    ref_in, _ = split(scene, "cpu")
    args = dict(width=rest["width"], height=rest["height"], t=rest["t"], **kw)

    def call(fn, tensors):
        named = dict(zip(INPUT_NAMES, tensors))
        background = named.pop("background")
        return fn(**named, background=background, **args)

    ours = call(tomgs.rasterize, ours_in)
    ref = call(tomgs.rasterize_reference, ref_in)
    return ours, ref, ours_in, ref_in


def rel_l2(a: torch.Tensor, b: torch.Tensor) -> float:
    """|a - b| / |b| in float64; 0 when both are exactly zero."""
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    denom = b.norm()
    if denom == 0:
        return float(a.norm())
    return float((a - b).norm() / denom)


def object_scene(frames: int = 5, width: int = 32, height: int = 24):
    """A small scene for editing tests: a wall of flat, opaque Gaussians at z = 4 and a ball of
    Gaussians at z = 2.5 in front of it, both alive all clip long, seen by a camera that drifts
    right. Returns (GaussianModel, Cameras, object indices int64 [n]); the ball comes last."""
    import numpy as np

    from tomgs.cameras import Cameras, intrinsics
    from tomgs.cameras import look_at as c2w_look_at
    from tomgs.model import GaussianModel

    g = torch.Generator().manual_seed(SEED_BASE * 1000 + 11)
    gx, gy = torch.meshgrid(torch.linspace(-2.6, 2.6, 16), torch.linspace(-2.0, 2.0, 13), indexing="ij")
    wall = torch.stack([gx.flatten(), gy.flatten(), torch.full((gx.numel(),), 4.0)], 1)
    ball = torch.randn(60, 3, generator=g) * 0.18 + torch.tensor([0.0, 0.0, 2.5])
    colors = torch.cat([torch.rand(len(wall), 3, generator=g) * 0.5, torch.tensor([[0.9, 0.2, 0.1]]).repeat(60, 1)])
    means = torch.cat([wall, ball])
    model = GaussianModel.from_points(means, colors, torch.full((len(means),), 0.5), t_scale=5.0, max_sh_degree=0,
                                      opacity=0.95, sizes=torch.cat([torch.full((len(wall),), 0.25),
                                                                     torch.full((60,), 0.08)]))
    with torch.no_grad():
        model.log_scales[: len(wall), 2] = float(np.log(1e-4))  # the wall is flat: its tets must be thickened
    c2w = np.stack([c2w_look_at([0.1 * k, 0.0, 0.0], [0.1 * k, 0.0, 3.0]) for k in range(frames)])
    cams = Cameras.create(c2w, intrinsics(26.0, width, height), width, height)
    return model, cams, np.arange(len(wall), len(means))


# ---- scene files (tomgs.io.scene version 2) taken apart and put back, for tests of bad files -------

def clip_parts(path) -> tuple[bytes, bytes, bytes]:
    """(PLY header and vertex rows, the clip's JSON, the camera records) of a version 2 scene file."""
    from tomgs.io.scene import TRAILER_MAGIC

    data = open(path, "rb").read()
    end = data.index(TRAILER_MAGIC)
    start = end + len(TRAILER_MAGIC) + 8
    length = int.from_bytes(data[start - 8:start], "little")
    return data[:end], data[start:start + length], data[start + length:]


def with_clip_text(path, dst, text: bytes):
    """A copy of scene `path` at `dst` whose clip JSON is `text` (its length field rewritten to match)."""
    from tomgs.io.scene import TRAILER_MAGIC

    head, _, records = clip_parts(path)
    open(dst, "wb").write(head + TRAILER_MAGIC + len(text).to_bytes(8, "little") + text + records)
    return dst


def patch_clip(path, dst, **fields):
    """A copy of scene `path` at `dst` whose clip JSON has `fields` set (None removes a key)."""
    import json

    clip = json.loads(clip_parts(path)[1])
    clip.update(fields)
    return with_clip_text(path, dst, json.dumps({k: v for k, v in clip.items() if v is not None}).encode())


def rewrite_vertex(path, dst, edit):
    """A copy of scene `path` at `dst` with its vertex rows replaced by `edit(rows)` (a structured
    array of float32 properties, named as in the file); the clip after them kept."""
    from plyfile import PlyData

    from tomgs.io.scene import HEADER_NOTE, ply_header

    rows = edit(PlyData.read(str(path))["vertex"].data.copy())
    data = open(path, "rb").read()
    trailer = data[len(clip_parts(path)[0]):]
    open(dst, "wb").write(ply_header(rows.dtype.names, len(rows), [HEADER_NOTE]) + rows.tobytes() + trailer)
    return dst


def inria_load_ply(path, max_sh_degree: int) -> dict:
    """graphdeco-inria/gaussian-splatting GaussianModel.load_ply, transcribed (numpy): the first
    element, names by prefix, the assert on the f_rest_ count for the degree it was started with."""
    from plyfile import PlyData

    el = PlyData.read(str(path)).elements[0]
    xyz = np.stack([np.asarray(el[k]) for k in ("x", "y", "z")], axis=1)
    opacities = np.asarray(el["opacity"])[..., None]
    dc = np.stack([np.asarray(el[f"f_dc_{i}"]) for i in range(3)], axis=1)[:, :, None]
    extra = sorted((p.name for p in el.properties if p.name.startswith("f_rest_")), key=lambda x: int(x.split("_")[-1]))
    assert len(extra) == 3 * (max_sh_degree + 1) ** 2 - 3
    rest = np.stack([np.asarray(el[k]) for k in extra], axis=1).reshape(len(xyz), 3, -1) if extra else \
        np.zeros((len(xyz), 3, 0))
    scales = np.stack([np.asarray(el[p.name]) for p in sorted(
        (p for p in el.properties if p.name.startswith("scale_")), key=lambda p: int(p.name.split("_")[-1]))], axis=1)
    rots = np.stack([np.asarray(el[p.name]) for p in sorted(
        (p for p in el.properties if p.name.startswith("rot")), key=lambda p: int(p.name.split("_")[-1]))], axis=1)
    return {"means": xyz, "opacity_logits": opacities[:, 0], "sh_dc": dc[:, :, 0], "sh_rest": rest.transpose(0, 2, 1),
            "log_scales": scales, "quats": rots}
