"""What a frame's tile-key sort would cost split in two (issue 15: a camel frame spends 0.27 of its
1.41 ms of kernels in the sort).

Now (`render._sort_and_range`): M intersections, int64 keys `tile << 32 | depth bits`, sorted over
32 + tile bits (43 at 854x480: six 8-bit passes over 12 bytes a pair). Split: the V visible Gaussians
sorted once by depth (float32 keys, four passes over 8 bytes a pair); their entries then written in
that order, so a stable sort by the tile alone (int32 keys, 11 bits: two passes over 8 bytes a pair)
gives the same list, ties in depth still in Gaussian order. This times the sorts only, on synthetic
keys (V Gaussians of random depth, M entries on random tiles), both ways in turns, and checks on
each size that both give the same ids. What the split adds is not timed: the scan and the key writing
would read Gaussians through the depth order.

    python benchmarks/sort_split.py --device cuda --json sort_split.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import torch
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_raster import parse_count  # noqa: E402
from tomgs.runtime import sort_pairs  # noqa: E402

TILES = 54 * 30  # 854x480 in 16x16 tiles
TILE_BITS = TILES.bit_length()


def synthetic(entries: int, gaussians: int, device: torch.device, seed: int = 0):
    """(depth [V] float32 > 0, owner [M] int64 the Gaussian of each entry, ascending, tile [M] int64)."""
    gen = torch.Generator().manual_seed(seed)
    depth = torch.empty(gaussians).uniform_(0.5, 20.0, generator=gen)
    owner = torch.sort(torch.randint(0, gaussians, (entries,), generator=gen)).values
    tile = torch.randint(0, TILES, (entries,), generator=gen)
    return depth.to(device), owner.to(device), tile.to(device)


def depth_bits(depth: torch.Tensor) -> torch.Tensor:
    """A positive float32's bits as an int64: the same order as the floats."""
    return depth.view(torch.int32).to(torch.int64)


class Now:
    """The present sort: int64 `tile << 32 | depth bits` over M entries in Gaussian order."""

    def __init__(self, depth, owner, tile):
        m = owner.numel()
        self.keys0 = (tile << 32) | depth_bits(depth)[owner]
        self.ids0 = owner.to(torch.int32)
        self.keys = torch.empty(2 * m, dtype=torch.int64, device=owner.device)
        self.ids = torch.empty(2 * m, dtype=torch.int32, device=owner.device)

    def reset(self):
        m = self.ids0.numel()
        self.keys[:m].copy_(self.keys0)
        self.ids[:m].copy_(self.ids0)

    def run(self):
        sort_pairs(self.keys, self.ids, self.ids0.numel(), 32 + TILE_BITS)

    def result(self) -> torch.Tensor:
        return self.ids[: self.ids0.numel()].clone()


class Split:
    """Depth first over the V Gaussians (float32 keys), then the entries, written in that order,
    by tile alone (int32 keys over TILE_BITS bits)."""

    def __init__(self, depth, owner, tile):
        v, m, dev = depth.numel(), owner.numel(), owner.device
        self.depth0, self.gaussian0 = depth, torch.arange(v, dtype=torch.int32, device=dev)
        self.depth = wp.zeros(2 * v, dtype=wp.float32, device=str(dev))
        self.gaussian = wp.zeros(2 * v, dtype=wp.int32, device=str(dev))
        # the entries as a key writer would give them after the depth sort (made here once, not timed)
        order = torch.sort(depth, stable=True).indices
        per_gaussian = torch.bincount(owner, minlength=v)
        first = torch.cumsum(per_gaussian, 0) - per_gaussian
        entry = _in_order(order, first, per_gaussian)
        self.tile0, self.ids0 = tile[entry].to(torch.int32), owner[entry].to(torch.int32)
        self.tile = wp.zeros(2 * m, dtype=wp.int32, device=str(dev))
        self.ids = wp.zeros(2 * m, dtype=wp.int32, device=str(dev))
        self.v, self.m = v, m

    def reset(self):
        wp.to_torch(self.depth)[: self.v].copy_(self.depth0)
        wp.to_torch(self.gaussian)[: self.v].copy_(self.gaussian0)
        wp.to_torch(self.tile)[: self.m].copy_(self.tile0)
        wp.to_torch(self.ids)[: self.m].copy_(self.ids0)

    def run(self):
        wp.utils.radix_sort_pairs(self.depth, self.gaussian, self.v)
        wp.utils.radix_sort_pairs(self.tile, self.ids, self.m, 0, TILE_BITS)

    def result(self) -> torch.Tensor:
        return wp.to_torch(self.ids)[: self.m].clone()


def _in_order(order, first, per_gaussian) -> torch.Tensor:
    """The entry numbers of Gaussians `order[0]`, `order[1]`, ... in turn (owner ascending gives each
    Gaussian's entries the run [first[g], first[g] + per_gaussian[g]))."""
    counts = per_gaussian[order]
    starts = torch.repeat_interleave(first[order], counts)
    within = torch.arange(int(counts.sum()), device=order.device) - torch.repeat_interleave(
        torch.cumsum(counts, 0) - counts, counts)
    return starts + within


def timed(way, device, repeats: int) -> float:
    """Median ms of `way.run()` over `repeats`, inputs restored before each (not timed)."""
    times = []
    for _ in range(repeats):
        way.reset()
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            torch.cuda.synchronize()
            start.record()
            way.run()
            end.record()
            torch.cuda.synchronize()
            times.append(start.elapsed_time(end))
        else:
            t0 = time.perf_counter()
            way.run()
            times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--entries", default="1M,2M,4M,8M", help="intersection counts M, comma-separated")
    p.add_argument("--per-gaussian", default="4,8", help="M / V: entries a visible Gaussian has")
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    wp.init()
    device = torch.device(args.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    rows = []
    for m in map(parse_count, args.entries.split(",")):
        for ratio in (int(r) for r in args.per_gaussian.split(",")):
            depth, owner, tile = synthetic(m, max(1, m // ratio), device)
            now, split = Now(depth, owner, tile), Split(depth, owner, tile)
            for way in (now, split):
                way.reset()
                way.run()
            if not torch.equal(now.result(), split.result()):
                raise SystemExit(f"M={m}, M/V={ratio}: the split sort gives another order")
            now_ms, split_ms = [], []
            for _ in range(3):  # in turns
                now_ms.append(timed(now, device, args.repeats))
                split_ms.append(timed(split, device, args.repeats))
            row = dict(entries=m, gaussians=depth.numel(), now_ms=min(now_ms), split_ms=min(split_ms),
                       ratio=min(split_ms) / min(now_ms))
            rows.append(row)
            print(f"M {m:>9,} V {depth.numel():>9,}: now {row['now_ms']:.4f} ms, split {row['split_ms']:.4f} ms "
                  f"({row['ratio']:.2f}x), same ids", flush=True)
    if args.json:
        args.json.write_text(json.dumps(dict(device=str(torch.cuda.get_device_name(device)) if device.type == "cuda"
                                             else "cpu", tile_bits=TILE_BITS, rows=rows), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
