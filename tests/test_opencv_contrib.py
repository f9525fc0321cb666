"""coin_cl.opencv_contrib: a cv2 without its contrib modules is refused before a run starts."""

import cv2
import pytest

from coin_cl.opencv_contrib import CONTRIB, missing_contrib, require_contrib


def test_the_installed_opencv_has_every_contrib_module_used():
    assert missing_contrib() == []
    require_contrib()


def test_a_plain_opencv_is_refused_with_the_module_its_user_and_the_fix(monkeypatch):
    monkeypatch.delattr(cv2, "quality")
    assert missing_contrib() == ["quality"]
    with pytest.raises(
        RuntimeError, match=r"cv2\.quality: the evaluation's GMSD.*pip install opencv-contrib"
    ):
        require_contrib()


def test_a_run_stops_before_writing_anything(monkeypatch, tmp_path):
    from coin_cl.pipeline.coin import inpaint
    from coin_cl.scene import load_scene
    from coin_cl.scene.synthetic import write_synthetic

    scene = load_scene(write_synthetic(tmp_path / "scene", n_views=6, width=48, height=32, n_points=500))
    for m in CONTRIB:
        monkeypatch.delattr(cv2, m)
    with pytest.raises(RuntimeError, match="xphoto.*quality"):
        inpaint(scene, tmp_path / "run")
    assert not (tmp_path / "run").exists()
