"""What the tile sort's depth bits change in a fitted scene's frames: each frame rendered as the
renderer sorts (a key's tile and the high bits of its depth, constants.DEPTH_SORT_BITS) and
with every bit of float32 depth read, the PSNR between the two and the share of pixels that differ
by more than 1/255 (issue 15: the sort in fewer radix passes).

    python benchmarks/depth_bits.py scene.ply --json depth_bits.json
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch

import tomgs
from tomgs import constants
from tomgs.render import frame as render
from tomgs.render.frame import rasterize


def frames(inputs: dict, cams, device: torch.device) -> list[torch.Tensor]:
    """Every frame of `cams` rendered from `inputs`, [H, W, 3] float32 on `device`."""
    viewmats, Ks = cams.viewmats(device), cams.Ks(device)
    with torch.no_grad():
        return [rasterize(**inputs, viewmat=viewmats[k], K=Ks[k], width=cams.width, height=cams.height,
                          t=float(cams.times[k]))[0] for k in range(len(cams))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    device = torch.device(args.device)
    scene = tomgs.load_scene(args.scene, device=device)
    inputs = {k: v.detach() for k, v in scene.model.render_inputs().items()}
    cams = scene.cameras
    sorted_as_rendered = frames(inputs, cams, device)
    low_bit = render.sort_low_bit(cams.width, cams.height)
    render.sort_low_bit = lambda width, height: 0  # every depth bit
    try:
        exact = frames(inputs, cams, device)
    finally:
        render.sort_low_bit = constants.sort_low_bit
    psnr, differing, largest = [], [], 0.0  # per frame; the largest difference of any pixel
    for ours, full in zip(sorted_as_rendered, exact):
        diff = (ours - full).abs()
        mse = float((diff.double() ** 2).mean())
        psnr.append(math.inf if mse == 0 else -10 * math.log10(mse))
        differing.append(float((diff.amax(-1) > 1 / 255).float().mean()))
        largest = max(largest, float(diff.max()))
    finite = [p for p in psnr if p < math.inf]
    out = dict(scene=str(args.scene), gaussians=len(scene.model), size=[cams.width, cams.height],
               depth_bits_read=32 - low_bit, psnr_min=round(min(psnr), 2),
               psnr_mean=round(sum(finite) / len(finite), 2) if finite else None,  # of the frames that differ
               identical_frames=len(psnr) - len(finite),
               pixels_past_1_255_max=round(max(differing), 6), largest_difference=round(largest, 4))
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
