"""Benchmark: nothing lost. Kill a CoIn run at any moment, hand it bad input of every kind,
run two on one folder; count what survives.

On a tiny synthetic scene (`coin_cl.scene.write_synthetic`, 6 views of 64x48 px, step counts
fixed so that runs are deterministic):

1. an uninterrupted run (the reference);
2. one run folder killed with SIGKILL again and again, each time at a seeded random moment inside
   a chosen stage (`--kills-per-stage` kills for every stage, the stage found by polling its
   `started.json`), resumed after every kill, then run to the end; after every kill every file
   under the folder must read back whole (a PNG decodes, a .pt loads, a JSON parses); at the end
   every output (images, PLY, GIF, arrays, model and prior tensors, JSON without timings) is
   compared with the reference;
3. while a run works in a folder (the kill chain's last resumption, stopped with SIGSTOP while the
   second command tries, so that it cannot end first), a second `coin-cl run` on the same folder:
   it must be refused with one line naming the holder (`lock_conflicts_caught`);
4. the bad-input corpus, built from the synthetic scene, each case through `coin-cl run` (as
   `python -m coin_cl.cli` runs it, every case in one process) and through `coin_cl.inpaint`: an
   error case passes when it gives one line naming the culprit (CLI: exit code 2, no traceback), a
   handled case when the run completes (`--cli-cases errors`, the CI test's size, runs the handled
   ones through `coin_cl.inpaint` only);
5. hostile input (`--skip-hostile` leaves it out), through `coin-cl` on copies of one finished
   tiny run folder (`hostile_cases`): a checkpoint whose unpickling would run code (planted at
   each checkpoint site and shown to run code when loaded unsafely; passes when the run refuses it
   in one line naming it and its marker file was not created: `exec_refused`); a successful
   prepare with --out the photos' parent (the photos' folder called photos/ or images/, and again
   with --replace), whose photos must stay byte-identical; a symlink to a file or folder outside
   planted where a rerun writes (log.json, report/, eval/ with --force eval; a prepare folder's
   sparse/ before a prepare with other settings), to be refused in one
   line naming it (the originals / the targets hashed before and after: `data_loss` counts what
   changed); a scene.json path leading out of its folder; malformed JSON of each run-folder file,
   a plan.json asking for 10^9 steps; a header-only PNG declaring 12000x12000; `coin-cl prepare`
   and a second `coin-cl run` on a folder a run holds; and Ctrl-C (SIGINT) in a run: exit 130,
   one line, the lock released, and the same command then resumes to the end.

Every error message (corpus and hostile, CLI's last stderr line) is judged by `vague`: clear when
it is one line that names the file or value and says what to do (the rule is in its docstring);
`vague_messages` counts the others.

The step counts, the checkpoint interval ($COIN_CKPT_SECONDS = 0.25, so kills land between
checkpoints) and the kill moments come from the command line and --seed. The last line is JSON:
kills, resumed_identical, bad_inputs, clear_errors, tracebacks (corpus and hostile), half_written_files,
lock_conflicts_caught, hostile_cases, hostile_ok, exec_refused (of exec_tried), data_loss,
vague_messages and more. `--skip-chain` leaves out 1-3 (the kill chain and its reference run).

    nice -n 15 python benchmarks/faults.py --out /tmp/faults     (about 5 minutes on 2 cores)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import cpu_model, git_commit  # noqa: E402

STAGES = ("0_scene", "0_refine", "1_inpaint", "2_refgs", "3_clg", "4_ted", "eval")
CHILD_ENV = {"COIN_CKPT_SECONDS": "0.25", "OMP_WAIT_POLICY": "PASSIVE", "PYTHONUNBUFFERED": "1"}


# ------------------------------------------------------------------------------------------ the run


def tiny_config(iters: int, prior_steps: int):
    """The harness's CoIn settings: fixed step counts at every stage (deterministic runs)."""
    from coin_cl.diffusion.inpaint2d import InpaintConfig
    from coin_cl.diffusion.sampling import SamplerConfig
    from coin_cl.diffusion.scene_prior import ScenePriorConfig

    from coin_cl.gs.refgs import RefGSConfig
    from coin_cl.pipeline.clg import CLGConfig
    from coin_cl.pipeline.coin import CoInConfig
    from coin_cl.pipeline.inpaint2d import Inpaint2DConfig
    from coin_cl.pipeline.ted import TEDConfig

    sampler = SamplerConfig(num_steps=8, discretization="uniform", eta=0.0)
    return CoInConfig(
        iters_refgs=iters,
        iters_ted_finetune=iters // 2,
        iters_ted_adversarial=iters // 2,
        prior_seconds=10,
        inpaint2d=Inpaint2DConfig(
            prior=ScenePriorConfig(patch=32, base=8, batch=4, train_steps=prior_steps),
            inpaint=InpaintConfig(sampler_prior=sampler),
        ),
        # the scene prior's sampler: its training checkpoint and cache are files a run reads back
        # (killed mid-training), which the kill chain must cover
        clg=CLGConfig(steps=4, prior_sampler=True),
        ted=TEDConfig(n_patches=2),
        refgs=RefGSConfig(depth_prior_iters=10),
    )


def _own_streams(out_path: str, err_path: str, append: bool = False) -> None:
    """A forked child's stdout and stderr (fds 1 and 2, and sys.stdout / sys.stderr, line-buffered)
    to files: its output, not the fork server's."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
    for fd, path in ((1, out_path), (2, err_path)):
        opened = os.open(path, flags)
        os.dup2(opened, fd)
        os.close(opened)
    sys.stdout = open(1, "w", buffering=1, closefd=False)  # noqa: SIM115 - the process's own streams
    sys.stderr = open(2, "w", buffering=1, closefd=False)  # noqa: SIM115


def child_main(scene: str, out: str, log_path: str, iters: int, prior_steps: int) -> None:
    """One CoIn run, what the harness starts and kills: a child of the fork server (`spawn`), its
    output appended to `log_path`."""
    _own_streams(log_path, log_path, append=True)
    from coin_cl.pipeline.coin import inpaint

    inpaint(scene, out, config=tiny_config(iters, prior_steps))


class Child:
    """A run started by `spawn`, with the `subprocess.Popen` calls the kill chain makes."""

    def __init__(self, proc) -> None:
        self.proc = proc

    @property
    def pid(self) -> int:
        return self.proc.pid

    def poll(self) -> int | None:
        return self.proc.exitcode  # None while it runs

    def wait(self) -> int:
        self.proc.join()
        return self.proc.exitcode

    def send_signal(self, sig: int) -> None:
        os.kill(self.proc.pid, sig)

    def kill(self) -> None:
        self.proc.kill()


_FORKS = None


def forks():
    """The fork server's context: runs and commands start as processes forked from a server that
    has imported torch, torch._dynamo (the first Adam imports it), the pipeline and the CLI, and
    nothing else: a fresh process (no run state, OpenCL not started), without the 6-7 s of imports a
    new interpreter pays on 2 cores, which made up most of the kill chain's and the hostile cases'
    time. The real `coin-cl` entry point starts as its own interpreter where that matters (a second
    command on a held folder, Ctrl-C)."""
    global _FORKS
    if _FORKS is None:
        import multiprocessing

        _FORKS = multiprocessing.get_context("forkserver")
        _FORKS.set_forkserver_preload(["torch", "torch._dynamo", "coin_cl.pipeline.coin", "coin_cl.cli"])
    return _FORKS


def harness_child(argv: list[str], out_path: str, err_path: str) -> None:
    """This script with `argv` (its --api or --cli mode) in a child of the fork server, stdout and
    stderr to the two files."""
    _own_streams(out_path, err_path)
    sys.argv = [__file__, *argv]
    sys.exit(main())


def run_forked(target, args: tuple, timeout: float) -> int | None:
    """`target(*args)` in a new process from the fork server (`forks`), waited for: its exit code,
    or None when it ran past `timeout` (then it is killed)."""
    proc = forks().Process(target=target, args=args)
    proc.start()
    proc.join(timeout)
    if proc.exitcode is None:
        proc.kill()
        proc.join()
        return None
    return proc.exitcode


def _read(path: str) -> str:
    return Path(path).read_text(errors="replace") if os.path.exists(path) else ""


def harness_process(argv: list[str], timeout: float) -> subprocess.CompletedProcess:
    """`python faults.py ARGV` as a new process from the fork server (`run_forked`): its exit code
    (None when it ran past `timeout`), stdout and stderr."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out_path, err_path = os.path.join(tmp, "stdout"), os.path.join(tmp, "stderr")
        rc = run_forked(harness_child, (list(argv), out_path, err_path), timeout)
        return subprocess.CompletedProcess(argv, rc, _read(out_path), _read(err_path))


def spawn(args, scene: Path, out: Path, log_path: Path) -> Child:
    """Start a CoIn run (`child_main`) in a new process from the fork server (`forks`)."""
    proc = forks().Process(
        target=child_main, args=(str(scene), str(out), str(log_path), args.iters, args.prior_steps)
    )
    proc.start()
    return Child(proc)


@contextlib.contextmanager
def case_env(env: dict[str, str]) -> Iterator[None]:
    """A corpus case's environment variables set for the block, the old values back after it."""
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def api_main(args: argparse.Namespace) -> int:
    """The bad-input corpus through `coin_cl.inpaint` (`--api CASES.json`), one JSON line per case."""
    import traceback

    from coin_cl.pipeline.coin import inpaint

    cases = json.loads(Path(args.api).read_text())
    for c in cases:
        rec, t = {"name": c["name"]}, time.time()
        with case_env(c.get("env", {})):
            try:
                inpaint(c["scene"], c["out_api"], config=tiny_config(args.iters, args.prior_steps))
                rec["outcome"] = "completed"
            except (ValueError, OSError, RuntimeError) as exc:
                rec.update(outcome="error", type=type(exc).__name__, message=str(exc))
            except Exception as exc:  # noqa: BLE001 - an unexpected kind is what this counts
                rec.update(outcome="crash", type=type(exc).__name__, message=traceback.format_exc())
        rec["seconds"] = round(time.time() - t, 2)
        print("CASE " + json.dumps(rec), flush=True)
    return 0


def cli_main(args: argparse.Namespace) -> int:
    """The corpus's `coin-cl run` calls (`--cli CASES.json`), each as `python -m coin_cl.cli ARGS`
    runs it (`runpy`: the package's `__main__`, its exit code from SystemExit), all in one process,
    one JSON line per case: what a process per case would show (exit code, stderr, a traceback)
    without paying Python's and torch's start-up for each (the hostile cases and the kill chain
    start real `coin-cl` processes)."""
    import io
    import logging
    import runpy
    import traceback

    for c in json.loads(Path(args.cli).read_text()):
        for h in logging.root.handlers[:]:  # each case's log lines go to its own stderr
            logging.root.removeHandler(h)
        err, t = io.StringIO(), time.time()
        with (
            case_env(c.get("env", {})),
            contextlib.redirect_stderr(err),
            contextlib.redirect_stdout(io.StringIO()),
        ):
            sys.argv = ["coin-cl", *c["argv"]]
            try:
                runpy.run_module("coin_cl.cli", run_name="__main__", alter_sys=True)
                rc = 0
            except SystemExit as exc:  # the command's exit, or argparse's refusal
                rc = exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 1
            except BaseException:  # noqa: BLE001 - what a process would die of, as its stderr shows it
                traceback.print_exc()
                rc = 1
        text = err.getvalue()
        rec = {"name": c["name"], "rc": rc, "stderr_tail": [_last_line(text)] if text.strip() else [],
               "traceback": "Traceback" in text, "seconds": time.time() - t}  # fmt: skip
        print("CLI " + json.dumps(rec), flush=True)
    return 0


def stage_started_after(out: Path, stage: str, t0: float) -> bool:
    p = out / stage / "started.json"
    try:
        return p.stat().st_mtime >= t0 - 1e-3
    except FileNotFoundError:
        return False


def stage_done(out: Path, stage: str) -> bool:
    return (out / stage / "manifest.json").is_file()


# ------------------------------------------------------------------------------------------ checks


def unreadable_files(root: Path) -> list[str]:
    """Files under final names that do not read back whole (PNG/GIF decode, .pt loads, JSON parses,
    PLY parses, .npy loads): what a kill must never leave."""
    import imageio.v3 as iio

    from coin_cl.checkpoint import load_checkpoint

    bad = []
    for p in sorted(root.rglob("*")):
        if not p.is_file() or p.name.startswith(".tmp") or p.name == ".coin-cl.lock":
            continue
        try:
            if p.suffix in (".png", ".jpg", ".gif"):
                iio.imread(p, index=None) if p.suffix == ".gif" else iio.imread(p)
            elif p.suffix == ".pt":
                load_checkpoint(p)
            elif p.suffix == ".json":
                json.loads(p.read_text())
            elif p.suffix == ".npy":
                np.load(p)
            elif p.suffix == ".ply":
                from plyfile import PlyData

                PlyData.read(str(p))
        except Exception as exc:  # noqa: BLE001
            bad.append(f"{p.relative_to(root)} ({type(exc).__name__})")
    return bad


VOLATILE = (
    "second",
    "time",
    "train_s",
    "peak_rss",
    "t_fwd",
    "t_bwd",
    "t_opt",
    "t_refine",
    "command",
    "started",
    "eval_s",
    "minutes",
    "per_s",
    "resumed",  # a stage's record of whether it resumed: true only in the killed run
)


def _strip(obj, root: str):
    """A JSON or checkpoint tree without timings, with the run folder's path as <OUT> (both differ
    between any two runs)."""
    if isinstance(obj, dict):
        return {k: _strip(v, root) for k, v in obj.items() if not any(w in str(k).lower() for w in VOLATILE)}
    if isinstance(obj, list | tuple):
        return [_strip(v, root) for v in obj]
    return obj.replace(root, "<OUT>") if isinstance(obj, str) else obj


def _equal(a, b) -> bool:
    import torch

    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        return (
            isinstance(a, torch.Tensor)
            and isinstance(b, torch.Tensor)
            and a.shape == b.shape
            and bool(torch.equal(a, b))
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))


def compare_outputs(ref: Path, run: Path) -> tuple[int, list[str]]:
    """(files compared, those that differ): every file of every stage folder, bytes for images,
    PLY and arrays; tensors for .pt; JSON without timings; trainer logs without timings."""

    from coin_cl.checkpoint import load_checkpoint

    n, diff = 0, []
    for st in [s for s in STAGES if (ref / s).is_dir() or (run / s).is_dir()]:
        a_files = {p.relative_to(ref / st) for p in (ref / st).rglob("*") if p.is_file()}
        b_files = {p.relative_to(run / st) for p in (run / st).rglob("*") if p.is_file()}
        skip = {"started.json", "manifest.json"}
        a_files = {f for f in a_files if f.name not in skip and not f.name.startswith(".tmp")}
        b_files = {f for f in b_files if f.name not in skip and not f.name.startswith(".tmp")}
        for f in sorted(a_files ^ b_files):
            diff.append(f"{st}/{f} (only in {'reference' if f in a_files else 'resumed run'})")
        for f in sorted(a_files & b_files):
            n += 1
            pa, pb = ref / st / f, run / st / f
            if f.suffix in (".pt", ".json"):
                load = load_checkpoint if f.suffix == ".pt" else (lambda p: json.loads(p.read_text()))
                same = _equal(_strip(load(pa), str(ref)), _strip(load(pb), str(run)))
            else:
                same = pa.read_bytes() == pb.read_bytes()
            if not same:
                diff.append(f"{st}/{f}")
    return n, diff


# ------------------------------------------------------------------------------------------ kills


def wrote_progress(folder: Path, since: float) -> bool:
    """Whether a checkpoint or a per-view image under `folder` was written after `since`."""
    for p in folder.rglob("*"):
        keep = p.name == "ckpt.pt" or p.name.endswith(".ckpt.pt") or p.suffix == ".png"
        try:
            if keep and p.stat().st_mtime > since:
                return True
        except FileNotFoundError:
            continue
    return False


def progress_kept(folder: Path) -> int:
    """Work a killed stage keeps for its resumption: training steps in its checkpoints (GS trainer,
    scene prior) plus per-view images already written."""
    from coin_cl.checkpoint import load_checkpoint

    n = 0
    for p in folder.rglob("*.pt"):
        if p.name == "ckpt.pt" or p.name.endswith(".ckpt.pt"):
            try:
                st = load_checkpoint(p)
            except Exception:  # noqa: BLE001 - counted as unreadable elsewhere
                continue
            n += int(st["trainer"]["step"]) if "trainer" in st else int(st.get("steps", 0))
    return n + sum(1 for _ in folder.glob("images/*.png"))


def lock_conflict(proc: Child, scene: Path, out: Path) -> tuple[int, int]:
    """One run at a time: while the run `proc` holds `out`'s lock, `coin-cl run` on the same folder
    must be refused with one line naming it. The holder is stopped (SIGSTOP) while the second
    command tries, so it cannot finish first, and continued afterwards: a stopped process keeps its
    lock, and its outputs are the same. Returns (caught, tried)."""
    from coin_cl.pipeline.lock import LOCK_NAME

    def holds_lock() -> bool:
        try:
            return json.loads((out / LOCK_NAME).read_text()).get("pid") == proc.pid
        except (OSError, ValueError, AttributeError):  # not there yet, or half written
            return False

    while proc.poll() is None and not holds_lock():
        time.sleep(0.02)
    if proc.poll() is not None:
        return 0, 0
    proc.send_signal(signal.SIGSTOP)
    try:
        cli = _cli(["run", str(scene), "--out", str(out), "--iters", "3"], timeout=300)
    finally:
        proc.send_signal(signal.SIGCONT)
    last = cli["last"]
    ok = cli["rc"] == 2 and "in use by another coin-cl run" in last and f"process {proc.pid}" in last
    ok = ok and not cli["traceback"] and proc.poll() is None  # and the first run goes on
    print(f"  lock conflict: rc {cli['rc']}: {last}", flush=True)
    return int(ok), 1


def kill_chain(args, scene: Path, ref: Path, out: Path, ref_seconds: dict[str, float]) -> dict:
    """Kill the run in `out` `kills_per_stage` times in every stage (seeded moments), resuming after
    each; then run it to the end. Also the lock conflict: a second run while one is alive."""
    rng = random.Random(args.seed)
    log_path = out.parent / "kill_chain.log"
    kills, per_stage, half, mid = 0, {}, [], 0
    proc, t_spawn = None, 0.0
    for st in [s for s in STAGES if (ref / s).is_dir() for _ in range(args.kills_per_stage)]:
        if stage_done(out, st):
            continue  # finished before its kill moment came: the next stage's turn
        if proc is None or proc.poll() is not None:
            t_spawn, proc = time.time(), spawn(args, scene, out, log_path)
        while proc.poll() is None and not stage_started_after(out, st, t_spawn):
            time.sleep(0.02)
        if proc.poll() is not None:
            continue
        # The moment: shortly (0-0.3 s) after the stage wrote new progress in this life (a checkpoint,
        # a finished view), so that every resumption has work to keep and the stage is still
        # running; stages that write no progress (0_scene, eval) at 30-90 % of their length.
        t_st, rand_after, delay = time.time(), rng.uniform(0.0, 0.3), None
        fallback = rng.uniform(0.3, 0.9) * max(0.2, ref_seconds.get(st, 1.0))
        while proc.poll() is None and not stage_done(out, st):
            now = time.time()
            if delay is None and wrote_progress(out / st, t_st):
                delay = now - t_st + rand_after
            if (delay is not None and now - t_st >= delay) or (delay is None and now - t_st >= fallback):
                delay = now - t_st
                break
            time.sleep(0.01)
        if proc.poll() is not None or stage_done(out, st):
            continue
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc = None
        kills += 1
        per_stage[st] = per_stage.get(st, 0) + 1
        bad = unreadable_files(out)
        half += bad
        kept = progress_kept(out / st)
        mid += kept > 0
        print(
            f"  kill {kills}: {st} after {delay:.2f} s; kept for resumption: {kept} steps + views; "
            f"unreadable files: {len(bad)}",
            flush=True,
        )
    if proc is not None:
        proc.wait()
    t0 = time.time()
    proc = spawn(args, scene, out, log_path)  # resumes what is left (skips what is done)
    conflicts, conflict_tries = lock_conflict(proc, scene, out)
    rc = proc.wait()
    n_cmp, diff = compare_outputs(ref, out)
    return {
        "kills": kills,
        "kills_per_stage": per_stage,
        "final_rc": rc,
        "final_s": time.time() - t0,
        "compared_files": n_cmp,
        "differing": diff,
        "half_written": half,
        "lock_conflicts_caught": conflicts,
        "lock_conflict_tries": conflict_tries,
        "kills_resumed_mid_stage": mid,
    }


# ------------------------------------------------------------------------------------------ bad input


def _copy(base: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(base, dst)
    return dst


def _train_names(root: Path) -> list[str]:
    names = []
    for line in (root / "views.txt").read_text().splitlines():
        t = line.split()
        if t and not line.startswith("#") and t[2] == "train":
            names.append(t[1])
    return names


def build_corpus(base: Path, root: Path) -> list[dict]:
    """The bad-input cases: {name, scene, expect ("error" | "handled"), culprit (what the error must
    name), env, out}. Built from the synthetic scene `base` (SPIn-NeRF layout)."""
    import cv2
    import imageio.v3 as iio

    cases = []
    train = _train_names(base)
    t0, t1 = train[0], train[1]

    def case(name, expect, culprit="", env=None, out=None):
        d = root / "scenes" / name
        cases.append(
            {
                "name": name,
                "scene": str(d),
                "expect": expect,
                "culprit": culprit,
                "env": env or {},
                "out": out,
            }
        )
        return d

    d = _copy(base, case("truncated_image", "error", t0))
    p = d / "images_4" / t0
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 3])
    d = _copy(base, case("unreadable_image", "error", t0))
    (d / "images_4" / t0).write_bytes(b"not an image " * 40)
    # Readable but unusual formats, one per view, in one scene (each a whole run to the end): a grey
    # image, an RGBA one, a 16-bit one, and every mask a lossy JPEG.
    d = _copy(base, case("grey_rgba_16bit_images_jpeg_masks", "handled"))
    p = d / "images_4" / t0
    iio.imwrite(p, iio.imread(p)[..., :3].mean(axis=2).astype(np.uint8))
    p = d / "images_4" / t1
    a = iio.imread(p)[..., :3]
    iio.imwrite(p, np.concatenate([a, np.full(a.shape[:2] + (1,), 255, np.uint8)], 2))
    p = d / "images_4" / train[2]
    cv2.imwrite(str(p), iio.imread(p)[..., 2::-1].astype(np.uint16) * 257)
    for p in sorted((d / "images_4" / "label").glob("*.png")):
        iio.imwrite(
            p.with_suffix(".jpg"), (iio.imread(p) > 0).astype(np.uint8) * 255, extension=".jpg", quality=70
        )
        p.unlink()
    d = _copy(base, case("mask_size_differs", "error", f"label/{t0}"))
    m = iio.imread(d / "images_4" / "label" / t0)
    iio.imwrite(d / "images_4" / "label" / t0, cv2.resize(m, (m.shape[1] // 2, m.shape[0] // 2)))
    d = _copy(base, case("masks_empty_everywhere", "error", "no training view with a mask"))
    for p in (d / "images_4" / "label").glob("*.png"):
        iio.imwrite(p, np.zeros_like(iio.imread(p)))
    d = _copy(base, case("mask_full_in_a_view", "error", f"label/{t1}"))
    p = d / "images_4" / "label" / t1
    iio.imwrite(p, np.ones_like(iio.imread(p)))
    d = _copy(base, case("mask_in_one_view_only", "handled"))
    for n in train[1:]:
        p = d / "images_4" / "label" / n
        iio.imwrite(p, np.zeros_like(iio.imread(p)))
    d = _copy(base, case("one_view", "handled"))
    keep = [ln for ln in (d / "views.txt").read_text().splitlines() if ln.startswith("#") or t0 in ln]
    (d / "views.txt").write_text("\n".join(keep) + "\n")
    for p in (d / "images_4").glob("*.png"):
        if p.name != t0:
            p.unlink()
    d = _copy(base, case("duplicate_names", "error", Path(t0).stem))
    iio.imwrite((d / "images_4" / t0).with_suffix(".jpg"), iio.imread(d / "images_4" / t0))
    d = _copy(base, case("nan_pose", "error", "poses_bounds.npy"))
    (d / "sparse" / "0" / "images.bin").unlink()
    pb = np.load(d / "poses_bounds.npy")
    pb[1, 3] = np.nan
    np.save(d / "poses_bounds.npy", pb)
    d = _copy(base, case("inf_bounds", "error", "poses_bounds.npy"))
    (d / "sparse" / "0" / "images.bin").unlink()
    pb = np.load(d / "poses_bounds.npy")
    pb[2, -1] = np.inf
    np.save(d / "poses_bounds.npy", pb)
    d = _copy(base, case("colmap_names_missing_images", "handled"))
    gone = train[-1]
    (d / "images_4" / gone).unlink()
    (d / "images_4" / "label" / gone).unlink()
    _copy(base, case("spaces and non-ASCII ünïcødé 場景", "handled"))
    case("memory_too_large", "error", "--resolution", env={"COIN_MEMORY_LIMIT_GB": "0.3"})
    cases[-1]["scene"] = str(base)
    case("read_only_output", "error", "read-only", out="ro")
    cases[-1]["scene"] = str(base)
    case("full_output_disk", "error", "disk is full", out="full")
    cases[-1]["scene"] = str(base)
    return cases


def _mount(path: Path, opts: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(path)], capture_output=True)
    return r.returncode == 0


def _umount(path: Path) -> None:
    subprocess.run(["umount", str(path)], capture_output=True)


def run_corpus(args, base: Path, root: Path) -> list[dict]:
    cases = build_corpus(base, root)
    mounts = []
    for c in cases:
        c["out_cli"] = str(root / "out_cli" / c["name"])
        c["out_api"] = str(root / "out_api" / c["name"])
        if c["out"] == "ro":  # a read-only file system: an empty tmpfs remounted read-only
            mnt = root / "mnt_ro"
            if (
                _mount(mnt, "size=4m")
                and subprocess.run(["mount", "-o", "remount,ro", str(mnt)]).returncode == 0
            ):
                mounts.append(mnt)
                c["out_cli"], c["out_api"] = str(mnt / "cli"), str(mnt / "api")
            else:
                c["skipped"] = "cannot mount a tmpfs here (needs root)"
        elif c["out"] == "full":  # a full disk: a tmpfs too small for the run's outputs
            mnt = root / "mnt_full"
            if _mount(mnt, "size=160k"):
                mounts.append(mnt)
                c["out_cli"], c["out_api"] = str(mnt / "cli"), str(mnt / "api")
            else:
                c["skipped"] = "cannot mount a tmpfs here (needs root)"
    todo = [c for c in cases if "skipped" not in c]
    try:
        # the API: every case in one process (coin_cl.inpaint), one JSON line per case
        (root / "cases.json").write_text(json.dumps(todo))
        api = harness_process(["--api", str(root / "cases.json"), "--iters", str(args.corpus_iters),
                               "--prior-steps", str(args.corpus_iters)], timeout=1800)  # fmt: skip
        got = {}
        for line in api.stdout.splitlines():
            if line.startswith("CASE "):
                r = json.loads(line[5:])
                got[r["name"]] = r
        batch = []
        for c in todo:
            c["api"] = got.get(c["name"], {"outcome": "crash", "message": api.stderr[-2000:]})
            if args.cli_cases == "errors" and c["expect"] == "handled":
                # the API has run it to the end; the CLI adds only its exit code (CI's size)
                c["cli"] = {"rc": None, "stderr_tail": [], "traceback": False, "seconds": 0.0}
                continue
            if c["out"] == "full":
                shutil.rmtree(c["out_api"], ignore_errors=True)  # room for the CLI's attempt
            argv = ["run", c["scene"], "--out", c["out_cli"], "--iters", str(args.corpus_iters),
                    "--prior-seconds", "2"]  # fmt: skip
            batch.append({"name": c["name"], "argv": argv, "env": c["env"]})
        # the CLI: every case as `python -m coin_cl.cli run ...` runs it, in one process (cli_main)
        (root / "cli_cases.json").write_text(json.dumps(batch))
        proc = harness_process(["--cli", str(root / "cli_cases.json")], timeout=1800)
        clis = {}
        for line in proc.stdout.splitlines():
            if line.startswith("CLI "):
                r = json.loads(line[4:])
                clis[r.pop("name")] = r
        for c in todo:
            if "cli" not in c:
                died = {"rc": proc.returncode, "stderr_tail": [_last_line(proc.stderr)],
                        "traceback": "Traceback" in proc.stderr, "seconds": 0.0}  # fmt: skip
                c["cli"] = clis.get(c["name"], died)
            for key in ("out_cli", "out_api"):
                if Path(c[key]).exists():
                    c.setdefault("half_written", []).extend(unreadable_files(Path(c[key])))
    finally:
        for m in mounts:
            _umount(m)
    return cases


def judge(c: dict) -> dict:
    """Per case: clear (the expected outcome, as one line naming the culprit), traceback."""
    out = {"name": c["name"], "expect": c["expect"]}
    if "skipped" in c:
        return {**out, "skipped": c["skipped"]}
    api, cli = c["api"], c["cli"]
    if c["expect"] == "handled":
        api_ok = api["outcome"] == "completed"
        cli_ok = None if cli["rc"] is None else cli["rc"] == 0  # None: not run (--cli-cases errors)
    else:
        msg = api.get("message", "")
        api_ok = api["outcome"] == "error" and "\n" not in msg and c["culprit"] in msg
        last = cli["stderr_tail"][0] if cli["stderr_tail"] else ""
        cli_ok = cli["rc"] == 2 and last.startswith("coin-cl run: error:") and c["culprit"] in last
    return {
        **out,
        "api_ok": api_ok,
        "cli_ok": cli_ok,
        "tracebacks": int(api["outcome"] == "crash") + int(cli["traceback"]),
        "api": api.get("message", api["outcome"])[:300],
        "cli": "" if c["expect"] == "handled" and cli["rc"] == 0 else (cli["stderr_tail"] or [""])[0][:300],
        "half_written": c.get("half_written", []),
        "seconds": (api.get("seconds", 0.0), cli.get("seconds", 0.0)),
        "cli_last": (cli["stderr_tail"] or [""])[0],  # whole, for `vague` (the 300 above are for tables)
    }


# ------------------------------------------------------------------------------------------ hostile input

# What a message must contain to say what to do: one of these imperative cues (case-insensitive).
FIX_WORDS = ("use ", "give ", "delete ", "remove ", "re-run", "rerun", "run ", "fix ", "pick ", "check ",
             "add ", "replace ", "re-create", "re-export", "downscale", "lower ", "set ", "pass ", "make ",
             "keep ", "rename ", "save ", "wait", "free ", "leave ", "move ", "choose ", "retry",
             "try ", "install ", "mark ", "point ", "take ")  # fmt: skip


def vague(msg: str) -> bool:
    """The harness's judgement of an error message: clear (False) when it is one non-empty line
    that (a) names the file or the value: a path (a '/'), a file name with an extension, a --flag
    or a quoted value (a bare number is not enough: "only 0 points left" names no culprit); and
    (b) says what to do: one of FIX_WORDS. Vague (True) otherwise: a Python exception's bare text
    ("list index out of range", "'NoneType' object has no attribute 'get'"), a traceback, or a
    message that names neither culprit nor remedy."""
    import re

    msg = msg.strip()
    if not msg or "\n" in msg or "Traceback" in msg:
        return True
    names = bool(
        re.search(r"/|\b[\w.-]+\.(json|png|jpe?g|npy|bin|txt|pt|ply)\b|--[a-z]|'[^']*'|\"[^\"]*\"", msg)
    )
    fixes = any(w in msg.lower() for w in FIX_WORDS)
    return not (names and fixes)


def _hash_tree(root: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `root` (a single file: {"": hash}); symlinks are
    not followed."""
    import hashlib

    if root.is_file():
        return {"": hashlib.sha256(root.read_bytes()).hexdigest()}
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and not p.is_symlink():
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def cli_child(argv: list[str], err_path: str) -> None:
    """`python -m coin_cl.cli ARGV` in a child of the fork server (`_cli`): stderr to `err_path`,
    the exit code from the command's SystemExit, as the interpreter would give it."""
    import runpy

    _own_streams(os.devnull, err_path)
    sys.argv = ["coin-cl", *argv]
    runpy.run_module("coin_cl.cli", run_name="__main__", alter_sys=True)


def _cli(args: list[str], timeout: float = 600) -> dict:
    """`python -m coin_cl.cli ARGS` in a new process (forked from the server `forks` keeps: no run
    state, without the interpreter's start-up): {rc, last (stderr's last line), traceback, seconds}."""
    import tempfile

    t = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        err_path = os.path.join(tmp, "stderr")
        rc = run_forked(cli_child, (list(args), err_path), timeout)
        err = _read(err_path)
    return {"rc": rc, "last": _last_line(err), "traceback": "Traceback" in err,
            "seconds": round(time.time() - t, 1)}  # fmt: skip


def _last_line(err: str) -> str:
    """The message a command ended with: its last "coin-cl ...: error:" line when there is one (a
    progress bar may redraw after it), else stderr's last line."""
    lines = [ln for ln in err.replace("\r", "\n").splitlines() if ln.strip()]
    # a progress bar's cursor moves (ANSI escapes) may sit before the error on its line
    errors = [ln[ln.index("coin-cl ") :] for ln in lines if "coin-cl " in ln and ": error:" in ln]
    return errors[-1] if errors else (lines[-1] if lines else "")


def _run_args(scene: Path, out: Path, iters: int) -> list[str]:
    return ["run", str(scene), "--out", str(out), "--iters", str(iters), "--prior-seconds", "2"]


class _Exec:
    """Pickled, runs `open(marker, "w")` on unpickling: the proof that a load executed code."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _plant_exec(path: Path, marker: Path) -> None:
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    path.unlink(missing_ok=True)
    torch.save({"trainer": _Exec(marker), "model": _Exec(marker), "steps": 1}, path)


def _exec_armed(path: Path, marker: Path) -> bool:
    """Whether the planted checkpoint `path` does run code when unpickled the unsafe way
    (`torch.load(weights_only=False)`, in a child process): its `marker` appears. The marker is
    removed again, so that only the run under test can make it reappear."""
    code = "import sys, torch; torch.load(sys.argv[1], weights_only=False)"
    subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, timeout=120)
    armed = marker.exists()
    marker.unlink(missing_ok=True)
    return armed


def _posed_views(folder: Path) -> int:
    """Views of the scene `coin-cl prepare` wrote in `folder` (0 when it holds none)."""
    import logging

    from coin_cl.scene import load_scene

    logging.disable(logging.WARNING)  # "no mask file": prepare was given no annotation, as meant
    try:
        return len(load_scene(folder).images)
    except (OSError, ValueError):
        return 0
    finally:
        logging.disable(logging.NOTSET)


def _error_case(name: str, res: dict, culprit: str, **extra) -> dict:
    """An error case: passes with exit code 2 and one line naming `culprit`."""
    ok = res["rc"] == 2 and not res["traceback"] and culprit in res["last"]
    return {"name": name, "ok": ok, "rc": res["rc"], "message": res["last"], "traceback": res["traceback"],
            "vague": vague(res["last"]) if res["rc"] != 0 else False, **extra}  # fmt: skip


# The groups of hostile cases (`--hostile` picks some), in the order they run.
HOSTILE_GROUPS = ("ckpt", "prepare", "symlink", "scene_json", "json", "png", "second", "ctrl_c")


def hostile_cases(args, scene: Path, root: Path) -> list[dict]:
    """The hostile-input cases (module docstring, 5.), each a dict: name, ok, rc, message,
    traceback, vague, and where it applies exec_tried / exec_refused / data_loss."""
    import cv2  # noqa: F401 - imported here so a missing OpenCV fails before the base run

    root.mkdir(parents=True, exist_ok=True)
    iters = args.corpus_iters
    groups = set(args.hostile)
    base = root / "base"
    if groups & {"ckpt", "symlink", "json"}:  # the cases that work on a finished run folder
        res = _cli(_run_args(scene, base, iters))
        print(f"  base run: rc {res['rc']} in {res['seconds']} s", flush=True)
        if res["rc"] != 0:
            return [{"name": "base_run", "ok": False, "rc": res["rc"], "message": res["last"],
                     "traceback": res["traceback"], "vague": vague(res["last"])}]  # fmt: skip
    cases = []

    def copy(name: str) -> Path:
        return _copy(base, root / name)

    if "ckpt" in groups:
        # a checkpoint whose unpickling runs code, at each checkpoint site a resumed run loads
        # (Ref-GS's trainer, TE-D's, the scene prior CLG loads: the three loaders of a run folder's .pt)
        sites = [base / "2_refgs" / "gs" / "ckpt.pt", base / "4_ted" / "finetune" / "ckpt.pt"]
        sites += sorted(base.glob("*/scene_prior_*.pt"))[:1]
        sites = [p for p in sites if p.is_file()]
        for site in sites:
            rel = site.relative_to(base)
            d = copy(f"ckpt_exec_{'_'.join(rel.parts[:2])}")
            marker = root / f"EXECUTED_{'_'.join(rel.parts[:2])}"
            marker.unlink(missing_ok=True)
            _plant_exec(d / rel, marker)
            armed = _exec_armed(d / rel, marker)
            r = _cli(_run_args(scene, d, iters))
            ran = marker.exists()
            c = _error_case(f"ckpt_exec {rel}", r, rel.name, exec_tried=1, exec_refused=int(not ran))
            # passes only when the plant would run code if unpickled (armed), the run did not run it,
            # and the run stopped at that file with a one-line refusal naming it: a run that exits 0
            # without reading the file has proven nothing
            c["ok"] = c["ok"] and armed and not ran and "refused" in r["last"]
            c["armed"] = armed
            cases.append(c)

    if "prepare" in groups:
        # prepare with --out the photos' parent: a prepare that succeeds (SfM poses the synthetic room's
        # views) must keep every photo byte for byte, whatever the photos' folder is called (images/ is
        # the name prepare's own output would take) and with --replace on that folder again
        from coin_cl.prepare.capture import synthetic_capture

        for name, extra in (("photos", []), ("images", []), ("images", ["--replace"])):
            parent = root / f"prep_{name}"
            if not extra:
                shutil.rmtree(parent, ignore_errors=True)
                synthetic_capture(parent / name, n_views=8, width=192, height=144)
                (parent / name / "notes.txt").write_text("not a photo")
            before = _hash_tree(parent / name)
            r = _cli(["prepare", str(parent / name), "--out", str(parent), *extra], timeout=300)
            after = _hash_tree(parent / name) if (parent / name).is_dir() else {}
            lost = sum(1 for k, h in before.items() if after.get(k) != h) + len(after.keys() - before.keys())
            posed = r["rc"] == 0 and _posed_views(parent) == 8
            case = f"prepare_out_is_photos_parent {name}/{' ' + extra[0] if extra else ''}"
            ok = posed and lost == 0 and not r["traceback"]
            cases.append({"name": case, "ok": ok, "rc": r["rc"], "message": r["last"],
                          "traceback": r["traceback"], "vague": vague(r["last"]) if r["rc"] != 0 else False,
                          "data_loss": lost})  # fmt: skip
        # that prepare folder with its sparse/ a link to a folder outside, prepared again with other
        # settings (which clears sparse/0 and writes a new model): refused, the target unchanged
        parent, victim = root / "prep_photos", root / "victim_sparse"
        shutil.rmtree(victim, ignore_errors=True)
        if (parent / "sparse").is_dir():
            (parent / "sparse").rename(victim)
            (parent / "sparse").symlink_to(victim, target_is_directory=True)
            before = _hash_tree(victim)
            r = _cli(["prepare", str(parent / "photos"), "--out", str(parent), "--width", "160"], timeout=300)
            after = _hash_tree(victim)
            lost = sum(1 for k, h in before.items() if after.get(k) != h) + len(after.keys() - before.keys())
            c = _error_case("symlink_out prepare sparse/", r, str(parent / "sparse"), data_loss=lost)
            c["ok"] = c["ok"] and lost == 0 and "symbolic link" in r["last"]
            cases.append(c)

    if "symlink" in groups:
        # a symlink planted in a finished run folder, pointing outside, where the rerun writes: a file
        # every rerun rewrites (log.json), a folder every rerun writes into (report/), a stage folder a
        # forced stage clears (eval/ with --force eval); each must be refused in one line naming the
        # link, the target keeping every byte
        for rel, force in (("log.json", []), ("report", []), ("eval", ["--force", "eval"])):
            d = copy(f"symlink_{rel}")
            victim = root / f"victim_{rel}"
            shutil.rmtree(victim, ignore_errors=True)
            victim.unlink(missing_ok=True)
            (d / rel).rename(victim)
            (d / rel).symlink_to(victim, target_is_directory=victim.is_dir())
            before = _hash_tree(victim)
            r = _cli([*_run_args(scene, d, iters), *force])
            after = _hash_tree(victim) if victim.exists() else {}
            lost = sum(1 for k, h in before.items() if after.get(k) != h) + len(after.keys() - before.keys())
            name = f"symlink_out {rel}{' --force eval' if force else ''}"
            c = _error_case(name, r, str(d / rel), data_loss=lost)
            c["ok"] = c["ok"] and lost == 0 and "symbolic link" in r["last"]
            cases.append(c)

    if "scene_json" in groups:
        # a scene.json naming a file outside its folder
        from coin_cl.scene import load_scene, save_scene

        nat = save_scene(load_scene(scene), root / "native_scene")
        secret = root / "secret.png"
        shutil.copy2(next((nat / "images").glob("*.png")), secret)
        doc = json.loads((nat / "scene.json").read_text())
        doc["views"][1]["image"] = "../secret.png"
        (nat / "scene.json").write_text(json.dumps(doc))
        r = _cli(_run_args(nat, root / "out_native", iters))
        cases.append(_error_case("scene_json_path_escapes", r, "scene.json"))

    if "json" in groups:
        # malformed JSON of each run-folder file (and a plan asking for 10^9 steps)
        for rel, content in (
            ("plan.json", "{half"),
            ("run.json", "[1, 2]"),
            ("2_refgs/manifest.json", "{half"),
            ("2_refgs/started.json", '{"key": 1, "unknown": 2}'),
            ("plan.json", None),
        ):
            tag = "huge_steps" if content is None else "malformed"
            d = copy(f"json_{tag}_{rel.replace('/', '_')}")
            if content is None:
                plan = json.loads((d / rel).read_text())
                plan["steps"]["refgs"] = 10**9
                content = json.dumps(plan)
            if rel.endswith("started.json"):
                (d / "2_refgs" / "manifest.json").unlink()  # as if killed: started.json decides
            (d / rel).write_text(content)
            r = _cli(_run_args(scene, d, iters))
            cases.append(_error_case(f"{tag} {rel}", r, rel.split("/")[-1]))

    if "png" in groups:
        # a header-only PNG declaring 12000x12000 (4 GB as float32 if decoded)
        d = _copy(scene, root / "huge_png_scene")
        name = _train_names(scene)[0]
        _header_only_png(d / "images_4" / name, 12000, 12000)
        r = _cli(_run_args(d, root / "out_huge", iters))
        cases.append(_error_case("header_only_12000x12000_png", r, name))

    if "second" in groups:
        # two commands on one folder: `coin-cl prepare` into a folder a run holds
        two = root / "two"
        first = subprocess.Popen([sys.executable, "-m", "coin_cl.cli", *_run_args(scene, two, iters)],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                 env={**os.environ, **CHILD_ENV})  # fmt: skip
        try:
            t0 = time.time()
            while (
                first.poll() is None
                and not (two / "0_scene" / "started.json").exists()
                and time.time() - t0 < 120
            ):
                time.sleep(0.05)
            if first.poll() is None:
                # prepare into the folder a run holds (marked as the run's, locked): refused in one line
                # naming the folder, nothing of prepare's written there
                r = _cli(["prepare", str(scene / "images_4"), "--out", str(two)], timeout=300)
                theirs = ("images", "images_prepared", "sparse", "masks", ".prepare", "prepare_report.txt")
                wrote = [n for n in theirs if (two / n).exists()]
                c = _error_case("second_command_on_a_run_folder prepare", r, str(two))
                c["ok"] = c["ok"] and not wrote and first.poll() is None
                c["wrote"] = wrote
                cases.append(c)
                # a second run with other settings on it: refused by the lock, naming the first
                r = _cli(_run_args(scene, two, iters + 1), timeout=300)
                c = _error_case("second_command_on_a_run_folder run", r, f"process {first.pid}")
                c["ok"] = c["ok"] and "in use by another coin-cl run" in r["last"] and first.poll() is None
                cases.append(c)
        finally:
            first.kill()
            first.wait()

    if "ctrl_c" in groups:
        # Ctrl-C: SIGINT in the middle of a run: a prompt exit, no traceback, nothing half written
        d = root / "ctrl_c"
        proc = subprocess.Popen([sys.executable, "-m", "coin_cl.cli", *_run_args(scene, d, iters)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, **CHILD_ENV})  # fmt: skip
        t0 = time.time()
        while (
            proc.poll() is None and not (d / "2_refgs" / "started.json").exists() and time.time() - t0 < 300
        ):
            time.sleep(0.05)
        time.sleep(0.3)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                _, err = proc.communicate(timeout=30)
                rc = proc.returncode
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
                rc = None
            last = _last_line(err)
            half = unreadable_files(d)
            lock_left = (d / ".coin-cl.lock").exists()
            # the one line says "run the same command again to resume": it must
            again = _cli(_run_args(scene, d, iters)) if rc == 130 else {"rc": None, "traceback": False}
            ok = rc == 130 and "interrupted" in last and "Traceback" not in err and not half
            ok = ok and not lock_left and not vague(last) and again["rc"] == 0
            cases.append({"name": "ctrl_c", "ok": ok,
                          "rc": rc, "message": last, "traceback": "Traceback" in err or again["traceback"],
                          "vague": vague(last), "half_written": half, "lock_left": lock_left,
                          "resumed_rc": again["rc"]})  # fmt: skip
        else:
            proc.wait()

    return cases


def _header_only_png(path: Path, width: int, height: int) -> None:
    """A valid PNG signature and IHDR declaring width x height RGB, a tiny IDAT, IEND."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(4096)))
                     + chunk(b"IEND", b""))  # fmt: skip


# ------------------------------------------------------------------------------------------ main


def run_chain(args, scene: Path) -> tuple[float, dict]:
    """The reference run, the kill chain and the lock conflict (module docstring, 1-3):
    (reference seconds, the chain's record)."""
    ref = args.out / "ref"
    t0 = time.time()
    rc = spawn(args, scene, ref, args.out / "ref.log").wait()
    if rc != 0:
        print((args.out / "ref.log").read_text()[-3000:])
        raise SystemExit(f"the reference run failed (rc {rc}); see {args.out / 'ref.log'}")
    ref_s = time.time() - t0
    logd = json.loads((ref / "log.json").read_text())["stages"]
    ref_seconds = {k: float(v.get("seconds", 0.0)) for k, v in logd.items()}
    print(
        f"reference run: {ref_s:.0f} s; stages " + ", ".join(f"{k} {v:.1f} s" for k, v in ref_seconds.items())
    )
    print("kill chain:", flush=True)
    chain = kill_chain(args, scene, ref, args.out / "killed", ref_seconds)
    chain["identical"] = chain["final_rc"] == 0 and not chain["differing"]
    print(
        "\n| kills | per stage | compared files | differing | unreadable after a kill "
        "| lock conflicts caught |"
    )
    print("|---|---|---|---|---|---|")
    c = chain
    print(
        f"| {c['kills']} | {c['kills_per_stage']} | {c['compared_files']} | {len(c['differing'])} "
        f"| {len(c['half_written'])} | {c['lock_conflicts_caught']} / {c['lock_conflict_tries']} |"
    )
    for d in chain["differing"][:20]:
        print(f"  differs: {d}")
    return ref_s, chain


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/coin_faults"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--iters", type=int, default=40, help="Ref-GS steps (TE-D: half each phase)")
    ap.add_argument("--prior-steps", type=int, default=30)
    ap.add_argument("--kills-per-stage", type=int, default=5)
    ap.add_argument("--corpus-iters", type=int, default=10, help="GS and prior steps of the bad-input runs")
    ap.add_argument("--skip-corpus", action="store_true")
    ap.add_argument(
        "--skip-chain", action="store_true", help="leave out the reference run and the kill chain"
    )
    ap.add_argument("--skip-hostile", action="store_true", help="leave out the hostile-input cases")
    ap.add_argument(
        "--hostile",
        nargs="+",
        choices=HOSTILE_GROUPS,
        default=list(HOSTILE_GROUPS),
        help="which groups of hostile cases to run (default all)",
    )
    ap.add_argument(
        "--cli-cases",
        choices=("all", "errors"),
        default="all",
        help="corpus cases also run through `coin-cl run`: all, or only those that must "
        "fail (the handled ones then run to the end through coin_cl.inpaint alone)",
    )
    ap.add_argument("--api", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--cli", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.api:
        return api_main(args)
    if args.cli:
        return cli_main(args)
    os.environ.update(CHILD_ENV)
    from coin_cl.scene import write_synthetic

    t_start = time.time()
    if args.out.exists():
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True)
    scene = write_synthetic(args.out / "scene", n_views=args.views, width=64, height=48, seed=args.seed)
    from coin_cl.engine.runtime import get_runtime

    print(
        f"# faults: CPU {cpu_model()}, {os.cpu_count()} cores, OpenCL {get_runtime().name}, commit "
        f"{git_commit()}, {args.views} views 64x48, Ref-GS {args.iters} "
        f"steps, TE-D {args.iters // 2} + {args.iters // 2}, prior {args.prior_steps} steps, "
        f"checkpoints every 0.25 s ($COIN_CKPT_SECONDS), seed {args.seed}",
        flush=True,
    )
    ref_s, chain = 0.0, None
    if not args.skip_chain:
        ref_s, chain = run_chain(args, scene)
    rows = []
    if not args.skip_corpus:
        print("\nbad-input corpus:", flush=True)
        rows = [judge(c) for c in run_corpus(args, scene, args.out / "bad")]
        print("\n| case | expected | coin_cl.inpaint | coin-cl run | message (CLI) |")
        print("|---|---|---|---|---|")
        for r in rows:
            if "skipped" in r:
                print(f"| {r['name']} | {r['expect']} | skipped | skipped | {r['skipped']} |")
                continue
            print(
                f"| {r['name']} | {r['expect']} | {'ok' if r['api_ok'] else 'FAIL'} | "
                f"{'not run' if r['cli_ok'] is None else 'ok' if r['cli_ok'] else 'FAIL'} | "
                f"{r['cli'] or '(completed)'} |"
            )
        times = ", ".join(f"{r['name']} {r['seconds'][0]:.1f} + {r['seconds'][1]:.1f}" for r in rows
                          if "skipped" not in r)  # fmt: skip
        print(f"seconds per case (coin_cl.inpaint + coin-cl run): {times}")
        for r in rows:
            if "skipped" not in r and not (r["api_ok"] and r["cli_ok"] is not False):
                print(f"  {r['name']}: api: {r['api']!r}\n  {' ' * len(r['name'])}  cli: {r['cli']!r}")
    hostile = []
    if not args.skip_hostile:
        print("\nhostile input:", flush=True)
        hostile = hostile_cases(args, scene, args.out / "hostile")
        print("\n| hostile case | ok | rc | message (CLI) |")
        print("|---|---|---|---|")
        for h in hostile:
            extra = "".join(f", {k} {h[k]}" for k in ("exec_refused", "data_loss") if k in h)
            print(
                f"| {h['name']} | {'ok' if h['ok'] else 'FAIL'}{extra} | {h['rc']} | {h['message'][:300]} |"
            )
    judged = [r for r in rows if "skipped" not in r]
    ch = chain or {
        "kills": 0,
        "kills_per_stage": {},
        "kills_resumed_mid_stage": 0,
        "identical": None,
        "compared_files": 0,
        "differing": [],
        "half_written": [],
        "lock_conflicts_caught": None,
    }
    half = (len(ch["half_written"]) + sum(len(r["half_written"]) for r in judged)
            + sum(len(h.get("half_written", [])) for h in hostile))  # fmt: skip
    messages = [r["cli_last"] for r in judged if r["expect"] == "error" and r["cli_ok"] is not None] + [
        h["message"] for h in hostile if h["rc"] not in (0, None)
    ]
    for m in messages:
        if vague(m):
            print(f"  vague: {m[:400]}")
    result = {
        "kills": ch["kills"],
        "kills_per_stage": ch["kills_per_stage"],
        "kills_resumed_mid_stage": ch["kills_resumed_mid_stage"],
        "resumed_identical": ch["identical"],
        "compared_files": ch["compared_files"],
        "differing_files": len(ch["differing"]),
        "bad_inputs": len(judged),
        "clear_errors": sum(r["api_ok"] and r["cli_ok"] is not False for r in judged),
        "cli_not_run": [r["name"] for r in judged if r["cli_ok"] is None],
        "bad_inputs_skipped": [r["name"] for r in rows if "skipped" in r],
        "tracebacks": sum(r["tracebacks"] for r in judged) + sum(int(h["traceback"]) for h in hostile),
        "half_written_files": half,
        "lock_conflicts_caught": ch["lock_conflicts_caught"],
        "hostile_cases": len(hostile),
        "hostile_ok": sum(bool(h["ok"]) for h in hostile),
        "hostile_failed": [h["name"] for h in hostile if not h["ok"]],
        "exec_tried": sum(h.get("exec_tried", 0) for h in hostile),
        "exec_refused": sum(h.get("exec_refused", 0) for h in hostile),
        "data_loss": sum(h.get("data_loss", 0) for h in hostile),
        "vague_messages": sum(vague(m) for m in messages),
        "reference_s": round(ref_s, 1),
        "total_s": round(time.time() - t_start, 1),
        "cpu": cpu_model(),
        "device": get_runtime().name,
        "commit": git_commit(),
        "seed": args.seed,
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
