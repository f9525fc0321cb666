"""Memory known in advance: the estimate's parts, the machine's memory, refusal with the flag that fits."""

from types import SimpleNamespace

import numpy as np
import pytest

from coin_cl.pipeline import memory
from coin_cl.pipeline.memory import (
    GIB,
    SceneTooLargeError,
    available_bytes,
    check_memory,
    estimate_peak_bytes,
)


class _Scene(SimpleNamespace):
    def __len__(self):
        return len(self.cameras)


def scene(w, h, n, pts):
    return _Scene(cameras=[SimpleNamespace(width=w, height=h)] * n, points=np.zeros((pts, 3)), path="/data/s")


def test_estimate_is_its_parts_times_the_margin_and_grows_with_each_input():
    need, parts = estimate_peak_bytes(100, 50, 10, 1000)
    assert need == int(memory.SAFETY * sum(parts.values()))
    assert parts["images"] == memory.BYTES_PER_VIEW_PIXEL * 100 * 50 * 10
    for bigger in ((200, 50, 10, 1000), (100, 50, 20, 1000), (100, 50, 10, 5000)):
        assert estimate_peak_bytes(*bigger)[0] > need


def test_calibration_run_is_bracketed():
    """SPIn-NeRF's 34 views at 504x284, 73k points: the measured trainer peak (1.10 GiB) lies below
    the pipeline's estimate, which holds more image copies and anchor growth."""
    need, _ = estimate_peak_bytes(504, 284, 34, 73_000)
    assert 1.10 * GIB < need < 3 * GIB


def test_available_memory_is_read_and_capped_by_the_environment(monkeypatch):
    have = available_bytes()
    assert have is not None and have > 0  # /proc/meminfo on Linux
    monkeypatch.setenv(memory.ENV_LIMIT, "0.5")
    assert available_bytes() == int(0.5 * GIB)


def test_fitting_scene_passes_and_too_large_one_names_the_resolution_that_fits(monkeypatch):
    monkeypatch.setenv(memory.ENV_LIMIT, "4")
    est = check_memory(scene(504, 284, 34, 73_000))
    assert est.fits and est.available == 4 * GIB
    big = scene(4032, 3024, 60, 73_000)  # phone pictures at full size
    with pytest.raises(
        SceneTooLargeError, match=r"60 views of 4032x3024 .* GiB are available: use --resolution"
    ) as e:
        check_memory(big)
    msg = str(e.value)
    assert "\n" not in msg
    r = float(msg.split("--resolution ")[1].split()[0])
    assert estimate_peak_bytes(round(4032 * r), round(3024 * r), 60, 73_000)[0] <= 4 * GIB
    if r != memory.RESOLUTIONS[0]:  # and it is the largest such scale
        r_up = memory.RESOLUTIONS[memory.RESOLUTIONS.index(r) - 1]
        assert estimate_peak_bytes(round(4032 * r_up), round(3024 * r_up), 60, 73_000)[0] > 4 * GIB


def test_no_resolution_fits_suggests_fewer_views_or_more_memory(monkeypatch):
    monkeypatch.setenv(memory.ENV_LIMIT, "2")
    with pytest.raises(SceneTooLargeError, match=r"fewer views \(about \d+ at --resolution 0.125\)"):
        check_memory(scene(8000, 6000, 400, 1000))
    with pytest.raises(SceneTooLargeError, match="more memory"):
        check_memory(scene(64, 48, 4, 200_000_000))


def test_the_check_before_loading_reads_headers_only(tmp_path, monkeypatch):
    """8 phone photos (4032x2268) under a 1.5 GB limit: refused from their headers, before any
    decode (imageio's decoder is never called), with the decode estimate; a header beyond the
    pixel limit is refused naming the file."""
    from test_scene_io import header_only_png

    from coin_cl.scene import io as scene_io

    monkeypatch.setattr(scene_io.iio, "imread", lambda *a, **k: pytest.fail("decoded"))
    (tmp_path / "s" / "images").mkdir(parents=True)
    for i in range(8):
        header_only_png(tmp_path / "s" / "images" / f"p{i}.png", 4032, 2268)
    monkeypatch.setenv("COIN_MEMORY_LIMIT_GB", "1.5")
    with pytest.raises(memory.SceneTooLargeError) as e:
        memory.check_scene_files(tmp_path / "s", None)
    msg = str(e.value)
    assert "\n" not in msg and "decoding its 8 images" in msg and "4032x2268" in msg and "downscale" in msg
    monkeypatch.setenv("COIN_MEMORY_LIMIT_GB", "64")
    est = memory.check_scene_files(tmp_path / "s", None)
    assert est.parts["decode"] > 8 * 4032 * 2268 * 12  # the float32 RGB of every view at file size
    header_only_png(tmp_path / "s" / "images" / "p9.png", 12000, 12000)
    with pytest.raises(ValueError, match="p9.png declares 12000x12000"):
        memory.check_scene_files(tmp_path / "s", None)
