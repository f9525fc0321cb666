import torch

from coin_cl.gs.losses import LossConfig, photometric_loss, ssim_map


def _imgs(b=2, h=20, w=24, seed=0):
    g = torch.Generator().manual_seed(seed)
    pred = torch.rand(b, h, w, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(b, h, w, 3, generator=g, dtype=torch.float64)
    return pred, target


def test_identical_images_give_zero_loss_and_unit_ssim():
    _, t = _imgs()
    loss, parts = photometric_loss(t.clone(), t)
    assert abs(float(loss)) < 1e-12
    assert torch.allclose(ssim_map(t, t), torch.ones(t.shape[:3], dtype=t.dtype))


def test_loss_is_the_paper_mix():
    p, t = _imgs(b=1)
    cfg = LossConfig(lambda_dssim=0.2)
    loss, parts = photometric_loss(p, t, cfg=cfg)
    l1 = (p - t).abs().mean()
    s = ssim_map(p, t).mean()
    assert torch.allclose(loss, 0.8 * l1 + 0.2 * (1 - s))


def test_zero_weight_view_contributes_nothing():
    p, t = _imgs()
    loss, _ = photometric_loss(p, t, torch.tensor([0.0, 1.0]))
    loss.backward()
    assert torch.count_nonzero(p.grad[0]) == 0
    assert torch.count_nonzero(p.grad[1]) > 0
    # The batch gradient equals the gradient of the weighted view alone.
    p1 = p.detach()[1:].clone().requires_grad_()
    photometric_loss(p1, t[1:])[0].backward()
    assert torch.allclose(p.grad[1], p1.grad[0])


def test_weights_scale_gradients_linearly():
    p, t = _imgs()
    photometric_loss(p, t, torch.tensor([1.0, 1.0]))[0].backward()
    g1 = p.grad.clone()
    p.grad = None
    photometric_loss(p, t, torch.tensor([3.0, 0.5]))[0].backward()
    assert torch.allclose(p.grad[0], 3 * g1[0]) and torch.allclose(p.grad[1], 0.5 * g1[1])


def test_masked_pixels_are_excluded():
    p, t = _imgs()
    ex = torch.zeros(t.shape[:3], dtype=torch.bool)
    ex[:, 5:12, 6:15] = True
    loss, _ = photometric_loss(p, t, exclude=ex)
    loss.backward()
    assert torch.count_nonzero(p.grad[ex]) == 0  # no gradient inside the mask
    assert torch.count_nonzero(p.grad[~ex]) > 0.9 * (~ex).sum() * 3
    # Neither the target's nor the render's content inside the mask can change the loss.
    t2 = t.clone()
    t2[ex] = 1.0 - t2[ex]
    p2 = p.detach().clone()
    p2[ex] = 0.3
    loss2, _ = photometric_loss(p2, t2, exclude=ex)
    assert torch.allclose(loss2, loss.detach())
    # ... while the same change outside the mask does.
    t3 = t.clone()
    t3[~ex] = 1.0 - t3[~ex]
    assert not torch.allclose(photometric_loss(p2, t3, exclude=ex)[0], loss.detach())


def test_fully_masked_view_gives_zero():
    p, t = _imgs(b=1)
    ex = torch.ones(t.shape[:3], dtype=torch.bool)
    loss, _ = photometric_loss(p, t, exclude=ex)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.count_nonzero(p.grad) == 0
