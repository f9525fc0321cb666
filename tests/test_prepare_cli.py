"""`coin-cl prepare` (coin_cl/cli/prepare.py): bad input ends in one clear line, exit status 2."""

import numpy as np
import pytest

from coin_cl.cli import main
from coin_cl.scene.io import write_png


def run(args, capsys):
    code = main(["prepare", *map(str, args)])
    err = capsys.readouterr().err.strip().splitlines()
    return code, err


def test_empty_folder(tmp_path, capsys):
    code, err = run([tmp_path, "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1 and "no .jpg/.png images" in err[0] and str(tmp_path) in err[0]


def test_one_image(tmp_path, capsys):
    write_png(tmp_path / "a.png", np.zeros((8, 8, 3), np.float32))
    code, err = run([tmp_path, "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1 and "at least 3" in err[0]


def test_mixed_aspect(tmp_path, capsys):
    for i, (w, h) in enumerate([(64, 48), (64, 48), (48, 64)]):
        write_png(tmp_path / f"p{i}.png", np.zeros((h, w, 3), np.float32))
    code, err = run([tmp_path, "--out", tmp_path / "s"], capsys)
    assert code == 2 and len(err) == 1 and "p2.png is 48x64" in err[0]
    assert not (tmp_path / "s").exists()


def test_box_needs_numbers(tmp_path, capsys):
    for i in range(3):
        write_png(tmp_path / f"p{i}.png", np.zeros((48, 64, 3), np.float32))
    code, err = run([tmp_path, "--out", tmp_path / "s", "--box", "p0", "a", "1", "2", "3"], capsys)
    assert code == 2 and len(err) == 1 and "four numbers" in err[0]


def test_one_annotation_only(tmp_path):
    with pytest.raises(SystemExit):  # argparse: --box and --mask are mutually exclusive
        main(["prepare", str(tmp_path), "--out", str(tmp_path / "s"), "--box", "0", "1", "2", "3", "4",
              "--mask", "0", "m.png"])  # fmt: skip


def test_out_the_photos_parent_keeps_every_photo_and_an_existing_scene_is_refused(tmp_path, capsys):
    import hashlib

    from coin_cl import load_scene
    from coin_cl.prepare.capture import synthetic_capture

    photos = tmp_path / "myscene" / "images"  # COLMAP's layout: --out is the photos' parent
    synthetic_capture(photos, n_views=10, width=256, height=192)
    (photos / "notes.txt").write_text("not a photo")

    def hashes():
        return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(photos.iterdir())}

    before = hashes()
    code, err = run([photos, "--out", photos.parent, "--width", "256"], capsys)
    assert code == 0, err
    assert hashes() == before  # every original byte-identical, nothing added or removed
    assert load_scene(photos.parent).images[0].shape == (192, 256, 3)  # read from images_prepared/
    # another folder holding a scene prepare did not make: refused, untouched
    other = tmp_path / "other"
    (other / "sparse" / "0").mkdir(parents=True)
    (other / "sparse" / "0" / "cameras.txt").write_text("# theirs")
    code, err = run([photos, "--out", other], capsys)
    assert code == 2 and err[-1] == (
        f"coin-cl prepare: error: {other} holds a scene coin-cl prepare did not make (sparse/): add "
        "--replace to replace its images/, sparse/0 and masks/ (the photos are never touched), or "
        "choose another --out"
    )
    assert (other / "sparse" / "0" / "cameras.txt").read_text() == "# theirs"
    assert sorted(p.name for p in other.rglob("*")) == ["0", "cameras.txt", "sparse"]


def test_a_second_prepare_on_a_folder_being_prepared_is_refused_and_the_first_completes(
    tmp_path, capsys, monkeypatch
):
    """The first prepare is paused between feature extraction and matching (in a thread, holding
    its folder's lock); a second prepare with other settings on that folder is refused in one line
    and changes no byte of it; the first then finishes its scene."""
    import threading

    import coin_cl.prepare.sfm as sfm
    from coin_cl import load_scene
    from coin_cl.prepare.capture import synthetic_capture

    photos, out = tmp_path / "photos", tmp_path / "scene"
    synthetic_capture(photos, n_views=8, width=192, height=144)
    paused, go = threading.Event(), threading.Event()
    match = sfm._match

    def pausing_match(*a, **k):
        paused.set()
        assert go.wait(60)
        return match(*a, **k)

    monkeypatch.setattr(sfm, "_match", pausing_match)
    rc: list[int] = []
    first = threading.Thread(target=lambda: rc.append(main(["prepare", str(photos), "--out", str(out)])))
    first.start()
    try:
        assert paused.wait(60)
        files = {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
        assert ".coin-cl.lock" in files and any(name.endswith(".png") for name in files)
        capsys.readouterr()
        code, err = run([photos, "--out", out, "--width", "96", "--replace"], capsys)
        assert code == 2 and len(err) == 1
        assert err[0].startswith(f"coin-cl prepare: error: {out} is in use by another coin-cl run")
        assert {
            str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()
        } == files
    finally:
        go.set()
        first.join(120)
    assert rc == [0]
    assert load_scene(out).images[0].shape == (144, 192, 3)
    assert not (out / ".coin-cl.lock").exists()


def test_a_prepare_folder_with_a_planted_link_is_refused_and_the_target_untouched(tmp_path, capsys):
    """A prepare folder whose sparse/ is a link to a folder outside: a rerun with other settings
    would clear sparse/0 and write the new model through the link (pycolmap and shutil follow it);
    refused in one line naming the link, no byte of the target changed."""
    import hashlib

    from coin_cl.prepare.capture import synthetic_capture

    photos, out, outside = tmp_path / "photos", tmp_path / "scene", tmp_path / "theirs"
    synthetic_capture(photos, n_views=8, width=192, height=144)
    code, err = run([photos, "--out", out], capsys)
    assert code == 0, err
    (out / "sparse").rename(outside)
    (out / "sparse").symlink_to(outside, target_is_directory=True)

    def hashes():
        return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(outside.rglob("*"))
                if p.is_file()}  # fmt: skip

    before = hashes()
    code, err = run([photos, "--out", out, "--width", "160"], capsys)
    assert code == 2 and len(err) == 1
    assert err[0].startswith(
        f"coin-cl prepare: error: refusing to write {out / 'sparse'}: it is a symbolic link"
    )
    assert hashes() == before
