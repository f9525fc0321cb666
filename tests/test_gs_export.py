"""Gaussian export formats (`coin_cl.gs.export`, `Splats.to_ply`): the padded 3DGS PLY read back by
field name (plyfile) and as graphdeco's SIBR reads it (a fixed 62-float record after the header),
NaN rows left out and counted, the .splat record, the graphdeco folder, `export_run` and the CLI,
unreadable PLYs as one line."""

import json
import logging

import numpy as np
import pytest
import torch
from plyfile import PlyData

from coin_cl.gs.export import (
    SPLAT_RECORD_BYTES,
    export_run,
    graphdeco_camera,
    read_splat,
    write_graphdeco,
    write_splat,
)
from coin_cl.gs.sh import C0
from coin_cl.gs.splats import Splats
from coin_cl.scene.conventions import look_at
from coin_cl.scene.ply import read_points_ply
from coin_cl.scene.types import Camera

GRAPHDECO_FIELDS = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _splats(n=40, k=0, seed=0) -> Splats:
    g = torch.Generator().manual_seed(seed)

    def r(*s, scale=1.0):
        return torch.randn(*s, generator=g) * scale

    return Splats(r(n, 3), r(n, 4), r(n, 3, scale=0.5) - 3, r(n), r(n, 3, scale=0.5), r(n, k, 3))


def fixed_record_read(path):
    """What SIBR does: skip the header, read N records of 62 float32 (degree 3)."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    n = int(next(line.split()[2] for line in header.splitlines() if line.startswith("element vertex")))
    assert len(data) - end == n * 62 * 4  # the record size the header declares is SIBR's
    return header, np.frombuffer(data, "<f4", offset=end).reshape(n, 62)


def test_ply_padded_to_degree_3_by_name_and_fixed_record(tmp_path):
    g = _splats(k=0)  # coin-cl's models export degree 0
    p = tmp_path / "point_cloud.ply"
    assert g.to_ply(p) == 0
    v = PlyData.read(str(p))["vertex"]
    assert [prop.name for prop in v.properties] == GRAPHDECO_FIELDS
    assert all(prop.val_dtype in ("f4", "float32", "<f4") for prop in v.properties)
    header, rec = fixed_record_read(p)
    assert "format binary_little_endian" in header
    for j, name in enumerate(GRAPHDECO_FIELDS):  # the fixed-record view equals the named fields
        np.testing.assert_array_equal(rec[:, j], v.data[name])
    np.testing.assert_array_equal(rec[:, 0:3], g.means.numpy())
    np.testing.assert_array_equal(rec[:, 6:9], g.sh_dc.numpy())
    np.testing.assert_array_equal(rec[:, 9:54], 0)  # padding
    np.testing.assert_array_equal(rec[:, 54], g.opacity_logits.numpy())
    np.testing.assert_array_equal(rec[:, 58:62], g.quats.numpy())
    h = Splats.from_ply(p)
    assert h.sh_degree == 3
    # zero bands: the colour seen from anywhere is the degree-0 colour
    cam = torch.tensor([5.0, -2.0, 1.0])
    torch.testing.assert_close(h.gaussians(cam).colors, g.gaussians().colors)


def test_ply_degree_1_kept_channel_major_then_padded(tmp_path):
    g = _splats(n=6, k=3, seed=1)
    g.to_ply(tmp_path / "a.ply")
    _, rec = fixed_record_read(tmp_path / "a.ply")
    rest = rec[:, 9:54].reshape(6, 3, 15)  # channel-major: [N, channel, coefficient]
    np.testing.assert_array_equal(rest[:, :, :3], g.sh_rest.numpy().transpose(0, 2, 1))
    np.testing.assert_array_equal(rest[:, :, 3:], 0)
    g.to_ply(tmp_path / "b.ply", sh_degree=None)  # as held
    assert len(PlyData.read(str(tmp_path / "b.ply"))["vertex"].properties) == 17 + 9


def test_nan_rows_dropped_and_counted(tmp_path, caplog):
    g = _splats(n=10)
    g.means[2, 1] = float("nan")
    g.log_scales[7, 0] = float("inf")
    with caplog.at_level(logging.WARNING):
        assert g.to_ply(tmp_path / "g.ply") == 2
    assert "left out 2 of 10" in caplog.text
    h = Splats.from_ply(tmp_path / "g.ply")
    keep = [i for i in range(10) if i not in (2, 7)]
    assert len(h) == 8 and torch.equal(h.means, g.means[keep])
    assert all(torch.isfinite(t).all() for t in h.tensors())
    bad = _splats(n=3)
    bad.opacity_logits[:] = float("nan")
    with pytest.raises(ValueError, match="all 3 Gaussians hold NaN"):
        bad.to_ply(tmp_path / "bad.ply")
    assert not (tmp_path / "bad.ply").exists()


def test_splat_record_round_trip_within_u8(tmp_path):
    g = _splats(n=50, seed=3)
    g.means[4, 0] = float("inf")
    p = tmp_path / "s.splat"
    assert write_splat(g, p) == 1
    assert p.stat().st_size == 49 * SPLAT_RECORD_BYTES
    d = read_splat(p)
    keep = torch.ones(50, dtype=torch.bool)
    keep[4] = False
    f = g.subset(keep)
    # sorted by size * opacity, largest first
    alpha = torch.sigmoid(f.opacity_logits)
    key = torch.exp(f.log_scales.sum(1)) * alpha
    order = torch.argsort(-key, stable=True).numpy()
    np.testing.assert_array_equal(d["means"], f.means.numpy()[order])
    np.testing.assert_allclose(d["scales"], torch.exp(f.log_scales).numpy()[order], rtol=1e-6)
    rgb = np.clip(0.5 + C0 * f.sh_dc.numpy()[order], 0, 1)
    np.testing.assert_allclose(d["rgba"][:, :3], rgb, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(d["rgba"][:, 3], alpha.numpy()[order], atol=0.5 / 255 + 1e-6)
    q = f.quats.numpy()[order]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(d["quats"], q, atol=0.5 / 128 + 1e-6)
    assert np.all(np.diff(np.prod(d["scales"], 1) * d["rgba"][:, 3]) <= 1e-3)  # descending (u8 alpha)
    p.write_bytes(p.read_bytes()[:-5])
    with pytest.raises(ValueError, match="s.splat.*not a whole number of 32-byte"):
        read_splat(p)


def _camera(name="frame_0001.png"):
    K = np.array([[300.0, 0, 160], [0, 310.0, 120], [0, 0, 1]])
    V = look_at(np.array([1.0, 2.0, -3.0]), np.zeros(3), np.array([0.0, -1.0, 0.0]))
    return Camera(K=K, viewmat=V, width=320, height=240, name=name)


def test_graphdeco_folder(tmp_path):
    g = _splats(n=5)
    cam = _camera()
    out = tmp_path / "gd"
    write_graphdeco(g, out, [cam, _camera("b.jpg")], iteration=7000, source_path=tmp_path)
    ply = out / "point_cloud" / "iteration_7000" / "point_cloud.ply"
    assert [p.name for p in PlyData.read(str(ply))["vertex"].properties] == GRAPHDECO_FIELDS
    doc = json.loads((out / "cameras.json").read_text())
    assert [c["id"] for c in doc] == [0, 1] and doc[0]["img_name"] == "frame_0001"
    c = doc[0]
    assert set(c) == {"id", "img_name", "width", "height", "position", "rotation", "fx", "fy"}
    # graphdeco's convention: position = camera centre, rotation = camera-to-world (OpenCV axes)
    np.testing.assert_allclose(c["position"], [1.0, 2.0, -3.0], atol=1e-12)
    R = np.array(c["rotation"])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = R.T, -R.T @ np.array(c["position"])
    np.testing.assert_allclose(w2c, cam.viewmat, atol=1e-12)
    assert (c["fx"], c["fy"], c["width"], c["height"]) == (300.0, 310.0, 320, 240)
    cfg = (out / "cfg_args").read_text()
    assert cfg.startswith("Namespace(sh_degree=3, source_path=") and f"'{tmp_path.resolve()}'" in cfg
    assert graphdeco_camera(3, cam)["id"] == 3


def test_export_run_and_cli(tmp_path, capsys):
    from coin_cl.cli import main

    run = tmp_path / "run"
    g = _splats(n=12)
    g.means[0] = float("nan")
    g.to_ply(run / "eval" / "point_cloud.ply", sh_degree=None)
    out, n, dropped = export_run(run, "splat", tmp_path / "x.splat")
    assert (n, dropped) == (11, 0)  # the run's PLY already left the NaN row out
    assert main(["export", str(run), "--format", "ply", "--out", str(tmp_path / "y.ply")]) == 0
    assert "wrote 11 Gaussians as ply" in capsys.readouterr().out
    fixed_record_read(tmp_path / "y.ply")
    assert main(["export", str(tmp_path / "y.ply"), "--format", "graphdeco", "--out", str(tmp_path / "gd"),
                 "--iteration", "5"]) == 0  # fmt: skip
    assert (tmp_path / "gd" / "point_cloud" / "iteration_5" / "point_cloud.ply").is_file()
    assert main(["export", str(tmp_path / "nothing"), "--out", str(tmp_path / "z.ply")]) == 2
    assert "nothing not found" in capsys.readouterr().err


def test_truncated_or_malformed_ply_is_one_line(tmp_path, capsys):
    g = _splats(n=30)
    p = tmp_path / "t.ply"
    g.to_ply(p)
    p.write_bytes(p.read_bytes()[:-100])
    with pytest.raises(ValueError, match=r"t.ply is not a readable Gaussian PLY \(truncated or malformed"):
        Splats.from_ply(p)
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty flot x\nend_header\n")
    with pytest.raises(ValueError, match="junk.ply is not a readable point cloud"):
        read_points_ply(junk)
    (tmp_path / "text.ply").write_text("hello\n")
    with pytest.raises(ValueError, match="text.ply is not a readable"):
        Splats.from_ply(tmp_path / "text.ply")
    from coin_cl.cli import main

    assert main(["export", str(p), "--format", "splat", "--out", str(tmp_path / "o.splat")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "t.ply is not a readable Gaussian PLY" in err
    assert not (tmp_path / "o.splat").exists()
    assert main(["render", str(p)]) == 2  # `coin-cl render PLY`
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "t.ply is not a readable Gaussian PLY" in err
    g.to_ply(tmp_path / "ok.ply")
    assert main(["render", str(tmp_path / "ok.ply")]) == 2
    assert "ok.ply holds 30 Gaussians but no cameras" in capsys.readouterr().err


def test_graphdeco_from_a_run_folder_has_its_cameras_and_source(tmp_path):
    from coin_cl.scene import load_scene, save_scene
    from coin_cl.scene.synthetic import write_synthetic

    captured = write_synthetic(
        tmp_path / "captured", coverage=90, seed=1, n_views=4, width=32, height=24, n_points=200
    )
    scene = load_scene(captured)
    run = tmp_path / "run"
    save_scene(scene, run / "0_scene" / "scene")
    (run / "run.json").write_text(json.dumps({"scene": {"path": str(captured)}}))
    _splats(n=8).to_ply(run / "eval" / "point_cloud.ply")
    out, n, _ = export_run(run, "graphdeco", tmp_path / "gd", iteration=123)
    doc = json.loads((out / "cameras.json").read_text())
    assert n == 8 and len(doc) == len(scene.cameras)
    for entry, cam in zip(doc, scene.cameras, strict=True):
        np.testing.assert_allclose(entry["position"], cam.center, atol=1e-9)
        assert entry["img_name"] == cam.name.rsplit(".", 1)[0]
    assert f"source_path='{captured.resolve()}'" in (out / "cfg_args").read_text()
    assert (out / "point_cloud" / "iteration_123" / "point_cloud.ply").is_file()
