"""The stage runner: CoIn as a chain of stages, each a function from files to files.

A stage reads the folders of the stages before it and writes its own, `OUT/<stage name>/`. After it
finishes the runner writes `OUT/<stage>/manifest.json`: the stage's *key* (a hash of its settings
and of the manifests of the stages it reads) and a hash of every file it wrote. On the next run a
stage is skipped when its manifest is there, its key is the same and its files still hash the
same: a manifest decides, never the mere existence of files. Consequences:

- changing a setting reruns that stage; the stages after it rerun only if its outputs changed
  (their key includes its output hashes);
- a run killed inside a stage leaves no manifest for it; the next run calls the stage again in the
  same folder, so a stage that checkpoints (training) or writes per-view files resumes where it
  stopped. A folder made with *other* settings (`started.json` says which) is moved aside to
  `<name>.old-<time>` (deleted only when the stage is forced), so nothing stale is resumed and
  nothing costly is lost;
- one run per folder: `OUT/.coin-cl.lock` (`coin_cl.pipeline.lock`) names the run holding it;
- `OUT/run.json` names the scene the folder belongs to; another scene is a clear error.

Every stage decision (ran, skipped and why, resumed, cleared) is logged and recorded in
`OUT/log.json` with the stage's result (a JSON-able dict: settings, which models were used,
timings, figures).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar, overload

from coin_cl import schema
from coin_cl.atomic import check_path
from coin_cl.schema import parse_optional, run_folder_fix

log = logging.getLogger(__name__)

MANIFEST = "manifest.json"
STARTED = "started.json"


# What the caller gives every stage (the CoIn pipeline: `pipeline.run_inputs.RunInputs`). The runner
# only passes it on, so it stays generic: it decides what runs from files and settings, never from
# what the stages are given.
T = TypeVar("T")


class OutputFolderError(ValueError):
    """The output folder belongs to another scene (or is not a pipeline folder)."""


@dataclass
class StageContext(Generic[T]):
    """What a stage function sees: its own folder, the folders of the stages it reads, the inputs
    the runner was given for every stage (`run`, e.g. the loaded scene) and a log of notes."""

    name: str
    out: Path
    inputs: dict[str, Path]
    settings: dict[str, Any]
    run: T
    notes: list[str] = field(default_factory=list)

    def note(self, msg: str) -> None:
        """Log a decision (a view skipped, a default model used) and keep it in the run log."""
        log.info("[%s] %s", self.name, msg)
        self.notes.append(msg)


@dataclass
class Stage(Generic[T]):
    """name: folder name (e.g. "2_refgs"); fn(ctx) -> dict does the work; reads: names of the
    stages whose folders it reads; settings: JSON-able values its output depends on, or a function
    returning them, called when the stage is reached (for values that depend on what the stages
    before it measured, such as TE-D's step count after Ref-GS's timing); skip: a reason to leave
    it out (logged), or None."""

    name: str
    fn: Callable[[StageContext[T]], dict]
    reads: Sequence[str] = ()
    settings: dict[str, Any] | Callable[[], dict[str, Any]] = field(default_factory=dict)
    skip: str | None = None


def _json(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str)


def hash_files(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `folder` except the runner's own."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name not in (MANIFEST, STARTED) and not p.name.startswith(".tmp"):
            h = hashlib.sha256()
            with p.open("rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
            out[str(p.relative_to(folder))] = h.hexdigest()
    return out


def _write_json(path: Path, obj: Any) -> None:
    from coin_cl.atomic import write_text

    write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str))


def read_manifest(folder: Path) -> dict | None:
    """A stage folder's manifest.json checked against `coin_cl.schema.MANIFEST`; None when absent.
    A malformed one is a `SchemaError` naming it (deleting it makes the stage run again)."""
    path = Path(folder) / MANIFEST
    return parse_optional(path, schema.MANIFEST, run_folder_fix(path, "that stage runs again"))


def read_started(folder: Path) -> dict | None:
    """A stage folder's started.json checked against `coin_cl.schema.STARTED`; None when absent."""
    path = Path(folder) / STARTED
    return parse_optional(path, schema.STARTED, run_folder_fix(path, "that stage starts over"))


def read_run_record(out: Path) -> dict | None:
    """OUT/run.json (the scene the folder belongs to) checked against `coin_cl.schema.RUN`; None
    when absent."""
    path = Path(out) / "run.json"
    return parse_optional(
        path, schema.RUN, f"pick another --out, or delete {path} if that folder is your own run"
    )


def check_output_folder(out: Path, scene_id: dict[str, Any]) -> None:
    """Claim `out` for the scene `scene_id` (JSON-able: path, content hash); refuse another's."""
    from coin_cl.atomic import disk_error

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a read-only or full disk: one line naming the folder
        raise (disk_error(exc, out) or exc) from None
    run = out / "run.json"
    have = read_run_record(out)
    if have is None:
        if any(p.name[0].isdigit() for p in out.iterdir()):
            raise OutputFolderError(
                f"{out} holds stage folders but no run.json: not a coin-cl run; pick another --out"
            )
        _write_json(run, {"scene": scene_id})
        return
    if _json(have.get("scene")) != _json(scene_id):
        raise OutputFolderError(
            f"{out} holds a run of another scene ({have.get('scene')}), not {scene_id}: "
            "pick another --out (or delete that folder)"
        )


@overload
def run_stages(
    out: Path, stages: Sequence[Stage[None]], run: None = None, force: Sequence[str] = ()
) -> dict[str, dict]: ...


@overload
def run_stages(
    out: Path, stages: Sequence[Stage[T]], run: T, force: Sequence[str] = ()
) -> dict[str, dict]: ...


def run_stages(
    out: Path,
    stages: Sequence[Stage[T]],
    run: T | None = None,
    force: Sequence[str] = (),
) -> dict[str, dict]:
    """Run `stages` in order under `out`; returns {stage name: record} (also in OUT/log.json).

    A record holds status ("ran", "skipped: up to date", "skipped: <reason>"), seconds (of this
    run; an up-to-date stage has `seconds_when_run` instead, from its manifest), the stage's result
    and notes. `run` reaches every stage function as `ctx.run`, unchanged. `force` names stages to
    rerun regardless of their manifest. The run holds `out`'s lock throughout
    (`coin_cl.pipeline.lock`: a second run on the folder is refused, naming this one)."""
    from coin_cl.pipeline.lock import folder_lock

    with folder_lock(out):
        return _run_stages(Path(out), stages, run, force)


def move_aside(folder: Path) -> Path:
    """Rename a stage folder made with other settings to `<name>.old-<UTC time>` beside it (kept,
    not deleted: it may hold hours of training); returns the new path."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    dest = folder.with_name(f"{folder.name}.old-{stamp}")
    n = 1
    while dest.exists():
        dest, n = folder.with_name(f"{folder.name}.old-{stamp}-{n}"), n + 1
    folder.rename(dest)
    return dest


def _run_stages(out: Path, stages: Sequence[Stage[T]], run: T, force: Sequence[str]) -> dict[str, dict]:
    records: dict[str, dict] = {}
    manifests: dict[str, dict] = {}
    log_path = out / "log.json"
    for st in stages:
        # a stage folder that is a link (planted in a folder from anyone) is neither read as up to
        # date, cleared, moved nor written through: one line naming it (UnsafePathError)
        folder = out / st.name
        check_path(folder)
        if st.skip:
            log.info("[%s] skipped: %s", st.name, st.skip)
            records[st.name] = {"status": f"skipped: {st.skip}"}
            continue
        missing = [r for r in st.reads if r not in manifests]
        if missing:
            raise RuntimeError(f"stage {st.name} reads {missing}, which did not run before it")
        if callable(st.settings):
            st = Stage(st.name, st.fn, st.reads, st.settings(), st.skip)
        key = hashlib.sha256(
            _json(
                {"settings": st.settings, "inputs": {r: manifests[r]["outputs"] for r in st.reads}}
            ).encode()
        ).hexdigest()
        man = read_manifest(folder)
        if (
            st.name not in force
            and man is not None
            and man.get("key") == key
            and folder.is_dir()
            and hash_files(folder) == man.get("outputs")
        ):
            log.info("[%s] skipped: up to date (manifest key and output hashes match)", st.name)
            manifests[st.name] = man
            records[st.name] = {"status": "skipped: up to date", "result": man.get("result", {}),
                                "seconds_when_run": man.get("seconds")}  # fmt: skip
            continue
        started = read_started(folder)
        if folder.exists() and (started is None or started.get("key") != key or st.name in force):
            if st.name in force:
                log.info("[%s] clearing %s (forced)", st.name, folder)
                shutil.rmtree(folder)
            else:
                kept = move_aside(folder)
                log.warning(
                    "[%s] settings or inputs changed: the old %s is kept as %s (delete it, or "
                    "use --force %s next time, to discard it)",
                    st.name,
                    folder.name,
                    kept,
                    st.name,
                )
        elif folder.exists():
            log.info("[%s] resuming an interrupted run in %s", st.name, folder)
            for tmp in folder.rglob(".tmp-*"):  # what a kill left of an atomic write (coin_cl.atomic)
                tmp.unlink()
        folder.mkdir(parents=True, exist_ok=True)
        (folder / MANIFEST).unlink(missing_ok=True)
        _write_json(folder / STARTED, {"key": key, "settings": st.settings})
        ctx = StageContext(st.name, folder, {r: out / r for r in st.reads}, dict(st.settings), run)
        t0 = time.perf_counter()
        result = st.fn(ctx) or {}
        seconds = time.perf_counter() - t0
        man = {"key": key, "settings": st.settings, "outputs": hash_files(folder), "result": result,
               "seconds": seconds}  # fmt: skip
        _write_json(folder / MANIFEST, man)
        manifests[st.name] = man
        records[st.name] = {"status": "ran", "seconds": seconds, "result": result, "notes": ctx.notes}
        log.info("[%s] done in %.1f s", st.name, seconds)
        _write_json(log_path, {"stages": records})
    _write_json(log_path, {"stages": records})
    return records


def jsonable(obj: Any) -> Any:
    """`obj` with dataclasses as dicts and anything not JSON-able as its str (stage settings)."""
    if hasattr(obj, "__dataclass_fields__"):
        return jsonable(asdict(obj))
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    return obj if isinstance(obj, str | int | float | bool | type(None)) else str(obj)


def share_stages(
    src: str | Path, dst: str | Path, stages: tuple[str, ...] = ("0_scene", "0_refine", "1_inpaint")
) -> None:
    """Start run folder `dst` from the `stages` folders of run `src` (and its scene record), so a
    comparison row (a baseline, an ablation) reuses them instead of redoing them. Safe by
    construction: the runner reruns any copied stage whose manifest does not match `dst`'s settings.
    Existing folders in `dst` are left alone."""
    import shutil

    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True, exist_ok=True)
    if (src / "run.json").is_file() and not (dst / "run.json").exists():
        shutil.copy2(src / "run.json", dst / "run.json")
    for name in stages:
        if (src / name / "manifest.json").is_file() and not (dst / name).exists():
            shutil.copytree(src / name, dst / name)
