"""Stage 1 (coin_cl.pipeline.inpaint2d): the inpainter choice. Without SD2 or dataset inpaints "auto"
is the embedded exemplar inpainter (or LaMa when a file is named), each named in sources.json;
"lama" without a file is a clear error naming COIN_LAMA_PATH; the SD2 cost estimate is logged
before an SD2 run; `coin-cl run --inpainter/--lama-path` reach the config."""

import json
import logging

import numpy as np
import pytest
import torch
from coin_cl.diffusion.exemplar import EXEMPLAR_NAME
from coin_cl.diffusion.lama import LAMA_ENV, LAMA_NAME
from coin_cl.diffusion.sd2 import sd2_run_estimate

from coin_cl.pipeline.inpaint2d import (
    Inpaint2DConfig,
    neighbour_views,
    rerun_key,
    resolve_inpainter,
    run_inpaint2d,
)
from coin_cl.scene import load_scene, write_synthetic
from coin_cl.scene.io import read_image


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(write_synthetic(tmp_path_factory.mktemp("room"), n_views=8, width=64, height=48))


class _MeanFill(torch.nn.Module):
    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return image * (1 - mask) + 0.25 * mask


def _views(scene):
    return [i for i in scene.train_idx if scene.masks[i].any()][:2]


def test_auto_is_embedded_without_lama(scene, tmp_path, monkeypatch):
    monkeypatch.delenv(LAMA_ENV, raising=False)
    cfg = Inpaint2DConfig(use_dataset=False)
    assert resolve_inpainter(cfg) == "embedded"
    views = _views(scene)
    res = run_inpaint2d(scene, scene.masks, views, tmp_path, cfg)
    assert res["sources"] == [EXEMPLAR_NAME] and res["prior"] is None  # no scene prior trained
    src = json.loads((tmp_path / "sources.json").read_text())
    assert set(src.values()) == {EXEMPLAR_NAME}
    for i in views:
        out = read_image(tmp_path / "images" / (scene.cameras[i].name.rsplit(".", 1)[0] + ".png"))
        m = scene.masks[i]
        assert np.abs(out[~m] - scene.images[i][~m]).max() <= 1 / 255 + 1e-6
        assert np.isfinite(out).all()


def test_lama_by_env_and_missing_file(scene, tmp_path, monkeypatch):
    p = tmp_path / "big-lama.pt"
    torch.jit.script(_MeanFill()).save(str(p))
    monkeypatch.setenv(LAMA_ENV, str(p))
    cfg = Inpaint2DConfig(use_dataset=False)
    assert resolve_inpainter(cfg) == "lama"
    i = _views(scene)[0]
    res = run_inpaint2d(scene, scene.masks, [i], tmp_path / "a", cfg)
    assert res["sources"] == [LAMA_NAME]
    out = read_image(tmp_path / "a" / "images" / (scene.cameras[i].name.rsplit(".", 1)[0] + ".png"))
    from coin_cl.diffusion.inpaint2d import feather_weights

    deep = feather_weights(scene.masks[i], 2) == 1.0
    np.testing.assert_allclose(out[deep], 0.25, atol=1 / 255)
    monkeypatch.delenv(LAMA_ENV)
    with pytest.raises(FileNotFoundError, match=LAMA_ENV):
        run_inpaint2d(
            scene, scene.masks, [i], tmp_path / "b", Inpaint2DConfig(use_dataset=False, inpainter="lama")
        )
    with pytest.raises(ValueError, match="inpainter must be"):
        Inpaint2DConfig(inpainter="magic")


def test_rerun_key_follows_the_lama_file_the_run_reads(tmp_path, monkeypatch):
    """COIN_LAMA_PATH is part of stage 1's rerun key: another file (or the same path rewritten)
    changes it; with an inpainter that reads no LaMa file the variable does not."""
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    torch.jit.script(_MeanFill()).save(str(a))
    b.write_bytes(a.read_bytes() + b"-")  # another file (size differs)
    monkeypatch.delenv(LAMA_ENV, raising=False)
    no_lama = rerun_key(Inpaint2DConfig())
    assert "lama" not in no_lama
    monkeypatch.setenv(LAMA_ENV, str(a))
    key_a = rerun_key(Inpaint2DConfig())
    assert key_a["lama"]["path"] == str(a.resolve()) and key_a != no_lama
    assert "lama" not in rerun_key(Inpaint2DConfig(inpainter="embedded"))
    monkeypatch.setenv(LAMA_ENV, str(b))
    assert rerun_key(Inpaint2DConfig()) != key_a
    monkeypatch.setenv(LAMA_ENV, str(a))
    assert rerun_key(Inpaint2DConfig()) == key_a
    import os

    os.utime(a, ns=(a.stat().st_atime_ns, a.stat().st_mtime_ns + 10**9))  # the same path, a new file
    assert rerun_key(Inpaint2DConfig()) != key_a
    # the config's own path wins over the variable (and is what the key names)
    assert rerun_key(Inpaint2DConfig(lama_path=str(b)))["lama"]["path"] == str(b.resolve())


def test_neighbour_views():
    assert neighbour_views(5, list(range(10)), 3) == [4, 6, 3]
    assert neighbour_views(0, [0], 4) == []


def test_sd2_estimate_is_arithmetic():
    e = sd2_run_estimate(10, 50, measured={"unguided_step_s": 2.0, "guided_step_s": 6.0, "peak_gib": 9.0})
    assert e["stage1_s"] == 10 * 50 * 2.0 and e["clg_s"] == 9 * 50 * 6.0
    assert e["total_s"] == e["stage1_s"] + e["clg_s"] and "h" in e["message"]


def test_cli_flags_reach_the_config(monkeypatch, tmp_path):
    import coin_cl.pipeline.coin as coin
    from coin_cl.cli import main

    seen = {}
    lama = tmp_path / "x.pt"  # --lama-path must name a file that exists (its content is not read here)
    lama.write_bytes(b"")

    def fake_inpaint(scene, out, **kw):
        seen["cfg"] = kw["config"]
        raise SystemExit(0)

    monkeypatch.setattr(coin, "inpaint", fake_inpaint)
    with pytest.raises(SystemExit):
        main(
            [
                "run",
                str(tmp_path),
                "--out",
                str(tmp_path / "o"),
                "--inpainter",
                "telea",
                "--lama-path",
                str(lama),
            ]
        )
    assert seen["cfg"].inpaint2d.inpainter == "telea" and seen["cfg"].inpaint2d.lama_path == str(lama)


def test_sd2_estimate_logged_before_sd2_run(scene, tmp_path, caplog):
    class _Boom:  # an SD2 stand-in that stops the run at its first use
        def inpaint(self, *a, **k):
            raise RuntimeError("stop")

    with caplog.at_level(logging.WARNING), pytest.raises(RuntimeError, match="stop"):
        run_inpaint2d(scene, scene.masks, _views(scene), tmp_path, Inpaint2DConfig(), sd2=_Boom())
    assert any("SD2" in r.message for r in caplog.records)


def test_killed_between_views_resumes_with_every_source_recorded(scene, tmp_path, monkeypatch):
    """sources.json is written view by view (before the view's image), so a run killed after its
    first view resumes to the same record and images as an uninterrupted one."""
    import coin_cl.pipeline.inpaint2d as stage

    monkeypatch.delenv(LAMA_ENV, raising=False)
    cfg, views = Inpaint2DConfig(use_dataset=False), _views(scene)
    run_inpaint2d(scene, scene.masks, views, tmp_path / "ref", cfg)
    real, calls = stage.exemplar_inpaint, []

    def dying(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # the kill, inside the second view
        return real(*a, **k)

    monkeypatch.setattr(stage, "exemplar_inpaint", dying)
    with pytest.raises(KeyboardInterrupt):
        run_inpaint2d(scene, scene.masks, views, tmp_path / "run", cfg)
    monkeypatch.setattr(stage, "exemplar_inpaint", real)
    run_inpaint2d(scene, scene.masks, views, tmp_path / "run", cfg)
    assert (tmp_path / "run" / "sources.json").read_text() == (tmp_path / "ref" / "sources.json").read_text()
    for p in (tmp_path / "ref" / "images").iterdir():
        assert (tmp_path / "run" / "images" / p.name).read_bytes() == p.read_bytes(), p.name


def test_threads_fill_the_same_images_as_one_and_are_not_part_of_the_key(scene, tmp_path, monkeypatch):
    """The exemplar fills run several views at once (`Inpaint2DConfig.workers`); each view's fill
    depends on its own seed alone, so three threads write the same bytes and record as one, and the
    count does not rerun the stage."""
    monkeypatch.delenv(LAMA_ENV, raising=False)
    views = [i for i in scene.train_idx if scene.masks[i].any()][:5]
    assert len(views) == 5
    for n in (1, 3):
        run_inpaint2d(
            scene, scene.masks, views, tmp_path / str(n), Inpaint2DConfig(use_dataset=False, workers=n)
        )
    one, three = tmp_path / "1", tmp_path / "3"
    assert (three / "sources.json").read_text() == (one / "sources.json").read_text()
    names = sorted(p.name for p in (one / "images").iterdir())
    assert len(names) == 5 and names == sorted(p.name for p in (three / "images").iterdir())
    for name in names:
        assert (three / "images" / name).read_bytes() == (one / "images" / name).read_bytes(), name
    assert rerun_key(Inpaint2DConfig(workers=3)) == rerun_key(Inpaint2DConfig())
    assert "workers" not in json.dumps(rerun_key(Inpaint2DConfig()))
    for bad in (-1, 1.5, "2"):
        with pytest.raises(ValueError, match="Inpaint2DConfig.workers"):
            Inpaint2DConfig(workers=bad)


def test_an_error_in_one_thread_is_raised_and_no_later_view_is_written(scene, tmp_path, monkeypatch):
    """A view whose fill fails ends the stage with that error; the views after it are not
    written (the pool's waiting fills are dropped), the ones before it are."""
    import coin_cl.pipeline.inpaint2d as stage

    monkeypatch.delenv(LAMA_ENV, raising=False)
    views = [i for i in scene.train_idx if scene.masks[i].any()][:5]
    real = stage.exemplar_inpaint
    bad_view = scene.images[views[2]]

    def failing(image, *a, **k):
        if image is bad_view:
            raise ValueError("exemplar inpainting: no fully known patch around the hole")
        return real(image, *a, **k)

    monkeypatch.setattr(stage, "exemplar_inpaint", failing)
    with pytest.raises(ValueError, match="no fully known patch"):
        run_inpaint2d(scene, scene.masks, views, tmp_path, Inpaint2DConfig(use_dataset=False, workers=2))
    written = {p.name for p in (tmp_path / "images").iterdir()}
    name = [scene.cameras[i].name.rsplit(".", 1)[0] + ".png" for i in views]
    assert written == set(name[:2])


def test_effective_prior_steps_come_from_the_plan():
    """The plan's measured prior step count reaches stage 1 (and CLG), unless the config fixes one."""
    from coin_cl.diffusion.scene_prior import ScenePriorConfig, steps_for_seconds

    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig, effective_config

    cfg = Inpaint2DConfig()
    assert effective_config(cfg, 120.0, 0, 192, 144, prior_steps=67).prior.train_steps == 67
    assert effective_config(cfg, 120.0, 0, 192, 144).prior.train_steps == steps_for_seconds(120.0)
    fixed = Inpaint2DConfig(prior=ScenePriorConfig(train_steps=5))
    assert effective_config(fixed, 120.0, 0, 192, 144, prior_steps=67).prior.train_steps == 5


@pytest.mark.parametrize("inpainter", ["embedded", "telea"])
def test_a_refined_core_is_filled_from_the_captures_around_the_input_mask(scene, tmp_path, inpainter):
    """A refined run's image holds a grey render in the observed ring around the unseen core; the
    captures around the input mask are a flat orange. With the captures as context the core is
    filled orange (the ring keeps the render: the core alone changes); inpainted on the split's
    image it takes the grey the render put around it."""
    views = _views(scene)
    orange, grey = np.array([0.8, 0.5, 0.2], np.float32), np.array([0.5, 0.5, 0.5], np.float32)
    captures, split = list(scene.images), list(scene.images)
    inputs, cores = list(scene.masks), list(scene.masks)
    for i in views:
        h, w = scene.masks[i].shape
        yy, xx = np.mgrid[0:h, 0:w]
        inputs[i] = (np.abs(yy - h / 2) < 12) & (np.abs(xx - w / 2) < 16)
        cores[i] = (np.abs(yy - h / 2) < 5) & (np.abs(xx - w / 2) < 7)
        captures[i] = np.broadcast_to(orange, (h, w, 3)).copy()
        split[i] = np.where((inputs[i] & ~cores[i])[..., None], grey, captures[i]).astype(np.float32)
    from dataclasses import replace

    shown = replace(scene, images=split)
    cfg = Inpaint2DConfig(use_dataset=False, inpainter=inpainter)
    run_inpaint2d(shown, cores, views, tmp_path / "ctx", cfg, context=(captures, inputs))
    run_inpaint2d(shown, cores, views, tmp_path / "split", cfg)
    for i in views:
        stem = scene.cameras[i].name.rsplit(".", 1)[0] + ".png"
        ctx, old = (read_image(tmp_path / d / "images" / stem) for d in ("ctx", "split"))
        assert np.abs(ctx[cores[i]] - orange).max() < 0.03, "the core continues the captures"
        near_grey = np.abs(old[cores[i]] - grey).mean() < 0.5 * np.abs(old[cores[i]] - orange).mean()
        assert near_grey, "without them it continues the render"
        ring = inputs[i] & ~cores[i]
        assert np.abs(ctx[ring] - grey).max() <= 1 / 255 + 1e-6  # the observed ring keeps the split's image


def test_stage_1_is_keyed_by_the_scene_prior_only_where_it_trains_it():
    """An embedded (or Telea, LaMa) fill does not depend on the scene prior's planned seconds and
    steps, so a comparison row with another plan keeps the fills; the prior inpainter's does."""
    from coin_cl.pipeline.inpaint2d import prior_key

    for kind in ("embedded", "telea"):
        cfg = Inpaint2DConfig(inpainter=kind)
        assert prior_key(cfg, 270.0, 376) == prior_key(cfg, 120.0, None) == {}
    prior = Inpaint2DConfig(inpainter="prior")
    assert prior_key(prior, 270.0, 376) == {"prior_seconds": 270.0, "prior_steps": 376}
    assert prior_key(prior, 120.0, None) == {"prior_seconds": 120.0}
    assert prior_key(Inpaint2DConfig(inpainter="prior", use_prior=False), 270.0, 376) == {}
