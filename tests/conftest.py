import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from coin_cl.oclgrind import process_log  # noqa: E402

process_log()  # under `python -m coin_cl.oclgrind`: each worker's reports in a file of its own

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

# The longest test files (worker-seconds on 2 cores, `--durations`), longest first: with
# `--dist loadfile --no-loadscope-reorder` (pyproject's addopts) xdist hands out whole files in this
# order, so the workers of `-n auto` end together instead of one of them running a long file last
# while the other waits (xdist's own order, by the number of tests in a file, put the fault harness
# last). The rest follow in collection order.
LONGEST_FIRST = ("test_faults_harness.py", "test_pipeline_coin.py", "test_pipeline_refgs.py",
                 "test_examples.py", "test_pipeline_insert.py", "test_refine_masks.py",
                 "test_benchmarks_budget_curve.py", "test_pipeline_clg.py", "test_benchmarks_real.py",
                 "test_gs_background_depth.py", "test_diffusion_scene_prior.py", "test_cli_run.py",
                 "test_cli_engine.py", "test_diffusion_exemplar.py")  # fmt: skip


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda it: rank.get(Path(str(it.fspath)).name, len(rank)))  # stable: the rest keep order


def load_script(relpath: str, name: str):
    """A script of the repository (`benchmarks/NAME.py`, `examples/NAME.py`: not a package) run as
    the module `name`, registered in sys.modules (dataclasses look their module up there)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / relpath)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


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


@pytest.fixture
def poisoned_rt():
    """The default runtime with every kernel output starting as NaN / INT32_MIN, so an element a
    kernel leaves unwritten shows in the comparison."""
    from coin_cl.engine.runtime import get_runtime

    r = get_runtime()
    r.poison = True
    yield r
    r.poison = False


def small_mode() -> bool:
    """True under Oclgrind (or COIN_CL_SMALL=1): kernel tests shrink to sizes a simulator runs."""
    return (
        os.environ.get("COIN_CL_SMALL") == "1" or "oclgrind" in os.environ.get("COIN_CL_DEVICE", "").lower()
    )


# ---------------------------------------------------------------- network weight files (random values)


def random_lpips_files(tmp_path, net, seed=0):
    """Random weights under the real file layouts (torchvision backbone, lpips heads)."""
    import torch

    from coin_cl.nets.lpips import backbone as lpips_backbone

    torch.manual_seed(seed)
    feats, _, chans = lpips_backbone(net)
    backbone = {f"features.{k}": v for k, v in feats.state_dict().items()}
    backbone["classifier.1.weight"] = torch.zeros(3, 3)  # real files carry the classifier too
    heads = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1) for i, c in enumerate(chans)}
    b, h = tmp_path / f"{net}_backbone.pth", tmp_path / f"{net}_heads.pth"
    torch.save(backbone, b)
    torch.save(heads, h)
    return b, h, backbone, heads


@pytest.fixture
def lpips_files():
    """`random_lpips_files(tmp_path, net, seed=0) -> (backbone, heads, backbone_sd, heads_sd)`."""
    return random_lpips_files


@pytest.fixture(scope="module")
def inception_file(tmp_path_factory):
    """pytorch-fid's state_dict layout with random weights (BN statistics made non-trivial)."""
    import torch

    from coin_cl.nets.inception import FIDInception

    torch.manual_seed(0)
    model = FIDInception()
    sd = model.state_dict()
    for k, v in sd.items():
        if k.endswith("running_var"):
            sd[k] = torch.rand_like(v) + 0.5
        elif k.endswith("running_mean"):
            sd[k] = torch.randn_like(v) * 0.1
    sd = {k: v for k, v in sd.items() if not k.endswith("num_batches_tracked")}  # as the real file
    p = tmp_path_factory.mktemp("fid") / "pt_inception.pth"
    torch.save(sd, p)
    return p, sd
