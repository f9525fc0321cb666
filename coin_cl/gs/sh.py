"""Real spherical harmonics up to degree 3, evaluated per view in torch (3DGS convention).

Colour = SH(dir) + 0.5, with the DC coefficient stored as (rgb - 0.5) / C0, so that an
all-zero higher-order tail leaves a view-independent colour.
"""

from __future__ import annotations

from torch import Tensor

MAX_SH_DEGREE = 3
C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per channel for a given degree: (degree + 1)^2."""
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"SH degree {degree} not in [0, {MAX_SH_DEGREE}]")
    return (degree + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """[..., 3] colour in [0, 1] -> [..., 3] DC coefficient."""
    return (rgb - 0.5) / C0


def sh_to_rgb(sh0: Tensor) -> Tensor:
    """[..., 3] DC coefficient -> [..., 3] colour."""
    return sh0 * C0 + 0.5


def eval_sh(degree: int, coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate SH colour.

    Args:
        degree: active degree (0..3); coefficients beyond (degree + 1)^2 are ignored.
        coeffs: [N, K, 3] with K >= (degree + 1)^2.
        dirs: [N, 3] viewing directions (need not be normalised).
    Returns:
        [N, 3] colour, clamped at 0 from below (as 3DGS), not above.
    """
    res = C0 * coeffs[:, 0]
    if degree > 0:
        d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
        res = res - C1 * y * coeffs[:, 1] + C1 * z * coeffs[:, 2] - C1 * x * coeffs[:, 3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (
                res
                + C2[0] * xy * coeffs[:, 4]
                + C2[1] * yz * coeffs[:, 5]
                + C2[2] * (2.0 * zz - xx - yy) * coeffs[:, 6]
                + C2[3] * xz * coeffs[:, 7]
                + C2[4] * (xx - yy) * coeffs[:, 8]
            )
            if degree > 2:
                res = (
                    res
                    + C3[0] * y * (3 * xx - yy) * coeffs[:, 9]
                    + C3[1] * xy * z * coeffs[:, 10]
                    + C3[2] * y * (4 * zz - xx - yy) * coeffs[:, 11]
                    + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * coeffs[:, 12]
                    + C3[4] * x * (4 * zz - xx - yy) * coeffs[:, 13]
                    + C3[5] * z * (xx - yy) * coeffs[:, 14]
                    + C3[6] * x * (xx - 3 * yy) * coeffs[:, 15]
                )
    return (res + 0.5).clamp_min(0.0)
