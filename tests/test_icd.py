"""Registration of pip-installed OpenCL implementations (coin_cl.engine.icd)."""

import logging
import os
import stat
from pathlib import Path

import pytest

from coin_cl.engine import icd


@pytest.fixture
def fake_env(tmp_path, monkeypatch):
    """A fake pip-installed implementation, a system vendors folder and a user folder."""
    lib = tmp_path / "venv" / "libintelocl.so"
    lib.parent.mkdir()
    lib.write_bytes(b"")
    monkeypatch.setattr(icd, "environment_libraries", lambda: {"intel-opencl-rt.icd": lib})
    system = tmp_path / "etc_vendors"
    system.mkdir()
    (system / "nvidia.icd").write_text("libnvidia-opencl.so.1\n")
    monkeypatch.setattr(icd, "SYSTEM_VENDORS", system)
    user = tmp_path / "user_vendors"
    user.mkdir()
    (user / "oclgrind.icd").write_text("/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so\n")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("COIN_CL_NO_ICD", raising=False)
    monkeypatch.delenv(icd._MARKER, raising=False)
    monkeypatch.delenv("OCL_ICD_VENDORS", raising=False)
    # register_platforms sets variables; monkeypatch restores them after the test.
    monkeypatch.setenv("OCL_ICD_VENDORS", str(user))
    return lib, system, user


def test_keeps_user_and_system_entries_and_adds_the_environment(fake_env):
    lib, system, user = fake_env
    folder = icd.register_platforms()
    assert os.environ["OCL_ICD_VENDORS"] == str(folder)
    lines = sorted(f.read_text().strip() for f in folder.glob("*.icd"))
    assert lines == sorted(
        [str(lib), "libnvidia-opencl.so.1", "/usr/lib/x86_64-linux-gnu/liboclgrind-rt-icd.so"]
    )
    assert folder.parent == Path(os.environ["XDG_CACHE_HOME"]) / "coin-cl"


def test_user_variable_naming_a_file_is_kept(fake_env, monkeypatch, tmp_path):
    lib, _, _ = fake_env
    one = tmp_path / "mine.icd"
    one.write_text("/opt/vendor/libmine.so\n")
    monkeypatch.setenv("OCL_ICD_VENDORS", str(one))
    folder = icd.register_platforms()
    lines = {f.read_text().strip() for f in folder.glob("*.icd")}
    assert {"/opt/vendor/libmine.so", str(lib), "libnvidia-opencl.so.1"} == lines


def test_current_folder_is_not_rewritten(fake_env, monkeypatch):
    _, _, user = fake_env
    first = icd.register_platforms()
    stamps = {f.name: f.stat().st_mtime_ns for f in first.iterdir()}
    # A fresh process: same inputs, the marker not yet set.
    monkeypatch.setenv("OCL_ICD_VENDORS", str(user))
    monkeypatch.delenv(icd._MARKER)
    second = icd.register_platforms()
    assert second == first
    assert {f.name: f.stat().st_mtime_ns for f in second.iterdir()} == stamps
    assert [p.name for p in first.parent.iterdir()] == [first.name]  # no temporary left behind
    # The same process again: a no-op (the variable already names our folder).
    assert icd.register_platforms() == first


def test_same_library_twice_is_listed_once(fake_env, monkeypatch):
    lib, system, _ = fake_env
    (system / "intel.icd").write_text(f"{lib}\n")
    folder = icd.register_platforms()
    lines = [f.read_text().strip() for f in folder.glob("*.icd")]
    assert lines.count(str(lib)) == 1


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes to read-only folders")
def test_read_only_cache_falls_back_to_a_temporary_folder(fake_env, tmp_path, monkeypatch, caplog):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    monkeypatch.setenv("XDG_CACHE_HOME", str(ro))
    with caplog.at_level(logging.INFO, logger="coin_cl.engine.icd"):
        folder = icd.register_platforms()
    assert not str(folder).startswith(str(ro))
    assert "not writable" in caplog.text
    assert len(list(folder.glob("*.icd"))) == 3


def test_unwritable_cache_falls_back_to_a_temporary_folder(fake_env, tmp_path, monkeypatch, caplog):
    """Same as above where root ignores permissions: the cache root is a file, not a folder."""
    blocker = tmp_path / "blocked"
    blocker.write_text("a file where a folder should be")
    monkeypatch.setenv("XDG_CACHE_HOME", str(blocker))
    with caplog.at_level(logging.INFO, logger="coin_cl.engine.icd"):
        folder = icd.register_platforms()
    assert not str(folder).startswith(str(blocker))
    assert "not writable" in caplog.text
    assert len(list(folder.glob("*.icd"))) == 3


def test_switch_off_and_nothing_to_register(fake_env, monkeypatch):
    _, _, user = fake_env
    monkeypatch.setenv("COIN_CL_NO_ICD", "1")
    assert icd.register_platforms() is None
    assert os.environ["OCL_ICD_VENDORS"] == str(user)
    monkeypatch.delenv("COIN_CL_NO_ICD")
    monkeypatch.setattr(icd, "environment_libraries", lambda: {})
    assert icd.register_platforms() is None
    assert os.environ["OCL_ICD_VENDORS"] == str(user)
