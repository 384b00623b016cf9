"""Kernels called by name (``ops.common.launch``): the signature parsed from the ``.cl`` source,
conditional parameters under ``#ifdef``, and clear errors for missing or unknown arguments."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_raster import cam, soup
from triplet_cl.ops.common import _signature_text, grid_1d, kernel_params, launch
from triplet_cl.ops.project import camera_params, project


def test_signature_parsed_with_its_defines():
    base = [p.name for p in kernel_params("fragment_bwd", "fragment_bwd", frozenset())]
    assert base[:8] == ["entry_setup", "F", "tile_off", "frag_face", "frag_entry", "frag_bary", "frag_depth",
                        "frag_count"]
    assert "v_bary_out" in base and "partial_mom" not in base and "attr" not in base and "v_win" not in base
    full = {p.name: p for p in kernel_params("fragment_bwd", "fragment_bwd",
                                             frozenset({"ATTR", "V_BARY_IN", "V_DEPTH", "V_WIN", "GEOMETRY"}))}
    assert {"attr", "v_out", "C", "v_bary_in", "v_depth", "v_win", "partial_mom", "v_sigma_tile"} <= set(full)
    assert "v_bary_out" not in full
    assert (full["C"].kind, full["C"].ctype) == ("scalar", "int")
    assert (full["sigma"].kind, full["sigma"].ctype) == ("scalar", "REAL")
    assert full["attr"].kind == "buffer"


def test_signature_preprocessor_lines():
    body = "int a,\n#ifdef X\nint b,\n#else\nint c,\n#endif\n#if !defined(Y)\nint d,\n#endif\nint e"
    assert _signature_text(body, frozenset(), "t").split() == ["int", "a,", "int", "c,", "int", "d,", "int", "e"]
    assert _signature_text(body, frozenset({"X", "Y"}), "t").split() == ["int", "a,", "int", "b,", "int", "e"]
    with pytest.raises(ValueError, match="unsupported preprocessor"):
        _signature_text("int a,\n#define Z 1\nint b", frozenset(), "t")
    with pytest.raises(ValueError, match="unterminated"):
        _signature_text("int a,\n#ifdef X\nint b", frozenset(), "t")


def test_launch_binds_by_name(device, rng):
    V, _ = soup(rng)
    c = cam()
    n = len(V)
    Vd = project(device, V.astype(np.float32), c)  # the op's own (positional) launch
    import pyopencl.array as cla

    Vw = cla.to_device(device.queue, V.astype(np.float32))
    cp = cla.to_device(device.queue, camera_params(c, np.float32))
    out = cla.empty(device.queue, (n, 3), np.float32)
    # keyword order is irrelevant
    launch(device, "project", "project_fwd", *grid_1d(n), vs=out, n=n, cam=cp, V=Vw)
    np.testing.assert_array_equal(out.get(), Vd.get())
    with pytest.raises(ValueError, match=r"missing arguments \['n'\]"):
        launch(device, "project", "project_fwd", *grid_1d(n), vs=out, cam=cp, V=Vw)
    with pytest.raises(ValueError, match=r"unknown arguments \['m'\]"):
        launch(device, "project", "project_fwd", *grid_1d(n), vs=out, n=n, m=n, cam=cp, V=Vw)
    with pytest.raises(ValueError, match="not found"):
        kernel_params("project", "no_such_kernel")


def test_kernel_memo_by_defines(device):
    """Device.kernel memoises by the defines (any order); False (omitted) and 0 (defined) stay apart."""
    from triplet_cl.lights import kernel_defines
    from triplet_cl.materials import get_brdf
    from triplet_cl.ops.common import kernel_params

    base = {"ENV_MAX_DEG": 2, "RED_W": 16, "HAS_VLIGHT": False, "HAS_VIS": False, "HAS_REFL": False,
            "NUM_LIGHTS": 1, "LIGHT_TABLE": "0,0,0,0",  # one light (type 0 at offset 0): ops/shade.py _table_defines
            **get_brdf("cook_torrance").kernel_defines(), **kernel_defines()}
    a = device.kernel("shade", "shade_fwd", {**base, "HAS_EYE": False})
    b = device.kernel("shade", "shade_fwd", dict(reversed(list({**base, "HAS_EYE": False}.items()))))
    assert a is b
    c = device.kernel("shade", "shade_fwd", {**base, "HAS_EYE": True})
    assert c is not a
    d = device.kernel("shade", "shade_fwd", {**base, "HAS_EYE": 0})  # -DHAS_EYE=0 defines it
    assert d is not a
    defined = frozenset(k for k, v in base.items() if v is not False) | {"HAS_EYE"}
    names = [p.name for p in kernel_params("shade", "shade_fwd", defined)]
    assert names[-2:] == ["eye", "rgb"] and "vis" not in names


@pytest.mark.parametrize("shape", [(7,), (5, 3), (4, 0, 2), (0,), (2, 3, 4), 6])
def test_device_empty_and_head_are_pyopencl_arrays(device, shape):
    """``device_empty`` / ``device_head`` (pyopencl's fast constructor, no per-call shape checks) build the arrays that
    ``cla.empty`` and ``a[:n]`` build: shape, dtype, strides, size, nbytes, offset; a head is a view (writes go through
    to the buffer); a negative dimension or too many rows is refused."""
    import pyopencl.array as cla

    from triplet_cl.ops.common import device_empty, device_head, device_rows

    q = device.queue
    for dt in (np.float32, np.int32, np.float64):
        a, b = device_empty(q, shape, dt, allocator=device.allocator), cla.empty(q, shape, dt)
        for k in ("shape", "dtype", "strides", "size", "nbytes", "offset"):
            assert getattr(a, k) == getattr(b, k), k
        assert a.flags.c_contiguous and a.queue is q and a.allocator is device.allocator
    base = cla.to_device(q, np.arange(24, dtype=np.float32).reshape(8, 3))
    for n in (0, 1, 5, 8):
        h, ref = device_head(base, n), base[:n]
        for k in ("shape", "dtype", "strides", "size", "nbytes", "offset"):
            assert getattr(h, k) == getattr(ref, k), (n, k)
        np.testing.assert_array_equal(h.get(), ref.get())
    device_head(base, 2).fill(-1.0)
    assert (base.get()[:2] == -1).all() and (base.get()[2:] >= 6).all()
    for shape, want in (((0, 3), (0, 3)), ((4, 2), (4, 2)), (0, (0,)), (5, (5,))):  # pooled, first dim may be 0
        r = device_rows(device, shape, np.float32)
        assert r.shape == want and r.base_data is not None and r.allocator is device.allocator
    with pytest.raises(ValueError, match="negative"):
        device_empty(q, (3, -1), np.float32)
    with pytest.raises(ValueError, match="rows"):
        device_head(base, 9)
