"""Profilers: where the time of a frame or a training step goes (GPU time per kernel, host time).

Run from the repository root as `python -m benchmarks.profilers.<name>`. (Not `profile`: a script run as
a file from benchmarks/ would find that folder before the standard library's `profile`, which cProfile,
and Warp through it, import.)"""
