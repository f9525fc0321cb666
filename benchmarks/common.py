"""What every benchmark prints in its header: the CPU model and the commit. The benchmarks run as
scripts (`python benchmarks/NAME.py`), so this folder is on sys.path and they `from common import ...`."""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), else what `platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_commit() -> str:
    """The repository's short HEAD commit, "+changes" appended when tracked files differ from it
    (a copy of a working tree, say), or "uncommitted" outside a git checkout."""
    try:
        head = subprocess.check_output(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], stderr=subprocess.DEVNULL, text=True
        ).strip()
    except (subprocess.CalledProcessError, FileNotFoundError):
        return "uncommitted"
    clean = subprocess.run(["git", "-C", str(ROOT), "diff", "--quiet", "HEAD"], capture_output=True)
    return head if clean.returncode == 0 else f"{head}+changes"


def default_data() -> Path:
    """The shared SPIn-NeRF scene: `$COIN_DATA/spinnerf_scene1`, else `../shared/data/spinnerf_scene1`."""
    env = os.environ.get("COIN_DATA")
    return (Path(env) if env else ROOT.parent / "shared" / "data") / "spinnerf_scene1"


def write_result(out: Path, result: dict, rows: dict) -> None:
    """Keep the rows and the summary in `out/result.json`, then print the summary as the last line."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "result.json").write_text(json.dumps({"result": result, "rows": rows}, indent=1, default=str))
    print(json.dumps(result))


def other_references(scene, chosen: int, n: int, seed: int) -> list[int]:
    """n - 1 training views other than `chosen` whose masks are not empty, drawn without
    replacement by `np.random.default_rng(seed)` (the reference-robustness rows)."""
    import numpy as np

    cands = [i for i in scene.train_idx if i != chosen and np.asarray(scene.masks[i]).any()]
    rng = np.random.default_rng(seed)
    return [int(i) for i in rng.choice(cands, size=min(n - 1, len(cands)), replace=False)]


def mean_std(rows: dict, key: str) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof=1) of rows[*][key]."""
    import numpy as np

    v = np.array([r[key] for r in rows.values()], float)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else float("nan")


def median_time(fn, runs: int) -> float:
    """Median wall time of `runs` calls of fn() after one warm-up call (compiles, caches)."""
    fn()
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def vgg_pd_cell(v, digits: int = 3) -> str:
    """A VGG-PD table cell (`coin_cl.metrics.vgg_pd`): the value, or "n/a (weights absent)" when the
    run had no VGG16 weights; `vgg_pd_note` says what to install."""
    if v is None:
        return "n/a (weights absent)"
    return "nan" if v != v else f"{v:.{digits}f}"


def vgg_pd_note() -> str | None:
    """The line to print under a table with VGG-PD columns when the weights are absent here (what to
    install), else None."""
    from coin_cl.nets import vgg16_h5_from_env

    return vgg16_h5_from_env()[1]
