"""sRGB transfer + encoded-space compositing (kernels_cl/color.cl): forward, VJP, float64 FD, tape."""

from __future__ import annotations

import numpy as np
import pytest
from triplet_cl.autodiff import Param, Tape

from tests.gradients import cs_grad, fd_grad
from tests.reference import color as ref
from triplet_cl.ops import color

BG = np.array([1.0, 0.3, 0.0])


def _inputs(rng, H=7, W=9):
    A = rng.uniform(0, 1, (H, W))
    A[0, :3] = [0.0, 1e-8, 1.0]  # empty pixel, below the guard, opaque
    u = rng.uniform(0, 1.3, (H, W, 3))  # straight linear colour (also above 1: over-exposed)
    u[1, 0] = [0.0, 0.001, 0.0031]  # the linear segment of the transfer
    return u * A[..., None], A


def test_transfer_matches_the_standard_and_inverts():
    x = np.linspace(0, 1, 1001)
    y = color.srgb_encode(x)
    assert y[0] == 0 and y[-1] == pytest.approx(1.0, abs=1e-12)
    assert color.srgb_encode(0.5) == pytest.approx(0.735356983, abs=1e-8)  # IEC 61966-2-1
    assert color.srgb_encode(0.214041140) == pytest.approx(0.5, abs=1e-8)
    np.testing.assert_allclose(color.srgb_decode(y), x, atol=1e-12)
    np.testing.assert_allclose(y, ref.srgb_encode(x), atol=1e-15)


def test_forward_float32(device, rng):
    C, A = _inputs(rng)
    got = color.srgb_composite_host(C, A, BG, device=device)
    want = ref.srgb_composite(C, A, BG)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got[0, 0], BG, atol=1e-7)  # nothing covers: the background
    np.testing.assert_allclose(got[0, 2], ref.srgb_encode(C[0, 2]), rtol=1e-5)  # opaque: the encoded colour


def test_vjp_float32_vs_reference(device, rng):
    C, A = _inputs(rng)
    v = rng.standard_normal(C.shape)
    v_C, v_A = color.srgb_composite_backward_host(C, A, BG, v, device=device)
    want_C = cs_grad(lambda x: np.sum(ref.srgb_composite(x, A, BG) * v), C)
    want_A = cs_grad(lambda x: np.sum(ref.srgb_composite(C, x, BG) * v), A)
    np.testing.assert_allclose(v_C, want_C, rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(v_A, want_A, rtol=2e-4, atol=2e-4)


def test_vjp_float64_central_differences(device64, rng):
    C, A = _inputs(rng, 4, 5)
    A[0, :2] = 0.3  # keep every entry away from the kinks (the guard, the knee) for the differences
    C[1, 0] = [0.2, 0.3, 0.4]
    _check_float64_differences(device64, rng, C, A, clip=False)


def _check_float64_differences(device64, rng, C, A, clip):
    """The float64 kernel VJP of a random cotangent against central differences of the float64 forward."""
    v = rng.standard_normal(C.shape)
    kw = {"device": device64, "real": np.float64, "clip": clip}
    v_C, v_A = color.srgb_composite_backward_host(C, A, BG, v, **kw)
    kf = kw

    def f_C(x):
        return float(np.sum(color.srgb_composite_host(x, A, BG, **kf) * v))

    def f_A(x):
        return float(np.sum(color.srgb_composite_host(C, x, BG, **kf) * v))

    np.testing.assert_allclose(v_C, fd_grad(f_C, C, 1e-7), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(v_A, fd_grad(f_A, A, 1e-7), rtol=1e-6, atol=1e-7)


def test_tape_function_propagates_both_inputs(device64, rng):
    import pyopencl.array as cla

    C, A = _inputs(rng, 3, 4)
    pc, pa = Param(C, "C"), Param(A, "A")
    fn = color.SRGBComposite(device64, BG, np.float64)
    with Tape() as tape:
        out = fn(pc, pa)
    assert isinstance(out.data, cla.Array)
    np.testing.assert_allclose(out.data.get(), ref.srgb_composite(C, A, BG), rtol=1e-12, atol=1e-14)
    v = rng.standard_normal(C.shape)
    tape.backward(out, v)
    v_C, v_A = color.srgb_composite_backward_host(C, A, BG, v, device=device64, real=np.float64)
    np.testing.assert_allclose(np.asarray(pc.grad.get() if hasattr(pc.grad, "get") else pc.grad), v_C, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(pa.grad.get() if hasattr(pa.grad, "get") else pa.grad), v_A, rtol=1e-12)


def test_bad_shapes_raise(device):
    with pytest.raises(ValueError, match="A must have shape"):
        color.srgb_composite_host(np.zeros((2, 3, 3)), np.zeros((3, 2)), BG, device=device)
    with pytest.raises(ValueError, match="background"):
        color.srgb_composite_host(np.zeros((2, 3, 3)), np.zeros((2, 3)), [np.nan, 0, 0], device=device)


def _clip_inputs(rng, H=6, W=7):
    """Straight colours on both sides of the clip at u = 1 but away from it (the kink) for the differences."""
    C, A = _inputs(rng, H, W)
    u = rng.uniform(0.05, 0.9, (H, W, 3))
    u[::2, :, 0] = rng.uniform(1.1, 2.0, u[::2, :, 0].shape)  # over-exposed in red on every other row
    u[1, 0] = [0.0, 0.001, 0.0031]
    A = np.where(A < 1e-6, A, np.maximum(A, 0.05))
    return u * A[..., None], A


def test_sensor_clip_forward_and_vjp(device, rng):
    """SRGB_CLIP: encoded colour = min(s(u), 1) (forward against the numpy reference); the adjoint takes the unclipped
    curve's slope (straight-through: a saturated channel still passes its cotangent back) with the clipped value in
    v_A: v_C against complex-step derivatives of the unclipped reference, both against the reference adjoint."""
    C, A = _clip_inputs(rng)
    got = color.srgb_composite_host(C, A, BG, device=device, clip=True)
    want = ref.srgb_composite(C, A, BG, clip=True)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    assert not np.allclose(got, color.srgb_composite_host(C, A, BG, device=device))  # the clip did something
    v = rng.standard_normal(C.shape)
    v_C, v_A = color.srgb_composite_backward_host(C, A, BG, v, device=device, clip=True)
    sat = C / np.maximum(A, 1e-6)[..., None] >= 1
    v_up = np.where(sat, np.maximum(v, 0.0), v)  # above the clip only what lowers the value passes
    want_C = cs_grad(lambda x: np.sum(ref.srgb_composite(x, A, BG) * v_up), C)  # the unclipped curve's
    np.testing.assert_allclose(v_C, want_C, rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(v_C, ref.srgb_composite_clip_adjoint(C, A, BG, v)[0], rtol=2e-4, atol=2e-4)
    np.testing.assert_allclose(v_A, ref.srgb_composite_clip_adjoint(C, A, BG, v)[1], rtol=2e-4, atol=2e-4)
    assert sat.any() and np.all(v_C[sat & (v > 0)] != 0)  # no trap: a saturated channel can still be lowered
    assert np.all(v_C[sat & (v < 0)] == 0)  # ... and is never pushed further up


def test_sensor_clip_float64_central_differences(device64, rng):
    """The float64 v_C is the unclipped forward's central differences (the straight-through slope) of the cotangent
    with its upward part dropped above the clip (one-sided); v_A equals the
    reference adjoint to rounding (with the clipped value, it is no function's derivative above the clip); below the
    clip everywhere, both are the clipped forward's central differences."""
    C, A = _clip_inputs(rng, 4, 5)
    A[0, :2] = 0.3
    C[0, :2] = np.array([[0.2, 0.3, 1.5], [1.6, 0.1, 0.5]]) * 0.3  # straight u on both sides of 1
    v = rng.standard_normal(C.shape)
    kw = {"device": device64, "real": np.float64}
    v_C, v_A = color.srgb_composite_backward_host(C, A, BG, v, clip=True, **kw)

    v_up = np.where(C / np.maximum(A, 1e-6)[..., None] >= 1, np.maximum(v, 0.0), v)

    def f_C(x):
        return float(np.sum(color.srgb_composite_host(x, A, BG, **kw) * v_up))

    np.testing.assert_allclose(v_C, fd_grad(f_C, C, 1e-7), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(v_A, ref.srgb_composite_clip_adjoint(C, A, BG, v)[1], rtol=1e-10, atol=1e-12)
    below = np.where(C / np.maximum(A, 1e-6)[..., None] >= 1, 0.5 * C, C)  # every channel under the clip
    _check_float64_differences(device64, rng, below, A, clip=True)


def test_sensor_clip_pulls_down_only_where_the_photo_is_not_clipped(device64):
    """The point of the straight-through adjoint, through the photometric L1 term: a render over-exposed (u = 1.5) is
    not pulled down where the photo is clipped (it reads 1 like the render: zero cotangent), and is pulled down
    where the photo is not clipped (0.4): with the clip's zero slope it had no gradient there either (a trap)."""
    C = np.array([[[1.5, 0.2, 0.2], [1.5, 0.2, 0.2]]])
    A = np.ones((1, 2))
    out = color.srgb_composite_host(C, A, BG, device=device64, real=np.float64, clip=True)
    assert out[0, 0, 0] == 1.0 and out[0, 1, 0] == 1.0
    photo = out.copy()  # encoded photo values: red clipped (1) in the first pixel, 0.4 in the second
    photo[0, 1, 0] = 0.4
    v = np.sign(out - photo)  # d|out - photo| / d out
    v_C, _ = color.srgb_composite_backward_host(C, A, BG, v, device=device64, real=np.float64, clip=True)
    assert v_C[0, 0, 0] == 0.0  # clipped photo: the render is free above it
    assert v_C[0, 1, 0] > 0.1  # unclipped photo: descent lowers the over-exposed red


@pytest.mark.parametrize("clip", [False, True])
@pytest.mark.parametrize("real", [np.float32, np.float64])
def test_kept_root_is_bit_for_bit(device, device64, rng, clip, real):
    """The forward's roots (keep_root, what SRGBComposite keeps for its backward) change neither the image nor the
    adjoint: the same bits as the pair without them (float32 and float64, with and without the clip)."""
    dev = device64 if real == np.float64 else device
    C, A = _clip_inputs(rng) if clip else _inputs(rng)
    Cd, Ad = color._device_pair(dev, C, A, np.dtype(real))
    v = color.to_device(dev.queue, rng.standard_normal(C.shape).astype(real))
    plain = color.srgb_composite(dev, Cd, Ad, BG, clip=clip).get()
    out, root = color.srgb_composite(dev, Cd, Ad, BG, clip=clip, keep_root=True)
    assert np.array_equal(out.get(), plain)
    u = C / np.maximum(A, color.ALPHA_EPS)[..., None]
    r = root.get()
    assert np.all(r[u <= 0.0031308] == 0) and np.allclose(r[u > 0.0031308], u[u > 0.0031308] ** (1 / 2.4), rtol=1e-5)
    for a, b in zip(color.srgb_composite_backward(dev, Cd, Ad, BG, v, clip=clip),
                    color.srgb_composite_backward(dev, Cd, Ad, BG, v, clip=clip, root=root), strict=True):
        assert np.array_equal(a.get(), b.get())
