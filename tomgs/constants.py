"""Rasterizer constants shared by the Warp kernels and the torch reference (REFERENCES.md)."""

TILE_SIZE = 16  # pixels per tile side; one tile is one CUDA block of 256 threads
ALPHA_MIN = 1.0 / 255.0  # a Gaussian below this opacity (temporal or per pixel) is skipped
ALPHA_MAX = 0.99  # per-pixel alpha clamp
T_MIN = 1e-4  # compositing stops before transmittance would fall to this; that Gaussian is not drawn
EPS2D = 0.3  # screen-space dilation added to the 2D covariance diagonal (pixels^2)
RADIUS_SIGMAS = 3.33  # bounding radius in standard deviations, shrunk further by opacity
FOV_CLAMP = 1.3  # the EWA Jacobian is evaluated at x/z clamped to 1.3 tan(half field of view)
QUAT_EPS = 1e-12  # quaternions are divided by max(|q|, QUAT_EPS): a zero quaternion is the identity
ONE_MINUS_ALPHA_FLOOR = 1e-6  # floor on (1 - alpha) when the backward divides transmittance back out
