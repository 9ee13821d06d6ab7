"""Rasterizer constants shared by the Warp kernels and the torch reference (3DGS's values, docs/design.md),
and the spherical-harmonics basis: its constants and the degree a coefficient count has."""

import math

TILE_SIZE = 16  # pixels per tile side; one tile is one CUDA block of 256 threads
ALPHA_MIN = 1.0 / 255.0  # a Gaussian below this opacity (temporal or per pixel) is skipped
ALPHA_MAX = 0.99  # per-pixel alpha clamp
T_MIN = 1e-4  # compositing stops before transmittance would fall to this; that Gaussian is not drawn
EPS2D = 0.3  # screen-space dilation added to the 2D covariance diagonal (pixels^2)
RADIUS_SIGMAS = 3.33  # bounding radius in standard deviations, shrunk further by opacity
FOV_CLAMP = 1.3  # the EWA Jacobian is evaluated at x/z clamped to 1.3 tan(half field of view)
QUAT_EPS = 1e-12  # quaternions are divided by max(|q|, QUAT_EPS): a zero quaternion is the identity
ONE_MINUS_ALPHA_FLOOR = 1e-6  # floor on (1 - alpha) when the backward divides transmittance back out
# The tile-key sort reads a key's tile and only the high bits of its float32 depth: a radix sort makes a
# pass per 8 bits, and at 854x480 (11 bits of tile) the whole depth took 6 passes where 29 bits of it (sign,
# exponent, 20 of mantissa) take 5. Depths within ~2^-20 relative tie (about the projection's own float32
# rounding of a depth), and tied Gaussians are drawn in index order, the reference's order too. 21 bits
# (4 passes) sorted camel's frames 33% quicker but cost a small CPU fit of a flat static clip 2.2 dB (43.40
# -> 41.21; 25 bits, 29 and every bit: 43.40; tests/train/test_stiff_clips.py): docs/notes/rasterizer.md.
DEPTH_SORT_BITS = 29


def sort_low_bit(width: int, height: int) -> int:
    """The lowest bit of a tile key `tile << 32 | float32 depth bits` that the sort reads, for a frame
    of width x height pixels: at least DEPTH_SORT_BITS of depth, rounded up to whole 8-bit passes."""
    tile_bits = (-(-int(width) // TILE_SIZE) * -(-int(height) // TILE_SIZE)).bit_length()
    key_bits = 32 + tile_bits
    passes = -(-(tile_bits + DEPTH_SORT_BITS) // 8)
    return max(0, key_bits - 8 * passes)


MAX_SIDE = 16384
"""The largest image side in pixels, for width and height read from files. Nothing in a cameras
file or a scene header bounds these numbers, and renders allocate width x height x 3 floats (a
65536 side asks for 51 GB): 16384 (16K) is above what video codecs encode (H.264 and HEVC levels
stop at 8192) and what GPUs take as a texture side, and one float RGB frame of it is 3.2 GB."""

# the spherical-harmonics basis of degree 0..3 (3DGS's constants; tomgs.render.sh and tomgs.kernels.sh)
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
# a view direction is (mean - centre) / max(|mean - centre|, SH_DIR_EPS): torch's normalize, its default eps
SH_DIR_EPS = 1e-12


def sh_degree_of(num_coeffs: int) -> int:
    """Degree d of an SH block with (d + 1)^2 coefficients; raises for other counts."""
    degree = int(round(math.sqrt(num_coeffs))) - 1
    if degree < 0 or degree > 3 or (degree + 1) ** 2 != num_coeffs:
        raise ValueError(f"SH coefficients per channel must be 1, 4, 9 or 16, got {num_coeffs}")
    return degree
