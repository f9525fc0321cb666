"""benchmarks/budget_curve.py end to end on a tiny synthetic room (smoke steps): a point per budget with
its wall minutes and figures, the table, the plot, the JSON line, a rerun that trains nothing, and a
budget the machine cannot fit recorded as refused with the minimum the run named."""

import json
import math

import cv2
import pytest
from conftest import load_script


def _curve():
    return load_script("benchmarks/budget_curve.py", "budget_curve_benchmark")


# two tiny CoIn runs through the CLI, a rerun and a refused budget: about a minute on 2 cores
@pytest.mark.slow
def test_budget_curve_tiny_room_points_table_plot_resume_and_refusal(tmp_path, capfd):
    from coin_cl.scene import write_synthetic

    curve = _curve()
    scene = write_synthetic(tmp_path / "scene", n_views=8, width=64, height=48, seed=0)
    out = tmp_path / "out"
    argv = ["--out", str(out), "--scene-dir", "room", str(scene), "--budgets", "1", "2",
            "--iters", "3", "--prior-seconds", "2", "--ghost-iters", "10"]  # fmt: skip
    assert curve.main(argv) == 0
    result = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    for b in ("1", "2"):
        for k in ("wall_minutes", "m_psnr", "bbox_gmsd", "ghost"):
            assert math.isfinite(result[f"room_b{b}_{k}"]), (b, k)
        assert (out / "room" / f"b{b}" / "eval" / "metrics" / "metrics.json").is_file()
    md = (out / "budget_curve.md").read_text()
    assert "| room | 1 |" in md and "| room | 2 |" in md and "m-PSNR" in md
    png = cv2.imread(str(out / "budget_curve.png"))
    assert png is not None and png.shape[1] > png.shape[0] and (png < 250).any()  # something drawn

    before = {p: p.stat().st_mtime_ns for p in out.rglob("manifest.json")}
    assert curve.main(argv) == 0  # a rerun: every point kept, nothing trained again
    again = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    assert {p: p.stat().st_mtime_ns for p in out.rglob("manifest.json")} == before
    assert again["room_b1_wall_minutes"] == result["room_b1_wall_minutes"]

    # a budget this machine cannot fit: the probes run, nothing trains, the point says the minimum
    tiny = [
        "--out",
        str(tmp_path / "tiny"),
        "--scene-dir",
        "room",
        str(scene),
        "--budgets",
        "0.05",
        "--no-ghost",
    ]
    assert curve.main(tiny) == 0
    refused = json.loads(capfd.readouterr().out.strip().splitlines()[-1])
    assert refused["room_b0.05_refused_minimum"] > 0.05
    assert not any((tmp_path / "tiny" / "room" / "b0.05").glob("[0-9]_*"))  # no stage folder
    assert "refused" in (tmp_path / "tiny" / "budget_curve.md").read_text()
    assert not (tmp_path / "tiny" / "room" / "b0.05" / "point.json").exists()  # probed again next time
