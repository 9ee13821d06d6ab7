"""The benchmark suite: one script per claim tomgs makes (benchmarks/README.md)."""
