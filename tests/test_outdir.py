"""The one rule for an output folder (coin_cl/outdir.py): new, empty, or marked as the command's."""

import json

import pytest

from coin_cl.outdir import MARKER, OutputFolderError, check_output, mark_output, read_marker


def test_new_and_empty_folders_are_accepted_and_marked(tmp_path):
    assert check_output(tmp_path / "new", "run") == "new"
    (tmp_path / "empty").mkdir()
    assert check_output(tmp_path / "empty", "run") == "empty"
    mark_output(tmp_path / "empty", "run")
    assert json.loads((tmp_path / "empty" / MARKER).read_text())["command"] == "run"
    (tmp_path / "empty" / "plan.json").write_text("{}")
    assert check_output(tmp_path / "empty", "run") == "ours"


def test_an_unrelated_folder_is_refused_in_one_line(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(OutputFolderError) as e:
        check_output(tmp_path, "run")
    msg = str(e.value)
    assert str(tmp_path) in msg and "not empty" in msg and "new or empty folder" in msg and "\n" not in msg
    assert check_output(tmp_path, "prepare", adopt=True) == "adopted"  # prepare --replace
    assert not (tmp_path / MARKER).exists()  # checking writes nothing


def test_another_commands_folder_is_refused_even_with_adopt(tmp_path):
    mark_output(tmp_path, "train")
    with pytest.raises(OutputFolderError, match="output folder of coin-cl train, not of coin-cl run"):
        check_output(tmp_path, "run")
    with pytest.raises(OutputFolderError):
        check_output(tmp_path, "prepare", adopt=True)


def test_folders_made_before_the_marker_are_recognised(tmp_path):
    (tmp_path / "run.json").write_text("{}")
    assert check_output(tmp_path, "run") == "ours"
    with pytest.raises(OutputFolderError):
        check_output(tmp_path, "train")


def test_ignored_names_and_a_file_as_out(tmp_path):
    (tmp_path / "images").mkdir()
    assert check_output(tmp_path, "prepare", ignore=("images",)) == "empty"
    (tmp_path / "f").write_text("x")
    with pytest.raises(OutputFolderError, match="is a file"):
        check_output(tmp_path / "f", "run")


def test_a_linked_marker_does_not_count(tmp_path):
    outside = tmp_path / "m.json"
    outside.write_text(json.dumps({"command": "run"}))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / MARKER).symlink_to(outside)
    assert read_marker(tmp_path / "out") is None
    with pytest.raises(OutputFolderError):
        check_output(tmp_path / "out", "run")
