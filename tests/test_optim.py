"""Adam: a hand-written reference on a quadratic, clipping, schedules, checkpoints and remap."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from triplet_cl.autodiff import Param

from triplet_cl.optim import Adam, Constant, ExponentialDecay, StepUp, schedule_from_dict, schedule_to_dict


def reference_adam(x0, grad_fn, lrs, b1, b2, eps, steps, max_norm=None):
    """Textbook Adam (Kingma & Ba) with PyTorch's eps placement and clip_grad_norm_."""
    x, m, v = x0.copy(), np.zeros_like(x0), np.zeros_like(x0)
    for t in range(1, steps + 1):
        g = grad_fn(x)
        if max_norm is not None:
            n = np.sqrt(np.sum(g * g))
            if n > max_norm:
                g = g * (max_norm / (n + 1e-6))
        m = b1 * m + (1 - b1) * g
        v = b2 * v + (1 - b2) * g * g
        mh, vh = m / (1 - b1**t), v / (1 - b2**t)
        x = x - lrs(t - 1) * mh / (np.sqrt(vh) + eps)
    return x


A = np.diag([1.0, 3.0, 10.0])


def quad_grad(x):  # f = ½ xᵀAx − 1ᵀx per row
    return x @ A - 1.0


def _run(opt, p, steps):
    for _ in range(steps):
        p.grad = quad_grad(p.data)
        opt.step()
        opt.zero_grad()


@pytest.mark.parametrize(
    ("lr", "max_norm"),
    [(0.05, None), (ExponentialDecay(0.1, 0.001, 20), None), (StepUp(Constant(0.01), {5: 5.0, 9: 0.5}), None),
     (0.05, 0.3)],
)
def test_adam_matches_reference(lr, max_norm, rng):
    x0 = rng.standard_normal((4, 3))
    p = Param(x0.copy(), "x")
    opt = Adam()
    opt.add_group("x", [p], lr=lr, betas=(0.8, 0.99), eps=1e-8, max_grad_norm=max_norm)
    _run(opt, p, 12)
    sched = opt.group("x").schedule
    np.testing.assert_allclose(p.data, reference_adam(x0, quad_grad, sched, 0.8, 0.99, 1e-8, 12, max_norm),
                               rtol=1e-12, atol=1e-14)
    if max_norm is not None:
        assert opt.group("x").last_grad_norm > max_norm  # clipping was active


def test_adam_converges_on_quadratic():
    p = Param(np.zeros((2, 3)), "x")
    opt = Adam()
    opt.add_group("x", [p], lr=ExponentialDecay(0.1, 1e-4, 2000))
    _run(opt, p, 2000)
    np.testing.assert_allclose(p.data, np.tile(1.0 / np.diag(A), (2, 1)), atol=1e-3)


def test_clipping_is_per_group_global_norm():
    a, b, c = Param(np.zeros(2), "a"), Param(np.zeros(2), "b"), Param(np.zeros(2), "c")
    opt = Adam()
    opt.add_group("ab", [a, b], lr=1.0, max_grad_norm=1.0)
    opt.add_group("c", [c], lr=1.0)
    a.grad, b.grad, c.grad = np.array([3.0, 0.0]), np.array([0.0, 4.0]), np.array([3.0, 4.0])
    opt.step()
    assert opt.group("ab").last_grad_norm == pytest.approx(5.0)
    # first Adam step moves by lr·sign(g) whatever the scale: check the moments instead
    np.testing.assert_allclose(opt.group("ab").exp_avg[0], 0.1 * np.array([3.0, 0.0]) / (5 + 1e-6))
    np.testing.assert_allclose(opt.group("c").exp_avg[0], 0.1 * np.array([3.0, 4.0]))


def test_schedules():
    e = ExponentialDecay(1e-2, 1e-4, 100)
    assert e(0) == pytest.approx(1e-2) and e(100) == pytest.approx(1e-4) and e(500) == pytest.approx(1e-4)
    assert e(50) == pytest.approx(1e-3)  # log-linear: the geometric mean halfway
    d = ExponentialDecay(1e-2, 1e-4, 100, delay_steps=10, delay_mult=0.01)
    assert d(0) == pytest.approx(1e-4) and d(10) == pytest.approx(e(10))
    s = StepUp(Constant(0.01), {10_000: 5.0})
    assert s(9_999) == pytest.approx(0.01) and s(10_000) == pytest.approx(0.05)
    for sched in (e, d, s):
        assert schedule_from_dict(schedule_to_dict(sched)) == sched
    opt = Adam()
    opt.add_group("x", [Param(np.zeros(1), "x")], lr=e)
    assert opt.lr("x") == pytest.approx(1e-2) and opt.lr("x", 100) == pytest.approx(1e-4)


def test_state_dict_roundtrip_resumes_identically(rng):
    x0 = rng.standard_normal((3, 3))

    def make():
        p = Param(x0.copy(), "x")
        opt = Adam()
        opt.add_group("x", [p], lr=StepUp(ExponentialDecay(0.1, 0.01, 10), {4: 2.0}), betas=(0.5, 0.999))
        return p, opt

    p1, o1 = make()
    _run(o1, p1, 10)
    p2, o2 = make()
    _run(o2, p2, 5)
    state = pickle.loads(pickle.dumps(o2.state_dict()))
    data = p2.data.copy()
    p3, o3 = make()
    p3.data[...] = data
    o3.group("x").schedule = Constant(123.0)  # overwritten by the checkpoint
    o3.load_state_dict(state)
    assert o3.t == 5
    _run(o3, p3, 5)
    np.testing.assert_allclose(p3.data, p1.data, rtol=1e-14)
    bad = o2.state_dict()
    bad["groups"]["x"]["exp_avg"] = [np.zeros((2, 3))]
    with pytest.raises(ValueError, match="does not match"):
        o3.load_state_dict(bad)


def test_remap_keeps_surviving_moments_and_zeroes_new_rows(rng):
    pos = Param(rng.standard_normal((5, 3)), "pos")
    col = Param(rng.standard_normal((5, 2)).astype(np.float32), "col")
    opt = Adam()
    opt.add_group("soup", [pos, col], lr=0.01)
    for _ in range(3):
        pos.grad, col.grad = rng.standard_normal((5, 3)), rng.standard_normal((5, 2))
        opt.step()
    g = opt.group("soup")
    m_old = [m.copy() for m in g.exp_avg]
    v_old = [v.copy() for v in g.exp_avg_sq]
    old_pos, old_col = pos.data.copy(), col.data.copy()
    # prune rows 1 and 3, duplicate row 4, add two brand-new rows
    index_map = np.array([0, 2, 4, 4, -1, -1])
    new_pos, new_col = rng.standard_normal((2, 3)), rng.standard_normal((2, 2))
    opt.remap("soup", index_map, {"pos": new_pos, "col": new_col})
    keep = index_map >= 0
    for k, (m0, v0) in enumerate(zip(m_old, v_old, strict=True)):
        np.testing.assert_array_equal(g.exp_avg[k][keep], m0[index_map[keep]])
        np.testing.assert_array_equal(g.exp_avg_sq[k][keep], v0[index_map[keep]])
        assert not g.exp_avg[k][~keep].any() and not g.exp_avg_sq[k][~keep].any()
        assert g.exp_avg[k].dtype == (np.float64, np.float32)[k]
    np.testing.assert_array_equal(pos.data[keep], old_pos[index_map[keep]])
    np.testing.assert_array_equal(pos.data[~keep], new_pos)
    np.testing.assert_array_equal(col.data[~keep], new_col.astype(np.float32))
    np.testing.assert_array_equal(col.data[keep], old_col[index_map[keep]])
    assert pos.grad is None and col.data.dtype == np.float32
    # full new arrays (a split that moves the children) are accepted too; the step still works
    opt.remap("soup", np.array([0, 0, 1]), [np.zeros((3, 3)), np.zeros((3, 2))])
    assert pos.data.shape == (3, 3) and g.exp_avg[0].shape == (3, 3)
    pos.grad, col.grad = np.ones((3, 3)), np.ones((3, 2))
    opt.step()
    assert np.isfinite(pos.data).all() and math.isfinite(float(col.data.sum()))


def test_remap_and_group_errors():
    p = Param(np.zeros((3, 2)), "p")
    opt = Adam()
    opt.add_group("g", [p], lr=0.1)
    with pytest.raises(ValueError, match="new_rows is required"):
        opt.remap("g", np.array([0, -1]))
    with pytest.raises(ValueError, match=r"index_map values must lie in \[-1, 2\]"):
        opt.remap("g", np.array([0, 3]))
    with pytest.raises(ValueError, match="group_name 'nope'"):
        opt.remap("nope", np.array([0]))
    with pytest.raises(ValueError, match=r"new_rows\[0\] must have shape"):
        opt.remap("g", np.array([0, -1]), [np.zeros((4, 2))])
    with pytest.raises(ValueError, match="name must be a new"):
        opt.add_group("g", [p])
    with pytest.raises(ValueError, match="lr must be"):
        opt.add_group("h", [Param(np.zeros(1), "q")], lr=-1.0)
    with pytest.raises(ValueError, match="betas"):
        opt.add_group("h", [Param(np.zeros(1), "q")], betas=(1.0, 0.9))


# ---- Adam as a device kernel (kernels_cl/adam.cl) -------------------------------------------------


def _twin_optimizers(rng, device, dtype):
    """The same three groups (a decaying schedule, a step-up schedule with clipping, a constant)
    on fresh parameters, once numpy and once on ``device``."""
    x0 = {"V": rng.standard_normal((40, 3)), "mat": rng.standard_normal((40, 6)), "a": rng.standard_normal((40, 1)),
          "sh": rng.standard_normal((40, 6, 4))}
    out = []
    for dev in (None, device):
        ps = {k: Param(v.astype(dtype), k) for k, v in x0.items()}
        opt = Adam(device=dev, device_min_size=1)  # the kernel at every size
        kw = {"betas": (0.5, 0.999), "eps": 1e-15}
        opt.add_group("V", [ps["V"]], lr=ExponentialDecay(1e-2, 1e-4, 30), **kw)
        opt.add_group("mat", [ps["mat"], ps["a"]], lr=StepUp(Constant(0.05), {3: 5.0}), **kw)
        opt.add_group("sh", [ps["sh"]], lr=0.005, max_grad_norm=1.0, **kw)
        out.append((ps, opt))
    return out


def _assert_same(a, b, exact):
    (pa, oa), (pb, ob) = a, b
    assert oa.t == ob.t
    for k in pa:
        if exact:
            np.testing.assert_array_equal(pb[k].data, pa[k].data, err_msg=k)
        else:
            np.testing.assert_allclose(pb[k].data, pa[k].data, rtol=1e-6, atol=1e-6, err_msg=k)
    for name, g in oa.groups.items():
        h = ob.groups[name]
        assert h.last_grad_norm == g.last_grad_norm
        for m0, m1 in zip(g.exp_avg + g.exp_avg_sq, h.exp_avg + h.exp_avg_sq, strict=True):
            assert m1.dtype == m0.dtype
            if exact:
                np.testing.assert_array_equal(m1, m0)
            else:
                np.testing.assert_allclose(m1, m0, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_device_adam_matches_numpy(device, rng, dtype):
    """adam.cl against the numpy step, bit for bit on PoCL (schedules, clipping, a group of two
    parameters, a parameter without a gradient), through a prune + split remap and a state_dict
    round trip into a fresh device optimizer."""
    if dtype == np.float64 and not device.fp64:
        pytest.skip("device has no fp64")
    exact = "portable" in device.info.platform_name.lower() or "pocl" in device.info.platform_name.lower()
    a, b = _twin_optimizers(rng, device, dtype)
    g = b[1].group("mat")
    assert b[1]._on_device(b[0]["mat"].data, g.exp_avg[0], g.exp_avg_sq[0])  # the kernel path, not numpy

    def run(steps, skip_alpha=False):
        for _ in range(steps):
            grads = {k: 3.0 * rng.standard_normal(p.data.shape) for k, p in a[0].items()}
            for ps, opt in (a, b):
                for k, p in ps.items():
                    p.grad = None if skip_alpha and k == "a" else grads[k].astype(dtype)
                opt.step()
                opt.zero_grad()
            _assert_same(a, b, exact)

    run(5)
    assert a[1].group("sh").last_grad_norm > 1.0  # clipping was active
    run(2, skip_alpha=True)
    # density control: prune rows 1 and 5, duplicate 7, two brand-new rows (zero moments)
    idx = np.array([0, 2, 3, 4, 6, 7, 7] + list(range(8, 40)) + [-1, -1])
    new = {"V": rng.standard_normal((2, 3)), "mat": rng.standard_normal((2, 6)), "a": rng.standard_normal((2, 1)),
           "sh": rng.standard_normal((2, 6, 4))}
    for _, opt in (a, b):
        opt.remap("V", idx, [new["V"]])
        opt.remap("mat", idx, {"mat": new["mat"], "a": new["a"]})
        opt.remap("sh", idx, [new["sh"]])
    run(4)
    # resume: a fresh device optimizer from the numpy one's state continues identically
    state = pickle.loads(pickle.dumps(a[1].state_dict()))
    ps_c = {k: Param(p.data.copy(), k) for k, p in a[0].items()}
    opt_c = Adam(device=device, device_min_size=1)
    opt_c.add_group("V", [ps_c["V"]], lr=1.0)
    opt_c.add_group("mat", [ps_c["mat"], ps_c["a"]], lr=1.0)
    opt_c.add_group("sh", [ps_c["sh"]], lr=1.0)
    opt_c.load_state_dict(state)
    b = (ps_c, opt_c)
    run(3)


def test_device_adam_keeps_numpy_for_small_parameters(device):
    """The kernel's fixed cost exceeds numpy's passes below ``DEVICE_MIN_SIZE`` elements: such parameters take the
    numpy update (the same bits), larger ones the kernel; ``device_min_size`` moves the line."""
    from triplet_cl.optim import DEVICE_MIN_SIZE

    small, big = np.zeros(DEVICE_MIN_SIZE - 1, np.float32), np.zeros(DEVICE_MIN_SIZE, np.float32)
    opt = Adam(device=device)
    assert not opt._on_device(small, small, small) and opt._on_device(big, big, big)
    assert Adam(device=device, device_min_size=1)._on_device(small, small, small)
    assert not Adam()._on_device(big, big, big)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")  # the deliberate overflow
def test_device_adam_finiteness_guard(device):
    """The kernel flags a parameter the update made NaN/Inf: NonFiniteStep("parameter") after the
    step, as the numpy path raises it; a NaN gradient stops both before any update."""
    from triplet_cl.optim import NonFiniteStep

    for dev in (None, device):
        a, b = Param(np.ones((4, 3), np.float32), "a"), Param(np.ones((5, 2), np.float32), "b")
        opt = Adam(device=dev, device_min_size=1)
        opt.add_group("a", [a], lr=0.1)
        opt.add_group("b", [b], lr=1e39)  # inf once rounded to float32: the update overflows
        a.grad, b.grad = np.ones((4, 3), np.float32), np.ones((5, 2), np.float32)
        with pytest.raises(NonFiniteStep) as ei:
            opt.step()
        assert (ei.value.group, ei.value.what) == ("b", "parameter")
        assert np.isfinite(a.data).all() and not np.isfinite(b.data).all()
        a.grad, b.grad = np.full((4, 3), np.nan, np.float32), np.ones((5, 2), np.float32)
        before = a.data.copy()
        with pytest.raises(NonFiniteStep) as ei:
            opt.step()
        assert (ei.value.group, ei.value.what) == ("a", "gradient")
        np.testing.assert_array_equal(a.data, before)


def test_lr_scale_multiplies_the_update_elementwise(rng):
    """``lr_scale``: the update of each element is the plain one times its factor (0 freezes it); a bad scale is
    refused when the group is added; with a device the scaled parameter is updated by numpy."""
    x0 = rng.normal(size=6)
    scale = np.array([1.0, 2.0, 0.5, 0.0, 10.0, 1.0])
    plain, scaled = Param(x0.copy(), "a"), Param(x0.copy(), "b")
    a, b = Adam(), Adam()
    a.add_group("p", [plain], lr=0.01)
    b.add_group("p", [scaled], lr=0.01, lr_scale=[scale])
    for _ in range(3):
        g = rng.normal(size=6)
        plain.grad, scaled.grad = g.copy(), g.copy()
        a.step()
        b.step()
    np.testing.assert_allclose(scaled.data - x0, (plain.data - x0) * scale, rtol=1e-12, atol=1e-15)
    for bad, what in (([np.ones(5)], "broadcast"), ([-np.ones(6)], ">= 0"), ([None, None], "one entry")):
        with pytest.raises(ValueError, match=what):
            Adam().add_group("p", [Param(x0.copy(), "c")], lr=0.01, lr_scale=bad)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_numpy_update_is_bit_for_bit_the_textbook_expressions(rng, dtype):
    """The in-place numpy update (two scratch arrays, no temporaries) against the plain expressions it
    replaced, evaluated here literally: identical bits for float32 and float64, with and without clipping,
    through a row-count change (density control) that needs a new scratch pair."""
    x0 = {"a": rng.standard_normal((50, 3)).astype(dtype), "b": rng.standard_normal((50, 6, 2)).astype(dtype)}
    ps = {k: Param(v.copy(), k) for k, v in x0.items()}
    opt = Adam()
    opt.add_group("a", [ps["a"]], lr=ExponentialDecay(1e-2, 1e-4, 30), betas=(0.5, 0.999), eps=1e-15)
    opt.add_group("b", [ps["b"]], lr=0.05, max_grad_norm=1.0)
    ref = {k: (v.copy(), np.zeros_like(v), np.zeros_like(v)) for k, v in x0.items()}
    for t in range(1, 9):
        if t == 5:  # prune / duplicate rows of "a"
            idx = np.r_[0:20, 25:50, 3, 3]
            opt.remap("a", idx)
            x, m, v = ref["a"]
            ref["a"] = (x[idx].copy(), m[idx].copy(), v[idx].copy())
        for p in ps.values():
            p.grad = (3.0 * rng.standard_normal(p.data.shape)).astype(np.float32)
        grads = {k: p.grad for k, p in ps.items()}
        opt.step()
        for k, g in opt.groups.items():
            x, m, v = ref[k]
            gr = grads[k]
            norm = math.sqrt(float(np.sum(np.square(gr, dtype=np.float64))))
            coef = g.max_grad_norm / (norm + 1e-6) if g.max_grad_norm is not None and norm > g.max_grad_norm else 1.0
            b1, b2 = g.betas
            lr, bc1, bc2 = g.schedule(t - 1), 1.0 - b1**t, 1.0 - b2**t
            gr = gr.astype(dtype, copy=False) * coef
            m *= b1
            m += (1.0 - b1) * gr
            v *= b2
            v += (1.0 - b2) * gr * gr
            x -= (lr / bc1) * m / (np.sqrt(v / bc2) + g.eps)
            np.testing.assert_array_equal(ps[k].data, x, err_msg=f"{k} step {t}")
            np.testing.assert_array_equal(g.exp_avg[0], m)
            np.testing.assert_array_equal(g.exp_avg_sq[0], v)
    assert opt.group("b").last_grad_norm > 1.0  # clipping was active


def test_gradient_norm_guard_tells_nan_and_inf_from_a_float32_overflow():
    """The finiteness guard's norm (a float32 dot product where the group does not clip): a NaN or an Inf gradient
    stops the step before any update; a gradient whose float32 square overflows (|g| ~ 1e20) is finite and steps
    (no NonFiniteStep), its norm taken in float64."""
    from triplet_cl.optim import NonFiniteStep

    for bad in (np.nan, np.inf):
        p = Param(np.ones(4, np.float32), "x")
        opt = Adam()
        opt.add_group("x", [p], lr=0.1)
        p.grad = np.array([1.0, bad, 0.0, 0.0], np.float32)
        with pytest.raises(NonFiniteStep) as ei:
            opt.step()
        assert ei.value.what == "gradient"
        np.testing.assert_array_equal(p.data, 1.0)  # nothing updated
    p = Param(np.ones(4, np.float32), "x")
    opt = Adam()
    opt.add_group("x", [p], lr=0.1)
    p.grad = np.array([3e20, -4e20, 0.0, 0.0], np.float32)
    with np.errstate(over="ignore", divide="ignore"):  # Adam's own float32 second moment overflows at this size
        opt.step()
    assert opt.group("x").last_grad_norm == pytest.approx(5e20, rel=1e-6)
    assert np.isfinite(p.data).all()
