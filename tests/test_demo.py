"""The demo (coin_cl.demo) beyond the CLI's runs (tests/test_cli_engine.py): the turntable renders the
procedural scene through the one orbit renderer, and the room's table is written from the runs'
metrics as they are."""

import math

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from coin_cl.demo import ROOM_METRICS, _row, room_markdown, turntable


def test_turntable_frames_are_the_engines_renders_of_the_circle(tmp_path):
    import coin_cl
    from coin_cl.scene.io import read_image
    from coin_cl.scene.procedural import embedded_scene, turntable_viewmat

    W, H, n = 48, 32, 4
    doc = turntable(tmp_path, frames=n, size=(W, H))
    assert doc["frames"] == n and doc["size"] == [W, H] and doc["median_pairs"] > 0
    assert doc["gaussians"] == len(embedded_scene().means) and doc["median_render_s"] > 0
    files = sorted(tmp_path.glob("frame_*.png"))
    assert [f.name for f in files] == [f"frame_{i:03d}.png" for i in range(n)]
    # frame 1 is the engine's render at a quarter turn, as written
    gs = embedded_scene()
    f = 0.9 * W
    K = torch.tensor([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    img = coin_cl.rasterize(*gs.tensors(), turntable_viewmat(2 * math.pi / n), K, W, H,
                            background=torch.tensor([0.06, 0.07, 0.1]))[0]  # fmt: skip
    want = (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    got = (read_image(files[1]) * 255 + 0.5).astype(np.uint8)
    assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
    frames = iio.imread(tmp_path / "turntable.gif", index=None)
    assert frames.shape[:3] == (n, H, W)
    assert np.abs(frames[0].astype(int) - frames[2].astype(int)).mean() > 1  # the camera moved


def test_room_rows_and_table_report_the_metrics_as_measured():
    metrics = {
        "psnr": 21.234,
        "m_psnr": 14.5,
        "ssim": 0.81234,
        "hf_ratio": None,
        "bbox_gmsd": 0.2,
        "swd": 3.0,
    }
    row = _row(metrics, 12.4, "a method")
    assert set(row) == {"what", "seconds", *ROOM_METRICS} and "swd" not in row
    assert row["m_psnr"] == 14.5 and row["hf_ratio"] is None
    assert _row(None, 1.0, "x")["psnr"] is None  # a run without ground truth: no figure invented
    md = room_markdown({"scene": "room 64x48", "inpainting_model": "embedded exemplar",
                        "methods": {"coin": row, "baseline": _row({"psnr": 9.0}, 3.0, "b")}})  # fmt: skip
    lines = md.splitlines()
    coin = next(ln for ln in lines if ln.startswith("| coin |"))
    assert coin == "| coin | 21.23 | 14.50 | 0.812 | n/a | 0.200 | 12 | a method |"
    base = next(ln for ln in lines if ln.startswith("| baseline |"))
    assert base.split(" | ")[1:3] == ["9.00", "n/a"]
    assert lines.index(coin) < lines.index(base) and "embedded exemplar" in md


def test_baselines_train_coins_gs_steps():
    """Same budget: the baselines get Ref-GS's and TE-D's steps of CoIn's plan together (a missing
    stage counts 0, the scene prior's seconds are not steps)."""
    from coin_cl.demo import baseline_steps

    assert baseline_steps({"refgs": 591, "ted_finetune": 411, "ted_adversarial": 499}) == 1501
    assert baseline_steps({"refgs": 12, "prior_seconds": 30}) == 12


def test_a_budget_the_machine_cannot_fit_is_retried_above_the_minimum_named():
    """The demo must run: a refused budget is tried again at 1.25x the minimum the refusal named (a
    second probe may measure a busier machine), up to three tries; the third refusal is the error."""
    from coin_cl.demo import within_reach
    from coin_cl.pipeline.budget import BudgetTooSmall
    from coin_cl.pipeline.coin import CoInConfig

    tried = []

    def run(cfg, refusals=2, minimum=7.0):
        tried.append(cfg.budget_minutes)
        if len(tried) <= refusals:
            raise BudgetTooSmall(f"--budget {cfg.budget_minutes} cannot fit", minimum + len(tried))
        return "result"

    res, cfg = within_reach(CoInConfig(budget_minutes=6.0), run)
    assert res == "result" and tried == [6.0, 10.0, 11.3] and cfg.budget_minutes == 11.3
    tried.clear()
    with pytest.raises(BudgetTooSmall):
        within_reach(CoInConfig(budget_minutes=6.0), lambda c: run(c, refusals=5))
    assert len(tried) == 3
