"""Splats, the one Gaussians container: 3DGS PLY round trip (exact), the 3DGS property layout, the
renderer's view (`gaussians()`) and its inverse, what the models export, bad input."""

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from coin_cl.engine import Gaussians
from coin_cl.gs.sh import C0, C1
from coin_cl.gs.splats import Splats


def _splats(seed: int, n: int = 57, k: int = 15) -> Splats:
    g = torch.Generator().manual_seed(seed)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    return Splats(r(n, 3), r(n, 4), r(n, 3), r(n), r(n, 3), r(n, k, 3))


@pytest.mark.parametrize("k", [0, 3, 15])
def test_ply_round_trip_exact(tmp_path, k):
    g = _splats(k, k=k)
    p = tmp_path / "point_cloud.ply"
    g.to_ply(p, sh_degree=None)  # as held (the default pads to degree 3: tests/test_gs_export.py)
    h = Splats.from_ply(p)
    for a, b, name in zip(h.tensors(), g.tensors(), ("means", "quats", "log_scales", "opacity", "dc", "rest"),
                          strict=True):  # fmt: skip
        assert a.dtype == torch.float32 and torch.equal(a, b), name
    assert len(h) == len(g) and h.sh_degree == {0: 0, 3: 1, 15: 3}[k]
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_ply_layout_matches_3dgs(tmp_path):
    g = _splats(1, n=4, k=3)
    p = tmp_path / "g.ply"
    g.to_ply(p, sh_degree=None)
    v = PlyData.read(str(p))["vertex"]
    names = [prop.name for prop in v.properties]
    want = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    want += [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2"]
    want += ["rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == want
    assert all(prop.val_dtype in ("f4", "float32", "<f4") for prop in v.properties)
    # channel-major f_rest: f_rest_0..2 are the red coefficients of SH bands 1..3
    np.testing.assert_array_equal(v.data["f_rest_1"], g.sh_rest[:, 1, 0].numpy())
    np.testing.assert_array_equal(v.data["f_rest_3"], g.sh_rest[:, 0, 1].numpy())
    np.testing.assert_array_equal(v.data["rot_0"], g.quats[:, 0].numpy())  # w first
    np.testing.assert_array_equal(v.data["opacity"], g.opacity_logits.numpy())
    np.testing.assert_array_equal(v.data["nx"], 0)


def test_non_3dgs_ply_is_rejected_with_file_name(tmp_path):
    arr = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "pts.ply"))
    with pytest.raises(ValueError, match="pts.ply.*not a 3DGS PLY"):
        Splats.from_ply(tmp_path / "pts.ply")
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        Splats.from_ply(tmp_path / "missing.ply")


def test_shapes_are_checked():
    g = _splats(0, n=5, k=3)
    with pytest.raises(ValueError, match="quats"):
        Splats(g.means, g.quats[:, :3], g.log_scales, g.opacity_logits, g.sh_dc, g.sh_rest)
    with pytest.raises(ValueError, match="sh_rest"):
        Splats(g.means, g.quats, g.log_scales, g.opacity_logits, g.sh_dc, torch.zeros(5, 4, 3))


def test_renderer_view_activates_and_evaluates_sh():
    g = _splats(2, n=6, k=3)
    r = g.gaussians()  # no camera: the view-independent colour
    assert isinstance(r, Gaussians)
    torch.testing.assert_close(r.scales, g.log_scales.exp())
    torch.testing.assert_close(r.opacities, torch.sigmoid(g.opacity_logits))
    torch.testing.assert_close(r.colors, (C0 * g.sh_dc + 0.5).clamp_min(0))
    # Seen from a camera: degree-1 SH along the direction from the camera (3DGS's sign convention).
    eye = torch.tensor([0.3, -2.0, 0.5])
    d = g.means - eye
    d = d / d.norm(dim=1, keepdim=True)
    want = C0 * g.sh_dc - C1 * (d[:, 1:2] * g.sh_rest[:, 0] - d[:, 2:3] * g.sh_rest[:, 1]
                                + d[:, 0:1] * g.sh_rest[:, 2]) + 0.5  # fmt: skip
    torch.testing.assert_close(g.gaussians(eye).colors, want.clamp_min(0))


def test_from_gaussians_inverts_the_view():
    n = 8
    gen = torch.Generator().manual_seed(3)
    src = Gaussians(torch.randn(n, 3, generator=gen), torch.randn(n, 4, generator=gen),
                    torch.rand(n, 3, generator=gen) + 0.01, torch.rand(n, generator=gen) * 0.9 + 0.05,
                    torch.rand(n, 3, generator=gen))  # fmt: skip
    back = Splats.from_gaussians(src).gaussians()
    for a, b in zip(back.tensors(), src.tensors(), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="RGB"):
        Splats.from_gaussians(Gaussians(src.means, src.quats, src.scales, src.opacities, torch.rand(n, 5)))


@pytest.mark.parametrize("kind", ["3dgs", "scaffold"])
def test_models_export_splats_that_render_like_the_model(tmp_path, kind):
    """A model's export (seen from the camera: Scaffold-GS decodes its colours there, 3DGS keeps
    its SH), written to PLY and read back, renders the model's own image."""
    from coin_cl.gs.base import splat
    from coin_cl.gs.gaussians import GaussianModel
    from coin_cl.gs.scaffold import ScaffoldModel
    from coin_cl.gs.synthetic import tiny_scene

    scene = tiny_scene(n=60, n_views=2, seed=0)
    pts = scene.noisy_points()
    if kind == "3dgs":
        model = GaussianModel(pts, None, extent=2.0, seed=0)
        with torch.no_grad():  # a view-dependent colour, so the SH's direction convention is tested
            model.p["shN"].normal_(0.0, 0.3, generator=torch.Generator().manual_seed(1))
    else:
        model = ScaffoldModel(pts, None, extent=2.0, seed=0)
    cam = scene.views[0].camera
    with torch.no_grad():
        want = model.render(cam, 10**9, backend="torch").image
        model.export_gaussians(cam.center_t).to_ply(tmp_path / "m.ply")
    g = Splats.from_ply(tmp_path / "m.ply")
    assert len(g) == (model.n_primitives if kind == "3dgs" else len(g.means)) and len(g) > 0
    gs = g.gaussians(cam.center_t)
    with torch.no_grad():
        image = splat(cam, *gs.tensors(), backend="torch", background=None, return_depth=False,
                      training=False)[0]  # fmt: skip
    assert want.std() > 0.01  # something was drawn
    torch.testing.assert_close(image, want, atol=2e-4, rtol=0)
