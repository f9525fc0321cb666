"""The stage runner: manifests decide what reruns; killed stages resume; folders belong to a scene."""

import json
import logging

import pytest

from coin_cl.pipeline.runner import OutputFolderError, Stage, check_output_folder, run_stages


class Calls:
    def __init__(self):
        self.n = {}

    def stage(self, name, content_fn):
        def fn(ctx):
            self.n[name] = self.n.get(name, 0) + 1
            for r, folder in ctx.inputs.items():  # reads its inputs, as a real stage does
                assert (folder / "out.txt").is_file(), r
            (ctx.out / "out.txt").write_text(content_fn(ctx))
            ctx.note(f"{name} wrote out.txt")
            return {"value": content_fn(ctx)}

        return fn


def chain(calls, a_setting=1, b_setting="x", b_content=None):
    return [
        Stage("1_a", calls.stage("a", lambda ctx: f"a{ctx.settings['k']}"), settings={"k": a_setting}),
        Stage("2_b", calls.stage("b", b_content or (lambda ctx: f"b{ctx.settings['k']}")), reads=["1_a"],
              settings={"k": b_setting}),
        Stage("3_c", calls.stage("c", lambda ctx: "c"), reads=["2_b"]),
    ]  # fmt: skip


def test_second_run_skips_everything(tmp_path):
    calls = Calls()
    rec1 = run_stages(tmp_path, chain(calls))
    assert calls.n == {"a": 1, "b": 1, "c": 1} and all(r["status"] == "ran" for r in rec1.values())
    rec2 = run_stages(tmp_path, chain(calls))
    assert calls.n == {"a": 1, "b": 1, "c": 1}
    assert all(r["status"] == "skipped: up to date" for r in rec2.values())
    assert rec2["2_b"]["result"] == {"value": "bx"}
    # the time a stage took is kept with it: a rerun that skips it still reports what it cost
    assert all(rec2[k]["seconds_when_run"] == rec1[k]["seconds"] >= 0 for k in rec1)
    logged = json.loads((tmp_path / "log.json").read_text())["stages"]
    assert set(logged) == {"1_a", "2_b", "3_c"}


def test_changed_setting_reruns_that_stage_and_the_ones_after(tmp_path):
    calls = Calls()
    run_stages(tmp_path, chain(calls))
    run_stages(tmp_path, chain(calls, b_setting="y"))
    assert calls.n == {"a": 1, "b": 2, "c": 2}  # b's output changed, so c reran; a did not
    assert (tmp_path / "2_b" / "out.txt").read_text() == "by"


def test_rerun_with_identical_output_leaves_later_stages_alone(tmp_path):
    calls = Calls()
    same = lambda ctx: "constant"  # noqa: E731
    run_stages(tmp_path, chain(calls, b_content=same))
    run_stages(tmp_path, chain(calls, b_setting="y", b_content=same))
    assert calls.n == {"a": 1, "b": 2, "c": 1}


def test_tampered_output_reruns_the_stage(tmp_path):
    calls = Calls()
    run_stages(tmp_path, chain(calls))
    (tmp_path / "1_a" / "out.txt").write_text("edited by hand")
    run_stages(tmp_path, chain(calls))
    assert calls.n["a"] == 2 and (tmp_path / "1_a" / "out.txt").read_text() == "a1"


def test_killed_stage_resumes_in_place_and_loses_nothing(tmp_path):
    calls = Calls()

    def resumable(ctx):
        # Two units of work; the first run is killed after the first one.
        done = sorted(p.name for p in ctx.out.glob("part*"))
        for part in ("part1", "part2"):
            if part in done:
                continue
            if calls.n.get("kill") is None and part == "part2":
                calls.n["kill"] = 1
                raise KeyboardInterrupt
            calls.n[part] = calls.n.get(part, 0) + 1
            (ctx.out / part).write_text(part)
        (ctx.out / "out.txt").write_text("done")
        return {}

    stages = [Stage("1_a", calls.stage("a", lambda ctx: "a")), Stage("2_r", resumable, reads=["1_a"])]
    with pytest.raises(KeyboardInterrupt):
        run_stages(tmp_path, stages)
    assert not (tmp_path / "2_r" / "manifest.json").exists()
    rec = run_stages(tmp_path, stages)
    assert rec["1_a"]["status"] == "skipped: up to date" and rec["2_r"]["status"] == "ran"
    assert calls.n["part1"] == 1 and calls.n["part2"] == 1  # part1 was not redone


def test_interrupted_folder_with_other_settings_is_moved_aside(tmp_path, caplog):
    calls = Calls()
    run_stages(tmp_path, chain(calls))
    (tmp_path / "2_b" / "manifest.json").unlink()  # as if killed
    (tmp_path / "2_b" / "stale.bin").write_bytes(b"x")
    with caplog.at_level(logging.WARNING):
        run_stages(tmp_path, chain(calls, b_setting="z"))
    assert not (tmp_path / "2_b" / "stale.bin").exists()  # nothing stale is resumed...
    (old,) = tmp_path.glob("2_b.old-*")  # ...and nothing is lost
    assert (old / "stale.bin").read_bytes() == b"x" and old.name in caplog.text


def test_finished_folder_with_other_settings_is_kept_unless_forced(tmp_path):
    calls = Calls()
    run_stages(tmp_path, chain(calls))
    run_stages(tmp_path, chain(calls, b_setting="y"))
    run_stages(tmp_path, chain(calls, b_setting="w"))  # two moves within a second get two names
    kept = sorted(p for p in tmp_path.glob("2_b.old-*"))
    assert sorted((p / "out.txt").read_text() for p in kept) == ["bx", "by"]
    assert len(list(tmp_path.glob("3_c.old-*"))) == 2  # c's inputs changed each time
    run_stages(tmp_path, chain(calls, b_setting="v"), force=["2_b"])
    assert len(list(tmp_path.glob("2_b.old-*"))) == 2  # forced: cleared, not kept


def test_skipped_stage_is_logged_with_its_reason(tmp_path):
    calls = Calls()
    stages = [Stage("1_a", calls.stage("a", lambda ctx: "a")), Stage("2_b", calls.stage("b", lambda c: "b"),
              skip="no view has a mask")]  # fmt: skip
    rec = run_stages(tmp_path, stages)
    assert rec["2_b"]["status"] == "skipped: no view has a mask" and "b" not in calls.n


def test_force_reruns(tmp_path):
    calls = Calls()
    run_stages(tmp_path, chain(calls))
    run_stages(tmp_path, chain(calls), force=["1_a"])
    assert calls.n["a"] == 2 and calls.n["b"] == 1  # same output: b stays


def test_output_folder_of_another_scene_is_refused(tmp_path):
    check_output_folder(tmp_path, {"scene": "/data/a", "hash": "1"})
    check_output_folder(tmp_path, {"scene": "/data/a", "hash": "1"})
    with pytest.raises(OutputFolderError, match="another scene"):
        check_output_folder(tmp_path, {"scene": "/data/b", "hash": "2"})
    other = tmp_path / "other"
    (other / "2_refgs").mkdir(parents=True)
    with pytest.raises(OutputFolderError, match="not a coin-cl run"):
        check_output_folder(other, {"scene": "x"})


def test_read_only_output_folder_is_one_line_naming_it(tmp_path, monkeypatch):
    import errno
    from pathlib import Path

    from coin_cl.atomic import OutputWriteError

    def mkdir(self, *a, **k):
        raise OSError(errno.EROFS, "Read-only file system", str(self))

    monkeypatch.setattr(Path, "mkdir", mkdir)
    with pytest.raises(
        OutputWriteError, match=f"cannot write in {tmp_path / 'out'}: the file system is read-only"
    ):
        check_output_folder(tmp_path / "out", {"scene": "a"})


@pytest.mark.parametrize("name", ["manifest.json", "started.json", "run.json"])
@pytest.mark.parametrize("content", ["{half", "[1, 2]", '{"key": "k", "surprise": 1}'])
def test_a_malformed_run_folder_file_is_one_line_naming_it(tmp_path, name, content):
    """A run folder's own JSON that is not JSON, not an object or carries unknown keys: a ValueError
    (one line in the CLI) naming the file and what to do, never a traceback."""
    calls = Calls()
    check_output_folder(tmp_path, {"scene": "a"})
    run_stages(tmp_path, chain(calls))
    path = tmp_path / name if name == "run.json" else tmp_path / "2_b" / name
    path.write_text(content)
    if name == "started.json":
        (tmp_path / "2_b" / "manifest.json").unlink()  # as if killed: started.json is read
    with pytest.raises(ValueError) as e:
        if name == "run.json":
            check_output_folder(tmp_path, {"scene": "a"})
        else:
            run_stages(tmp_path, chain(calls))
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{path}: ") and ("delete" in msg or "pick another" in msg)


@pytest.mark.parametrize("force", [[], ["2_b"]])
def test_a_stage_folder_that_is_a_link_is_refused_and_its_target_untouched(tmp_path, force):
    """A finished run folder whose 2_b is replaced by a link to a folder outside: skipping it (its
    files read through the link), clearing it (--force) or writing into it would each follow the
    link; the run is refused in one line naming the link, and the target keeps every byte."""
    from coin_cl.atomic import UnsafePathError

    out, outside = tmp_path / "out", tmp_path / "outside"
    calls = Calls()
    run_stages(out, chain(calls))
    (out / "2_b").rename(outside)
    (out / "2_b").symlink_to(outside, target_is_directory=True)
    before = {p.name: p.read_bytes() for p in outside.iterdir()}
    with pytest.raises(UnsafePathError) as exc:
        run_stages(out, chain(calls), force=force)
    assert str(exc.value).startswith(f"refusing to write {out / '2_b'}: it is a symbolic link (to {outside})")
    assert {p.name: p.read_bytes() for p in outside.iterdir()} == before
    assert calls.n["b"] == 1 and calls.n["c"] == 1  # nothing after the link ran
