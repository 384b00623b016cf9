"""Activations: values, float64 gradchecks on the tape, device arrays, bad input."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest
import scipy.special
from triplet_cl.autodiff import assert_gradcheck

from triplet_cl import activations as act

CASES = [
    ("sigmoid", act.Sigmoid, lambda x: scipy.special.expit(x)),
    ("softplus", act.Softplus, lambda x: np.log1p(np.exp(x))),
    ("exp", act.Exp, np.exp),
    ("normalize", act.Normalize, lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)),
]


@pytest.mark.parametrize(("name", "cls", "ref"), CASES)
def test_forward_matches_closed_form(name, cls, ref, rng):
    x = rng.standard_normal((7, 3)) * 3
    np.testing.assert_allclose(cls()(x), ref(x), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize(("name", "cls", "ref"), CASES)
def test_gradcheck(name, cls, ref, rng):
    x = rng.standard_normal((6, 3)) * 2
    assert_gradcheck(lambda v: cls()(v), {"x": x}, rtol=1e-6, atol=1e-9)


def test_softplus_and_sigmoid_do_not_overflow():
    x = np.array([-800.0, -50.0, 0.0, 50.0, 800.0])
    y = act.softplus(x)
    assert np.isfinite(y).all() and y[-1] == 800.0 and y[0] == 0.0
    assert np.isfinite(act.sigmoid(x)).all()
    np.testing.assert_allclose(act.softplus_bwd(x, np.ones_like(x)), act.sigmoid(x))


@pytest.mark.parametrize(("name", "cls", "ref"), CASES)
def test_device_arrays_match_host(name, cls, ref, device64, rng):
    x = rng.standard_normal((9, 3))
    v = rng.standard_normal((9, 3))
    xd, vd = cla.to_device(device64.queue, x), cla.to_device(device64.queue, v)
    fn_h, fn_d = cls(), cls()
    from triplet_cl.autodiff import Context

    ch, cd = Context((True,)), Context((True,))
    yh, yd = fn_h.forward(ch, x), fn_d.forward(cd, xd)
    assert isinstance(yd, cla.Array)
    np.testing.assert_allclose(yd.get(), yh, rtol=1e-12, atol=1e-14)
    vxd = fn_d.backward(cd, vd)
    assert isinstance(vxd, cla.Array)
    np.testing.assert_allclose(vxd.get(), fn_h.backward(ch, v), rtol=1e-12, atol=1e-14)


def test_normalize_is_smooth_at_zero():
    x = np.zeros((2, 3))
    assert np.isfinite(act.normalize(x)).all()
    assert np.isfinite(act.normalize_bwd(x, np.ones_like(x))).all()
