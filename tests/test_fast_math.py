"""``kernels_cl/common/fast_math.h``: the arithmetic replacements of builtins that PoCL's CPU device runs as
scalar library calls, held to the builtins' own accuracy against float64; and the sRGB root built on it."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from triplet_cl.ops import color

SRC = """
#include "real.h"
#include "fast_math.h"
__kernel void ours(__global const float* x, __global float* y) { const int i = get_global_id(0); y[i] = tl_log2(x[i]); }
__kernel void builtin(__global const float* x, __global float* y) { const int i = get_global_id(0); y[i] = log2(x[i]); }
"""


ROOT_BUILTIN = """
__kernel void root_builtin(__global const float* u, __global float* r) {
    const int i = get_global_id(0); r[i] = exp2(log2(u[i]) * (float)(1.0 / 2.4)); }
"""


def _log2_both(device, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    prg = device.build_source(SRC, device.build_options(None, np.float32), "test_fast_math")
    xd = cla.to_device(device.queue, x)
    out = []
    for name in ("ours", "builtin"):
        y = cla.empty(device.queue, x.shape, np.float32)
        cl.Kernel(prg, name)(device.queue, x.shape, None, xd.data, y.data)
        out.append(y.get())
    return out[0], out[1]


def test_log2_is_as_accurate_as_the_builtin(device):
    """tl_log2 over every binade of the normal floats (dense, and at the mantissa split sqrt(2), powers of two and
    the largest float) against float64: within 6e-7 + 0.5 ulp of the result, and no worse than the builtin's
    own largest error on the same values (+10 %); +inf and NaN stay as they are."""
    x = np.geomspace(np.float32(1.2e-38), np.float32(3e38), 400_003).astype(np.float32)
    specials = np.array([1, 2, 0.5, 1.4142135, 1.4142137, 0.70710677, 3.4028235e38, 1.1754944e-38, 0.0031308],
                        np.float32)
    with np.errstate(over="ignore"):  # the largest float's successor is inf (dropped below)
        x = np.concatenate([x, specials, np.nextafter(specials, np.float32(np.inf))])
    x = x[np.isfinite(x) & (x > 0)]
    ours, builtin = _log2_both(device, x)
    ref = np.log2(x.astype(np.float64))
    err, err_builtin = np.abs(ours - ref), np.abs(builtin - ref)
    assert np.all(err <= 6e-7 + 6e-8 * np.abs(ref)), (x[np.argmax(err)], err.max())
    # the same bound measured against the builtin on the values it is used for (the sRGB root's u in [knee, 1e6])
    near = (x >= 0.0031308) & (x <= 1e6)
    assert err[near].max() <= 1.1 * err_builtin[near].max() + 1e-9, (err[near].max(), err_builtin[near].max())
    odd, _ = _log2_both(device, np.array([np.inf, 1.0, np.nan], np.float32))
    assert odd[0] == np.inf and odd[1] == 0.0 and np.isnan(odd[2])


def test_a_nan_render_stays_nan_through_the_srgb_encoding(device):
    """A NaN (or +inf) linear colour comes out of the sRGB compositing non-finite, as with the builtins: the training's
    finiteness check on the rendered image sees it."""
    C = cla.to_device(device.queue, np.array([[np.nan, 0.5, np.inf]], np.float32))
    A = cla.to_device(device.queue, np.ones(1, np.float32))
    for keep in (False, True):
        out = color.srgb_composite(device, C, A, (1.0, 1.0, 1.0), keep_root=keep)
        out = (out[0] if keep else out).get()
        assert np.isnan(out[0, 0]) and np.isfinite(out[0, 1]) and not np.isfinite(out[0, 2])


def test_srgb_root_relative_error(device):
    """The float sRGB root u^(1/2.4) that color.cl keeps for its adjoint (exp of fast_math.h's log2) from the knee to
    1e4, relative to float64: below 3.5e-7 and no larger than the builtins' exp2(log2(u) / 2.4) on the same values
    (measured 3.1e-7 against 4.2e-7; the error grows with log2(u), whose float rounding both carry)."""
    u = np.geomspace(0.0032, 1e4, 200_001).astype(np.float32)
    C = cla.to_device(device.queue, np.repeat(u[:, None], 3, axis=1))
    A = cla.to_device(device.queue, np.ones(len(u), np.float32))
    _, root = color.srgb_composite(device, C, A, (0.0, 0.0, 0.0), keep_root=True)
    prg = device.build_source(ROOT_BUILTIN, device.build_options(None, np.float32), "test_fast_math")
    ud, yd = cla.to_device(device.queue, u), cla.empty(device.queue, u.shape, np.float32)
    cl.Kernel(prg, "root_builtin")(device.queue, u.shape, None, ud.data, yd.data)
    want = u.astype(np.float64) ** (1 / 2.4)
    rel = np.abs(root.get() / want[:, None] - 1).max()
    rel_builtin = np.abs(yd.get() / want - 1).max()
    assert rel < 3.5e-7 and rel <= rel_builtin, (rel, rel_builtin)
