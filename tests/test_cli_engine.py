"""`coin-cl demo` and `coin-cl doctor` end to end (small sizes)."""

import json

from coin_cl.cli import main


def test_demo_turntable_writes_frames(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--render-only", "--frames", "2", "--size", "64", "48"]) == 0
    doc = json.loads((tmp_path / "demo.json").read_text())
    assert doc["turntable"]["frames"] == 2 and doc["turntable"]["median_pairs"] > 0
    assert (tmp_path / "turntable" / "turntable.gif").is_file()
    assert len(list((tmp_path / "turntable").glob("frame_*.png"))) == 2
    assert not list(tmp_path.rglob(".*")), "temporary files left behind"


def test_demo_room_trains_and_scores(tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--frames", "1", "--size", "32", "32", "--steps", "30"]) == 0
    room = json.loads((tmp_path / "demo.json").read_text())["room"]
    assert room["steps"] == 30
    # a reconstruction, however short, beats a blank image on the held-out ground truth
    assert room["test_psnr"] > 12.0
    assert (tmp_path / "room" / "eval" / "metrics.json").is_file()
    assert len(list((tmp_path / "room" / "eval" / "grids").glob("*.png"))) >= 1


def test_doctor_lists_the_device(capsys):
    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "OpenCL devices:" in out and "default device:" in out
