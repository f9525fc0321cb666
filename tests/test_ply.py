"""PLY point clouds (`coin_cl.scene.ply`); 3DGS PLYs are tested with their container in
tests/test_gs_splats.py."""

import numpy as np

from coin_cl.scene.ply import read_points_ply, write_points_ply


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
