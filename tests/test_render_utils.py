"""Rendering to files (coin_cl.render_utils): the depth colour map, the one orbit (cameras on a
circle looking at the scene's depth), frames / PNG names / GIF, and `coin-cl render`'s errors."""

import cv2
import imageio.v3 as iio
import numpy as np
import pytest
import torch

from coin_cl.gs.base import RenderOutput
from coin_cl.render_utils import (
    colorize_depth,
    gif_palette_frames,
    orbit_cameras,
    orbit_gif,
    render_checkpoint,
    render_views,
    write_gif,
)
from coin_cl.scene.conventions import look_at
from coin_cl.scene.types import Camera

W, H = 40, 30
K = np.array([[35.0, 0, W / 2], [0, 35.0, H / 2], [0, 0, 1]])


class _FlatModel:
    """Renders a constant depth and an image that encodes the camera centre's x (to tell views apart)."""

    def __init__(self, depth: float = 2.0):
        self.depth = depth
        self.calls = []

    def render(self, cam, step, backend="opencl", return_depth=False, **kw):
        self.calls.append((cam.name, step, backend))
        x = float(cam.center_t[0])
        img = torch.full((cam.height, cam.width, 3), 0.5 + 0.4 * np.tanh(x))
        img[:, : cam.width // 2, 1] = 0.0
        return RenderOutput(
            img, torch.ones(cam.height, cam.width), torch.full((cam.height, cam.width), self.depth)
        )


def _captured(n: int = 5) -> list[Camera]:
    """Forward-facing cameras on a line along x at z = -3, all looking down +z."""
    xs = [0.2 * (i - n // 2) for i in range(n)]
    return [
        Camera(K, look_at((x, 0.0, -3.0), (x, 0.0, 0.0), (0, -1, 0)), W, H, f"cap_{i}.png")
        for i, x in enumerate(xs)
    ]


def test_colorize_depth_near_is_warm_and_invalid_is_black():
    depth = np.tile(np.linspace(1.0, 10.0, 32, dtype=np.float32), (4, 1))
    alpha = np.ones_like(depth)
    alpha[:, -4:] = 0.0  # not drawn
    depth[0, 0] = np.nan
    rgb = colorize_depth(depth, alpha)
    assert rgb.shape == (4, 32, 3) and rgb.dtype == np.uint8
    near, far = rgb[1, 1].astype(int), rgb[1, 27].astype(int)
    assert near[0] > near[2] and far[2] > far[0]  # turbo: red near, blue far
    assert (rgb[:, -4:] == 0).all() and (rgb[0, 0] == 0).all()
    assert (colorize_depth(depth, np.zeros_like(depth)) == 0).all()  # nothing valid: black, no NaN


def test_orbit_cameras_circle_the_mean_camera_and_look_at_the_rendered_depth():
    cams = _captured()
    model = _FlatModel(depth=2.0)
    orbit = orbit_cameras(cams, 8, model, step=7, backend="torch")
    assert len(orbit) == 8 and model.calls == [("mean", 7, "torch")]
    centres = np.stack([c.center for c in orbit])
    c0 = np.mean([c.center for c in cams], 0)
    # on a circle around the mean centre, in the captured cameras' image plane (z = -3), radius half
    # the cameras' spread (0.4 on either side of the mean)
    np.testing.assert_allclose(np.linalg.norm(centres - c0, axis=1), 0.2, atol=1e-5)
    np.testing.assert_allclose(centres[:, 2], -3.0, atol=1e-5)
    assert len({tuple(np.round(c, 5)) for c in centres}) == 8
    # every orbit camera looks at the point the mean camera sees at the rendered depth
    target = c0 + np.array([0, 0, 2.0])
    for c in orbit:
        uv, z = c.project(target[None])
        np.testing.assert_allclose(uv[0], [W / 2, H / 2], atol=1e-3)
        assert z[0] > 0
    with pytest.raises(ValueError, match="at least one"):
        orbit_cameras([], 4, model, 0)


def test_render_views_names_files_and_writes_the_gif(tmp_path):
    cams = _captured(3)
    model = _FlatModel()
    render = lambda c: model.render(c, 0, return_depth=True)  # noqa: E731
    frames = render_views(render, cams, tmp_path / "v", tmp_path / "v.gif", depth=True)
    assert [f.shape for f in frames] == [(H, 2 * W, 3)] * 3  # image | depth
    names = sorted(p.name for p in (tmp_path / "v").iterdir())
    assert names == sorted([f"{i:03d}_cap_{i}{s}.png" for i in range(3) for s in ("", "_depth")])
    gif = iio.imread(tmp_path / "v.gif", index=None)
    assert gif.shape[:3] == (3, H, 2 * W)
    assert not np.array_equal(gif[0], gif[2])  # the frames are the views, in order
    plain = render_views(lambda c: model.render(c, 0), cams[:2], tmp_path / "n", names=["a", "b"])
    assert plain[0].shape == (H, W, 3) and sorted(p.name for p in (tmp_path / "n").iterdir()) == [
        "a.png",
        "b.png",
    ]


def test_gif_frames_share_one_palette_close_to_the_frames(tmp_path):
    # smooth colour ramps (the case a 256-colour palette bands) in two frames of different content
    y, x = np.mgrid[0:48, 0:64] / np.array([47.0, 63.0])[:, None, None]
    a = (np.stack([x, y, 0.5 * (x + y)], -1) * 255 + 0.5).astype(np.uint8)
    b = np.ascontiguousarray(a[::-1, ::-1, [2, 0, 1]])
    images = gif_palette_frames([a, b])
    assert [im.mode for im in images] == ["P", "P"]
    assert images[0].getpalette() == images[1].getpalette()  # one palette: no flicker between frames
    for im, f in zip(images, (a, b)):
        got, want = np.asarray(im.convert("RGB")).astype(np.float32), f.astype(np.float32)
        # measured 6.0-6.3 per pixel (the dither's noise) and 1.1-1.3 over 5x5 boxes, where a
        # median cut per frame gives 3.6-4.1 and 0.8-0.9
        assert np.abs(got - want).mean() < 8
        assert np.abs(cv2.blur(got, (5, 5)) - cv2.blur(want, (5, 5))).mean() < 2
    write_gif(tmp_path / "g.gif", [a, b])
    back = iio.imread(tmp_path / "g.gif", index=None)
    assert back.shape[:3] == (2, 48, 64) and np.abs(back[1][..., :3].astype(int) - b).mean() < 8
    with pytest.raises(ValueError, match="at least one frame"):
        gif_palette_frames([])


def test_orbit_gif_renders_the_orbit(tmp_path):
    model = _FlatModel()
    orbit = orbit_gif(model, _captured(), tmp_path / "o.gif", frames=6, step=3, backend="torch")
    assert len(orbit) == 6 and [c[0] for c in model.calls] == ["mean"] + [c.name for c in orbit]
    assert iio.imread(tmp_path / "o.gif", index=None).shape[0] == 6


def test_render_checkpoint_without_a_model_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="ckpt.pt not found: train into"):
        render_checkpoint(tmp_path)
    (tmp_path / "run.json").write_text("{}")  # a coin-cl run folder with no trained stage yet
    with pytest.raises(FileNotFoundError, match="without a trained stage"):
        render_checkpoint(tmp_path)


def test_render_checkpoint_names_views_as_eval_reads_them_and_finds_a_stages_test_cameras(
    tmp_path, monkeypatch
):
    """A run stage's model (4_ted/finetune) trained on training views only: its test views are the
    run's scene's; the files are `<view stem>.png`, the names `coin-cl eval` looks for. A model with
    no cameras of the kind asked for is an error, not an empty folder."""
    import json

    import coin_cl.checkpoint
    import coin_cl.gs.model_kinds
    import coin_cl.render_utils as R

    cams = _captured(3)
    stage = tmp_path / "run" / "4_ted" / "finetune"
    stage.mkdir(parents=True)
    (stage / "ckpt.pt").write_bytes(b"")
    (stage / "cameras.json").write_text(json.dumps({"train": [c.to_json() for c in cams], "test": []}))
    state = {"model": {}, "trainer": {"step": 3}}
    monkeypatch.setattr(coin_cl.checkpoint, "load_checkpoint", lambda *a: state)
    monkeypatch.setattr(coin_cl.gs.model_kinds, "model_from_state", lambda s: _FlatModel())
    with pytest.raises(ValueError, match="no test cameras"):
        render_checkpoint(stage, views="test", backend="torch")
    (tmp_path / "run" / "run.json").write_text("{}")
    monkeypatch.setattr(R, "_run_folder", lambda run: (run / "x", {"train": [], "test": [cams[1].to_json()]}))
    n, dest = render_checkpoint(stage, views="test", backend="torch", dest=tmp_path / "out")
    assert n == 1 and sorted(p.name for p in dest.iterdir()) == ["cap_1.png", "cap_1_depth.png"]
    n, dest = render_checkpoint(stage, views="train", backend="torch", dest=tmp_path / "out")
    assert n == 3 and {p.name for p in dest.iterdir()} >= {"cap_0.png", "cap_2.png"}


def test_render_checkpoint_scales_the_cameras_and_finds_a_runs_capture_size(tmp_path, monkeypatch):
    """--scale 2 renders at twice the cameras' size; "capture" takes a run's photos' size from the
    working resolution its plan records (0.5 -> x2); a folder that is no run, or a plan with a bad
    resolution, is one clear error."""
    import json

    import coin_cl.checkpoint
    import coin_cl.gs.model_kinds
    import coin_cl.render_utils as R

    cams = _captured(2)
    stage = tmp_path / "run" / "2_refgs" / "gs"
    stage.mkdir(parents=True)
    (stage / "ckpt.pt").write_bytes(b"")
    (stage / "cameras.json").write_text(json.dumps({"train": [], "test": [c.to_json() for c in cams]}))
    monkeypatch.setattr(
        coin_cl.checkpoint, "load_checkpoint", lambda *a: {"model": {}, "trainer": {"step": 1}}
    )
    monkeypatch.setattr(coin_cl.gs.model_kinds, "model_from_state", lambda s: _FlatModel())
    _, dest = render_checkpoint(stage, backend="torch", dest=tmp_path / "x2", scale=2.0)
    assert iio.imread(dest / "cap_0.png").shape[:2] == (2 * H, 2 * W)
    with pytest.raises(ValueError, match="not a coin-cl run folder"):
        render_checkpoint(stage, backend="torch", dest=tmp_path / "c", scale="capture")
    run = tmp_path / "run"
    (run / "run.json").write_text("{}")
    plan = {"steps": {"refgs": 1, "ted_finetune": 0, "ted_adversarial": 0},
            "minutes": {"refgs": None, "ted_finetune": None, "ted_adversarial": None},
            "prior_seconds": 0.0, "probe_seconds_per_step": None, "source": "explicit",
            "key": {"resolution": 0.5, "explicit": [1, 0, 0, None]}}  # fmt: skip
    (run / "plan.json").write_text(json.dumps(plan))
    assert R.capture_scale(stage) == 2.0
    _, dest = render_checkpoint(stage, backend="torch", dest=tmp_path / "cap", scale="capture")
    assert iio.imread(dest / "cap_1.png").shape[:2] == (2 * H, 2 * W)
    (run / "plan.json").write_text(json.dumps({**plan, "key": {**plan["key"], "resolution": 0}}))
    with pytest.raises(ValueError, match="key.resolution is 0"):
        R.capture_scale(run)
