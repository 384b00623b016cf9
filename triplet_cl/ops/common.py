"""Shared host-side helpers of the ops: input validation and device arrays.

Every op wrapper validates at the boundary and raises ``ValueError`` naming the argument, what
was expected and what was found. Device data are ``pyopencl.array.Array`` objects (``cla``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

Array = np.ndarray | cla.Array


def _shape_str(shape: Sequence) -> str:
    return "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"


def check_shape(name: str, arr, shape: Sequence[int | None]) -> None:
    """Raise ``ValueError`` unless ``arr.shape`` matches ``shape`` (``None`` = any size)."""
    if len(arr.shape) != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape, strict=False)):
        raise ValueError(f"{name} must have shape {_shape_str(shape)}, got {list(arr.shape)}")


def check_real(name: str, arr, shape: Sequence[int | None], real=np.float32, finite: bool = True) -> np.ndarray:
    """Validate a floating host array and return it C-contiguous in dtype ``real``.

    Accepts any floating dtype (cast to ``real``); rejects integer/bool/object data, wrong shapes
    and (when ``finite``) NaN or Inf values.
    """
    if isinstance(arr, cla.Array):
        check_shape(name, arr, shape)
        if arr.dtype != np.dtype(real):
            raise ValueError(f"{name} must be a device array of dtype {np.dtype(real)}, got {arr.dtype}")
        return arr
    a = np.asarray(arr)
    if a.dtype.kind != "f":
        raise ValueError(f"{name} must be a floating-point array, got dtype {a.dtype}")
    check_shape(name, a, shape)
    a = np.ascontiguousarray(a, dtype=real)
    if finite and a.size and not np.isfinite(a).all():
        bad = int((~np.isfinite(a)).sum())
        raise ValueError(f"{name} must be finite, found {bad} NaN/Inf value(s)")
    return a


def check_faces(name: str, faces, num_vertices: int) -> np.ndarray:
    """Validate a face index array ``[M, 3]`` (any integer dtype) and return it as int32."""
    f = np.asarray(faces)
    if f.dtype.kind not in "iu":
        raise ValueError(f"{name} must be an integer array, got dtype {f.dtype}")
    check_shape(name, f, (None, 3))
    if f.size:
        lo, hi = int(f.min()), int(f.max())
        if lo < 0 or hi >= num_vertices:
            raise ValueError(
                f"{name} indices must lie in [0, {num_vertices - 1}] (the vertex count is {num_vertices}), "
                f"found values in [{lo}, {hi}]"
            )
    if num_vertices > np.iinfo(np.int32).max:
        raise ValueError(f"{name}: too many vertices for int32 indices ({num_vertices})")
    return np.ascontiguousarray(f, dtype=np.int32)


def to_device(queue: cl.CommandQueue, a) -> cla.Array:
    """A device copy of a host array (device arrays pass through unchanged)."""
    if isinstance(a, cla.Array):
        return a
    return cla.to_device(queue, np.ascontiguousarray(a))


def to_host(a) -> np.ndarray:
    """A host copy (numpy arrays pass through unchanged)."""
    return a.get() if isinstance(a, cla.Array) else np.asarray(a)


def empty(queue: cl.CommandQueue, shape, dtype) -> cla.Array:
    """A device array; zero-sized shapes still get a valid (1-element) buffer for kernel args."""
    shape = tuple(int(s) for s in shape)
    if int(np.prod(shape)) == 0:
        arr = cla.empty(queue, (1,), dtype)
        return arr[:0].reshape(shape) if len(shape) else arr
    return cla.empty(queue, shape, dtype)


def buf(a: cla.Array | None, queue: cl.CommandQueue | None = None):
    """The ``cl.Buffer`` behind a device array, or a 1-element dummy for ``None``/empty arrays."""
    if a is None or a.size == 0:
        if a is not None and a.base_data is not None:
            return a.base_data
        if queue is None:
            raise ValueError("a queue is needed for a placeholder buffer")
        return cla.empty(queue, (1,), np.float32).data
    return a.data


CONST_CACHE_SIZE = 512


def const_array(device, a: np.ndarray) -> cla.Array:
    """A small constant host array (camera parameters, a background colour) on the device, cached
    per device by value (LRU of ``CONST_CACHE_SIZE``): uploading it on every call is a blocking
    write, which makes the host wait for every kernel queued before it."""
    from collections import OrderedDict

    a = np.ascontiguousarray(a)
    cache = device.cached(("const-arrays",), OrderedDict)
    key = (a.dtype.str, a.shape, a.tobytes())
    d = cache.get(key)
    if d is None:
        d = cache[key] = cla.to_device(device.queue, a)
        if len(cache) > CONST_CACHE_SIZE:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return d


LOCAL_1D = 64  # work-group size of 1-D launches over a data-dependent count


def grid_1d(n: int) -> tuple[tuple[int], tuple[int]]:
    """``(global, local)`` sizes of a 1-D launch over ``n`` items (the kernel skips ids ≥ n).

    A fixed work-group size matters on PoCL: it compiles a kernel once per work-group size, and
    with ``local=None`` it picks a divisor of the global size, so a launch over the fragments or
    the (tile, face) entries of every new view compiled a new variant (895 compilations of
    ``interpolate_fwd`` in one 1500-step demo run from a cold cache)."""
    return (round_up(max(int(n), 1), LOCAL_1D),), (LOCAL_1D,)


def round_up(n: int, m: int) -> int:
    """``n`` rounded up to a multiple of ``m``."""
    return ((int(n) + m - 1) // m) * m


def fragment_array(queue: cl.CommandQueue, name: str, a, shape, real) -> cla.Array | None:
    """A per-fragment array on the device (``None`` passes through). Shape and dtype are checked,
    values are not: slots beyond a pixel's count are undefined by contract (may hold NaN)."""
    if a is None:
        return None
    if isinstance(a, cla.Array):
        check_shape(name, a, shape)
        if a.dtype != np.dtype(real):
            raise ValueError(f"{name} must have dtype {np.dtype(real)}, got {a.dtype}")
        return a
    return to_device(queue, check_real(name, a, shape, real, finite=False))
