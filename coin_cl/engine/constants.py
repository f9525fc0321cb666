"""Every numerical constant of the renderer, in one place.

`kernels/common.h` holds the same values as C macros; `tests/test_constants.py` checks that the two
agree, so a change here without the matching change there fails CI.
"""

TILE_SIZE = 16  # pixels per tile side; the CPU kernels vectorise a tile row as two float8
NEAR_PLANE = 0.01  # camera-space z below which a Gaussian is culled
FAR_PLANE = 1e10  # camera-space z above which a Gaussian is culled
EPS2D = 0.3  # low-pass filter added to the 2D covariance diagonal (pixels^2)
ALPHA_THRESHOLD = 1.0 / 255.0  # a splat with alpha below this is skipped for that pixel
MAX_ALPHA = 0.99  # alpha is clamped to this; gradients are zero where the clamp is active
TRANSMITTANCE_MIN = 1e-4  # compositing stops before T would drop to or below this
ONE_MINUS_ALPHA_MIN = 1e-6  # floor of (1 - alpha) when transmittance is divided back out
SIGMA_RADIUS = 3.0  # splat radius in standard deviations (drives tile binning)
FRUSTUM_MARGIN = 0.3  # EWA Jacobian: x/z clamped to the image edge + 0.3 x tan(half fov) (gsplat)
EIGEN_FLOOR = 0.1  # floor under the discriminant when the largest 2D eigenvalue is taken (3DGS)
MAX_RADIUS_PX = 1 << 24  # radii are clamped here before the float->int conversion
MAX_PAIRS_DEFAULT = 1 << 27  # cap on (tile, Gaussian) pairs per image (512 MiB of int32 ids)
MAX_CHANNELS = 128  # largest feature count a rasterize variant is compiled for

# Feature warping (kernels/warp.cl; passed to the kernels as arguments, not -D defines).
WARP_DEPTH_TOL = 0.01  # z-buffer: winners within 1% of the nearest candidate's camera z (relative)
WARP_SRC_DEPTH_TOL = 0.01  # source visibility: a point > 1% behind the rendered depth is occluded
