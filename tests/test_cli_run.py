"""`coin-cl run` as a user meets it: the reference by name, progress from every stage."""

import re

import pytest

from coin_cl.cli import main
from coin_cl.pipeline.reference import resolve_reference

NAMES = [f"{n:05d}.png" for n in (7, 12, 3, 0, 1, 2, 4, 5, 6, 8, 9, 10, 11, 13)]


def test_a_view_name_wins_over_an_index():
    cands = list(range(len(NAMES)))
    assert resolve_reference("00012", NAMES, cands) == 1  # the view named 00012.png, not index 12
    assert resolve_reference("00012.png", NAMES, cands) == 1
    assert resolve_reference(12, NAMES, cands) == 12  # an int from Python is an index
    assert resolve_reference("13", NAMES, cands) == 13  # no view is named 13: the index


def test_an_ambiguous_reference_lists_both_readings():
    names = ["a.png", "b.png", "1.png", "c.png"]
    with pytest.raises(ValueError, match=r"ambiguous.*'1.png' \(index 2\).*index 1 \('b.png'\)"):
        resolve_reference("1", names, [0, 1, 2, 3])
    assert resolve_reference("1.png", names, [0, 1, 2, 3]) == 2


def test_cli_hands_the_reference_over_as_typed(monkeypatch, tmp_path):
    seen = {}

    def fake_inpaint(scene, out, **kw):
        seen.update(kw)
        raise ValueError("stop here")

    monkeypatch.setattr("coin_cl.pipeline.coin.inpaint", fake_inpaint)
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--ref", "00012"]) == 2
    assert seen["reference"] == "00012" and seen["mask_kind"] == "seg"
    assert seen["config"].resolution is None  # picked from the image size unless given


def test_every_stage_shows_progress(tmp_path, capsys):
    """Each stage that loops (stage 1's views, prior training, Ref-GS and its depth GS, CLG views,
    TE-D, eval renders) draws a progress bar that reaches its total: none runs its steps silently."""
    from dataclasses import replace

    from coin_cl.diffusion.scene_prior import ScenePriorConfig

    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.pipeline.clg_config import CLGConfig
    from coin_cl.pipeline.coin import CoInConfig, inpaint
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
    from coin_cl.pipeline.ted import TEDConfig
    from coin_cl.scene import write_synthetic

    room = write_synthetic(tmp_path / "room", n_views=6, width=48, height=32, seed=1)
    cfg = CoInConfig(iters_refgs=9, iters_ted_finetune=4, iters_ted_adversarial=3, prior_seconds=3,
                     inpaint2d=Inpaint2DConfig(prior=ScenePriorConfig(patch=32, base=8, max_steps=4)),
                     clg=CLGConfig(steps=2, without_sampler=True), ted=TEDConfig(n_patches=2),
                     refgs=RefGSConfig(depth_prior_iters=5))  # fmt: skip
    inpaint(room, tmp_path / "run", config=replace(cfg))
    err = capsys.readouterr().err
    bars = [(m.group(1).strip(), int(m.group(2)), int(m.group(3)))
            for m in re.finditer(r"([A-Za-z][\w -]*?):\s+\d+%\|[^|]*\|\s*(\d+)/(\d+)", err)]  # fmt: skip
    done = {(name, total) for name, n, total in bars if n == total}
    names = {name for name, _ in done}
    assert ("train scaffold", 9) in done and ("train scaffold", 5) in done  # Ref-GS, its depth GS
    assert ("train scaffold", 4) in done and ("train scaffold", 3) in done  # TE-D's two phases
    assert any(name.startswith("CLG") for name in names)
    assert "stage 1 inpaint" in names  # one tick a view
    assert "eval renders" in names and "orbit" in names


def test_a_rerun_does_not_resume_from_a_hostile_checkpoint(tmp_path, capsys, monkeypatch):
    """`coin-cl run` on a half-finished run folder resumes 2_refgs from 2_refgs/gs/ckpt.pt: a file
    planted there that would run code when unpickled is refused, in one line naming it and the stage
    to rerun, and its code never runs."""
    from coin_cl.gs.trainer import Trainer
    from coin_cl.scene import write_synthetic
    from coin_cl.testing import hostile_checkpoint

    room = write_synthetic(tmp_path / "room", n_views=5, width=32, height=24, seed=1)
    out, marker = tmp_path / "run", tmp_path / "marker"
    args = ["run", str(room), "--out", str(out), "--iters", "2", "--prior-seconds", "1",
            "--inpaint-region", "input", "--skip-stage", "clg", "--skip-stage", "ted"]  # fmt: skip

    def killed(self):
        raise KeyboardInterrupt  # the run is killed in its first GS training, inside 2_refgs

    with monkeypatch.context() as m:
        m.setattr(Trainer, "train", killed)
        assert main(args) == 130  # Ctrl-C: one line, the finished stages kept
    assert (out / "2_refgs").is_dir() and not (out / "2_refgs" / "manifest.json").exists()
    ckpt = out / "2_refgs" / "gs" / "ckpt.pt"
    hostile_checkpoint(ckpt, marker)
    capsys.readouterr()
    assert main(args) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if "error" in ln]
    assert len(err) == 1 and str(ckpt) in err[0] and "refused" in err[0], err
    assert "Traceback" not in err[0] and not marker.exists()


@pytest.mark.parametrize(
    ("args", "flag"),
    [
        (["--budget", "-1", "--iters", "3"], "--budget"),
        (["--budget", "nan"], "--budget"),
        (["--prior-seconds", "-1"], "--prior-seconds"),
        (["--lama-path", "/nonexistent/big-lama.pt"], "--lama-path"),
        (["--iters", "0"], "--iters"),
    ],
)
def test_bad_values_are_one_line_naming_the_flag(tmp_path, capsys, args, flag):
    with pytest.raises(SystemExit) as e:
        main(["run", str(tmp_path), "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and f"argument {flag}: " in err and args[args.index(flag) + 1] in err
    assert not (tmp_path / "o").exists()


def test_an_empty_out_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["run", str(tmp_path), "--out", ""])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert e.value.code == 2 and "argument --out: '' is not a folder name" in err


def test_a_budget_that_cannot_fit_is_one_line_with_the_minimum_before_any_stage(
    tmp_path, capsys, monkeypatch
):
    """The probes measure the machine (faked here: a slow one), the plan finds the budget too small,
    and the CLI says so in one line naming the minimum; no stage folder and no plan are written."""
    from coin_cl.pipeline import coin_plan
    from coin_cl.scene import write_synthetic

    monkeypatch.setattr(coin_plan, "probe_seconds_per_step", lambda *a, **k: 2.0)
    monkeypatch.setattr(coin_plan, "prior_probe", lambda *a: lambda: 3.0)
    monkeypatch.setattr(coin_plan, "disc_probe", lambda *a: lambda: 0.5)
    room = write_synthetic(tmp_path / "room", n_views=6, width=48, height=32, seed=0)
    out = tmp_path / "out"
    assert main(["run", str(room), "--out", str(out), "--budget", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    m = re.search(r"--budget 2 minutes cannot fit .* needs at least ([0-9.]+) minutes", err)
    assert m is not None and float(m.group(1)) > 2, err
    assert not (out / "plan.json").exists() and not any(out.glob("[0-9]_*"))
