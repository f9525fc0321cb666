"""LaMa from a local TorchScript file (coin_cl.diffusion.lama): the calling convention of IOPaint's
big-lama.pt (image [0, 1], binary mask, sizes padded to multiples of 8, output [0, 1]) checked by a small
scripted module that refuses anything else, and clear errors for a missing or wrong file."""

import numpy as np
import pytest
import torch
from coin_cl.diffusion.lama import LAMA_ENV, PAD_MOD, lama_inpaint, load_lama


class _Convention(torch.nn.Module):
    """Same signature as big-lama.pt: forward(image (1,3,H,W), mask (1,1,H,W)) -> (1,3,H,W) in [0, 1].
    Fails unless H, W are multiples of 8, the image is in [0, 1] and the mask in {0, 1}; fills with the
    mean of the known pixels."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        torch._assert(image.shape[2] % 8 == 0 and image.shape[3] % 8 == 0, "not padded to 8")
        torch._assert(mask.shape[1] == 1 and image.shape[1] == 3, "channels")
        torch._assert(bool(image.min() >= 0.0) and bool(image.max() <= 1.0), "image range")
        torch._assert(bool(((mask == 0) | (mask == 1)).all()), "mask values")
        known = (image * (1 - mask)).sum(dim=(2, 3), keepdim=True) / (1 - mask).sum()
        return image * (1 - mask) + known * mask


@pytest.fixture()
def lama_file(tmp_path):
    p = tmp_path / "big-lama.pt"
    torch.jit.script(_Convention()).save(str(p))
    return p


def test_called_with_padding_and_ranges(lama_file):
    rng = np.random.default_rng(0)
    img = rng.uniform(0, 1, (37, 50, 3)).astype(np.float32)  # neither side a multiple of 8
    mask = np.zeros((37, 50), bool)
    mask[10:20, 30:45] = True
    model = load_lama(lama_file)
    out = lama_inpaint(model, img, mask)
    assert out.shape == img.shape and out.dtype == np.float32
    np.testing.assert_allclose(out[~mask], img[~mask], atol=1e-6)
    # the fill is the known pixels' mean over the PADDED (mirrored) image: close to the image's own
    known = img[~mask].mean(axis=0)
    np.testing.assert_allclose(out[mask].mean(axis=0), known, atol=0.02)
    assert PAD_MOD == 8


def test_env_var_and_errors(lama_file, tmp_path, monkeypatch):
    monkeypatch.delenv(LAMA_ENV, raising=False)
    with pytest.raises(FileNotFoundError, match=LAMA_ENV):
        load_lama()
    with pytest.raises(FileNotFoundError, match=LAMA_ENV):
        load_lama(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_text("not a model")
    with pytest.raises(ValueError, match=LAMA_ENV):
        load_lama(bad)
    monkeypatch.setenv(LAMA_ENV, str(lama_file))
    assert load_lama() is not None


def test_wrong_output_shape_is_a_clear_error(tmp_path):
    class Crop(torch.nn.Module):
        def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            return image[:, :, :8, :8]

    p = tmp_path / "crop.pt"
    torch.jit.script(Crop()).save(str(p))
    with pytest.raises(ValueError, match="expected"):
        lama_inpaint(load_lama(p), np.zeros((16, 16, 3), np.float32), np.eye(16, dtype=bool))
