"""The pixel filters of supersampled renders (``ops/downsample.py``): forward against the numpy reference, the
adjoint against the reference and as the transpose (random cotangents), float64 central differences; the radiance
and alpha filtered together (``gauss_*_rgba``) against the same reference and the per-array filters."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from tests.reference import downsample as ref
from triplet_cl.ops.downsample import box_down, box_up, gauss_down, gauss_down_rgba, gauss_up, gauss_up_rgba


@pytest.mark.parametrize("f", [1, 2, 3, 4])
@pytest.mark.parametrize("tail", [(), (3,), (1,)])
def test_box_filter_forward_and_adjoint(device, rng, f, tail):
    H, W = 5, 7
    x = rng.standard_normal((H * f, W * f) + tail).astype(np.float32)
    y = box_down(device, cla.to_device(device.queue, x), f).get()
    assert y.shape == (H, W) + tail
    np.testing.assert_allclose(y, ref.box_down(x, f), rtol=1e-6, atol=1e-6)
    v = rng.standard_normal((H, W) + tail).astype(np.float32)
    vx = box_up(device, cla.to_device(device.queue, v), f).get()
    np.testing.assert_allclose(vx, ref.box_up(v, f), rtol=1e-6, atol=1e-7)
    assert float((y * v).sum()) == pytest.approx(float((x * vx).sum()), rel=1e-4, abs=1e-4)  # <Ax, v> = <x, A'v>


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_filters_float64_central_differences(device64, rng, sigma):
    """The box (sigma 0) and the Gaussian filter: each adjoint against central differences of its float64 forward."""
    f, H, W = 3, 3, 4
    x = rng.standard_normal((H * f, W * f, 3))
    v = rng.standard_normal((H, W, 3))
    q = device64.queue
    g = (gauss_up(device64, cla.to_device(q, v), f, sigma) if sigma else box_up(device64, cla.to_device(q, v), f)).get()

    def loss(a):
        a = cla.to_device(q, a)
        y = gauss_down(device64, a, f, sigma) if sigma else box_down(device64, a, f)
        return float((y.get() * v).sum())

    h = 1e-6
    for idx in [(0, 0, 0), (4, 7, 1), (8, 11, 2), (5, 2, 0)]:
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        assert (loss(xp) - loss(xm)) / (2 * h) == pytest.approx(g[idx], rel=1e-7, abs=1e-9)


def test_box_filter_rejects_bad_input(device):
    x = cla.zeros(device.queue, (6, 6, 3), np.float32)
    with pytest.raises(ValueError, match="factor"):
        box_down(device, x, 0)
    with pytest.raises(ValueError, match="H\\*f"):
        box_down(device, x, 4)
    with pytest.raises(ValueError, match="device array"):
        box_down(device, np.zeros((6, 6)), 2)
    with pytest.raises(ValueError, match="float32 or float64"):
        box_down(device, cla.zeros(device.queue, (6, 6), np.int32), 2)


@pytest.mark.parametrize("f", [1, 2, 3])
@pytest.mark.parametrize("sigma", [0.5, 0.3, 1.1])
@pytest.mark.parametrize("tail", [(), (4,)])
def test_gauss_filter_forward_and_adjoint(device, rng, f, sigma, tail):
    """The separable device filter equals the dense definition (image borders included: a 5×7 image is mostly
    border for a 2-pixel radius), and its adjoint is the transpose."""
    H, W = 5, 7
    x = rng.standard_normal((H * f, W * f) + tail).astype(np.float32)
    y = gauss_down(device, cla.to_device(device.queue, x), f, sigma).get()
    assert y.shape == (H, W) + tail
    np.testing.assert_allclose(y, ref.gauss_down(x.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    v = rng.standard_normal((H, W) + tail).astype(np.float32)
    vx = gauss_up(device, cla.to_device(device.queue, v), f, sigma).get()
    assert vx.shape == x.shape
    np.testing.assert_allclose(vx, ref.gauss_up(v.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    assert float((y * v).sum()) == pytest.approx(float((x * vx).sum()), rel=1e-4, abs=1e-4)  # <Ax, v> = <x, A'v>


def test_gauss_filter_keeps_a_constant_and_spreads_an_edge(device):
    """Normalised weights: a constant image stays that constant (borders too); a sharp vertical edge at a pixel
    boundary becomes the Gaussian's integral across it (σ 0.5 px: the pixels beside it at 0.5 ± 0.35)."""
    f, H, W = 4, 6, 8
    x = np.full((H * f, W * f), 0.7, np.float32)
    np.testing.assert_allclose(gauss_down(device, cla.to_device(device.queue, x), f, 0.5).get(), 0.7, rtol=1e-6)
    x[:, : 4 * f] = 0.0
    x[:, 4 * f:] = 1.0
    y = gauss_down(device, cla.to_device(device.queue, x), f, 0.5).get()
    from scipy.special import erf

    # supersample average of the Gaussian CDF at the pixel centres' distances 0.5 and 1.5 from the edge
    assert y[2, 3] == pytest.approx(1 - y[2, 4], abs=1e-6)
    assert 0.1 < y[2, 4] - 0.5 < 0.45 and y[2, 5] > 0.97 and y[2, 2] < 0.03
    assert y[2, 4] == pytest.approx(ref.gauss_down(x.astype(np.float64), f, 0.5)[2, 4], abs=1e-6)
    assert 0.5 + 0.5 * erf(0.5 / (0.5 * np.sqrt(2))) == pytest.approx(y[2, 4], abs=0.05)


def test_gauss_filter_rejects_bad_input(device):
    x = cla.zeros(device.queue, (6, 6, 3), np.float32)
    with pytest.raises(ValueError, match="sigma"):
        gauss_down(device, x, 2, 0.0)
    with pytest.raises(ValueError, match="H\\*f"):
        gauss_down(device, x, 4, 0.5)
    with pytest.raises(ValueError, match="factor"):
        gauss_up(device, x, 0, 0.5)


@pytest.mark.parametrize("f", [1, 2, 3, 4])
@pytest.mark.parametrize("sigma", [0.5, 0.3, 1.1])
def test_gauss_rgba_forward_and_adjoint(device, rng, f, sigma):
    """The radiance and its alpha in one four-channel pass: each equals the dense reference (borders included) and,
    bit for bit, the per-array filter (the same sums in the same order); the adjoint is the transpose, with the
    alpha's cotangent given or absent (None: zero)."""
    H, W = 5, 7
    q = device.queue
    x = rng.standard_normal((H * f, W * f, 3)).astype(np.float32)
    a = rng.standard_normal((H * f, W * f)).astype(np.float32)
    y, ya = (r.get() for r in gauss_down_rgba(device, cla.to_device(q, x), cla.to_device(q, a), f, sigma))
    assert y.shape == (H, W, 3) and ya.shape == (H, W)
    np.testing.assert_allclose(y, ref.gauss_down(x.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(ya, ref.gauss_down(a.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(y, gauss_down(device, cla.to_device(q, x), f, sigma).get())
    np.testing.assert_array_equal(ya, gauss_down(device, cla.to_device(q, a), f, sigma).get())
    v = rng.standard_normal((H, W, 3)).astype(np.float32)
    va = rng.standard_normal((H, W)).astype(np.float32)
    vx, vxa = (r.get() for r in gauss_up_rgba(device, cla.to_device(q, v), cla.to_device(q, va), f, sigma))
    assert vx.shape == x.shape and vxa.shape == a.shape
    np.testing.assert_allclose(vx, ref.gauss_up(v.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(vxa, ref.gauss_up(va.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(vx, gauss_up(device, cla.to_device(q, v), f, sigma).get())
    np.testing.assert_array_equal(vxa, gauss_up(device, cla.to_device(q, va), f, sigma).get())
    lhs = float((y * v).sum() + (ya * va).sum())
    assert lhs == pytest.approx(float((x * vx).sum() + (a * vxa).sum()), rel=1e-4, abs=1e-4)  # <Ax, v> = <x, A'v>
    vx0, vxa0 = (r.get() for r in gauss_up_rgba(device, cla.to_device(q, v), None, f, sigma))
    np.testing.assert_array_equal(vx0, vx)
    assert not vxa0.any()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("H,W,f,sigma", [(4, 17, 3, 0.49), (3, 24, 3, 1.1), (2, 9, 2, 0.3), (5, 8, 1, 0.5),
                                         (1, 33, 4, 0.7)])
def test_gauss_rgba_blocks_of_eight(device, device64, rng, dtype, H, W, f, sigma):
    """The row passes take eight outputs of a row per work-item and the column adjoint the F rows of an output
    (``gauss4_rows_down8`` / ``gauss4_rows_up8`` / ``gauss4_cols_upF``): rows of whole blocks, a partial last block
    and a single partial block give the per-array filters' values bit for bit, in float32 and float64, and the
    dense reference."""
    dev = device if dtype == np.float32 else device64
    q = dev.queue
    x = rng.standard_normal((H * f, W * f, 3)).astype(dtype)
    a = rng.standard_normal((H * f, W * f)).astype(dtype)
    y, ya = (r.get() for r in gauss_down_rgba(dev, cla.to_device(q, x), cla.to_device(q, a), f, sigma))
    np.testing.assert_array_equal(y, gauss_down(dev, cla.to_device(q, x), f, sigma).get())
    np.testing.assert_array_equal(ya, gauss_down(dev, cla.to_device(q, a), f, sigma).get())
    np.testing.assert_allclose(y, ref.gauss_down(x.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)
    v = rng.standard_normal((H, W, 3)).astype(dtype)
    va = rng.standard_normal((H, W)).astype(dtype)
    vx, vxa = (r.get() for r in gauss_up_rgba(dev, cla.to_device(q, v), cla.to_device(q, va), f, sigma))
    np.testing.assert_array_equal(vx, gauss_up(dev, cla.to_device(q, v), f, sigma).get())
    np.testing.assert_array_equal(vxa, gauss_up(dev, cla.to_device(q, va), f, sigma).get())
    np.testing.assert_allclose(vxa, ref.gauss_up(va.astype(np.float64), f, sigma), rtol=1e-5, atol=1e-6)


def test_gauss_rgba_float64_central_differences(device64, rng):
    """The four-channel filter's adjoint against central differences of its float64 forward, in the radiance and
    in the alpha."""
    f, H, W, sigma = 3, 3, 4, 0.5
    q = device64.queue
    x, a = rng.standard_normal((H * f, W * f, 3)), rng.standard_normal((H * f, W * f))
    v, va = rng.standard_normal((H, W, 3)), rng.standard_normal((H, W))
    g, ga = (r.get() for r in gauss_up_rgba(device64, cla.to_device(q, v), cla.to_device(q, va), f, sigma))

    def loss(x_, a_):
        y, ya = gauss_down_rgba(device64, cla.to_device(q, x_), cla.to_device(q, a_), f, sigma)
        return float((y.get() * v).sum() + (ya.get() * va).sum())

    h = 1e-6
    for idx in [(0, 0, 0), (4, 7, 1), (8, 11, 2), (5, 2, 0)]:
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        assert (loss(xp, a) - loss(xm, a)) / (2 * h) == pytest.approx(g[idx], rel=1e-7, abs=1e-9)
    for idx in [(0, 0), (4, 7), (8, 11), (2, 9)]:
        ap, am = a.copy(), a.copy()
        ap[idx] += h
        am[idx] -= h
        assert (loss(x, ap) - loss(x, am)) / (2 * h) == pytest.approx(ga[idx], rel=1e-7, abs=1e-9)


def test_gauss_rgba_rejects_bad_input(device):
    q = device.queue
    x, a = cla.zeros(q, (6, 6, 3), np.float32), cla.zeros(q, (6, 6), np.float32)
    with pytest.raises(ValueError, match="\\[H, W, 3\\]"):
        gauss_down_rgba(device, cla.zeros(q, (6, 6, 4), np.float32), a, 2, 0.5)
    with pytest.raises(ValueError, match="alpha"):
        gauss_down_rgba(device, x, cla.zeros(q, (6, 5), np.float32), 2, 0.5)
    with pytest.raises(ValueError, match="alpha"):
        gauss_down_rgba(device, x, cla.zeros(q, (6, 6), np.float64), 2, 0.5)
    with pytest.raises(ValueError, match="H\\*f"):
        gauss_down_rgba(device, x, a, 4, 0.5)
    with pytest.raises(ValueError, match="sigma"):
        gauss_down_rgba(device, x, a, 2, 0.0)
    with pytest.raises(ValueError, match="factor"):
        gauss_up_rgba(device, x, a, 0, 0.5)
