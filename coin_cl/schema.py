"""Schemas of the JSON files coin-cl reads back: a run folder's `plan.json`, `run.json`, each stage's
`manifest.json` and `started.json`, and a scene's `scene.json` and `scene_info.json`.

Files come from anyone: a run folder may be copied, edited or planted, a scene downloaded. Every
reader goes through `parse(path, spec)`, which returns the document only when it matches the spec
and otherwise raises `SchemaError`, one line naming the file, the field and what to do, e.g.

    /runs/a/plan.json: steps.refgs is 1000000000, outside 0..10000000; delete /runs/a/plan.json
    (the next run plans again) or pick another --out

A spec is an `Obj` of named `Field`s, each a JSON kind (`int`, `float`, `str`, `bool`, `list`,
`dict`), optional or nullable, with an inclusive numeric range (NaN and Inf are out of every
range) or choices; a list's items and a dict's values may have their own `Field`, an object its
own `Obj`. Unknown keys are an error naming them: coin-cl writes every one of these files with a
fixed set of keys, so an unknown key means a file from another program or another version, and
reading it as if it were ours would silently drop what its writer meant. A key an older version
did not write is declared `required=False`. Free-form parts (a stage's `settings` and `result`,
a scene's `meta`) are declared as plain `dict`: their content is the stage's own and never names
a file that is opened.

No dependency: the checks are a few dozen lines; jsonschema or pydantic would add a package for
less control over the one-line message.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# Larger files are refused before parsing: the biggest coin-cl writes (a manifest with a few
# thousand output hashes) is well under 1 MiB.
MAX_JSON_BYTES = 16 * 1024 * 1024
# The largest step count any plan may hold: 1000x the paper's 10k schedule.
MAX_STEPS = 10_000_000


class SchemaError(ValueError):
    """A file does not match its schema; the message (one line) names the file, the field and
    what to do."""


@dataclass(frozen=True)
class Field:
    """One value: `kind` a JSON kind (int, float, str, bool, list, dict; float accepts ints; a tuple
    for several), `required` (False: the key may be absent), `nullable` (None allowed), `lo`/`hi`
    (inclusive bounds of a number, or of a list's length), `choices` (allowed values), `items`
    (the Field of each list item or dict value), `obj` (the `Obj` of a dict value)."""

    kind: type | tuple[type, ...]
    required: bool = True
    nullable: bool = False
    lo: float | None = None
    hi: float | None = None
    choices: tuple | None = None
    items: Field | None = None
    obj: Obj | None = None


@dataclass(frozen=True)
class Obj:
    """A JSON object: its `fields` by key; `extra` True lets unknown keys through (free-form maps)."""

    fields: dict[str, Field] = field(default_factory=dict)
    extra: bool = False


def _kind_name(kind) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    names = {int: "an integer", float: "a number", str: "a string", bool: "true/false",
             list: "a list", dict: "an object"}  # fmt: skip
    return " or ".join(names.get(k, k.__name__) for k in kinds)


def _is_kind(v: Any, kind) -> bool:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    for k in kinds:
        if k is bool and isinstance(v, bool):
            return True
        if k is int and isinstance(v, int) and not isinstance(v, bool):
            return True
        if k is float and isinstance(v, int | float) and not isinstance(v, bool):
            return True
        if k in (str, list, dict) and isinstance(v, k):
            return True
    return False


def _show(v: Any) -> str:
    s = json.dumps(v) if not isinstance(v, float) else repr(v)
    return s if len(s) <= 60 else s[:57] + "..."


def check_value(v: Any, f: Field, where: str) -> str | None:
    """What is wrong with value `v` at `where` (a dotted field path) under `f`, or None."""
    if v is None:
        return None if f.nullable else f"{where} is null, expected {_kind_name(f.kind)}"
    if not _is_kind(v, f.kind):
        return f"{where} is {_show(v)}, expected {_kind_name(f.kind)}"
    if f.choices is not None and v not in f.choices:
        return f"{where} is {_show(v)}, expected one of {', '.join(map(_show, f.choices))}"
    if isinstance(v, int | float) and not isinstance(v, bool) and (f.lo is not None or f.hi is not None):
        lo = -math.inf if f.lo is None else f.lo
        hi = math.inf if f.hi is None else f.hi
        if not (math.isfinite(v) and lo <= v <= hi):
            rng = f"{_bound(f.lo, '-inf')}..{_bound(f.hi, 'inf')}"
            return f"{where} is {_show(v)}, outside {rng}"
    if isinstance(v, list):
        if f.lo is not None and len(v) < f.lo or f.hi is not None and len(v) > f.hi:
            return f"{where} has {len(v)} items, expected {_bound(f.lo, '0')}..{_bound(f.hi, 'any')}"
        if f.items is not None:
            for i, x in enumerate(v):
                if (err := check_value(x, f.items, f"{where}[{i}]")) is not None:
                    return err
    if isinstance(v, dict):
        if f.obj is not None:
            return check_obj(v, f.obj, where)
        if f.items is not None:
            for k, x in v.items():
                if (err := check_value(x, f.items, f"{where}.{k}")) is not None:
                    return err
    return None


def _bound(b: float | None, none: str) -> str:
    if b is None:
        return none
    return str(int(b)) if float(b).is_integer() else str(b)


def check_obj(doc: Any, spec: Obj, where: str = "") -> str | None:
    """What is wrong with object `doc` under `spec` (fields named `where.key`), or None."""
    label = where or "the file"
    if not isinstance(doc, dict):
        return f"{label} is {_kind_name(type(doc)) if doc is not None else 'null'}, expected an object"
    prefix = f"{where}." if where else ""
    if not spec.extra:
        unknown = sorted(k for k in doc if k not in spec.fields)
        if unknown:
            return f"{label} has unknown key{'s' if len(unknown) > 1 else ''} {', '.join(unknown[:5])}"
    for k, f in spec.fields.items():
        if k not in doc:
            if f.required:
                return f"{prefix}{k} is missing"
            continue
        if (err := check_value(doc[k], f, prefix + k)) is not None:
            return err
    return None


def load_json(path: Path, fix: str) -> Any:
    """The JSON document in `path` (any kind); `SchemaError` naming the file when it cannot be read
    as JSON or is larger than MAX_JSON_BYTES; `fix` says what to do."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_JSON_BYTES:
            raise SchemaError(f"{path}: {size} bytes, more than the {MAX_JSON_BYTES} a coin-cl JSON file may "
                              f"have; {fix}")  # fmt: skip
        text = path.read_bytes().decode("utf-8")
        return json.loads(text)
    except UnicodeDecodeError:
        raise SchemaError(f"{path}: not UTF-8 text; {fix}") from None
    except json.JSONDecodeError as exc:
        raise SchemaError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}); {fix}") from None
    except RecursionError:
        raise SchemaError(f"{path}: nested too deeply to be a coin-cl file; {fix}") from None


def validate(doc: Any, spec: Obj | Field, path: Path, fix: str) -> dict:
    """`doc` when it matches `spec` (an `Obj`, or a `Field` for a file that is one value such as a
    map), else `SchemaError`: "`path`: <field> <problem>; `fix`"."""
    err = check_value(doc, spec, "the file") if isinstance(spec, Field) else check_obj(doc, spec)
    if err is not None:
        raise SchemaError(f"{path}: {err}; {fix}")
    return doc


def parse(path: str | Path, spec: Obj | Field, fix: str) -> dict:
    """Read the JSON object in `path` and check it against `spec`; `SchemaError` (one line: the
    file, the field, `fix`) otherwise. A missing file raises FileNotFoundError as open() does."""
    return validate(load_json(Path(path), fix), spec, Path(path), fix)


def parse_optional(path: str | Path, spec: Obj | Field, fix: str) -> dict | None:
    """`parse`, or None when `path` does not exist."""
    path = Path(path)
    if not path.exists():
        return None
    return parse(path, spec, fix)


# ---------------------------------------------------------------------------------------------------
# the run folder's files

_COUNT = Field(int, lo=0, hi=MAX_STEPS)
_OPT_COUNT = Field(int, required=False, lo=0, hi=MAX_STEPS)
_STAGE_KEYS = ("refgs", "ted_finetune", "ted_adversarial")
_MINUTES = Field(float, nullable=True, lo=0, hi=1e7)
_OPT_MINUTES = Field(float, required=False, nullable=True, lo=0, hi=1e7)
_RATE = Field(float, nullable=True, lo=1e-9, hi=1e6)  # seconds per step, when measured

PLAN = Obj(
    {
        # "refine" (0_refine's fit) only in a plan of a run that refines its masks
        "steps": Field(dict, obj=Obj({k: _COUNT for k in _STAGE_KEYS} | {"refine": _OPT_COUNT})),
        "minutes": Field(dict, obj=Obj({k: _MINUTES for k in _STAGE_KEYS} | {"refine": _OPT_MINUTES})),
        "prior_seconds": Field(float, lo=0, hi=1e9),
        "probe_seconds_per_step": _RATE,
        "source": Field(str, choices=("probe", "explicit")),
        "key": Field(dict),  # the settings the plan was made for: compared whole, never opened
        "prior_steps": Field(int, required=False, nullable=True, lo=0, hi=MAX_STEPS),
        "prior_seconds_per_step": Field(float, required=False, nullable=True, lo=1e-9, hi=1e6),
        "disc_seconds_per_step": Field(float, required=False, nullable=True, lo=0, hi=1e6),
        "shares": Field(
            dict,
            required=False,
            nullable=True,
            obj=Obj(
                {k: Field(float, lo=0, hi=1) for k in ("prior", *_STAGE_KEYS)}
                | {"refine": Field(float, required=False, lo=0, hi=1)}
            ),
        ),
        # the fixed stages' estimated seconds and the probes' wall time (`budget.Plan`)
        "fixed_seconds": Field(dict, required=False, nullable=True, items=Field(float, lo=0, hi=1e9)),
        "probe_wall_seconds": Field(float, required=False, nullable=True, lo=0, hi=1e9),
    }
)

# run.json: the scene a run folder belongs to (`runner.check_output_folder`'s scene id, compared
# whole, never opened).
RUN = Obj({"scene": Field(dict)})

_HASH = Field(str)
STARTED = Obj({"key": _HASH, "settings": Field(dict)})
MANIFEST = Obj(
    {
        "key": _HASH,
        "settings": Field(dict),
        "outputs": Field(dict, items=Field(str)),
        "result": Field(dict),
        "seconds": Field(float, lo=0, hi=1e9),
    }
)


# A stage's own records, read back when it resumes.
# 2_refgs/stage.json: the step count the stage was planned with (read back on resume), and the
# stage's result written beside it when it ends (free-form, reported, never opened).
REFGS_STAGE = Obj({"iters": Field(int, lo=1, hi=MAX_STEPS)}, extra=True)
# 2_refgs/depth_prior.json: what made the cached depth prior D_k.
DEPTH_PRIOR = Obj({"name": Field(str), "view": Field(int, lo=0, hi=1e6), "is_disparity": Field(bool)})
# 1_inpaint/sources.json: view name -> where its initial inpaint came from.
INPAINT_SOURCES = Field(dict, items=Field(str))
# 1_inpaint/sd2.json: how Stable Diffusion 2 was used.
SD2_PLAN = Obj({"mode": Field(str), "views": Field(list, items=Field(str)), "why": Field(str, nullable=True)})
# 3_clg/views/<view>.json: one CLG view's record (its figures, reported as they are).
CLG_VIEW = Obj({"view": Field(int, lo=0, hi=1e6)}, extra=True)


def run_folder_fix(path: Path, what: str = "") -> str:
    """The advice for a bad run-folder file: delete it (`what` says what happens then) or start
    another run folder."""
    then = f" ({what})" if what else ""
    return f"delete {path}{then} or pick another --out"


# ---------------------------------------------------------------------------------------------------
# a scene's files

_FINITE = Field(float, lo=-1e12, hi=1e12)
_ROW3 = Field(list, lo=3, hi=3, items=_FINITE)
_ROW4 = Field(list, lo=4, hi=4, items=_FINITE)
VIEW = Obj(
    {
        "name": Field(str),
        "width": Field(int, lo=1, hi=1_000_000),
        "height": Field(int, lo=1, hi=1_000_000),
        "K": Field(list, lo=3, hi=3, items=_ROW3),
        "viewmat": Field(list, lo=4, hi=4, items=_ROW4),
        "image": Field(str),
        "mask": Field(str),
    }
)
_INDEX = Field(int, lo=0, hi=1e6)
SCENE = Obj(
    {
        "format": Field(str, choices=("coin-cl scene",)),
        "version": Field(int, lo=1, hi=1),
        "views": Field(list, lo=1, items=Field(dict, obj=VIEW)),
        "train_idx": Field(list, items=_INDEX),
        "test_idx": Field(list, items=_INDEX),
        "ref_view": Field(int, nullable=True, lo=0, hi=1e6),
        "near": Field(list, nullable=True, items=Field(float, lo=0, hi=1e12)),
        "far": Field(list, nullable=True, items=Field(float, lo=0, hi=1e12)),
        "points": Field(str),
        "meta": Field(dict),
    }
)
# scene_info.json: what the synthetic generator records about its scene; "masks" is the key
# coin-cl reads, the rest is description, so unknown keys are let through.
SCENE_INFO = Obj({"masks": Field(str, required=False, nullable=True)}, extra=True)


def inside(root: Path, rel: str, source: Path, key: str) -> Path:
    """`root / rel` when it stays inside `root` (symlinks resolved), else `SchemaError` naming
    `source` and its field `key`: a scene file may name only files in its own folder."""
    root_r = Path(root).resolve()
    p = Path(rel)
    target = (root_r / p).resolve()
    if p.is_absolute() or not target.is_relative_to(root_r):
        raise SchemaError(
            f"{source}: {key} is {rel!r}, which leads outside the scene folder {root}; a scene may "
            "name only files inside its folder (use a relative path such as images/x.png)"
        )
    return Path(root) / p
