"""The eval stage's scoring at the capture's resolution (coin_cl.pipeline.eval_stage; the views it
scores come from coin_cl.pipeline.run_inputs.capture_views): the test views kept before the resize,
rendered at their own size and scored against the photos."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from coin_cl import metrics as M
from coin_cl.pipeline.eval_stage import score_at_capture
from coin_cl.pipeline.run_inputs import capture_views
from coin_cl.scene import load_scene, write_synthetic
from coin_cl.scene.io import read_image
from coin_cl.scene.types import resize_image


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    return load_scene(
        write_synthetic(tmp_path_factory.mktemp("room"), n_views=6, width=64, height=48, seed=1)
    )


class PhotoModel:
    """Renders each view's photo at the camera's size, or the photo seen through a 2x smaller working
    size (down, then up again): the blur a half-resolution run cannot avoid."""

    def __init__(self, scene, blur: bool):
        self.photos = {c.name: img for c, img in zip(scene.cameras, scene.images, strict=True)}
        self.blur = blur

    def render(self, cam, n):
        img = self.photos[cam.name]
        assert img.shape[:2] == (cam.height, cam.width)
        if self.blur:
            small = resize_image(img, cam.width // 2, cam.height // 2)
            img = resize_image(small, cam.width, cam.height)
        return type("R", (), {"image": torch.from_numpy(np.ascontiguousarray(img))})()


def test_capture_views_keeps_the_masked_test_views_at_their_size(room):
    views = capture_views(room)
    assert sorted(views.cameras) == [i for i in room.test_idx if room.masks[i].any()] and views.cameras
    for i, cam in views.cameras.items():
        assert views.images[i].shape == (cam.height, cam.width, 3) == room.images[i].shape
    none = replace(room, masks=[np.zeros_like(m) for m in room.masks])
    assert capture_views(none) is None


def test_a_blurred_render_scores_lower_at_the_capture_size(room, tmp_path):
    views = capture_views(room)
    sharp = score_at_capture(PhotoModel(room, blur=False), views, tmp_path / "sharp")
    blurred = score_at_capture(PhotoModel(room, blur=True), views, tmp_path / "blur")
    assert sharp["mean"]["m_psnr"] > 40  # the photo itself, up to 8-bit rounding
    assert blurred["mean"]["m_psnr"] < sharp["mean"]["m_psnr"] - 10
    i = next(iter(views.cameras))
    cam = views.cameras[i]
    written = read_image(tmp_path / "blur" / "renders" / f"{cam.name.rsplit('.', 1)[0]}.png")
    assert written.shape == room.images[i].shape
    want = M.masked_psnr(written, room.images[i], views.masks[i])
    assert blurred["per_view"][cam.name]["m_psnr"] == pytest.approx(want)
    assert (tmp_path / "blur" / "metrics.json").is_file()
