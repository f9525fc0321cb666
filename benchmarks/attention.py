"""Benchmark: Ref-GS's anchor attention (`coin_cl.gs.anchor_attention`), fused against written out.

Per size (in-mask x ring anchors; the caps are 2000 x 2000): forward + backward of the module on
random features (median of `--repeats`, torch's threads as set), for `AnchorAttention.attend` (torch's
fused attention) and `attend_written_out` (the [heads, I, S] weights held), and each one's largest
error against the written-out attention in float64 (output and feature gradients).

    python benchmarks/attention.py [--sizes 500x1000 1029x2000 2000x2000] [--repeats 9]

Prints a table (with the CPU model and commit); the LAST line is one JSON object.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see coin_cl/__init__.py

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import cpu_model, git_commit  # noqa: E402

from coin_cl.gs.anchor_attention import AnchorAttention, attend_written_out  # noqa: E402

ANCHORS = 12_509  # cup_plain's Ref-GS model at budget 10


def _run(att, fn, feats, n_in, n_side, grad):
    f = feats.detach().clone().requires_grad_(grad)
    out = fn(att, f[:n_in], f[n_in : n_in + n_side])
    if grad:
        out.sum().backward()
    return out.detach(), (f.grad if grad else None)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", nargs="+", default=["500x1000", "1029x2000", "2000x2000"])
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args(argv)
    fused = lambda a, i, s: a.attend(i, s)  # noqa: E731
    ways = {"fused": fused, "written out": attend_written_out}
    print(f"anchor attention, 4 heads, 32 features; {cpu_model()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads, commit {git_commit()}")  # fmt: skip
    print("| in x ring | way | fwd+bwd ms | max error, output | max error, feature gradient |")
    print("|---|---|---|---|---|")
    result = {}
    for size in args.sizes:
        n_in, n_side = (int(x) for x in size.split("x"))
        torch.manual_seed(0)
        feats = torch.randn(ANCHORS, 32, dtype=torch.float64)
        ref64 = AnchorAttention(32).double()
        want, want_g = _run(ref64, attend_written_out, feats, n_in, n_side, True)
        att = AnchorAttention(32)
        for name, fn in ways.items():
            got, got_g = _run(att, fn, feats.float(), n_in, n_side, True)
            err, err_g = (
                float((got.double() - want).abs().max()),
                float((got_g.double() - want_g).abs().max()),
            )
            times = []
            for _ in range(args.repeats):
                t = time.perf_counter()
                _run(att, fn, feats.float(), n_in, n_side, True)
                times.append(time.perf_counter() - t)
            ms = 1000 * sorted(times)[len(times) // 2]
            print(f"| {size} | {name} | {ms:.1f} | {err:.1e} | {err_g:.1e} |", flush=True)
            result[f"{size}_{name.replace(' ', '_')}"] = {"ms": ms, "err": err, "err_grad": err_g}
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
