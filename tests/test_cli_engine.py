"""`coin-cl demo` and `coin-cl doctor` end to end (small sizes)."""

import json
import re

import numpy as np

from coin_cl.cli import main


def test_demo_turntable_writes_frames(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path), "--render-only", "--frames", "2", "--size", "64", "48"]) == 0
    doc = json.loads((tmp_path / "demo.json").read_text())
    assert doc["turntable"]["frames"] == 2 and doc["turntable"]["median_pairs"] > 0
    assert (tmp_path / "turntable" / "turntable.gif").is_file()
    assert len(list((tmp_path / "turntable").glob("frame_*.png"))) == 2
    # the folder's marker (coin_cl.outdir) is the one dot file a command leaves, on purpose
    left = [p.name for p in tmp_path.rglob(".*")]
    assert left == [".coin-cl-out"], f"temporary files left behind: {left}"


def test_demo_room_runs_coin_and_baselines(tmp_path, capsys, monkeypatch):
    import coin_cl.pipeline.refgs as refgs_mod

    excluded: list = []  # Ref-GS's `exclude` per call: CoIn's first, the naive row's second
    real_refgs = refgs_mod.run_refgs

    def refgs_spy(*a, **k):
        excluded.append(k.get("exclude"))
        return real_refgs(*a, **k)

    monkeypatch.setattr(refgs_mod, "run_refgs", refgs_spy)
    args = ["demo", "--out", str(tmp_path), "--frames", "1", "--size", "32", "32", "--room-size", "64", "48",
            "--room-views", "8", "--prior-seconds", "1", "--iters", "3", "--steps", "30"]  # fmt: skip
    assert main(args) == 0
    room = json.loads((tmp_path / "demo.json").read_text())["room"]
    assert set(room["methods"]) == {"coin", "inpaint_then_gs", "masked_recon"}
    for row in room["methods"].values():
        assert all(np.isfinite(row[k]) for k in ("psnr", "m_psnr", "hf_ratio", "bbox_gmsd")), row
    # a reconstruction, however short, beats a blank image on the held-out ground truth
    assert room["methods"]["masked_recon"]["psnr"] > 10.0
    # the embedded default standing in for Stable Diffusion 2 is named in the results, and CoIn's row
    # names the stages its run had (without a sampler CLG is left out)
    assert "embedded exemplar" in room["inpainting_model"]
    assert room["methods"]["coin"]["what"] == "CoIn: Ref-GS, TE-D on the stage-1 inpaints"
    md = (tmp_path / "room" / "results.md").read_text()
    assert "| coin |" in md and "embedded exemplar" in md and md in capsys.readouterr().out
    # the baseline started from CoIn's very inpaints: its stage 1 was skipped, not redone
    log = json.loads((tmp_path / "room" / "inpaint_then_gs" / "log.json").read_text())
    assert log["stages"]["1_inpaint"]["status"] == "skipped: up to date"
    assert log["stages"]["2_refgs"]["status"] == "ran"
    # same budget: the naive row trains CoIn's GS steps (3 Ref-GS + 3 + 3 TE-D), masked reconstruction
    # the `--steps` given
    assert "Scaffold-GS, 9 steps" in room["methods"]["inpaint_then_gs"]["what"]
    # ... its growth capped at one Gaussian per MR_PIXELS_PER_GAUSSIAN training pixels (6 views of 64x48)
    assert "3DGS, 30 steps (at most 1843 Gaussians)" in room["methods"]["masked_recon"]["what"]
    # the naive row planned with CoIn's measured rates instead of probing again
    plan = json.loads((tmp_path / "room" / "inpaint_then_gs" / "plan.json").read_text())
    assert plan["key"]["rates_from"] == str(tmp_path / "room" / "coin")
    # the room takes the refined split; CoIn leaves its observed part to the other views' captures
    # (observed="captures"), the naive row trains on all of stage 1's pixels (observed="target")
    assert (tmp_path / "room" / "coin" / "0_refine").is_dir() and len(excluded) == 2
    assert excluded[0] is not None and any(e.any() for e in excluded[0] if e is not None)
    assert excluded[1] is None
    # CoIn's page is written at the end of its run, and every picture it shows is a file of the run
    coin = tmp_path / "room" / "coin"
    page = (coin / "report.html").read_text()
    links = re.findall(r'(?:src|href)="([^"]+)"', page)
    assert "eval/orbit.gif" in links and any(li.startswith("eval/renders/") for li in links)
    assert all((coin / li).exists() for li in links), [li for li in links if not (coin / li).exists()]
    assert 'id="splat-data"' in page


def test_doctor_lists_the_device(capsys):
    from coin_cl.engine.runtime import get_runtime

    assert main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert "OpenCL devices (probe" in out and "probe: works" in out
    assert f"default device: {get_runtime().name} (" in out
    for model in ("sd2", "dino", "scene_prior"):
        assert f"  {model}: " in out


def test_doctor_working_lists_usable_devices(capsys):
    from coin_cl.engine.runtime import get_runtime

    assert main(["doctor", "--working"]) == 0
    labels = capsys.readouterr().out.splitlines()
    assert labels and all(" / " in line for line in labels)
    if "COIN_CL_DEVICE" not in __import__("os").environ:
        assert labels[0] == get_runtime().name  # the default is the first working device


def test_doctor_fails_when_no_device_builds(capsys, monkeypatch):
    from coin_cl.engine import devices

    monkeypatch.setattr(devices, "_PROBES", {})
    monkeypatch.setattr(devices, "_PROBE_SOURCE", "__kernel void probe(__global float *x) { x[0] = y; }")
    assert main(["doctor"]) == 1
    out = capsys.readouterr().out
    assert "FAILS:" in out and "No OpenCL device can build kernels" in out and "intel-opencl-rt" in out
    assert main(["doctor", "--working"]) == 1


def _record_launches(monkeypatch) -> list[str]:
    from coin_cl.engine.runtime import Runtime

    seen: list[str] = []
    orig = Runtime.launch

    def launch(self, *a, **k):
        seen.append(self.name)
        return orig(self, *a, **k)

    monkeypatch.setattr(Runtime, "launch", launch)
    return seen


def test_demo_device_flag_is_the_device_that_renders(tmp_path, monkeypatch):
    """--device is honoured: every kernel launch of the demo goes to the named device (the last
    working one, so that with two implementations present it is not the default)."""
    from coin_cl.engine.devices import device_label, working_devices

    target = device_label(working_devices()[-1])
    seen = _record_launches(monkeypatch)
    args = ["demo", "--out", str(tmp_path), "--render-only", "--frames", "1", "--size", "32", "24"]
    assert main([*args, "--device", target]) == 0
    assert seen and set(seen) == {target}
    assert json.loads((tmp_path / "demo.json").read_text())["device"] == target
