import math

import torch

from coin_cl.gs.sh import eval_sh, num_sh_bases, rgb_to_sh, sh_to_rgb


def _sphere(n: int) -> torch.Tensor:
    """Fibonacci sphere: near-uniform directions, so means approximate sphere integrals."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = math.pi * (1 + 5**0.5) * i
    return torch.stack([phi.sin() * theta.cos(), phi.sin() * theta.sin(), phi.cos()], -1)


def test_dc_roundtrip_and_view_independence():
    g = torch.Generator().manual_seed(0)
    rgb = torch.rand(50, 3, generator=g, dtype=torch.float64)
    assert torch.allclose(sh_to_rgb(rgb_to_sh(rgb)), rgb)
    coeffs = torch.zeros(50, 16, 3, dtype=torch.float64)
    coeffs[:, 0] = rgb_to_sh(rgb)
    dirs = torch.randn(50, 3, generator=g, dtype=torch.float64)
    for deg in range(4):
        assert torch.allclose(eval_sh(deg, coeffs, dirs), rgb)


def test_basis_is_orthonormal_up_to_degree_3():
    dirs = _sphere(40_000)
    n = dirs.shape[0]
    basis = []
    for k in range(num_sh_bases(3)):
        c = torch.zeros(n, 16, 3, dtype=torch.float64)
        c[:, k, 0] = 0.1  # small, so that +0.5 keeps the clamp at 0 inactive
        basis.append((eval_sh(3, c, dirs)[:, 0] - 0.5) / 0.1)
    B = torch.stack(basis, 1)
    gram = 4 * math.pi * (B.T @ B) / n
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_degree_limits_which_coefficients_are_used():
    g = torch.Generator().manual_seed(1)
    c = torch.randn(20, 16, 3, generator=g) * 0.1
    d = torch.randn(20, 3, generator=g)
    c2 = c.clone()
    c2[:, 4:] = 5.0  # degree >= 2 coefficients must not matter at degree 1
    assert torch.equal(eval_sh(1, c, d), eval_sh(1, c2, d))
    assert not torch.allclose(eval_sh(2, c, d), eval_sh(2, c2, d))
