import json
from dataclasses import asdict, replace

import numpy as np
import pytest

from coin_cl.cli import main
from coin_cl.gs.model_kinds import scaled_strategy
from coin_cl.gs.synthetic import tiny_scene
from coin_cl.scene import Scene, save_scene


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    sc = tiny_scene(n=30, width=32, height=24, n_views=8, backend="opencl")
    cams = [replace(v.camera, name=f"{v.camera.name}.png") for v in sc.views]
    imgs = [v.image.numpy() for v in sc.views]
    masks = [np.zeros((24, 32), bool) for _ in sc.views]
    scene = Scene(cams, imgs, masks, sc.noisy_points().astype(np.float32), None,
                  train_idx=list(range(8)), test_idx=[])  # fmt: skip
    return save_scene(scene, tmp_path_factory.mktemp("tiny_scene"))


def test_train_then_render_all_view_kinds(scene_dir, tmp_path):
    out = tmp_path / "run"
    rc = main(["train", str(scene_dir), "--model", "3dgs", "--iters", "20", "--resolution", "1.0",
               "--out", str(out), "--ckpt-every", "10"])  # fmt: skip
    assert rc == 0
    log = json.loads((out / "log.json").read_text())
    assert log["eval"][-1]["step"] == 20 and np.isfinite(log["eval"][-1]["psnr"])
    # The run's densification is the published schedule compressed to its length, beside what the
    # size cap reads: the training pixels (7 training views of 32x24) and the limit (none for 3DGS).
    cap = {"train_pixels": 7 * 32 * 24, "size_limit": {}}
    assert log["strategy"] == {"kind": "DefaultStrategy", **asdict(scaled_strategy("3dgs", 20)), **cap}
    assert log["terms"] == {"photometric": 1.0}
    cams = json.loads((out / "cameras.json").read_text())
    assert len(cams["train"]) == 7 and len(cams["test"]) == 1  # every 8th view held out
    # A second call resumes at the end: nothing to do, same step.
    assert main(["train", str(scene_dir), "--model", "3dgs", "--iters", "20", "--resolution", "1.0",
                 "--out", str(out)]) == 0  # fmt: skip
    assert json.loads((out / "log.json").read_text())["train"][-1]["step"] == 20
    assert main(["render", str(out), "--views", "test"]) == 0
    assert len(list((out / "renders" / "test").glob("*_depth.png"))) == 1
    assert main(["render", str(out), "--views", "orbit", "--frames", "4"]) == 0
    assert (out / "renders" / "orbit.gif").is_file()
    assert len(list((out / "renders" / "orbit").glob("*.png"))) == 8  # image + depth per frame


def test_render_without_training_is_a_clear_error(tmp_path, capsys):
    assert main(["render", str(tmp_path)]) == 2
    assert "ckpt.pt" in capsys.readouterr().err


def test_train_and_render_honour_device(scene_dir, tmp_path, monkeypatch):
    from coin_cl.engine.devices import device_label, working_devices
    from coin_cl.engine.runtime import Runtime

    target = device_label(working_devices()[-1])
    seen: list[str] = []
    orig = Runtime.launch
    monkeypatch.setattr(
        Runtime, "launch", lambda self, *a, **k: (seen.append(self.name), orig(self, *a, **k))[1]
    )
    out = tmp_path / "run"
    assert main(["train", str(scene_dir), "--model", "3dgs", "--iters", "3", "--resolution", "1.0",
                 "--out", str(out), "--device", target]) == 0  # fmt: skip
    assert main(["render", str(out), "--views", "test", "--device", target]) == 0
    assert seen and set(seen) == {target}


def _files(folder):
    """{relative path: bytes} of every file under `folder`."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_second_train_on_a_training_folder_is_refused_and_the_first_completes(
    scene_dir, tmp_path, capsys, monkeypatch
):
    """The first training is paused mid-run (in a thread, holding its folder's lock); a second
    training with other settings on that folder is refused in one line and changes no byte of it;
    the first then finishes."""
    import threading

    from coin_cl.gs.trainer import Trainer

    out = tmp_path / "t"
    paused, go = threading.Event(), threading.Event()
    step = Trainer.train_step

    def pausing_step(self):
        if self.step == 2 and not paused.is_set():  # after step 2's checkpoint
            paused.set()
            assert go.wait(60)
        return step(self)

    monkeypatch.setattr(Trainer, "train_step", pausing_step)
    rc: list[int] = []
    first = threading.Thread(target=lambda: rc.append(main([
        "train", str(scene_dir), "--model", "3dgs", "--iters", "4", "--resolution", "1.0",
        "--out", str(out), "--ckpt-every", "2", "--backend", "torch"])))  # fmt: skip
    first.start()
    try:
        assert paused.wait(60)
        before = _files(out)
        assert ".coin-cl.lock" in before and "ckpt.pt" in before
        capsys.readouterr()
        assert main(["train", str(scene_dir), "--model", "scaffold", "--iters", "5", "--fresh",
                     "--out", str(out), "--backend", "torch"]) == 2  # fmt: skip
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"coin-cl train: error: {out} is in use by another")
        assert _files(out) == before
    finally:
        go.set()
        first.join(120)
    assert rc == [0]
    assert json.loads((out / "log.json").read_text())["train"][-1]["step"] == 4
    assert not (out / ".coin-cl.lock").exists()


def test_render_writes_only_in_its_trained_folder_or_its_own_out_and_waits_for_no_one(
    scene_dir, tmp_path, capsys
):
    from coin_cl.pipeline.lock import acquire

    out = tmp_path / "t"
    assert main(["train", str(scene_dir), "--model", "3dgs", "--iters", "2", "--resolution", "1.0",
                 "--out", str(out), "--backend", "torch"]) == 0  # fmt: skip
    render = ["render", str(out), "--views", "test", "--backend", "torch"]
    # a training still holding the folder: render is refused before writing anything
    lk = acquire(out)
    try:
        before = _files(out)
        capsys.readouterr()
        assert main(render) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"coin-cl render: error: {out} is in use by another")
        assert _files(out) == before
    finally:
        lk.release()
    # a folder no train or run made: refused, untouched
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "notes.txt").write_text("mine")
    assert main(["render", str(theirs)]) == 2
    assert "has no model to render" in capsys.readouterr().err
    assert sorted(p.name for p in theirs.iterdir()) == ["notes.txt"]
    # renders/ a link out of the folder: refused, nothing written through it
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (out / "renders").symlink_to(elsewhere, target_is_directory=True)
    assert main(render) == 2
    assert "is a symbolic link" in capsys.readouterr().err and not any(elsewhere.iterdir())
    (out / "renders").unlink()
    # --out: the trained folder is only read, the renders go to a folder render marks as its own
    before = _files(out)
    dest = tmp_path / "r"
    assert main([*render, "--out", str(dest)]) == 0
    assert _files(out) == before
    assert len(list((dest / "test").glob("*_depth.png"))) == 1
    assert json.loads((dest / ".coin-cl-out").read_text())["command"] == "render"
    assert main([*render, "--out", str(theirs)]) == 2  # --out follows the output-folder rule
    assert sorted(p.name for p in theirs.iterdir()) == ["notes.txt"]
    # and without --out, into the trained folder's renders/
    assert main(render) == 0
    assert len(list((out / "renders" / "test").glob("*_depth.png"))) == 1
    assert not (out / ".coin-cl.lock").exists()


def _one_line_naming(err: str, path) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and str(path) in lines[0] and "Traceback" not in err, err
    return lines[0]


def test_render_refuses_a_hostile_checkpoint_without_running_it(tmp_path, capsys):
    """`coin-cl render TRAIN_DIR` on a received folder whose ckpt.pt would run code when unpickled."""
    from coin_cl.testing import hostile_checkpoint

    out, marker = tmp_path / "received", tmp_path / "marker"
    hostile_checkpoint(out / "ckpt.pt", marker)
    (out / "cameras.json").write_text('{"train": [], "test": []}')
    assert main(["render", str(out)]) == 2
    line = _one_line_naming(capsys.readouterr().err, out / "ckpt.pt")
    assert "refused" in line and "nothing in it was run" in line and not marker.exists()


def test_render_of_a_run_folder_refuses_a_hostile_stage_checkpoint(scene_dir, tmp_path, capsys):
    """`coin-cl render RUN`: the model comes from the run's 2_refgs/gs/ckpt.pt; the error says
    which stage to rerun."""
    import shutil

    from coin_cl.testing import hostile_checkpoint

    run, marker = tmp_path / "run", tmp_path / "marker"
    shutil.copytree(scene_dir, run / "0_scene" / "scene")
    (run / "run.json").write_text("{}")
    hostile_checkpoint(run / "2_refgs" / "gs" / "ckpt.pt", marker)
    assert main(["render", str(run)]) == 2
    line = _one_line_naming(capsys.readouterr().err, run / "2_refgs" / "gs" / "ckpt.pt")
    assert "refused" in line and "--force 2_refgs" in line and not marker.exists()


def test_render_of_a_truncated_checkpoint_is_one_line(tmp_path, capsys):
    out = tmp_path / "cut"
    out.mkdir()
    (out / "ckpt.pt").write_bytes(b"PK\x03\x04 half of a checkpoint")
    (out / "cameras.json").write_text('{"train": [], "test": []}')
    assert main(["render", str(out)]) == 2
    assert "truncated" in _one_line_naming(capsys.readouterr().err, out / "ckpt.pt")


def test_train_does_not_resume_from_a_hostile_checkpoint(scene_dir, tmp_path, capsys):
    """`coin-cl train --out DIR` resumes from DIR/ckpt.pt: a planted one is refused, not run."""
    from coin_cl.testing import hostile_checkpoint

    out, marker = tmp_path / "out", tmp_path / "marker"
    hostile_checkpoint(out / "ckpt.pt", marker)
    assert main(["train", str(scene_dir), "--model", "3dgs", "--iters", "2", "--resolution", "1.0",
                 "--backend", "torch", "--out", str(out)]) == 2  # fmt: skip
    line = _one_line_naming(capsys.readouterr().err, out / "ckpt.pt")
    assert "refused" in line and "--fresh" in line and not marker.exists()


def test_train_names_a_checkpoint_of_another_shape(scene_dir, tmp_path, capsys):
    """A safe dict that is not a training checkpoint (another program's) is one line too."""
    import torch

    out = tmp_path / "out"
    out.mkdir()
    torch.save({"weights": torch.ones(2)}, out / "ckpt.pt")
    assert main(["train", str(scene_dir), "--model", "3dgs", "--iters", "2", "--resolution", "1.0",
                 "--backend", "torch", "--out", str(out)]) == 2  # fmt: skip
    assert "not the checkpoint expected here" in _one_line_naming(capsys.readouterr().err, out / "ckpt.pt")
