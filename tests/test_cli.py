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


def _tree(folder):
    """{relative path: bytes} of every file under `folder` (links as their target's text)."""
    return {
        str(p.relative_to(folder)): (str(p.readlink()) if p.is_symlink() else p.read_bytes())
        for p in sorted(folder.rglob("*"))
        if p.is_file() or p.is_symlink()
    }


def test_ctrl_c_in_a_stage_is_one_line_and_the_rerun_resumes(scene, tmp_path, capsys, caplog, monkeypatch):
    import logging

    import coin_cl.pipeline.coin as coin

    out = tmp_path / "out"
    args = ["run", str(scene), "--out", str(out), "--iters", "1", "--prior-seconds", "1"]

    def interrupted(ctx):
        raise KeyboardInterrupt

    monkeypatch.setattr(coin, "stage_inpaint", interrupted)
    assert main(args) == 130
    err = capsys.readouterr().err
    assert "Traceback" not in err
    said = [line for line in err.splitlines() if "interrupted" in line]
    assert said == [
        f"coin-cl run: interrupted; finished stages are kept in {out}; run the same command again to resume"
    ]
    assert err.strip().splitlines()[-1] == said[0]
    assert not (out / ".coin-cl.lock").exists()  # released
    assert (out / "0_scene" / "manifest.json").is_file()

    def stop(ctx):
        raise ValueError("stop after the resume check")

    monkeypatch.setattr(coin, "stage_inpaint", stop)
    with caplog.at_level(logging.INFO, "coin_cl.pipeline.runner"):
        assert main(args) == 2
    assert "[0_scene] skipped: up to date" in caplog.text
    assert "[1_inpaint] resuming an interrupted run" in caplog.text


def test_sigint_to_a_running_command_ends_in_one_line_and_130(scene, tmp_path):
    """A real Ctrl-C (SIGINT to the process) while a training runs: one line, exit 130, lock gone."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "t"
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    cmd = [sys.executable, "-m", "coin_cl.cli", "train", str(scene), "--model", "3dgs", "--iters",
           "100000", "--resolution", "1.0", "--out", str(out), "--backend", "torch"]  # fmt: skip
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, env=env, text=True)
    try:
        t0 = time.monotonic()
        while not (out / "cameras.json").is_file() and time.monotonic() - t0 < 60:
            time.sleep(0.2)  # the trainer has started (it writes cameras.json before its first step)
        assert (out / ".coin-cl.lock").is_file()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        f"coin-cl train: interrupted; the last checkpoint is kept in {out}; "
        "run the same command again to resume"
    )
    assert not (out / ".coin-cl.lock").exists()


def test_run_refuses_an_unrelated_folder_and_leaves_it_untouched(scene, tmp_path, capsys):
    out = tmp_path / "mine"
    (out / "eval").mkdir(parents=True)
    (out / "eval" / "notes.txt").write_text("my notes")
    (out / "photo.jpg").write_bytes(b"\xff\xd8 not really")
    before = _tree(out)
    for extra in ([], ["--force", "eval"]):
        assert main(["run", str(scene), "--out", str(out), "--iters", "1", *extra]) == 2
        line = _one_line(capsys)
        assert line == (
            f"coin-cl run: error: {out} is not empty and is not a coin-cl run folder (no .coin-cl-out "
            "in it): give a new or empty folder as --out (coin-cl writes and deletes only in folders it made)"
        )
        assert _tree(out) == before


def test_make_scene_and_train_refuse_another_commands_folder(scene, tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["make-scene", str(out), "--views", "4", "--width", "32", "--height", "24"]) == 0
    before = _tree(out)
    assert main(["train", str(scene), "--out", str(out), "--iters", "1"]) == 2
    assert "is the output folder of coin-cl make-scene, not of coin-cl train" in _one_line(capsys)
    assert main(["make-scene", str(out), "--views", "4", "--width", "32", "--height", "24"]) == 0
    assert _tree(out) == before  # the same scene written again in its own folder


def test_a_second_run_with_other_settings_leaves_the_running_runs_plan_alone(
    scene, tmp_path, capsys, monkeypatch
):
    """The first run is paused in its first stage, its plan made (in a thread, holding the folder's lock); a
    second run with other settings is refused in one line and the first's plan.json (the step counts
    every stage and every rerun uses) keeps every byte."""
    import hashlib
    import threading

    import coin_cl.pipeline.coin as coin

    out = tmp_path / "out"
    paused, go = threading.Event(), threading.Event()

    def pausing(ctx):
        paused.set()
        assert go.wait(60)
        raise ValueError("the first run stops here: its stages are not under test")

    monkeypatch.setattr(coin, "stage_scene", pausing)
    rc: list[int] = []
    first = threading.Thread(target=lambda: rc.append(main(
        ["run", str(scene), "--out", str(out), "--iters", "1", "--prior-seconds", "1"])))  # fmt: skip
    first.start()
    try:
        assert paused.wait(120)
        plan = hashlib.sha256((out / "plan.json").read_bytes()).hexdigest()
        capsys.readouterr()
        assert main(["run", str(scene), "--out", str(out), "--iters", "3", "--prior-seconds", "2",
                     "--seed", "7", "--force", "scene"]) == 2  # fmt: skip
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(
            f"coin-cl run: error: {out} is in use by another coin-cl run"
        )
        assert hashlib.sha256((out / "plan.json").read_bytes()).hexdigest() == plan
    finally:
        go.set()
        first.join(120)
    assert rc == [2]  # the first went on after the refusal, to its own (test) end
    assert hashlib.sha256((out / "plan.json").read_bytes()).hexdigest() == plan
    assert not (out / ".coin-cl.lock").exists()
