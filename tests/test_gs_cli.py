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
    # The run's densification is the published schedule compressed to its length.
    assert log["strategy"] == {"kind": "DefaultStrategy", **asdict(scaled_strategy("3dgs", 20))}
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
