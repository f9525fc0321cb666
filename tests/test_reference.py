"""The float64 twins themselves, checked by finite differences (torch.autograd.gradcheck) on tiny
single-tile scenes, so that the references the kernels are held to are right."""

import torch

from coin_cl.engine import reference
from coin_cl.engine.geometry import quat_to_rotmat
from coin_cl.testing import look_at_camera, random_gaussians


def test_project_gradcheck():
    gs = random_gaussians(6, seed=0, scale_range=(0.05, 0.2))
    viewmat, K = look_at_camera(16, 16)
    viewmat[:3, 3] = torch.tensor([0.05, -0.03, 0.1], dtype=torch.float64)

    def f(means, quats, scales):
        m2, con, dep, _ = reference.project(means, quats, scales, viewmat, K, 16, 16)
        return m2, con, dep

    inputs = [t.clone().requires_grad_(True) for t in (gs.means, gs.quats, gs.scales)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_rasterize_gradcheck_single_tile():
    g = torch.Generator().manual_seed(1)
    n = 5
    means2d = 2 + 12 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    # well-conditioned conics of splats 1.5-3 px wide
    sig = 1.5 + 1.5 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    rho = 0.4 * (torch.rand(n, generator=g, dtype=torch.float64) - 0.5)
    a, c, b = sig[:, 0] ** 2, sig[:, 1] ** 2, rho * sig[:, 0] * sig[:, 1]
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], 1)
    opac = 0.2 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64)  # away from the 0.99 clamp
    feats = torch.rand(n, 3, generator=g, dtype=torch.float64)
    depths = torch.rand(n, generator=g, dtype=torch.float64)
    radii = torch.full((n,), 8, dtype=torch.int32)
    bg = torch.rand(3, generator=g, dtype=torch.float64)

    def f(m2, con, op, ft, b):
        return reference.rasterize_to_pixels(m2, con, op, ft, depths, radii, 16, 16, b)

    inputs = [t.clone().requires_grad_(True) for t in (means2d, conics, opac, feats, bg)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_quat_to_rotmat_is_a_rotation_for_any_norm():
    q = torch.randn(50, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(2)) * 7
    R = quat_to_rotmat(q)
    eye = torch.eye(3, dtype=torch.float64).expand(50, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))
