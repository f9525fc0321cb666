"""Every script in examples/ runs (at a tiny size): users copy from them, so they must not rot."""

import numpy as np
import pytest
from conftest import load_script


def load(name: str):
    return load_script(f"examples/{name}.py", f"example_{name}")


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


def test_remove_bbox(room, tmp_path):
    # GS stages 3 steps each, 1 s of scene prior: the whole default pipeline at a smoke size (no SD2:
    # CLG is left out, with the reason)
    args = ["--iters", "3", "--prior-seconds", "1"]
    res = load("remove_bbox").main([str(room), "--out", str(tmp_path / "b"), *args])
    assert res.ply.is_file() and res.stages["3_clg"]["status"].startswith("skipped: no sampler")
    assert res.stages["0_scene"]["result"]["mask"] == "bbox"
    assert np.isfinite(res.metrics["m_psnr"])  # the room has ground truth


@pytest.mark.slow
@pytest.mark.real_data
def test_remove_spinnerf(spinnerf_dir, tmp_path):
    # the shared scene at 1/8 of its size (126x71), 3 steps per GS stage, the dataset's LaMa inpaints,
    # CLG with the scene prior's sampler (the example's option; the default propagates).
    # Slow (70-110 s on 2 cores): its 58k SfM points make 586k Gaussians, and the eval stage
    # renders 39 views and a 36-frame orbit of them; the image size hardly matters.
    res = load("remove_spinnerf").main(["--data", str(spinnerf_dir), "--out", str(tmp_path / "s"),
                                        "--resolution", "0.125", "--iters", "3", "--prior-sampler",
                                        "--prior-seconds", "1", "--clg-steps", "2"])  # fmt: skip
    assert res.ply.is_file() and np.isfinite(res.metrics["m_psnr"])
    assert "dataset" in " ".join(res.stages["1_inpaint"]["result"]["sources"])
    assert any("CLG model: " in n for n in res.stages["3_clg"]["notes"])  # the prior sampled


def test_use_sd2(room, tmp_path):
    # the tiny random SD2-format pipeline of the SD2 tests stands in for the weights
    from test_diffusion_sd2 import _tiny_pipeline

    (tmp_path / "sd2").mkdir()
    sd = _tiny_pipeline(tmp_path / "sd2")
    with pytest.raises(FileNotFoundError, match="is incomplete: missing"):
        load("use_sd2").main([str(room), "--sd-path", str(tmp_path), "--out", str(tmp_path / "x")])
    # SD2 fills the views in stage 1 (64 px crops, 2 steps); CLG is left out: at its 512 px working
    # size even the tiny pipeline (VAE factor 2) takes minutes per view on 2 cores
    # (--sd2-mode all: on a CPU the default would run the real-size estimate's reference-only mode)
    args = ["--iters", "3", "--sd-steps", "2", "--sd-crop", "64", "--skip-stage", "clg", "--sd2-mode", "all"]
    res = load("use_sd2").main([str(room), "--sd-path", str(sd), "--out", str(tmp_path / "u"), *args])
    assert res.ply.is_file() and res.stages["3_clg"]["status"].startswith("skipped: asked")
    assert res.stages["1_inpaint"]["result"]["sources"] == ["Stable Diffusion 2 inpainting"]


def test_insert_object_paste_and_upright(room):
    # the example's non-training parts on the synthetic room: quarter turns keep every ray, and the
    # paste changes the photo only where the pasted alpha is > 0
    ex = load("insert_object")
    from coin_cl.scene import load_scene

    scene = load_scene(room)
    cam, img = scene.cameras[0], scene.images[0]
    pts = scene.points[:200]
    for k in range(4):
        t = ex.turn_camera(cam, k)
        assert (t.width, t.height) == ((cam.width, cam.height) if k % 2 == 0 else (cam.height, cam.width))
        px, ok = cam.pixels(pts)
        tpx, tok = t.pixels(pts)
        both = ok & tok
        assert both.sum() > 20
        turned = np.rot90(img, -k)
        np.testing.assert_array_equal(turned[tpx[both, 1], tpx[both, 0]], img[px[both, 1], px[both, 0]])
        # the world's up comes back upright after the inverse turns
        up = -cam.camtoworld[:3, 1]
        assert (ex.quarter_turns(t, up) + k) % 4 == 0
    src, dst = scene.images[1], scene.images[2]
    hard = ex.polygon_mask([(10, 8), (40, 8), (44, 40), (8, 40)], src.shape[0], src.shape[1])
    edited, pasted = ex.paste(dst, src, ex.soft_alpha(hard), (26.0, 40.0), (30.0, 44.0), 0.8)
    assert edited.shape == dst.shape and edited.dtype == np.float32 and np.isfinite(edited).all()
    assert pasted.any() and pasted.sum() < 0.6 * pasted.size
    changed = np.abs(edited - dst).max(-1) > 0
    assert changed.any() and not (changed & ~pasted).any()
    with pytest.raises(ValueError, match="paste scale"):
        ex.paste(dst, src, ex.soft_alpha(hard), (26.0, 40.0), (30.0, 44.0), float("nan"))
