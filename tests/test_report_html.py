"""The run's page (`coin_cl.report_html`): built for a small run folder laid out as the runner writes
one, its links, the embedded Gaussians, and the page in a real headless Chromium (no console error,
every image loads, the WebGL view draws the scene as the test camera sees it)."""

import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import cv2
import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from coin_cl.cli import main
from coin_cl.report_html import MAX_SPLATS, MAX_TRAIN_VIEWS, splat_payload, write_report

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# Headless, software WebGL (SwiftShader), no network, one fresh profile per call; the same window
# for the DOM dump and the screenshot, so that the layout (the canvas's place) is the same.
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--no-first-run",
                  "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--force-device-scale-factor=1",
                  "--hide-scrollbars", "--window-size=1280,2600", "--virtual-time-budget=8000"]  # fmt: skip
# An extra metrics column (as a new metric would add): the page shows whatever metrics.json has.
EXTRA_METRIC = "vgg_dist"


def _splats_seen_by(cam, image: np.ndarray, depth: np.ndarray):
    """One Gaussian per pixel of `image` (H, W, 3) at its camera z `depth`, a pixel wide: seen from
    `cam` they draw the image again."""
    from coin_cl.gs.sh import rgb_to_sh
    from coin_cl.gs.splats import Splats

    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W] + 0.5
    K = cam.K
    xc = np.stack([(u - K[0, 2]) / K[0, 0] * depth, (v - K[1, 2]) / K[1, 1] * depth, depth], -1)
    xc = xc.reshape(-1, 3)
    c2w = cam.camtoworld
    world = xc @ c2w[:3, :3].T + c2w[:3, 3]
    n = len(world)
    size = (depth.reshape(-1) / K[0, 0]) * 0.7
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return Splats(means=t(world), quats=t(np.tile([1.0, 0, 0, 0], (n, 1))),
                  log_scales=t(np.log(np.repeat(size[:, None], 3, 1))), opacity_logits=t(np.full(n, 5.0)),
                  sh_dc=rgb_to_sh(t(image.reshape(-1, 3))), sh_rest=torch.zeros(n, 0, 3))  # fmt: skip


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A run folder as `coin-cl run` leaves it: 0_scene/scene, 0_refine's split, eval's renders,
    depths, orbit, PLY and metrics (`evaluate_folder`), log.json and plan.json. Its 'result' is
    the truth blurred; its Gaussians redraw the test view's truth."""
    from coin_cl.evaluation import evaluate_folder
    from coin_cl.render_utils import write_gif
    from coin_cl.scene import load_scene, save_scene, write_synthetic
    from coin_cl.scene.io import to_uint8, write_png

    root = tmp_path_factory.mktemp("report")
    scene = load_scene(write_synthetic(root / "room", n_views=6, width=48, height=32, seed=1))
    run = root / "run"
    save_scene(scene, run / "0_scene" / "scene")
    scene = load_scene(run / "0_scene" / "scene")
    ev = run / "eval"
    for i, cam in enumerate(scene.cameras):
        stem = Path(cam.name).stem
        write_png(ev / "renders" / f"{stem}.png", to_uint8(cv2.GaussianBlur(scene.images[i], (5, 5), 1.5)))
        obs = np.asarray(scene.masks[i], bool).copy()
        obs[: obs.shape[0] // 2] = False  # the lower half of the mask "observed by other views"
        write_png(run / "0_refine" / "observed" / f"{stem}.png", to_uint8(obs.astype(np.float32)))
    t = scene.test_idx[0]
    depth = scene.extras["depth"][t]
    (ev / "depths").mkdir(parents=True)
    np.save(ev / "depths" / f"{Path(scene.cameras[t].name).stem}.npy", depth.astype(np.float32))
    write_gif(ev / "orbit.gif", [to_uint8(scene.images[i]) for i in scene.train_idx[:3]])
    _splats_seen_by(scene.cameras[t], scene.images[t], depth).to_ply(ev / "point_cloud.ply")
    evaluate_folder(ev / "renders", run / "0_scene" / "scene", ev / "metrics", split_dir=run / "0_refine",
                    depth_dir=ev / "depths")  # fmt: skip
    mpath = ev / "metrics" / "metrics.json"
    doc = json.loads(mpath.read_text())
    for d in [doc["mean"], *doc["per_view"].values()]:
        d[EXTRA_METRIC] = 0.125
    mpath.write_text(json.dumps(doc))
    stages = {"0_scene": {"status": "ran", "seconds": 1.5, "notes": [], "result": {}},
              "2_refgs": {"status": "skipped: up to date", "seconds_when_run": 90.0,
                          "notes": ["Ref-GS: 9 steps"]},
              "eval": {"status": "ran", "seconds": 4.0, "notes": [],
                       "result": {"final_stage": "2_refgs"}}}  # fmt: skip
    (run / "log.json").write_text(json.dumps({"stages": stages}))
    (run / "plan.json").write_text(json.dumps({"source": "explicit", "steps": {"refgs": 9},
                                               "prior_seconds": 3, "key": {"device": None}}))  # fmt: skip
    write_report(run)
    return run, scene


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.links += [v for k, v in attrs if k in ("src", "href") and v]

    def handle_data(self, data):
        self.text.append(data)


def _links(page: Path) -> _Links:
    p = _Links()
    p.feed(page.read_text())
    return p


def check_links(run: Path) -> list[str]:
    """Every src/href of RUN/report.html is a relative path to a file or folder inside RUN."""
    links = [unquote(li) for li in _links(run / "report.html").links]
    for link in links:
        assert "://" not in link and not link.startswith("/"), f"not a relative link: {link}"
        target = (run / link).resolve()
        assert target.is_relative_to(run.resolve()) and target.exists(), f"{link} does not exist in {run}"
    return links


def test_the_page_links_only_files_of_the_run(run):
    folder, scene = run
    links = check_links(folder)
    stem = Path(scene.cameras[scene.test_idx[0]].name).stem
    for want in (f"eval/renders/{stem}.png", f"report/{stem}_capture.png", f"report/{stem}_truth.png",
                 f"report/{stem}_split.png", f"eval/metrics/grids/depth_{stem}.png",
                 f"eval/metrics/grids/{stem}.png", "eval/orbit.gif", "eval/point_cloud.ply"):  # fmt: skip
        assert want in links, want
    # the capture with the object is the scene's object-present picture, the truth its test image
    cap = cv2.imread(str(folder / f"report/{stem}_capture.png"))[..., ::-1] / 255.0
    present = scene.extras["object_present"][scene.test_idx[0]]
    assert np.abs(cap - present).max() < 1 / 255 + 1e-6
    assert np.abs(cap - scene.images[scene.test_idx[0]]).max() > 0.2  # the object is in it


def test_the_page_shows_every_metrics_column_and_what_ran(run):
    folder, _ = run
    text = " ".join(_links(folder / "report.html").text)
    doc = json.loads((folder / "eval" / "metrics" / "metrics.json").read_text())
    shown = [k for k, v in doc["mean"].items() if v is not None]
    assert EXTRA_METRIC in shown and "m_psnr_unseen" in shown
    for k in shown:
        assert k in text, k
    assert "0.1250" in text  # the extra column's value, as metrics.md writes numbers
    assert "(1.5)" in text and "skipped: up to date" in text  # the earlier run's minutes, bracketed
    assert "refgs 9 steps" in text and "device: not recorded in log.json" in text
    assert f"the page embeds at most {MAX_SPLATS}" in text


def test_splats_are_read_by_field_name_and_capped(tmp_path):
    """Fields in another order with padding fields (a padded-SH layout) read alike; the cap keeps
    the most visible (opacity x volume); a Gaussian with NaN is left out; covariance = R S^2 R^T."""
    n = 6
    names = ["rot_0", "rot_1", "rot_2", "rot_3", "f_rest_0", "opacity", "x", "y", "z", "scale_0", "scale_1",
             "scale_2", "f_dc_0", "f_dc_1", "f_dc_2", "pad"]  # fmt: skip
    arr = np.zeros(n, dtype=[(k, "<f4") for k in names])
    arr["rot_0"] = 1.0
    arr["opacity"] = [0.0, 3.0, 3.0, -3.0, 3.0, 3.0]
    for k in ("scale_0", "scale_1", "scale_2"):
        arr[k] = np.log([0.1, 0.1, 0.5, 0.5, 0.01, 0.2])
    arr["x"] = np.arange(n)
    arr["x"][5] = np.nan
    # Gaussian 2 turned 90 degrees about z, with scales (0.5, 0.1, 0.1): its long axis along y
    arr["rot_0"][2] = arr["rot_3"][2] = np.sqrt(0.5)
    arr["scale_1"][2] = arr["scale_2"][2] = np.log(0.1)
    ply = tmp_path / "g.ply"
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(ply))
    d = splat_payload(ply, cap=3)
    assert d["n_total"] == 6 and d["n"] == 3
    import base64

    geo = np.frombuffer(base64.b64decode(d["geometry"]), "<f4").reshape(-1, 9)
    assert sorted(geo[:, 0].tolist()) == [1.0, 2.0, 3.0]  # 2 and 3 (big), then 1; not 5 (NaN)
    g2 = geo[geo[:, 0] == 2.0][0]
    assert np.allclose(g2[3:], [0.01, 0.0, 0.0, 0.25, 0.0, 0.01], atol=1e-6)  # c00 c01 c02 c11 c12 c22
    rgba = np.frombuffer(base64.b64decode(d["colors"]), np.uint8).reshape(-1, 4)
    assert (rgba[:, :3] == 128).all()  # f_dc 0 is grey
    from numpy.lib import recfunctions

    PlyData([PlyElement.describe(recfunctions.drop_fields(arr, "opacity", usemask=False), "vertex")]).write(
        str(ply)
    )
    with pytest.raises(ValueError, match="opacity"):
        splat_payload(ply)
    ply.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nend_header\n1\n")
    with pytest.raises(ValueError, match="g.ply is not a readable PLY"):  # cut short
        splat_payload(ply)


def test_cli_report_rebuilds_the_page(run, tmp_path, capsys):
    """`coin-cl report RUN` writes the page again; without the depth grid (a scene without reference
    depth) the page colour-maps the rendered depth itself."""
    src, scene = run
    folder = tmp_path / "run"
    shutil.copytree(src, folder)
    stem = Path(scene.cameras[scene.test_idx[0]].name).stem
    (folder / "report.html").unlink()
    (folder / "eval" / "metrics" / "grids" / f"depth_{stem}.png").unlink()
    assert main(["report", str(folder)]) == 0
    assert (folder / "report.html").is_file() and "report.html" in capsys.readouterr().out
    assert f"report/{stem}_depth.png" in check_links(folder)
    assert not list(folder.rglob(".tmp-*"))
    assert main(["report", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a coin-cl run folder" in err
    (folder / "log.json").write_text('{"stages": ')  # cut short
    assert main(["report", str(folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "log.json is not valid JSON" in err


def _chromium(page: Path, *args: str, tmp: Path) -> subprocess.CompletedProcess:
    profile = tmp / f"profile{len(list(tmp.glob('profile*')))}"
    cmd = [CHROMIUM, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", *args, page.resolve().as_uri()]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=90)


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_the_page_in_headless_chromium(run, tmp_path):
    """No error on the page, every image loaded, and the 3D view from the test camera draws the
    test view's truth (its Gaussians are that picture's pixels)."""
    folder, scene = run
    page = folder / "report.html"
    dom = _chromium(page, "--dump-dom", tmp=tmp_path).stdout
    assert 'id="page-errors"' in dom, dom[:500]
    errors = dom.split('id="page-errors"', 1)[1].split("</ul>", 1)[0]
    assert 'data-count="0"' in errors and "<li>" not in errors, errors
    images = int(dom.split('data-images="', 1)[1].split('"', 1)[0])
    assert images >= 7 and 'data-broken-images="0"' in dom
    status = dom.split('id="viewer-status"', 1)[1].split("</p>", 1)[0]
    drawn = int(status.split('data-nonblank="', 1)[1].split('"', 1)[0])
    canvas = dom.split('<canvas id="viewer"', 1)[1].split(">", 1)[0]
    rect = [int(v) for v in canvas.split('data-rect="', 1)[1].split('"', 1)[0].split(",")]
    x, y, w, h = rect
    assert drawn > 0.9 * w * h, status  # the picture fills the view

    shot = tmp_path / "page.png"
    _chromium(page, f"--screenshot={shot}", tmp=tmp_path)
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[0] >= y + h, "no screenshot, or the view is outside it"
    view = img[y : y + h, x : x + w, ::-1].astype(np.float32) / 255.0
    assert view.std() > 0.05  # not a uniform box
    t = scene.test_idx[0]
    truth = scene.images[t]
    small = cv2.resize(view, (truth.shape[1], truth.shape[0]), interpolation=cv2.INTER_AREA)
    err = np.abs(small - truth).mean()
    corr = np.corrcoef(small.reshape(-1), truth.reshape(-1))[0, 1]
    assert err < 0.08 and corr > 0.85, (err, corr)
    # the test view's truth is drawn in its box, at the picture's size there
    rel = f"report/{Path(scene.cameras[t].name).stem}_truth.png"
    tag = dom.split(f'<img src="{rel}"', 1)[1].split(">", 1)[0]
    assert f'width="{truth.shape[1]}" height="{truth.shape[0]}"' in tag
    x, y, w, h = [int(v) for v in tag.split('data-rect="', 1)[1].split('"', 1)[0].split(",")]
    assert w > 100 and abs(h - w * truth.shape[0] / truth.shape[1]) <= 2
    box = cv2.resize(img[y : y + h, x : x + w, ::-1], truth.shape[1::-1], interpolation=cv2.INTER_AREA)
    assert np.abs(box / 255.0 - truth).mean() < 0.03


@pytest.mark.parametrize("case", ["real capture", "no test views"])
def test_the_page_without_an_object_picture_or_ground_truth(run, tmp_path, case):
    """A real capture has no picture of a test view with the object: the mask on the truth stands in.
    A scene without test views has no metrics: the page shows training views (capture | result)."""
    from dataclasses import replace

    from coin_cl.scene import load_scene, save_scene

    src, _ = run
    folder = tmp_path / "run"
    shutil.copytree(src, folder)
    scene = load_scene(folder / "0_scene" / "scene")
    shutil.rmtree(folder / "0_scene" / "scene")
    extras = {k: v for k, v in scene.extras.items() if k != "object_present"}
    if case == "no test views":
        scene = replace(scene, train_idx=sorted(scene.train_idx + scene.test_idx), test_idx=[])
        shutil.rmtree(folder / "eval" / "metrics")
    save_scene(replace(scene, extras=extras), folder / "0_scene" / "scene")
    write_report(folder)
    text = " ".join(_links(folder / "report.html").text)
    links = check_links(folder)
    if case == "real capture":
        assert "the object's mask (red) on the truth" in text and "truth (object absent)" in text
        assert not any(li.endswith("_capture.png") for li in links)
    else:
        assert "No metrics" in text and "Views: capture | result" in text
        assert "truth (object absent)" not in text
        assert sum(li.endswith("_capture.png") for li in links) == 2 * MAX_TRAIN_VIEWS  # link + picture


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_dragging_turns_the_3d_view(run, tmp_path):
    """A drag on the 3D view (pointer events, as a mouse sends them) draws it again from elsewhere."""
    src, _ = run
    folder = tmp_path / "run"
    shutil.copytree(src, folder)
    page = (folder / "report.html").read_text()
    drag = """<script>window.addEventListener('load', function () {
      const c = document.getElementById('viewer');
      const o = {bubbles: true, pointerId: 1, clientX: 100, clientY: 100};
      c.dispatchEvent(new PointerEvent('pointerdown', o));
      c.dispatchEvent(new PointerEvent('pointermove', Object.assign({}, o, {clientX: 160, clientY: 140})));
      c.dispatchEvent(new PointerEvent('pointerup', o));
    });</script>"""
    (folder / "dragged.html").write_text(page.replace("</body>", drag + "</body>"))
    dom = _chromium(folder / "report.html", "--dump-dom", tmp=tmp_path).stdout
    canvas = dom.split('<canvas id="viewer"', 1)[1].split(">", 1)[0]
    x, y, w, h = [int(v) for v in canvas.split('data-rect="', 1)[1].split('"', 1)[0].split(",")]
    shots = []
    for name in ("report.html", "dragged.html"):
        _chromium(folder / name, f"--screenshot={tmp_path / name}.png", tmp=tmp_path)
        shots.append(cv2.imread(f"{tmp_path / name}.png")[y : y + h, x : x + w].astype(np.float32) / 255)
    assert shots[1].std() > 0.05  # still a picture
    assert np.abs(shots[0] - shots[1]).mean() > 0.05  # of another view
