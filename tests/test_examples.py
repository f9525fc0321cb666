"""Every script in examples/ runs (at a tiny size): users copy from them, so they must not rot."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", ROOT / "examples" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from coin_cl.scene import write_synthetic

    return write_synthetic(tmp_path_factory.mktemp("room"), n_views=10, width=64, height=48, seed=0)


def test_render_ply(tmp_path):
    import torch

    from coin_cl.gs.splats import Splats

    g = torch.Generator().manual_seed(0)
    n = 200
    ply = tmp_path / "g.ply"
    Splats(
        means=torch.randn(n, 3, generator=g), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        log_scales=torch.full((n, 3), -2.5), opacity_logits=torch.full((n,), 2.0),
        sh_dc=torch.randn(n, 3, generator=g), sh_rest=torch.zeros(n, 3, 3),
    ).to_ply(ply)  # fmt: skip
    paths = load("render_ply").main(
        [str(ply), "--out", str(tmp_path / "r"), "--size", "48", "32", "--frames", "2"]
    )
    assert len(paths) == 2 and all(p.is_file() for p in paths)
    from coin_cl.scene.io import read_image

    assert read_image(paths[0]).std() > 0.01  # something was drawn


def test_train_colmap(room, tmp_path):
    res = load("train_colmap").main(
        [str(room), "--out", str(tmp_path / "t"), "--model", "3dgs", "--iters", "4"]
    )
    assert res["step"] == 4 and (tmp_path / "t" / "ckpt.pt").is_file()


def test_prepare_and_run(tmp_path):
    # photos of the synthetic room -> posed scene + masks from one box; the run itself is not done here
    out = load("prepare_and_run").main(["--out", str(tmp_path / "p"), "--width", "256"])
    assert out["registered"] == 12
    import coin_cl

    scene = coin_cl.load_scene(out["scene"])
    assert len(scene) == 12 and all(m.any() for m in scene.masks)
    assert (out["scene"] / "masks_contact_sheet.png").is_file()
