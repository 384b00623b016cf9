"""The tape: recording, reverse accumulation, host/device mixing, gradcheck and its report."""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pyopencl.clmath as clmath
import pytest
from triplet_cl.autodiff import Function, Param, Tape, Variable, assert_gradcheck, gradcheck

from triplet_cl.activations import Normalize, Sigmoid, Softplus
from triplet_cl.losses import L1Loss, PhotometricLoss


class Mul(Function):
    """``a * b`` elementwise (host or device)."""

    def forward(self, ctx, a, b):
        ctx.save(a, b)
        return a * b

    def backward(self, ctx, v):
        a, b = ctx.saved
        return v * b, v * a


class Sum(Function):
    def forward(self, ctx, a):
        ctx.shape = a.shape
        return np.asarray(a.sum())

    def backward(self, ctx, v):
        return np.full(ctx.shape, float(v))


class Upload(Function):
    """Host → device; the adjoint goes back to the host."""

    def __init__(self, queue):
        self.queue = queue

    def forward(self, ctx, a):
        return cla.to_device(self.queue, np.ascontiguousarray(a))

    def backward(self, ctx, v):
        return v.get()


class Download(Function):
    def forward(self, ctx, a):
        ctx.queue = a.queue
        return a.get()

    def backward(self, ctx, v):
        return cla.to_device(ctx.queue, np.ascontiguousarray(v))


class DeviceTanh(Function):
    """A device op built from pyopencl array maths: ``tanh`` with adjoint ``v (1 − y²)``."""

    def forward(self, ctx, a):
        ctx.y = clmath.tanh(a)
        return ctx.y

    def backward(self, ctx, v):
        return v * (1.0 - ctx.y * ctx.y)


def test_chain_accumulates_and_matches_closed_form(rng):
    x = Param(rng.standard_normal(5), "x")
    with Tape() as tape:
        y = Mul()(x, x)  # x used twice by one call
        z = Mul()(y, x)  # and once more: z = x³
        s = Sum()(z)
    assert len(tape) == 3 and s.creator is not None and x.is_leaf
    tape.backward(s)
    np.testing.assert_allclose(x.grad, 3 * x.data**2, rtol=1e-12)
    assert len(tape) == 0  # cleared by default


def test_a_cleared_tape_frees_its_arrays_without_the_collector(rng):
    """After ``backward`` (or ``clear``) the intermediates and the arrays the contexts saved are freed by reference
    counting: a node and its outputs referenced each other, and a training step's device arrays stayed allocated
    until Python's cyclic collector ran (the memory pool then allocated new buffers every step). An output keeps its
    creator: it is still no leaf, and a second backward is refused as before."""
    import gc
    import weakref

    x = Param(rng.standard_normal(5), "x")
    gc.disable()
    try:
        with Tape() as tape:
            y = Mul()(x, x)
            s = Sum()(y)
        saved = weakref.ref(y.creator.ctx.saved[1])
        y_data = weakref.ref(y.data)
        saved_x = y.creator.ctx.saved[0]  # x's own data: alive while x is
        tape.backward(s)
        del y
        assert y_data() is None, "the intermediate output's array"
        assert saved() is x.data or saved() is None
        assert saved_x is x.data and not s.is_leaf
        with pytest.raises(ValueError, match="not produced by a call recorded on this tape"):
            tape.backward(s)
    finally:
        gc.enable()


def test_grad_accumulates_over_backward_calls_until_zero_grad(rng):
    x = Param(rng.standard_normal(4), "x")
    for _ in range(2):
        with Tape() as tape:
            s = Sum()(Mul()(x, x))
        tape.backward(s)
    np.testing.assert_allclose(x.grad, 2 * (2 * x.data))
    x.zero_grad()
    assert x.grad is None


def test_retain_allows_a_second_backward(rng):
    x = Param(rng.standard_normal(3), "x")
    with Tape() as tape:
        s = Sum()(Mul()(x, x))
    tape.backward(s, retain=True)
    tape.backward(s, v_output=np.asarray(2.0))
    np.testing.assert_allclose(x.grad, 3 * 2 * x.data)


def test_unrelated_calls_are_not_differentiated(rng):
    calls = []

    class Spy(Mul):
        def backward(self, ctx, v):
            calls.append(1)
            return super().backward(ctx, v)

    x = Param(rng.standard_normal(3), "x")
    with Tape() as tape:
        Spy()(x, x)  # does not lead to the output
        s = Sum()(x)
    tape.backward(s)
    assert calls == []
    np.testing.assert_allclose(x.grad, np.ones(3))


def test_constants_and_plain_calls():
    const = np.arange(3.0)
    x = Param(np.ones(3), "x")
    with Tape() as tape:
        s = Sum()(Mul()(x, const))  # a constant second input gets no adjoint
    tape.backward(s)
    np.testing.assert_allclose(x.grad, const)
    out = Mul()(np.ones(2), np.ones(2))  # no Variable in: plain value out, nothing recorded
    assert isinstance(out, np.ndarray)
    v = Mul()(Variable(np.ones(2)), np.ones(2))  # Variables without requires_grad: not recorded
    assert isinstance(v, Variable) and v.creator is None


def test_wrong_adjoint_shape_raises_naming_the_op():
    class Bad(Function):
        def forward(self, ctx, a):
            return np.asarray(a.sum())

        def backward(self, ctx, v):
            return np.ones(7)

    x = Param(np.ones(3), "x")
    with Tape() as tape:
        s = Bad()(x)
    with pytest.raises(ValueError, match=r"Bad\.backward.*shape \[7\]"):
        tape.backward(s)


def test_backward_rejects_foreign_outputs_and_bad_seed():
    x = Param(np.ones(3), "x")
    with Tape():
        s = Sum()(x)
    with pytest.raises(ValueError, match="not produced"):
        Tape().backward(s)
    with Tape() as tape:
        y = Mul()(x, x)
    with pytest.raises(ValueError, match="v_output"):
        tape.backward(y, v_output=np.ones(4))


def test_activation_then_loss_end_to_end(rng):
    """sigmoid(raw albedo) → photometric loss against a target: gradcheck through the tape."""
    raw = rng.standard_normal((12, 13, 3))
    target = rng.random((12, 13, 3))
    assert_gradcheck(lambda r: PhotometricLoss(0.2)(Sigmoid()(r), target), {"raw": raw}, rtol=1e-5, atol=1e-9)


def test_multi_input_chain_with_normalize_and_softplus(rng):
    a, b = rng.standard_normal((4, 1, 3)), rng.standard_normal((4, 1, 3))
    target = rng.random((4, 1, 3))  # an [H=4, W=1, C=3] "image"

    def f(a, b):  # b reaches the loss along two paths (through n and directly)
        n = Normalize()(Mul()(a, Softplus()(b)))
        return L1Loss()(Mul()(n, Softplus()(b)), target)

    rep = assert_gradcheck(f, {"a": a, "b": b})
    assert rep["a"].checked == 12 and rep["b"].checked == 12


def test_mixed_device_and_host_chain(device64, rng):
    """host Param → Upload → device tanh → device sigmoid → Download → host L1; and a device Param
    used by both a device op and (downloaded) a host op, so adjoints of both kinds meet."""
    q = device64.queue
    x = rng.standard_normal((5, 4, 3))
    target = rng.random((5, 4, 3))

    def f_host_param(x):
        d = DeviceTanh()(Upload(q)(x))
        return L1Loss()(Download()(Sigmoid()(d)), target)

    assert_gradcheck(f_host_param, {"x": x}, rtol=1e-6, atol=1e-10)

    xd = cla.to_device(q, x)

    def f_device_param(x):
        a = Download()(DeviceTanh()(x))  # device path
        b = Download()(x)  # host path of the same variable
        return Sum()(Mul()(a, b))

    rep = assert_gradcheck(f_device_param, {"x": xd}, rtol=1e-6, atol=1e-10)
    assert rep.ok

    p = Param(xd, "x")
    with Tape() as tape:
        s = Sum()(Mul()(Download()(DeviceTanh()(p)), Download()(p)))
    tape.backward(s)
    assert isinstance(p.grad, cla.Array)  # the leaf keeps the kind of its data


def test_gradcheck_reports_a_wrong_adjoint(rng):
    class WrongSquare(Function):
        def forward(self, ctx, a):
            ctx.a = a
            return a * a

        def backward(self, ctx, v):
            out = 2 * ctx.a * v
            out[1] *= 1.5  # a planted bug at index 1
            return out

    x = rng.standard_normal(4) + 2.0
    rep = gradcheck(lambda a: Sum()(WrongSquare()(a)), {"x": x})
    assert not rep.ok and not rep["x"].ok
    assert rep["x"].worst[0].index == (1,)
    np.testing.assert_allclose(rep["x"].worst[0].numeric, 2 * x[1], rtol=1e-6)
    text = str(rep)
    assert "FAIL" in text and "(1,)" in text and "analytic" in text
    with pytest.raises(AssertionError, match="FAILED"):
        assert_gradcheck(lambda a: Sum()(WrongSquare()(a)), {"x": x})


def test_gradcheck_per_input_tolerances_and_sampling(rng):
    x, y = rng.standard_normal(50), rng.standard_normal(50)
    rep = gradcheck(lambda a, b: Sum()(Mul()(a, b)), {"x": x, "y": y}, rtol={"x": 1e-3}, max_checks=10)
    assert rep.ok and rep["x"].rtol == 1e-3 and rep["y"].rtol == 1e-5
    assert rep["x"].checked == 10 and rep["x"].total == 50
    with pytest.raises(ValueError, match="'x'"):
        gradcheck(lambda a: Sum()(a), {"x": np.arange(3)})


def test_leaf_adjoints_added_after_the_pass_in_order():
    """The tape adds leaves' adjoints once the pass is over, in the order they came (a device adjoint of a host
    leaf downloaded without a wait, a ``Deferred`` resolved there): the same sums as adding them on the spot."""
    import numpy as np
    from triplet_cl.autodiff import Function, Param, Tape
    from triplet_cl.autodiff.arrays import Deferred

    calls = []

    class Twice(Function):
        def forward(self, ctx, x):
            return 2.0 * x

        def backward(self, ctx, v):
            def late(v=v):
                calls.append("resolved")
                return 2.0 * np.asarray(v)

            return Deferred(np.shape(v), late)

    x = Param(np.array([1.0, -3.0]), "x")
    with Tape() as tape:
        y = Twice()(x)
        z = Twice()(y)  # noqa: F841 - only y's adjoint reaches x through the first call
    tape.backward(y, np.array([0.5, 0.25]))
    assert calls == ["resolved"]
    np.testing.assert_array_equal(x.grad, [1.0, 0.5])
