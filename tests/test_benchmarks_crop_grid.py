"""The crop grid (benchmarks/crop_grid.py): crops of each run's renders beside the truth, at the
working size or, for runs at different working sizes, at the photos' size."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import crop_grid  # noqa: E402

from coin_cl.scene import load_scene, save_scene, write_synthetic  # noqa: E402
from coin_cl.scene.io import to_uint8, view_stem, write_png  # noqa: E402


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A scene folder at its photos' size (64x48) and two runs made from it: one at half size whose
    eval wrote renders at the capture's size too, one at the capture's size. Each 'render' is a flat
    colour, so a grid's columns can be told apart."""
    root = tmp_path_factory.mktemp("crop_grid")
    scene = load_scene(write_synthetic(root / "room", n_views=6, width=64, height=48, seed=2))
    runs = {}
    for name, scale, colour in (("half", 0.5, 0.2), ("whole", 1.0, 0.8)):
        run = root / name
        work = scene.resized(scale)
        save_scene(work, run / "0_scene" / "scene")
        for i in work.test_idx:
            stem = view_stem(work.cameras[i].name, i)
            h, w = work.images[i].shape[:2]
            write_png(
                run / "eval" / "renders" / f"{stem}.png", to_uint8(np.full((h, w, 3), colour, np.float32))
            )
            if scale != 1.0:
                big = np.full((*scene.images[i].shape[:2], 3), colour, np.float32)
                write_png(run / "eval" / "capture" / "renders" / f"{stem}.png", to_uint8(big))
        runs[name] = run
    return scene, runs


def test_runs_at_different_sizes_meet_at_the_photos_size(capture):
    scene, runs = capture
    g = crop_grid.grid([runs["half"], runs["whole"]], cell=32, capture=scene.path)
    masked = [i for i in scene.test_idx if scene.masks[i].any()]
    assert g.shape == (len(masked) * 36, 3 * 36, 3)
    # the first cell of each row is the half-size run's capture-size render, the second the other's
    first, second = g[2:20, 2:20].astype(float), g[2:20, 38:56].astype(float)
    assert abs(first.mean() - 0.2 * 255) < 2 and abs(second.mean() - 0.8 * 255) < 2


def test_mixed_sizes_without_the_capture_are_refused_with_the_way_out(capture):
    _, runs = capture
    with pytest.raises(ValueError, match="--capture SCENE"):
        crop_grid.grid([runs["half"], runs["whole"]], cell=32)
    assert crop_grid.grid([runs["half"]], cell=32).shape[1] == 2 * 36  # one size: as before


def test_a_run_without_renders_at_the_photos_size_is_named(capture, tmp_path):
    scene, runs = capture
    bare = tmp_path / "bare"
    shutil.copytree(runs["half"], bare)
    shutil.rmtree(bare / "eval" / "capture")  # eval at the working size only
    with pytest.raises(ValueError, match=r"bare.*eval/capture/renders"):
        crop_grid.grid([bare], cell=32, capture=scene.path)
