"""Device listing, probing and choice (`coin_cl.engine.devices`)."""

import pytest

from coin_cl.engine import devices
from coin_cl.engine.errors import NoDeviceError
from coin_cl.engine.limits import min_raster_gpu_local_bytes
from coin_cl.engine.runtime import Runtime, get_runtime

# Kernel tests: CI runs them again on every OpenCL implementation present and under Oclgrind.
pytestmark = pytest.mark.kernel


def test_default_device_is_listed():
    rt = get_runtime()
    assert any(rt.device.name == d for _, d, _ in devices.list_devices())


def test_unknown_device_names_what_is_visible():
    with pytest.raises(NoDeviceError, match="no OpenCL device matches 'no-such-gpu'.*visible"):
        get_runtime("no-such-gpu")


def test_a_failing_kernel_cache_builds_from_source(monkeypatch):
    """pyopencl turns an on-disk cache failure into KeyError('PYOPENCL_CACHE_FAILURE_FATAL') unless
    that variable is set (`coin_cl.engine.devices` sets it empty on import): then a broken cache
    costs a warning, not the device."""
    import pyopencl.cache
    from pyopencl.characterize import has_src_build_cache

    if has_src_build_cache(get_runtime().device):
        # PoCL and NVIDIA cache builds themselves, so pyopencl never touches its disk cache there
        # and no cache failure can reach the device (CI runs this file again on PoCL where it builds).
        pytest.skip(f"pyopencl keeps no disk cache for {get_runtime().device.platform.name}")

    def broken(*a, **kw):
        raise OSError("simulated: the cache entry is being written by another process")

    monkeypatch.setattr(pyopencl.cache, "_create_built_program_from_source_cached", broken)
    rt = Runtime(get_runtime().device)
    with pytest.warns(UserWarning, match="caching failed"):
        prg = rt.program("project.cl")
    assert prg.get_info(__import__("pyopencl").program_info.NUM_KERNELS) > 0
    # Without that default pyopencl's own bug shows (what the default guards against).
    monkeypatch.delenv("PYOPENCL_CACHE_FAILURE_FATAL")
    with pytest.raises(KeyError, match="PYOPENCL_CACHE_FAILURE_FATAL"):
        Runtime(get_runtime().device).program("project.cl")


def test_no_opencl_platform_says_what_to_install(monkeypatch):
    import pyopencl as cl

    def no_platforms():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")

    monkeypatch.setattr(cl, "get_platforms", no_platforms)
    with pytest.raises(NoDeviceError, match="pip install pocl-binary-distribution"):
        devices.choose_device(None)
    assert devices.list_devices() == []


# -- probing: a device that cannot compile is skipped (default) or a clear error (requested) --------


def _device_list():
    return [d for _, d in devices.all_devices() if devices.default_rank(d)[0] < 9]


def test_broken_build_is_skipped_with_the_compiler_message(monkeypatch, caplog):
    monkeypatch.setattr(devices, "_PROBES", {})
    monkeypatch.setattr(devices, "_PROBE_SOURCE", "__kernel void probe(__global float *x) { x[0] = y; }")
    dev = _device_list()[0]
    probe = devices.probe_device(dev)
    assert not probe.ok and "y" in probe.message  # the compiler names the undeclared identifier
    with caplog.at_level("WARNING", logger="coin_cl.engine.devices"):
        with pytest.raises(NoDeviceError, match="no OpenCL device can build kernels.*intel-opencl-rt"):
            devices.choose_device(None)
    assert "skipped: it cannot build kernels" in caplog.text
    with pytest.raises(NoDeviceError, match="cannot build or run kernels.*Unset COIN_CL_DEVICE"):
        devices.choose_device(dev.name)


def test_default_skips_a_failing_device_for_the_next_one(monkeypatch):
    """Two implementations that really work: make the first fail its probe, the second is chosen.

    Listed is not working (PoCL 3.0 is listed on Zen 5 but compiles nothing), so the pair is taken
    from `working_devices()`, which probes each one.
    """
    working = devices.working_devices()
    if len(working) < 2:
        listed = [devices.device_label(d) for d in _device_list()]
        pytest.skip(f"needs two working OpenCL implementations; working: {len(working)} of listed {listed}")
    bad = working[0]
    monkeypatch.setattr(devices, "_PROBES", {devices._probe_key(bad): devices.Probe(False, "simulated", 0.0)})
    assert devices.device_label(devices.choose_device(None)) == devices.device_label(working[1])


class _ListedButBroken:
    """A device that ranks first (a GPU) and that the driver lists but cannot compile for."""

    def __init__(self, real):
        import pyopencl as cl

        self.name = "Simulated GPU"
        self.type = cl.device_type.GPU
        self.platform = real.platform
        self.vendor = "simulated"
        self.version = "OpenCL 1.2 simulated"
        self.driver_version = "0"
        self.extensions = ""


def test_a_listed_device_that_cannot_compile_is_passed_over(monkeypatch, caplog):
    """The Zen 5 case with one implementation that works: whatever ranks above it and fails its
    probe is skipped with a warning, and the working one is chosen; requested by name, the broken
    one is a clear error."""
    real = devices.working_devices()[0]
    fake = _ListedButBroken(real)
    monkeypatch.setattr(devices, "all_devices", lambda: [(fake.platform, fake), (real.platform, real)])
    broken = devices.Probe(False, "unknown target CPU 'generic'", 0.0)
    monkeypatch.setattr(devices, "_PROBES", {devices._probe_key(fake): broken})
    with caplog.at_level("WARNING", logger="coin_cl.engine.devices"):
        chosen = devices.choose_device(None)
    assert devices.device_label(chosen) == devices.device_label(real)
    assert "Simulated GPU" in caplog.text and "unknown target CPU" in caplog.text
    with pytest.raises(NoDeviceError, match="Simulated GPU.*cannot build or run kernels"):
        devices.choose_device("Simulated GPU")


# -- a GPU ranks first only with working float atomics and the local memory the kernels need ------


class _FakeGPU:
    """Device properties of a GPU (only what the ranking reads); no kernel runs on it."""

    def __init__(self, local_mem_size: int, name: str = "Fake GPU"):
        import types

        import pyopencl as cl

        self.name, self.version, self.extensions = name, "OpenCL 3.0 fake", ""
        self.type = cl.device_type.GPU
        self.local_mem_size = local_mem_size
        self.platform = types.SimpleNamespace(name="Fake platform")


def _rank_setup(monkeypatch, gpu, atomics_work: bool):
    monkeypatch.setattr(devices, "_GPU_CHECKS", {})
    monkeypatch.setattr(devices, "_PROBES", {devices._probe_key(gpu): devices.Probe(True, "ok", 0.0)})
    monkeypatch.setattr(devices, "probe_float_atomics", lambda d: False)
    monkeypatch.setattr(devices, "probe_cas_atomics", lambda d: atomics_work)
    # A CPU implementation that builds kernels (not the default under Oclgrind, a simulator).
    cpus = [d for _, d in devices.all_devices() if 1 <= devices.default_rank(d)[0] <= 3]
    cpu = next((d for d in cpus if devices.probe_device(d).ok), None)
    if cpu is None:
        pytest.skip("needs a CPU implementation that builds kernels")
    monkeypatch.setattr(devices, "all_devices", lambda: [(gpu.platform, gpu), (cpu.platform, cpu)])
    return cpu


def test_the_compare_and_swap_fallback_adds_exactly_on_this_device():
    assert devices.probe_cas_atomics(get_runtime().device)


def test_a_capable_gpu_ranks_first(monkeypatch):
    gpu = _FakeGPU(local_mem_size=48 * 1024)
    _rank_setup(monkeypatch, gpu, atomics_work=True)
    assert devices.default_rank(gpu) == (0, "a GPU")
    assert devices.choose_device(None) is gpu


@pytest.mark.parametrize(
    "local_mem, atomics, reason",
    [
        (512, True, f"local memory 512 B is below the {min_raster_gpu_local_bytes()} B"),
        (48 * 1024, False, "neither a float atomic add"),
    ],  # fmt: skip
)
def test_a_gpu_without_what_the_kernels_need_ranks_behind_the_cpu(
    monkeypatch, caplog, local_mem, atomics, reason
):
    gpu = _FakeGPU(local_mem_size=local_mem)
    cpu = _rank_setup(monkeypatch, gpu, atomics_work=atomics)
    with caplog.at_level("WARNING", logger="coin_cl.engine.devices"):
        rank, why = devices.default_rank(gpu)
        assert rank > devices.default_rank(cpu)[0] and reason in why
        assert devices.choose_device(None) is cpu
    assert f"Fake platform / Fake GPU ranks behind the CPU: {reason}" in caplog.text
