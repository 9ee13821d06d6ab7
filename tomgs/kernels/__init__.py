"""Warp kernels of the rasterizer: no torch, no file I/O, one source for CPU and CUDA.

Stages (docs/design.md): `project` (3D -> 2D, temporal opacity, culls), `binning` (tile keys, sort
helpers, tile ranges) and `raster` (per-tile compositing and its hand-written backward).
Generated adjoints are off: every backward here is written by hand.
"""
