"""The CLI's error printing (coin_cl/cli/__init__.py): bad input in one line naming the culprit."""

import pytest

from coin_cl.cli import main
from coin_cl.pipeline.lock import folder_lock
from coin_cl.scene import write_synthetic


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_synthetic(tmp_path_factory.mktemp("cli") / "scene", n_views=4, width=48, height=32, seed=1)


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert "Traceback" not in "\n".join(err)
    return err[-1]


def test_truncated_image_is_one_line_naming_it(scene, tmp_path, capsys):
    import shutil

    bad = tmp_path / "bad scène"
    shutil.copytree(scene, bad)
    img = sorted((bad / "images_4").glob("*.png"))[-1]
    img.write_bytes(img.read_bytes()[:100])
    assert main(["run", str(bad), "--out", str(tmp_path / "out"), "--iters", "1"]) == 2
    line = _one_line(capsys)
    assert line.startswith("coin-cl run: error: image ") and img.name in line and "truncated" in line


def test_second_run_on_a_held_folder_names_the_holder(scene, tmp_path, capsys):
    out = tmp_path / "out"
    with folder_lock(out) as lk:
        assert main(["run", str(scene), "--out", str(out), "--iters", "1"]) == 2
    line = _one_line(capsys)
    assert "in use by another coin-cl run" in line and f"process {lk.info['pid']}" in line


def test_scene_too_large_is_refused_before_any_stage(scene, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("COIN_MEMORY_LIMIT_GB", "0.2")  # below the process's own base: nothing fits
    assert main(["run", str(scene), "--out", str(tmp_path / "out"), "--iters", "1"]) == 2
    line = _one_line(capsys)
    assert "0.2 GiB are available: use a machine with more memory" in line
    assert not (tmp_path / "out").exists()  # refused before the output folder was touched
