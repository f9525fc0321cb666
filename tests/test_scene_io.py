"""Image reading and writing (coin_cl.scene.io): the documented conversions of `read_image`, exact
8-bit round trips, rounding in `to_uint8`, atomic writes, image listing, view stems, clear errors."""

import imageio.v3 as iio
import numpy as np
import pytest

from coin_cl.scene.io import (
    imread_checked,
    list_images,
    read_image,
    to_uint8,
    view_stem,
    write_npy,
    write_png,
)


def test_png_round_trip_is_exact_for_8_bit(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (7, 9, 3), dtype=np.uint8)
    write_png(tmp_path / "sub" / "a.png", a)  # the folder is created
    back = read_image(tmp_path / "sub" / "a.png")
    assert back.dtype == np.float32 and back.shape == (7, 9, 3)
    np.testing.assert_array_equal(to_uint8(back), a)
    np.testing.assert_allclose(back, a / 255.0, atol=1e-7)
    assert not [p for p in (tmp_path / "sub").iterdir() if p.name != "a.png"]  # no temporary left


def test_to_uint8_rounds_and_clips():
    x = np.array([-0.2, 0.0, 0.5 / 255 - 1e-6, 0.5 / 255 + 1e-6, 0.5, 1.0, 1.7], np.float32)
    np.testing.assert_array_equal(to_uint8(x), [0, 0, 0, 1, 128, 255, 255])
    u = np.array([3, 200], np.uint8)
    assert to_uint8(u) is u  # uint8 passes through untouched


@pytest.mark.parametrize("kind", ["grey", "grey_alpha", "rgba", "16bit"])
def test_documented_conversions(tmp_path, kind):
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (5, 6, 3), dtype=np.uint8)
    if kind == "grey":
        data, want = rgb[..., 0], np.repeat(rgb[..., :1], 3, 2) / 255.0
    elif kind == "grey_alpha":
        data, want = np.stack([rgb[..., 0], rgb[..., 1]], 2), np.repeat(rgb[..., :1], 3, 2) / 255.0
    elif kind == "rgba":  # alpha dropped, colour used as stored (not composited)
        data, want = np.concatenate([rgb, np.zeros((5, 6, 1), np.uint8)], 2), rgb / 255.0
    else:  # 16-bit grey (PIL writes and reads it as uint16): scaled by 65535, not 255
        data = rgb[..., 0].astype(np.uint16) * 257 + 3
        want = np.repeat(data[..., None], 3, 2) / 65535.0
    iio.imwrite(tmp_path / "x.png", data)
    np.testing.assert_allclose(read_image(tmp_path / "x.png"), want, atol=1e-6)


def test_float_images_are_clipped_and_nan_refused(tmp_path):
    a = np.array([[[-0.5, 0.25, 2.0]]], np.float32)
    iio.imwrite(tmp_path / "f.tiff", a)
    np.testing.assert_array_equal(read_image(tmp_path / "f.tiff"), [[[0.0, 0.25, 1.0]]])
    iio.imwrite(tmp_path / "n.tiff", np.array([[[np.nan, 0, 0]]], np.float32))
    with pytest.raises(ValueError, match="n.tiff holds NaN"):
        read_image(tmp_path / "n.tiff")


def test_unreadable_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="mask .*none.png not found"):
        imread_checked(tmp_path / "none.png", what="mask")
    good = tmp_path / "good.png"
    write_png(good, np.zeros((8, 8, 3), np.uint8))
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:40])
    with pytest.raises(ValueError, match="cut.png cannot be read .*truncated or not an image"):
        read_image(tmp_path / "cut.png")
    (tmp_path / "text.png").write_text("not a picture")
    with pytest.raises(ValueError, match="text.png cannot be read"):
        read_image(tmp_path / "text.png")


def test_write_npy_round_trip(tmp_path):
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    write_npy(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), a)
    assert [p.name for p in tmp_path.iterdir()] == ["a.npy"]


def test_list_images_and_view_stem(tmp_path):
    for n in ("b.JPG", "a.png", "c.jpeg", "notes.txt", "d.webp"):
        (tmp_path / n).write_bytes(b"")
    (tmp_path / "e.png").mkdir()  # a folder named like an image is not an image
    assert [p.name for p in list_images(tmp_path)] == ["a.png", "b.JPG", "c.jpeg"]
    assert view_stem("images/view_007.png", 3) == "view_007"
    assert view_stem("", 3) == "view_003"


def header_only_png(path, width, height):
    """A PNG whose IHDR declares width x height RGB and whose IDAT holds a few hundred bytes: what a
    decoder would allocate width*height*3 bytes for (4 GB as float32 at 12000x12000)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    body = chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 4096)) + chunk(b"IEND", b"")
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + body)
    return path


def test_huge_declared_size_is_refused_before_any_decode(tmp_path, monkeypatch):
    from coin_cl.scene import io as scene_io

    p = header_only_png(tmp_path / "bomb.png", 12000, 12000)
    assert p.stat().st_size < 1000

    def no_decode(*a, **k):
        raise AssertionError("decoded")

    monkeypatch.setattr(scene_io.iio, "imread", no_decode)
    with pytest.raises(ValueError) as e:
        read_image(p)
    msg = str(e.value)
    assert "\n" not in msg and str(p) in msg and "12000x12000" in msg and "downscale it" in msg
    assert scene_io.image_header(header_only_png(tmp_path / "ok.png", 640, 480)) == (640, 480, 3)
