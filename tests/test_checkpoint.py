"""coin_cl.checkpoint: checkpoints are read without running code; a refused, truncated, corrupt or
non-dict file is one CheckpointError line naming the file."""

import ast
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch

from coin_cl.checkpoint import CheckpointError, load_checkpoint, malformed
from coin_cl.testing import _Payload, hostile_checkpoint


def one_line(exc: pytest.ExceptionInfo, path) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and str(path) in msg, msg
    return msg


def test_the_hostile_payload_is_real(tmp_path):
    """The control: the planted file does run code when unpickled the unsafe way, so the tests
    below that find no marker prove the loader, not a dud payload."""
    hostile_checkpoint(tmp_path / "ckpt.pt", tmp_path / "marker")
    torch.load(tmp_path / "ckpt.pt", weights_only=False)
    assert (tmp_path / "marker").is_file()


def test_a_checkpoint_that_would_run_code_is_refused_and_nothing_runs(tmp_path):
    path, marker = tmp_path / "ckpt.pt", tmp_path / "marker"
    hostile_checkpoint(path, marker)
    with pytest.raises(CheckpointError) as exc:
        load_checkpoint(path, "rerun with --force 2_refgs")
    msg = one_line(exc, path)
    assert "refused" in msg and "coin_cl.testing.plant_marker" in msg and "not written by coin-cl" in msg
    assert msg.endswith("rerun with --force 2_refgs") and not marker.exists()


def test_old_format_and_bare_pickles_do_not_run_either(tmp_path):
    marker = tmp_path / "marker"
    legacy = tmp_path / "legacy.pt"  # torch.save's format before torch 1.6
    torch.save({"model": _Payload(str(marker))}, legacy, _use_new_zipfile_serialization=False)
    with pytest.raises(CheckpointError, match="refused") as exc:
        load_checkpoint(legacy)
    one_line(exc, legacy)
    bare = tmp_path / "bare.pt"
    bare.write_bytes(pickle.dumps({"model": _Payload(str(marker))}))
    with pytest.raises(CheckpointError, match="not a complete coin-cl checkpoint") as exc:
        load_checkpoint(bare)
    one_line(exc, bare)
    assert not marker.exists()


def test_random_bytes_empty_and_truncated_files_are_one_line(tmp_path):
    good = tmp_path / "good.pt"
    torch.save({"w": torch.arange(1000.0), "step": 3}, good)
    data = good.read_bytes()
    cases = {
        "random.pt": np.random.default_rng(0).bytes(4096),
        "empty.pt": b"",
        "truncated.pt": data[: len(data) // 2],
        "cut_at_the_end.pt": data[:-10],
    }
    for name, blob in cases.items():
        (tmp_path / name).write_bytes(blob)
        with pytest.raises(CheckpointError, match="truncated, empty or another kind of file") as exc:
            load_checkpoint(tmp_path / name)
        one_line(exc, tmp_path / name)


def test_a_damaged_archive_is_one_line(tmp_path):
    """Bytes overwritten inside the archive, its directory intact: the pickle or the tensor data no
    longer read back."""
    path = tmp_path / "ckpt.pt"
    torch.save({"w": torch.arange(1000.0), "step": 3}, path)
    data = bytearray(path.read_bytes())
    start = data.index(b"data.pkl") + 8
    data[start : start + 200] = np.random.default_rng(1).bytes(200)
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="corrupt|refused") as exc:
        load_checkpoint(path)
    one_line(exc, path)


def test_a_file_that_is_not_a_dict_is_one_line(tmp_path):
    path = tmp_path / "list.pt"
    torch.save([1, 2], path)
    with pytest.raises(CheckpointError, match="holds a list") as exc:
        load_checkpoint(path)
    one_line(exc, path)


def test_a_missing_file_is_an_os_error_naming_it(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt"):
        load_checkpoint(tmp_path / "nope.pt")


def test_what_coin_cl_saves_reads_back_whole(tmp_path):
    """Tensors, generator states, numpy's bit-generator state (128-bit ints), floats, None, tuples and
    nested dicts: all a checkpoint of the project holds, read with no allow-list."""
    g = torch.Generator().manual_seed(5)
    state = {
        "model": {"means": torch.randn(4, 3), "n": 4, "cfg": {"sh": (1, 2), "lr": 1e-3, "x": None}},
        "gen": g.get_state(),
        "rng": np.random.default_rng(7).bit_generator.state,
        "trainer": {"step": 9, "log": {"train": [{"loss": 0.5}]}, "evals_done": [0.5, 1.0]},
    }
    torch.save(state, tmp_path / "ckpt.pt")
    back = load_checkpoint(tmp_path / "ckpt.pt")
    assert torch.equal(back["model"]["means"], state["model"]["means"])
    assert torch.equal(back["gen"], state["gen"]) and back["rng"] == state["rng"]
    assert back["model"]["cfg"] == state["model"]["cfg"] and back["trainer"] == state["trainer"]


def test_malformed_names_the_file_and_what_is_missing(tmp_path):
    err = malformed(tmp_path / "ckpt.pt", KeyError("model"), "delete it")
    assert isinstance(err, ValueError) and str(tmp_path / "ckpt.pt") in str(err) and "'model'" in str(err)
    assert str(err).endswith("delete it")


def unsafe_loads(path: Path) -> list[int]:
    """Lines of `path` calling torch.load without weights_only=True."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and ast.unparse(node.func) == "torch.load":
            kw = {k.arg: k.value for k in node.keywords}
            if not (isinstance(kw.get("weights_only"), ast.Constant) and kw["weights_only"].value is True):
                out.append(node.lineno)
    return out


def test_nothing_in_the_project_unpickles_unsafely():
    """Every torch.load of the code, tests and benchmarks reads with weights_only=True (files go
    through load_checkpoint); the only exception is the control above, which must run the payload."""
    root = Path(__file__).resolve().parents[1]
    folders = ("coin_cl", "diffusion", "tests", "benchmarks")
    files = [f for d in folders for f in sorted((root / d).rglob("*.py"))]
    assert len(files) > 100
    bad = {str(f): unsafe_loads(f) for f in files if unsafe_loads(f)}
    assert bad == {str(Path(__file__).resolve()): [unsafe_loads(Path(__file__))[0]]}, bad
    assert len(unsafe_loads(Path(__file__))) == 1
