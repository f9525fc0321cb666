"""The page a person opens after a run: `OUT/report.html`, one self-contained file (no server, works
offline from the file browser) showing what ran (stages with minutes, the plan, the device), the
metrics when ground truth exists, each test view as capture | result | truth with its observed /
unseen split and depth, the orbit GIF, and the result's Gaussians in an interactive 3D view.

Images are referenced by relative path inside the run folder, not embedded: the run already holds
them (renders, grids, orbit.gif), a 90-degree room's page would otherwise grow by megabytes of
duplicated PNGs, and a link opens the picture at full size. The pictures the run does not hold as
files (the capture with the object, the truth, the split, a colour-mapped depth) are written once
to `OUT/report/`. The Gaussians are embedded (base64), at most `MAX_SPLATS` of them, so that the
3D view works from file:// where a page may not fetch files; `coin_cl/report_viewer.js` draws them.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

REPORT_NAME = "report.html"
# Pictures the page shows that the run does not already hold as files.
ASSET_DIR = "report"
# Gaussians embedded in the page (the most visible: opacity x ellipsoid volume): 40 bytes each, so
# 50k add about 2.7 MB of base64, which a browser parses in well under a second.
MAX_SPLATS = 50_000
# Views shown when the scene has no ground-truth test views (training views: capture | result).
MAX_TRAIN_VIEWS = 4
# Width in CSS pixels of the 3D view's canvas (its height follows the captured camera's aspect).
VIEWER_WIDTH = 640
SH_C0 = 0.28209479177387814
PLY_FIELDS = ("x", "y", "z", "opacity", *(f"scale_{i}" for i in range(3)), *(f"rot_{i}" for i in range(4)),
              *(f"f_dc_{i}" for i in range(3)))  # fmt: skip


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); rerun the stage that writes it") from exc


def splat_payload(ply: Path, cap: int = MAX_SPLATS) -> dict[str, Any]:
    """A 3DGS PLY (fields read by name, so any layout with the standard fields) -> the viewer's
    data: the `cap` most visible Gaussians (opacity x volume), each as float32 x y z and its
    world covariance (c00 c01 c02 c11 c12 c22), and uint8 RGBA (degree-0 SH colour, opacity).
    Non-finite Gaussians are dropped. Returns {"n", "n_total", "geometry", "colors" (base64),
    "means" (the kept centres, (n, 3) float64, for the cameras' focus)}."""
    from plyfile import PlyData, PlyParseError

    try:
        v = PlyData.read(str(ply))["vertex"].data
    except (PlyParseError, ValueError, KeyError) as exc:
        raise ValueError(f"{ply} is not a readable PLY with a vertex element ({exc})") from exc
    missing = [f for f in PLY_FIELDS if f not in v.dtype.names]
    if missing:
        raise ValueError(f"{ply} lacks the 3DGS PLY fields {missing}; export it with Splats.to_ply")

    def col(*names: str) -> np.ndarray:
        return np.stack([np.asarray(v[k], np.float64) for k in names], axis=1)

    means, q = col("x", "y", "z"), col("rot_0", "rot_1", "rot_2", "rot_3")
    log_s, dc = col("scale_0", "scale_1", "scale_2"), col("f_dc_0", "f_dc_1", "f_dc_2")
    logit = np.asarray(v["opacity"], np.float64)
    ok = np.isfinite(np.concatenate([means, q, log_s, dc, logit[:, None]], axis=1)).all(axis=1)
    qn = np.linalg.norm(q, axis=1)
    ok &= qn > 0
    with np.errstate(over="ignore"):
        opacity = 1.0 / (1.0 + np.exp(-logit))
    log_s = np.clip(log_s, -30.0, 10.0)
    score = np.where(ok, opacity * np.exp(log_s.sum(axis=1)), -1.0)
    keep = np.argsort(-score, kind="stable")[: min(cap, int(ok.sum()))]
    keep.sort()  # the file's order, for a stable page
    w, x, y, z = (q[keep] / qn[keep, None]).T
    R = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], axis=1)  # fmt: skip
    M = R * np.exp(log_s[keep])[:, None, :]
    cov = M @ M.transpose(0, 2, 1)
    geo = np.concatenate([means[keep], cov[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]], axis=1)
    rgba = np.concatenate([np.clip(SH_C0 * dc[keep] + 0.5, 0, 1), opacity[keep, None]], axis=1)
    return {
        "n": len(keep),
        "n_total": len(means),
        "geometry": base64.b64encode(geo.astype("<f4").tobytes()).decode(),
        "colors": base64.b64encode(np.round(rgba * 255).astype(np.uint8).tobytes()).decode(),
        "means": means[keep],
    }


def _cameras(scene, means: np.ndarray) -> tuple[list[dict], int, list[float]]:
    """The viewer's cameras (test views first, then training views), the starting one and the
    world's up direction. Each camera's focus (the orbit's centre) is the median depth of the
    Gaussians in front of it."""
    views = [(i, "test") for i in scene.test_idx] + [(i, "train") for i in scene.train_idx]
    cams = []
    for i, kind in views:
        c = scene.cameras[i]
        z = means @ c.viewmat[2, :3] + c.viewmat[2, 3] if len(means) else np.zeros(0)
        z = z[z > 0]
        cams.append({"label": f"{kind}: {c.name}", "viewmat": c.viewmat.tolist(), "K": c.K.tolist(),
                     "width": c.width, "height": c.height,
                     "focus": float(np.median(z)) if len(z) else 1.0})  # fmt: skip
    up = -np.mean([scene.cameras[i].viewmat[1, :3] for i, _ in views], axis=0)
    up = up / max(np.linalg.norm(up), 1e-12)
    return cams, 0, up.tolist()


def _esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(v: Any) -> str:
    from coin_cl.evaluation import fmt_metric

    return fmt_metric(v) if isinstance(v, int | float) or v is None else _esc(v)


def _size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's or GIF's header, None for anything else."""
    with open(path, "rb") as f:
        head = f.read(24)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) == 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:4] == b"GIF8" and len(head) >= 10:
        return int.from_bytes(head[6:8], "little"), int.from_bytes(head[8:10], "little")
    return None


def _img(run: Path, rel: str, caption: str) -> str:
    """A picture of the run (`rel` to it, percent-encoded in the link: a view may be named
    "a#1.png") that opens at full size on click. Its width and height are in the tag, so that
    the page does not move while the pictures load."""
    wh = _size(run / rel)
    dims = f' width="{wh[0]}" height="{wh[1]}"' if wh else ""
    url = _esc(quote(rel))
    return (f'<figure><a href="{url}" target="_blank"><img src="{url}"{dims} '
            f'alt="{_esc(caption)}"></a><figcaption>{_esc(caption)}</figcaption></figure>')  # fmt: skip


def _stages_html(logdoc: dict) -> str:
    from coin_cl.pipeline.report import minutes

    rows = []
    for name, rec in logdoc.get("stages", {}).items():
        notes = "<br>".join(_esc(n) for n in rec.get("notes", []))
        rows.append(f"<tr><td>{_esc(name)}</td><td class=num>{_esc(minutes(rec))}</td>"
                    f"<td>{_esc(rec.get('status', '?'))}</td><td class=notes>{notes}</td></tr>")  # fmt: skip
    total = sum(rec.get("seconds", 0.0) for rec in logdoc.get("stages", {}).values())
    rows.append(f"<tr class=total><td>total</td><td class=num>{total / 60:.1f}</td>"
                "<td colspan=2>this run; bracketed minutes are earlier runs'</td></tr>")  # fmt: skip
    return ("<table><tr><th>stage</th><th>minutes</th><th>status</th><th>notes</th></tr>"
            + "".join(rows) + "</table>")  # fmt: skip


def _plan_html(plan: dict | None, logdoc: dict) -> str:
    from coin_cl.pipeline.budget import prior_text

    items = []
    if plan:
        steps = ", ".join(f"{_esc(k)} {_esc(v)}" for k, v in plan.get("steps", {}).items())
        items.append(f"<li>plan ({_esc(plan.get('source', '?'))}): {steps} steps; "
                     f"{_esc(prior_text(plan))} (plan.json)</li>")  # fmt: skip
    device = logdoc.get("device")
    if device is None:
        asked = (plan or {}).get("key", {}).get("device")
        device = f"not recorded in log.json (asked for: {asked or 'the default device'})"
    items.append(f"<li>device: {_esc(device)}</li>")
    return "<ul>" + "".join(items) + "</ul>"


def _metrics_html(doc: dict) -> str:
    """Every column metrics.json has (per view and the mean), in its order."""
    mean = doc.get("mean", {})
    keys = [k for k, v in mean.items() if isinstance(v, int | float) or v is None]
    keys = [k for k in keys if any(d.get(k) is not None for d in [mean, *doc.get("per_view", {}).values()])]
    head = "".join(f"<th>{_esc(k)}</th>" for k in keys)
    rows = [f"<tr><td>{_esc(name)}</td>" + "".join(f"<td class=num>{_num(d.get(k))}</td>" for k in keys)
            + "</tr>" for name, d in doc.get("per_view", {}).items()]  # fmt: skip
    rows.append("<tr class=total><td>mean</td>"
                + "".join(f"<td class=num>{_num(mean.get(k))}</td>" for k in keys) + "</tr>")  # fmt: skip
    notes = [doc.get(k) for k in ("notes", "lpips", "fid") if isinstance(doc.get(k), str)]
    notes = [n for n in notes if n != "available"]
    return (f"<div class=scroll><table><tr><th>view</th>{head}</tr>{''.join(rows)}</table></div>"
            + "".join(f"<p class=note>{_esc(n)}</p>" for n in notes))  # fmt: skip


def _views_html(run: Path, scene, ev: Path, assets: Path) -> str:
    from coin_cl.evaluation import split_tile
    from coin_cl.render_utils import colorize_depth
    from coin_cl.scene.io import to_uint8, write_png
    from coin_cl.scene.masks import read_mask

    def rel(p: Path) -> str:
        return p.relative_to(run).as_posix()

    def asset(name: str, img: np.ndarray) -> str:
        write_png(assets / name, img if img.dtype == np.uint8 else to_uint8(np.clip(img, 0, 1)))
        return rel(assets / name)

    test = bool(scene.test_idx)
    idx = list(scene.test_idx) if test else list(scene.train_idx)[:MAX_TRAIN_VIEWS]
    blocks = []
    for i in idx:
        cam, img, m = scene.cameras[i], scene.images[i], np.asarray(scene.masks[i], bool)
        stem = Path(cam.name).stem
        figs = []
        present = scene.extras.get("object_present", {}).get(i)
        if present is not None:
            figs.append(_img(run, asset(f"{stem}_capture.png", present), "capture (object present)"))
        elif test:  # a real capture has no picture of a test view with the object: show its mask
            tint = np.where(m[..., None], 0.5 * img + 0.5 * np.array([1.0, 0.1, 0.1]), img)
            figs.append(_img(run, asset(f"{stem}_mask.png", tint), "the object's mask (red) on the truth"))
        else:
            figs.append(_img(run, asset(f"{stem}_capture.png", img), "capture"))
        render = ev / "renders" / f"{stem}.png"
        if render.is_file():
            figs.append(_img(run, rel(render), "result (render of the final Gaussians)"))
        if test:
            figs.append(_img(run, asset(f"{stem}_truth.png", img), "truth (object absent)"))
        extra = []
        obs_p = run / "0_refine" / "observed" / f"{stem}.png"
        if obs_p.is_file() and m.any():  # unseen = the mask less the observed part (as evaluate_folder)
            obs = read_mask(obs_p, m.shape) & m
            tile = split_tile(obs, m & ~obs)
            extra.append(_img(run, asset(f"{stem}_split.png", tile),
                              "mask split: observed by other views (green) | unseen (red)"))  # fmt: skip
        dgrid, dnpy = ev / "metrics" / "grids" / f"depth_{stem}.png", ev / "depths" / f"{stem}.npy"
        if dgrid.is_file():
            extra.append(_img(run, rel(dgrid), "depth: render | reference | ghost pixels (red)"))
        elif dnpy.is_file():
            d = np.load(dnpy, allow_pickle=False)
            ok = np.isfinite(d)
            cm = colorize_depth(np.where(ok, d, 0.0), ok.astype(np.float32))
            extra.append(_img(run, asset(f"{stem}_depth.png", cm), "rendered depth (near = warm)"))
        grid = ev / "metrics" / "grids" / f"{stem}.png"
        if grid.is_file():
            extra.append(_img(run, rel(grid), "input | mask | result | truth | error"))
        kind = "test view (ground truth)" if test else "training view"
        rows = f"<div class=row>{''.join(figs)}</div><div class=row>{''.join(extra)}</div>"
        blocks.append(f"<section class=view><h3>{_esc(cam.name)} <small>{kind}</small></h3>{rows}</section>")
    if not idx:
        return "<p>The scene has no views to show.</p>"
    return "".join(blocks)


def _viewer_html(ply: Path, scene) -> str:
    if not ply.is_file():
        return "<p>No Gaussians: eval/point_cloud.ply is missing.</p>"
    data = splat_payload(ply)
    cams, start, up = _cameras(scene, data.pop("means"))
    data.update(cameras=cams, start=start, up=up)
    c = cams[start] if cams else {"width": 4, "height": 3}
    h = round(VIEWER_WIDTH * c["height"] / c["width"])
    if data["n"] < data["n_total"]:
        cap = (f"{data['n']} of the {data['n_total']} Gaussians in eval/point_cloud.ply, the most "
               f"visible (opacity x size): the page embeds at most {MAX_SPLATS}")  # fmt: skip
    else:
        cap = f"all {data['n']} Gaussians of eval/point_cloud.ply (the page embeds at most {MAX_SPLATS})"
    js = (Path(__file__).with_name("report_viewer.js")).read_text(encoding="utf-8")
    payload = json.dumps(data).replace("<", "\\u003c")  # no "</script>" or "<!--" in the script's data
    return (f"<p class=note>{_esc(cap)}; colours without view dependence (degree-0 SH). Drag to orbit, "
            "shift- or right-drag to pan, wheel to zoom.</p>"
            f'<div><label>camera <select id="viewer-camera"></select></label> '
            f'<button id="viewer-reset">reset</button></div>'
            f'<canvas id="viewer" width="{VIEWER_WIDTH}" height="{h}"></canvas>'
            f'<p id="viewer-status" class=note data-nonblank="">the 3D view needs JavaScript and WebGL2</p>'
            f'<script type="application/json" id="splat-data">{payload}</script>'
            f"<script>{js}</script>")  # fmt: skip


CSS = """
body{font:14px/1.4 system-ui,sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{font-size:1.5em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ddd;padding:.2em .5em;text-align:left}
td.num{text-align:right;font-variant-numeric:tabular-nums}tr.total td{font-weight:600}
td.notes{font-size:.85em;color:#555;max-width:50em}.note{color:#555;font-size:.9em}.scroll{overflow-x:auto}
.row{display:flex;flex-wrap:wrap;gap:.8em;align-items:flex-start}
figure{margin:0}figure img{display:block;width:320px;height:auto;image-rendering:pixelated;
border:1px solid #ccc;background:#eee}figcaption{font-size:.85em;color:#444;max-width:320px}
.row+.row figure img{width:auto;max-width:640px;height:160px}
canvas#viewer{border:1px solid #999;cursor:grab;touch-action:none;display:block;margin:.5em 0}
#page-errors{color:#b00}
"""

# Errors on the page (a script that failed, an image that did not load) are written into the
# page itself, so that a person sees them and the page's test can read them from the DOM (with
# where each picture and the 3D view ended up, once the page has loaded).
ERROR_HOOK = """<script>
(function(){const box=document.getElementById('page-errors');let n=0;
function add(msg){n++;box.dataset.count=String(n);const li=document.createElement('li');
li.textContent=msg;box.appendChild(li);}
window.addEventListener('error',function(e){add(e.target&&e.target.src?'could not load '+e.target.src:
'script error: '+e.message);},true);
const ce=console.error;
console.error=function(){add(Array.from(arguments).join(' '));ce.apply(console,arguments);};
window.addEventListener('load',function(){let bad=0;for(const im of document.images){
if(!im.complete||im.naturalWidth===0)bad++;}for(const el of document.querySelectorAll('img,canvas')){
const r=el.getBoundingClientRect();el.dataset.rect=[r.left+el.clientLeft+scrollX,r.top+el.clientTop+scrollY,
el.clientWidth,el.clientHeight].map(Math.round).join(',');}document.body.dataset.brokenImages=String(bad);
document.body.dataset.images=String(document.images.length);});})();
</script>"""


def write_report(run_dir: str | Path) -> Path:
    """Write `run_dir/report.html` (and the pictures it needs under `run_dir/report/`) for a
    `coin-cl run` folder; returns the page's path. Needs the scene (0_scene) and, for the result,
    the eval stage's outputs; what the run lacks (metrics without ground truth, the split without
    stage 0_refine) is left out of the page."""
    from coin_cl.atomic import write_text
    from coin_cl.scene import load_scene

    run = Path(run_dir)
    scene_dir = run / "0_scene" / "scene"
    if not (run / "log.json").is_file() or not scene_dir.is_dir():
        raise FileNotFoundError(f"{run} is not a coin-cl run folder (no log.json or 0_scene/scene); "
                                "give the --out folder of a coin-cl run")  # fmt: skip
    logdoc = _read_json(run / "log.json")
    plan = _read_json(run / "plan.json") if (run / "plan.json").is_file() else None
    scene = load_scene(scene_dir)
    ev = run / "eval"
    parts = [f"<h1>coin-cl run: {_esc(run.resolve().name)}</h1>",
             f"<ul id=page-errors class=note data-count=0></ul>{ERROR_HOOK}"]  # fmt: skip
    mpath = ev / "metrics" / "metrics.json"
    if mpath.is_file():
        parts += ["<h2>Metrics against the ground truth (object absent)</h2>",
                  _metrics_html(_read_json(mpath))]  # fmt: skip
    else:
        parts.append("<p class=note>No metrics: the scene has no ground-truth test views with masks.</p>")
    title = "Test views: capture | result | truth" if scene.test_idx else "Views: capture | result"
    parts += [f"<h2>{title}</h2><p class=note>Click a picture for full size.</p>",
              _views_html(run, scene, ev, run / ASSET_DIR)]  # fmt: skip
    parts.append("<h2>3D view of the result</h2>" + _viewer_html(ev / "point_cloud.ply", scene))
    if (ev / "orbit.gif").is_file():
        parts += ["<h2>Orbit</h2>", _img(run, "eval/orbit.gif", "orbit of the result (eval/orbit.gif)")]
    parts += ["<h2>What ran</h2>", _stages_html(logdoc), _plan_html(plan, logdoc)]
    files = [("run log", "log.json"), ("plan", "plan.json"), ("metrics", "eval/metrics/metrics.md"),
             ("Gaussians (3DGS PLY)", "eval/point_cloud.ply"), ("renders", "eval/renders")]  # fmt: skip
    files = [(w, p) for w, p in files if (run / p).exists()]
    links = "".join(f'<li>{w}: <a href="{_esc(quote(p))}">{_esc(p)}</a></li>' for w, p in files)
    parts.append(f"<h2>Files</h2><ul>{links}</ul>")
    page = ("<!DOCTYPE html><html lang=en><head><meta charset=utf-8>"
            f"<title>coin-cl run {_esc(run.resolve().name)}</title><style>{CSS}</style></head><body>"
            + "\n".join(parts) + "</body></html>\n")  # fmt: skip
    out = run / REPORT_NAME
    write_text(out, page)
    return out
