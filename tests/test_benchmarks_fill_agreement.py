"""benchmarks/fill_agreement.py on a tiny CoIn run of the synthetic room (smoke steps): the table's
rows, the JSON line, the crop grid; one 3D model's renders agree across views more than the per-view
fills it was trained on."""

import json
import math

import cv2
from conftest import load_script


def _bench():
    return load_script("benchmarks/fill_agreement.py", "fill_agreement")


def test_fill_agreement_of_a_tiny_run(tmp_path, capfd):
    from coin_cl.pipeline.coin import CoInConfig, inpaint
    from coin_cl.scene import write_synthetic

    scene = write_synthetic(tmp_path / "scene", n_views=8, width=64, height=48, seed=0)
    run = tmp_path / "run"
    inpaint(scene, run, config=CoInConfig(prior_seconds=2, inpaint_region="input").with_iters(6))
    assert _bench().main([str(run), "--out", str(tmp_path / "agree"), "--crops", "3"]) == 0
    out = capfd.readouterr().out
    for row in (
        "| stage-1 fills |",
        "| CLG images |",
        "| final renders |",
        "| final render vs each view's fill",
    ):
        assert row in out, row
    res = json.loads(out.strip().splitlines()[-1])
    fills, renders = res["run_stage-1_disagreement"], res["run_final_disagreement"]
    assert math.isfinite(fills) and math.isfinite(renders) and math.isfinite(res["run_render_vs_fill"])
    assert renders < fills  # one model seen from two views agrees more than two views' own inpaints
    grid = cv2.imread(str(tmp_path / "agree" / "run_agreement.png"))
    assert grid is not None and grid.shape[1] > 4 * grid.shape[0] / 3  # five columns, up to three rows
