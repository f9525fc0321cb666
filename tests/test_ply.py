"""PLY: 3DGS layout round trip (exact), property names, point clouds."""

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from coin_cl.scene.ply import (
    GaussianPly,
    read_gaussians_ply,
    read_points_ply,
    write_gaussians_ply,
    write_points_ply,
)


def _gaussians(rng, n=57, k=15):
    f = np.float32
    return GaussianPly(
        means=rng.normal(size=(n, 3)).astype(f),
        sh_dc=rng.normal(size=(n, 3)).astype(f),
        sh_rest=rng.normal(size=(n, k, 3)).astype(f),
        opacities=rng.normal(size=n).astype(f),
        log_scales=rng.normal(size=(n, 3)).astype(f),
        quats=rng.normal(size=(n, 4)).astype(f),
    )


@pytest.mark.parametrize("k", [0, 3, 15])
def test_gaussian_ply_round_trip_exact(tmp_path, k):
    g = _gaussians(np.random.default_rng(k), k=k)
    p = tmp_path / "point_cloud.ply"
    write_gaussians_ply(p, g)
    h = read_gaussians_ply(p)
    for name in ("means", "sh_dc", "sh_rest", "opacities", "log_scales", "quats"):
        np.testing.assert_array_equal(getattr(h, name), getattr(g, name), err_msg=name)
    assert len(h) == len(g)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_gaussian_ply_layout_matches_3dgs(tmp_path):
    g = _gaussians(np.random.default_rng(1), n=4, k=3)
    p = tmp_path / "g.ply"
    write_gaussians_ply(p, g)
    v = PlyData.read(str(p))["vertex"]
    names = [prop.name for prop in v.properties]
    want = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    want += [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2"]
    want += ["rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == want
    assert all(prop.val_dtype in ("f4", "float32", "<f4") for prop in v.properties)
    # channel-major f_rest: f_rest_0..2 are the red coefficients of SH bands 1..3
    np.testing.assert_array_equal(v.data["f_rest_1"], g.sh_rest[:, 1, 0])
    np.testing.assert_array_equal(v.data["f_rest_3"], g.sh_rest[:, 0, 1])
    np.testing.assert_array_equal(v.data["rot_0"], g.quats[:, 0])  # w first
    np.testing.assert_array_equal(v.data["nx"], 0)


def test_points_ply_round_trip_and_zero_colours(tmp_path):
    rng = np.random.default_rng(2)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.integers(0, 256, size=(100, 3)) / 255.0
    write_points_ply(tmp_path / "p.ply", pts, cols)
    p2, c2 = read_points_ply(tmp_path / "p.ply")
    np.testing.assert_array_equal(p2, pts)
    np.testing.assert_allclose(c2, cols, atol=1e-6)
    write_points_ply(tmp_path / "z.ply", pts, np.zeros((100, 3)))
    _, cz = read_points_ply(tmp_path / "z.ply")
    assert cz is None  # all-zero colours mean unknown
    write_points_ply(tmp_path / "n.ply", pts, None)
    assert read_points_ply(tmp_path / "n.ply")[1] is None


def test_non_3dgs_ply_is_rejected_with_file_name(tmp_path):
    arr = np.zeros(3, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp_path / "pts.ply"))
    with pytest.raises(ValueError, match="pts.ply.*not a 3DGS PLY"):
        read_gaussians_ply(tmp_path / "pts.ply")
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        read_gaussians_ply(tmp_path / "missing.ply")
