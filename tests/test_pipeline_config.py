"""The run's settings (coin_cl.pipeline.config): every config the run holds refuses a bad value with
a message naming the field; fields the run decides are None until it does; `coin-cl run`'s flags
have the defaults of the config fields they set."""

from __future__ import annotations

import argparse
import dataclasses
import sys

import pytest
from coin_cl.diffusion.scene_prior import ScenePriorConfig

from coin_cl.gs.refgs import RefGSConfig
from coin_cl.pipeline.config import SKIPPABLE, STAGES, CoInConfig
from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
from coin_cl.pipeline.ted import TEDConfig


@pytest.mark.parametrize(
    "change, named",
    [
        ({"mask_kind": "segm"}, "CoInConfig.mask_kind"),
        ({"inpaint_region": "refine"}, "CoInConfig.inpaint_region"),
        ({"observed": "capture"}, "CoInConfig.observed"),
        ({"skip": ("clgg",)}, "CoInConfig.skip"),
        ({"skip": "clg"}, "CoInConfig.skip"),
        ({"mask_dilate": -1}, "CoInConfig.mask_dilate"),
        ({"seed": 1.5}, "CoInConfig.seed"),
        ({"budget_minutes": 0.0}, "budget_minutes"),
        ({"resolution": -0.5}, "resolution"),
        ({"prior_seconds": float("nan")}, "prior_seconds"),
        ({"iters_refgs": 0}, "iters_refgs"),
        ({"iters_ted_finetune": -1}, "iters_ted_finetune"),
        ({"iters_refgs": 50, "refgs_schedule_iters": 49}, "refgs_schedule_iters"),
        ({"refgs_schedule_iters": 0}, "refgs_schedule_iters"),
        ({"refgs_schedule_iters": True}, "refgs_schedule_iters"),
        ({"refgs": RefGSConfig(ref=2)}, "CoInConfig.refgs.ref"),
        (
            {"inpaint2d": Inpaint2DConfig(prior=ScenePriorConfig(train_seconds=60.0))},
            "CoInConfig.inpaint2d.prior.train_seconds",
        ),
        ({"inpaint2d": Inpaint2DConfig(prior=ScenePriorConfig(seed=4))}, "CoInConfig.inpaint2d.prior.seed"),
    ],
)
def test_coin_config_refuses_bad_values_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named.replace(".", r"\.")):
        CoInConfig(**change)


def test_a_skip_typo_names_the_allowed_stages():
    with pytest.raises(ValueError, match="CoInConfig.skip is 'tde': give one of refgs, clg, ted"):
        CoInConfig(skip=("clg", "tde"))
    assert CoInConfig(skip=SKIPPABLE).skip == SKIPPABLE
    assert all(any(s.endswith("_" + k) for s in STAGES) for k in SKIPPABLE)  # the names are stage keys


def test_replace_validates_too():
    """`dataclasses.replace` (how `inpaint` applies its arguments) runs the same checks."""
    with pytest.raises(ValueError, match="CoInConfig.mask_kind"):
        dataclasses.replace(CoInConfig(), mask_kind="box")


@pytest.mark.parametrize(
    "change, named",
    [
        ({"prune_min_fraction": 0.0}, "prune_min_fraction"),
        ({"lambda_r": -1.0}, "lambda_r"),
        ({"attn_mix": 0.0}, "attn_mix"),
        ({"attn_from": 1.5}, "attn_from"),
        ({"lambda_depth": -1.0}, "lambda_depth"),
        ({"seed": "0"}, "RefGSConfig.seed"),
        ({"depth_prior_iters": 0}, "RefGSConfig.depth_prior_iters"),
    ],
)
def test_refgs_config_refuses_bad_values_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named):
        RefGSConfig(**change)


@pytest.mark.parametrize(
    "change, named",
    [
        ({"iters_finetune": -1}, "TEDConfig.iters_finetune"),
        ({"iters_adversarial": 1.5}, "TEDConfig.iters_adversarial"),
        ({"lambda_gen": -0.1}, "TEDConfig.lambda_gen"),
        ({"patch": 30}, "TEDConfig.patch"),
        ({"patch": 36}, "TEDConfig.patch"),
        ({"n_patches": 0}, "TEDConfig.n_patches"),
        ({"margin": -1}, "TEDConfig.margin"),
        ({"p_near": 1.5}, "TEDConfig.p_near"),
        ({"lr_d": 0.0}, "TEDConfig.lr_d"),
        ({"betas_d": (0.5, 1.0)}, "TEDConfig.betas_d"),
        ({"seed": 0.5}, "TEDConfig.seed"),
    ],
)
def test_ted_config_refuses_bad_values_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named):
        TEDConfig(**change)


@pytest.mark.parametrize(
    "change, named",
    [
        ({"inpainter": "laMa"}, "Inpaint2DConfig.inpainter"),
        ({"sd2_mode": "some"}, "Inpaint2DConfig.sd2_mode"),
        ({"exemplar_views": -1}, "Inpaint2DConfig.exemplar_views"),
        ({"lama_path": "/no/such/lama.pt"}, "lama_path"),
    ],
)
def test_inpaint2d_config_refuses_bad_values_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named):
        Inpaint2DConfig(**change)


def test_refgs_seed_is_the_runs_unless_set():
    """RefGSConfig.seed None (default) = the run's seed; a number set there is the one Ref-GS uses
    (`CoInConfig.refgs_settings` resolves it, and its result is the 2_refgs stage key)."""
    assert RefGSConfig().seed is None
    assert CoInConfig(seed=5).refgs_settings(ref=1) == RefGSConfig(ref=1, seed=5)
    assert CoInConfig(seed=5, refgs=RefGSConfig(seed=7)).refgs_settings(ref=1).seed == 7
    assert CoInConfig().refgs_settings(ref=0) == RefGSConfig(ref=0, seed=0)  # the default run: as before
    assert CoInConfig(ref=3, refgs=RefGSConfig(ref=3)).refgs_settings(ref=3).ref == 3  # agreeing is fine


def test_run_refgs_uses_the_configs_seed(monkeypatch, tmp_path):
    """`run_refgs` trains with `cfg.seed` where set, else its `seed` argument (it stopped after the
    seed is resolved: the model is built with it)."""
    from coin_cl.pipeline import refgs as stage

    seen = []

    def build(kind, pts, cols, extent, seed, cfg):
        seen.append(seed)
        raise RuntimeError("stop")

    monkeypatch.setattr(stage, "build_model", build)
    from coin_cl.scene import load_scene, write_synthetic

    scene = load_scene(write_synthetic(tmp_path / "s", n_views=4, width=32, height=24, seed=0))
    scene = dataclasses.replace(scene, ref_view=scene.train_idx[0])
    targets = [img for img in scene.images]
    base = RefGSConfig(depth_loss=False, feature_attention=False, bg_depth=False, prune_points=False)
    for cfg, arg, want in ((base, 3, 3), (dataclasses.replace(base, seed=11), 3, 11)):
        with pytest.raises(RuntimeError, match="stop"):
            stage.run_refgs(
                scene, targets, tmp_path / f"o{want}", cfg, budget_minutes=None, iters=2, seed=arg
            )
        assert seen[-1] == want


# `coin-cl run` flags that are no config field, and why.
NOT_CONFIG = {
    "scene": "the scene folder: `inpaint`'s first argument",
    "out": "the run folder: `inpaint`'s second argument",
    "force": "stages to rerun: `inpaint(force=...)`, not a setting of the result",
    "help": "argparse's own",
    "clg": "a mode that sets CLGConfig fields (cli.run.CLG_MODES; test_the_clg_flag_sets_its_fields)",
}
# flag dest -> the config field it sets (a dotted path from CoInConfig).
FLAG_FIELDS = {
    "mask_kind": "mask_kind",
    "mask_dilate": "mask_dilate",
    "inpaint_region": "inpaint_region",
    "carve": "carve",
    "ref": "ref",
    "prompt": "prompt",
    "edited_ref": "edited_ref",
    "budget": "budget_minutes",
    "resolution": "resolution",
    "skip_stage": "skip",
    "iters": "iters_refgs",
    "prior_seconds": "prior_seconds",
    "sd_path": "sd_path",
    "sd2_mode": "inpaint2d.sd2_mode",
    "inpainter": "inpaint2d.inpainter",
    "insert_regions": "insert.regions",
    "insert_profile": "insert.profile",
    "lama_path": "inpaint2d.lama_path",
    "dino_path": "dino_path",
    "device": "device",
    "seed": "seed",
}


def _run_parser() -> argparse.ArgumentParser:
    from coin_cl.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["run"]


def _field(cfg: object, path: str) -> object:
    for part in path.split("."):
        cfg = getattr(cfg, part)
    return cfg


def test_every_run_flag_has_its_config_fields_default():
    """One source of defaults: each flag of `coin-cl run` maps to a config field with the same default
    (a list default is the field's tuple), and its choices are the values the field accepts."""
    actions = {a.dest: a for a in _run_parser()._actions}
    assert set(actions) == set(FLAG_FIELDS) | set(NOT_CONFIG), set(actions) ^ (
        set(FLAG_FIELDS) | set(NOT_CONFIG)
    )
    cfg = CoInConfig()
    for dest, path in FLAG_FIELDS.items():
        default = actions[dest].default
        default = tuple(default) if isinstance(default, list) else default
        flag, want = "--" + dest.replace("_", "-"), _field(cfg, path)
        assert default == want, f"{flag} defaults to {default!r}, {path} to {want!r}"
        for choice in actions[dest].choices or ():  # a value the CLI offers is one the config takes
            target, _, name = f"x.{path}".rpartition(".")
            if target == "x":
                CoInConfig(**{name: (choice,) if dest == "skip_stage" else choice})
            else:  # a nested config: the field's own dataclass
                type(_field(cfg, target[2:]))(**{name: choice})
    # --iters sets every GS stage's count (`CoInConfig.with_iters`): all three default to None
    assert (cfg.iters_refgs, cfg.iters_ted_finetune, cfg.iters_ted_adversarial) == (None, None, None)


def test_the_clg_flag_sets_its_fields():
    """--clg's default (auto) is CLGConfig's defaults; every other mode sets fields CLGConfig has to
    values that differ from their defaults, and the config accepts them."""
    from coin_cl.cli.run import CLG_MODES
    from coin_cl.pipeline.clg_config import CLGConfig

    assert _run_parser().get_default("clg") == "auto" and CLG_MODES["auto"] == {}
    default = CLGConfig()
    for mode, fields in CLG_MODES.items():
        cfg = CLGConfig(**fields)
        assert all(getattr(cfg, k) != getattr(default, k) for k in fields), mode
        assert (mode == "auto") == (not fields)


def test_a_flag_default_that_drifts_is_caught(monkeypatch):
    """The rule above can fail: a config default changed under the CLI is reported."""
    from coin_cl.pipeline import config

    changed = dataclasses.make_dataclass("Changed", [("budget_minutes", float, 45.0)], bases=(CoInConfig,))
    monkeypatch.setattr(sys.modules[__name__], "CoInConfig", changed)
    with pytest.raises(AssertionError, match="--budget defaults to 10.0, budget_minutes to 45.0"):
        test_every_run_flag_has_its_config_fields_default()
    assert config.CoInConfig().budget_minutes == 10.0


@pytest.mark.parametrize(
    "make, change, named",
    [
        ("carve", {"dilate_px": -1}, "CarveConfig.dilate_px"),
        ("carve", {"cell": 0}, "CarveConfig.cell"),
        ("carve", {"margin": 1.0}, "CarveConfig.margin"),
        ("carve", {"min_fraction": 0.0}, "CarveConfig.min_fraction"),
        ("carve", {"min_views": 0}, "CarveConfig.min_views"),
        ("carve", {"scale": 1.5}, "CarveConfig.scale"),
        ("insert", {"edit_tol": -0.1}, "InsertConfig.edit_tol"),
        ("insert", {"hull_fraction": 0.0}, "InsertConfig.hull_fraction"),
        ("insert", {"min_views": 0}, "InsertConfig.min_views"),
        ("insert", {"hull_samples": 1}, "InsertConfig.hull_samples"),
        ("insert", {"ref_match_tol": 0.0}, "InsertConfig.ref_match_tol"),
    ],
)
def test_carve_and_insert_configs_refuse_bad_values_naming_the_field(make, change, named):
    from coin_cl.gs.carve import CarveConfig
    from coin_cl.pipeline.insert import InsertConfig

    cls = {"carve": CarveConfig, "insert": InsertConfig}[make]
    cls()  # the defaults pass
    with pytest.raises(ValueError, match=named):
        cls(**change)


@pytest.mark.parametrize(
    "change, named",
    [
        ({"patch": 30}, "ScenePriorConfig.patch"),
        ({"base": 12}, "ScenePriorConfig.base"),
        ({"scales": ()}, "ScenePriorConfig.scales"),
        ({"scales": (1, 0)}, "ScenePriorConfig.scales"),
        ({"batch": 0}, "ScenePriorConfig.batch"),
        ({"lr": 0.0}, "ScenePriorConfig.lr"),
        ({"train_seconds": -1.0}, "ScenePriorConfig.train_seconds"),
        ({"train_steps": -1}, "ScenePriorConfig.train_steps"),
        ({"max_steps": 1.5}, "ScenePriorConfig.max_steps"),
        ({"hole_weight": -1.0}, "ScenePriorConfig.hole_weight"),
        ({"prediction_type": "x0"}, "ScenePriorConfig.prediction_type"),
    ],
)
def test_scene_prior_config_refuses_bad_values_naming_the_field(change, named):
    with pytest.raises(ValueError, match=named):
        ScenePriorConfig(**change)


@pytest.mark.parametrize(
    "change, named",
    [
        ({"iters": 0}, "RefineConfig.iters"),
        ({"model": "nerf"}, "RefineConfig.model"),
        ({"min_fraction": 0.0}, "RefineConfig.min_fraction"),
        ({"splat_px": 0.0}, "RefineConfig.splat_px"),
        ({"alpha_thresh": 1.5}, "RefineConfig.alpha_thresh"),
        ({"grow_px": -1}, "RefineConfig.grow_px"),
        ({"see_through": -0.1}, "RefineConfig.see_through"),
        ({"view_check": -0.1}, "RefineConfig.view_check"),
        ({"ray_samples": 0}, "RefineConfig.ray_samples"),
        ({"warp_tol": float("nan")}, "RefineConfig.warp_tol"),
    ],
)
def test_refine_config_refuses_bad_values_naming_the_field(change, named):
    from coin_cl.pipeline.refine_masks import RefineConfig

    with pytest.raises(ValueError, match=named):
        RefineConfig(**change)
