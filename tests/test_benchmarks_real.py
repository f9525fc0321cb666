"""benchmarks/real.py end to end on a tiny synthetic room (smoke steps): the table, the JSON line, the
crop grid's columns, and a second invocation that scores the finished rows without training."""

import json
import math
from pathlib import Path

import cv2
import pytest
from conftest import load_script


def _real():
    return load_script("benchmarks/real.py", "real_benchmark")


def _manifests(out: Path) -> dict[str, tuple[int, bytes]]:
    return {
        str(p.relative_to(out)): (p.stat().st_mtime_ns, p.read_bytes()) for p in out.rglob("manifest.json")
    }


@pytest.mark.slow  # two tiny CoIn runs (the default row through the CLI) and a rerun: about 70 s on 2 cores
def test_real_benchmark_tiny_room_table_json_grid_and_resume(tmp_path, capfd):
    from coin_cl.scene import write_synthetic

    real = _real()
    scene = write_synthetic(tmp_path / "scene", n_views=8, width=64, height=48, seed=0)
    out = tmp_path / "out"
    argv = ["--out", str(out), "--scene-dir", "room", str(scene), "--rows", "default", "naive",
            "--iters", "3", "--prior-seconds", "2", "--ghost-iters", "10"]  # fmt: skip
    assert real.main(argv) == 0
    first = capfd.readouterr().out
    result = json.loads(first.strip().splitlines()[-1])
    for key in ("room_coin_mpsnr", "room_naive_mpsnr", "room_coin_vggpd_m", "room_naive_vggpd_m",
                "room_coin_ghost", "room_default_minutes", "room_naive_minutes"):  # fmt: skip
        assert key in result, key
    assert math.isfinite(result["room_coin_mpsnr"]) and math.isfinite(result["room_naive_mpsnr"])
    md = (out / "real.md").read_text()
    assert "| default |" in md and "| naive |" in md and "m-PSNR" in md
    grid = cv2.imread(str(out / "room" / "crops.png"))
    assert grid is not None and grid.shape[1] == 3 * (160 + 4)  # default, naive, truth
    runs = out / "room"
    # the naive row is the paper's: each whole mask inpainted (no observed/unseen split, no 0_refine)
    stages = {r: json.loads((runs / r / "log.json").read_text())["stages"] for r in ("default", "naive")}
    assert stages["default"]["0_refine"]["status"] == "ran" and "0_refine" not in stages["naive"]
    assert not any("unseen cores" in n for n in stages["naive"]["1_inpaint"]["notes"])
    before = _manifests(runs)
    assert any(k.startswith("default/") for k in before) and any(
        k.startswith("naive/2_refgs") for k in before
    )

    assert real.main(argv) == 0
    second = capfd.readouterr().out
    assert _manifests(runs) == before  # nothing retrained: every stage found up to date
    again = json.loads(second.strip().splitlines()[-1])
    assert again["room_coin_mpsnr"] == result["room_coin_mpsnr"]
    assert again["room_naive_minutes"] == pytest.approx(result["room_naive_minutes"])


def test_truth_photos_takes_the_capture_by_name_from_data_only(tmp_path):
    """A virtual-object scene's ghost reference is fitted to its capture's photos: the capture is
    looked up in --data by the folder name virtual_object.json gives, never at the path it gives."""
    real = _real()
    scene = tmp_path / "scene"
    scene.mkdir()
    assert real.truth_photos(scene, tmp_path) is None  # not a virtual-object scene: test views only
    (tmp_path / "elsewhere" / "cap" / "images").mkdir(parents=True)  # where the file points
    (scene / "virtual_object.json").write_text(json.dumps({"capture": str(tmp_path / "elsewhere" / "cap")}))
    data = tmp_path / "data"
    with pytest.raises(SystemExit, match="capture cap is not in"):
        real.truth_photos(scene, data)
    (data / "cap" / "images").mkdir(parents=True)
    assert real.truth_photos(scene, data) == data / "cap" / "images"
