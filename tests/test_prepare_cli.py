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
