"""How counts read in what tomgs prints: a number with its noun in agreement."""

from __future__ import annotations


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """'1 frame', '2 frames', '12,000 Gaussians': `n` (thousands separated) and `noun`, or its
    `plural` (default noun + 's') unless n is 1."""
    return f"{n:,} {noun if n == 1 else plural or noun + 's'}"
