import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402


def shared_data_dir() -> Path | None:
    """The shared SPIn-NeRF data: $COIN_DATA, else ../shared/data beside the repository."""
    env = os.environ.get("COIN_DATA")
    cands = [Path(env)] if env else []
    cands.append(Path(__file__).resolve().parents[2] / "shared" / "data")
    for c in cands:
        if (c / "spinnerf_scene1").is_dir():
            return c
    return None


@pytest.fixture(scope="session")
def spinnerf_dir() -> Path:
    d = shared_data_dir()
    if d is None:
        pytest.skip("shared SPIn-NeRF data not found (set COIN_DATA)")
    return d / "spinnerf_scene1"


def small_mode() -> bool:
    """True under Oclgrind (or COIN_CL_SMALL=1): kernel tests shrink to sizes a simulator runs."""
    return (
        os.environ.get("COIN_CL_SMALL") == "1" or "oclgrind" in os.environ.get("COIN_CL_DEVICE", "").lower()
    )
