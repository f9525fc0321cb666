"""What a finished CoIn run prints: the stages (ran or skipped and why, minutes), the
plan each GS stage was given, the metrics as a table when ground truth exists, and the files a
person opens next."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from coin_cl.pipeline.coin import CoInResult

METRIC_COLUMNS = (("psnr", "PSNR"), ("ssim", "SSIM"), ("m_psnr", "m-PSNR"), ("m_ssim", "m-SSIM"),
                  ("hf_ratio", "HF ratio"), ("bbox_gmsd", "bbox GMSD"))  # fmt: skip


def minutes(rec: dict[str, Any]) -> str:
    """A stage record's minutes as the tables show them: "1.5", "(1.5)" when it ran earlier, "-"."""
    if "seconds" in rec:
        return f"{rec['seconds'] / 60:.1f}"
    if rec.get("seconds_when_run") is not None:
        return f"({rec['seconds_when_run'] / 60:.1f})"
    return "-"


def stage_table(stages: dict[str, dict]) -> list[str]:
    """Rows 'stage | status | minutes' (minutes in brackets: when the stage ran earlier)."""
    w = max([len(n) for n in stages] + [5])
    lines = [f"  {'stage':<{w}}  {'minutes':>7}  status", f"  {'-' * w}  {'-' * 7}  {'-' * 6}"]
    for name, rec in stages.items():
        lines.append(f"  {name:<{w}}  {minutes(rec):>7}  {rec.get('status', '?')}")
    total = sum(rec.get("seconds", 0.0) for rec in stages.values())
    lines.append(f"  {'total':<{w}}  {total / 60:>7.1f}  (this run; bracketed minutes are earlier runs')")
    return lines


def metric_table(metrics: dict[str, Any]) -> list[str]:
    """One row of the mean metrics over the ground-truth test views."""
    cols = [(k, h) for k, h in METRIC_COLUMNS if isinstance(metrics.get(k), int | float)]
    head = " | ".join(h for _, h in cols)
    vals = " | ".join(f"{metrics[k]:.2f}" if "psnr" in k else f"{metrics[k]:.3f}" for k, _ in cols)
    return [f"  | {head} |", "  |" + "|".join("---" for _ in cols) + "|", f"  | {vals} |"]


def run_report(res: CoInResult) -> str:
    """The text `coin-cl run` prints at the end, from a `CoInResult`."""
    out = Path(res.out)
    lines = [f"CoIn run in {out}/", ""]
    lines += stage_table(res.stages)
    plan_path = out / "plan.json"
    if plan_path.is_file():
        from dataclasses import asdict

        from coin_cl.pipeline.budget import prior_text, read_plan
        from coin_cl.pipeline.schedule import run_steps

        plan = asdict(read_plan(plan_path))
        # the counts as each GS stage was re-planned when reached (plan.json holds the probe's)
        given = ", ".join(f"{k} {n}" for k, n in run_steps(out).items())
        probe = plan.get("probe_seconds_per_step")
        probe = "" if probe is None else f", probe {probe:.3f} s/step"
        lines += ["", f"  plan ({plan['source']}{probe}): {given} steps; {prior_text(plan)} (plan.json)"]
    if res.metrics:
        lines += ["", "Metrics, mean over the ground-truth test views (object absent):"]
        lines += metric_table(res.metrics)
        at_capture = res.stages.get("eval", {}).get("result", {}).get("metrics_capture")
        if isinstance(at_capture, dict):
            lines += ["", "The same views rendered at the photos' own size (eval/capture):"]
            lines += metric_table(at_capture)
    lines += ["", "Open next:"]
    ev = out / "eval"
    for what, path in (
        ("report (open this)", out / "report.html"),
        ("metrics", ev / "metrics" / "metrics.md"),
        ("render | truth grids", ev / "metrics" / "grids"),
        ("renders", ev / "renders"),
        ("renders, photos' size", ev / "capture" / "renders"),
        ("orbit", ev / "orbit.gif"),
        ("Gaussians (PLY)", ev / "point_cloud.ply"),
        ("run log", out / "log.json"),
    ):
        if path.exists():
            lines.append(f"  {what:<22} {path}")
    return "\n".join(lines)
