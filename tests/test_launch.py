"""Kernels called by name (triplet_cl.ops.launch) and the kernel memo keyed by defines."""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from triplet_cl.ops.launch import launch, signature

SRC = """
__kernel void scale(__global REAL* out, __global const REAL* x, const int n, const REAL s, __local REAL* tmp
#if HAS_OFFSET
                    , const REAL offset
#endif
                    )
{
    const int i = get_global_id(0);
#if !HAS_OFFSET
    const REAL offset = (REAL)0;
#endif
    tmp[get_local_id(0)] = x[i < n ? i : 0];
    if (i < n) out[i] = s * tmp[get_local_id(0)] + offset;
}
"""


def _kernel(device, has_offset: bool):
    opts = device.build_options({"HAS_OFFSET": int(has_offset)}, np.float32)
    return cl.Kernel(device.build_source(SRC, opts, "<test scale>"), "scale")


def test_arguments_bound_by_name_in_any_order(device):
    k = _kernel(device, False)
    assert [s[0] for s in signature(k)] == ["out", "x", "n", "s", "tmp"]
    q = device.queue
    x = cla.to_device(q, np.arange(10, dtype=np.float32))
    out = cla.zeros(q, 16, np.float32)
    launch(k, q, (16,), (16,), s=2.5, n=10, tmp=cl.LocalMemory(64), x=x, out=out)  # python scalars converted
    assert np.array_equal(out.get()[:10], 2.5 * np.arange(10, dtype=np.float32))
    k2 = _kernel(device, True)  # an optional input compiled in is one more parameter
    launch(k2, q, (16,), (16,), out=out, x=x, n=10, s=1.0, tmp=cl.LocalMemory(64), offset=np.float64(0.5))
    assert np.array_equal(out.get()[:10], np.arange(10, dtype=np.float32) + 0.5)


def test_missing_unknown_and_wrong_arguments_are_named(device):
    k = _kernel(device, False)
    q = device.queue
    x = cla.zeros(q, 16, np.float32)
    with pytest.raises(TypeError, match=r"scale: missing arguments \['tmp'\], unknown arguments \['offset'\]"):
        launch(k, q, (16,), (16,), out=x, x=x, n=16, s=1.0, offset=0.5)
    with pytest.raises(TypeError, match="x is a buffer"):
        launch(k, q, (16,), (16,), out=x, x=np.zeros(16, np.float32), n=16, s=1.0, tmp=cl.LocalMemory(64))
    with pytest.raises(TypeError, match="tmp is __local memory"):
        launch(k, q, (16,), (16,), out=x, x=x, n=16, s=1.0, tmp=x)


def test_kernel_memo_by_defines(device):
    a = device.kernel("shade", "shade_fwd", _shade_defines(), np.float32)
    b = device.kernel("shade", "shade_fwd", dict(reversed(list(_shade_defines().items()))), np.float32)
    assert a is b
    c = device.kernel("shade", "shade_fwd", {**_shade_defines(), "HAS_EYE": 1}, np.float32)
    assert c is not a and [s[0] for s in signature(c)][-2:] == ["eye", "rgb"]


def _shade_defines():
    from triplet_cl.lights import kernel_defines
    from triplet_cl.materials import get_brdf

    return {"ENV_MAX_DEG": 2, "RED_W": 16, "HAS_VLIGHT": 0, "HAS_VIS": 0, "HAS_REFL": 0, "HAS_EYE": 0,
            **get_brdf("cook_torrance").kernel_defines(), **kernel_defines()}
