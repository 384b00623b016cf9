"""Shared host-side helpers of the ops: input validation and device arrays.

Every op wrapper validates at the boundary and raises ``ValueError`` naming the argument, what
was expected and what was found. Device data are ``pyopencl.array.Array`` objects (``cla``).
"""

from __future__ import annotations

import functools
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..autodiff.arrays import to_host as to_host  # re-exported for the ops (its one home: autodiff/arrays.py)

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
        check_contiguous(name, arr)
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


def real_of(a, name: str = "data") -> np.dtype:
    """The REAL of floating data: ``float32`` or ``float64`` (``a.dtype``); anything else is a
    ``ValueError`` naming ``name``. Selects the ``-DREAL=`` build of the kernels."""
    dt = np.dtype(a.dtype)
    if dt not in (np.float32, np.float64):
        raise ValueError(f"{name} must be float32 or float64 data, got {dt}")
    return dt


def check_contiguous(name: str, arr) -> None:
    """A device array the kernels will read is C-contiguous: they index its buffer as dense rows, so a strided view
    (``a[::2]``, ``a[..., ::2]``) was read as if it were one, silently (battery 10: a projection 33.7 px off)."""
    if isinstance(arr, cla.Array) and arr.size and not arr.flags.c_contiguous:
        raise ValueError(f"{name} must be a C-contiguous device array, got a strided view (strides {arr.strides}): "
                         "pass a contiguous copy")


def to_device(queue: cl.CommandQueue, a, name: str = "a device array") -> cla.Array:
    """A device copy of a host array (device arrays pass through unchanged, if C-contiguous)."""
    if isinstance(a, cla.Array):
        check_contiguous(name, a)
        return a
    return cla.to_device(queue, np.ascontiguousarray(a))


def device_empty(queue: cl.CommandQueue, shape, dtype, allocator=None) -> cla.Array:
    """``pyopencl.array.empty(queue, shape, dtype, allocator=allocator)``, the same array, built through pyopencl's
    fast constructor: its checked one validates the shape with ``np.array`` / ``np.any`` per call (~20 µs), and a
    training step allocates ~100 arrays (measured: 3 s of the demo's 21 s under a profiler)."""
    shape = (int(shape),) if isinstance(shape, (int, np.integer)) else tuple(int(s) for s in shape)
    dtype = np.dtype(dtype)
    size, stride, strides = 1, dtype.itemsize, []
    for s in reversed(shape):
        if s < 0:
            raise ValueError(f"negative dimensions are not allowed: {shape}")
        strides.append(stride)
        stride *= max(1, s)
        size *= s
    return cla.Array(None, shape, dtype, allocator=allocator, strides=tuple(reversed(strides)), _fast=True,
                     _size=size, _context=queue.context, _queue=queue)


def device_head(a: cla.Array, n: int) -> cla.Array:
    """``a[:n]`` (the first ``n`` rows, a view) through pyopencl's fast constructor (its ``__getitem__`` takes the
    checked one, as :func:`device_empty` says): the ``[P]`` views of the ``max(P, 1)``-row buffers."""
    n = int(n)
    if n == a.shape[0]:
        return a
    if not 0 <= n <= a.shape[0]:
        raise ValueError(f"device_head: {n} rows of an array of {a.shape[0]}")
    shape = (n,) + tuple(a.shape[1:])
    size = n
    for s in shape[1:]:
        size *= s
    return cla.Array(None, shape, a.dtype, allocator=a.allocator, data=a.base_data, offset=a.offset, strides=a.strides,
                     events=a.events, _fast=True, _size=size, _context=a.context, _queue=a.queue)


def device_rows(device, shape, dtype) -> cla.Array:
    """An array of ``shape`` (its first dimension may be 0: an empty view of a one-row buffer, so that kernels always
    get a valid buffer) from the device's pool (``device.allocator``: a training step's shapes recur)."""
    shape = (int(shape),) if isinstance(shape, (int, np.integer)) else tuple(int(x) for x in shape)
    full = device_empty(device.queue, (max(shape[0], 1),) + shape[1:], dtype, allocator=device.allocator)
    return device_head(full, shape[0])


def empty(queue: cl.CommandQueue, shape, dtype) -> cla.Array:
    """A device array; zero-sized shapes still get a valid (1-element) buffer for kernel args."""
    shape = tuple(int(s) for s in shape)
    if int(np.prod(shape)) == 0:
        arr = device_empty(queue, (1,), dtype)
        return arr[:0].reshape(shape) if len(shape) else arr
    return device_empty(queue, shape, dtype)


def buf(a: cla.Array | None, queue: cl.CommandQueue | None = None):
    """The ``cl.Buffer`` behind a device array, or a 1-element dummy for ``None``/empty arrays."""
    if a is None or a.size == 0:
        if a is not None and a.base_data is not None:
            return a.base_data
        if queue is None:
            raise ValueError("a queue is needed for a placeholder buffer")
        return device_empty(queue, (1,), np.float32).data
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


def c_max(C: int) -> int:
    """The ``C_MAX`` define of the kernels that keep ``C`` channels per fragment in private arrays
    (composite.cl, blend.cl): ``C`` rounded up to a multiple of 4, at least 4 (fewer program variants)."""
    return max(4, -(-C // 4) * 4)


def run_1d(device, kernel, n: int, *args) -> None:
    """Run a 1-D ``kernel`` over ``n`` items (:func:`grid_1d` sizes; nothing for ``n = 0``) with
    positional ``args`` (short argument lists; :func:`launch` binds long ones by name)."""
    if n > 0:
        kernel(device.queue, *grid_1d(n), *args)


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
        check_contiguous(name, a)
        if a.dtype != np.dtype(real):
            raise ValueError(f"{name} must have dtype {np.dtype(real)}, got {a.dtype}")
        return a
    return to_device(queue, check_real(name, a, shape, real, finite=False))


# ------------------------------------------------------------------------------------------------
# kernels called by name
# ------------------------------------------------------------------------------------------------

_SCALAR_TYPES = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16, "int": np.int32,
                 "uint": np.uint32, "long": np.int64, "ulong": np.uint64, "float": np.float32,
                 "double": np.float64, "REAL": None}  # None: the program's REAL
_QUALIFIERS = {"const", "__const", "__private", "private", "restrict", "__restrict", "volatile", "unsigned"}
_ADDRESS_SPACES = {"__global": "buffer", "global": "buffer", "__constant": "buffer", "constant": "buffer",
                   "__local": "local", "local": "local"}
LAUNCH_RESERVED = ("defines", "real")  # keyword arguments of launch(), so not usable as kernel parameter names


@dataclass(frozen=True)
class KernelParam:
    """One parameter of a ``__kernel`` signature: ``kind`` is ``"buffer"`` (a ``__global`` or
    ``__constant`` pointer), ``"local"`` (a ``__local`` pointer: pass a ``cl.LocalMemory``) or
    ``"scalar"`` (passed by value; ``ctype`` its C type, ``REAL`` included)."""

    name: str
    kind: str
    ctype: str


def _strip_comments(src: str) -> str:
    """C source without comments (newlines kept, so preprocessor lines stay lines)."""
    src = re.sub(r"/\*.*?\*/", lambda m: "\n" * m.group(0).count("\n"), src, flags=re.S)
    return re.sub(r"//[^\n]*", "", src)


def _defined(defines: dict | None) -> frozenset:
    """The names a build with ``defines`` defines (``Device.build_options``: ``False`` omits one)."""
    return frozenset(k for k, v in (defines or {}).items() if v is not False)


def _signature_text(body: str, defined: frozenset, where: str) -> str:
    """The parameter list ``body`` with its ``#ifdef`` / ``#ifndef`` / ``#if defined(X)`` /
    ``#else`` / ``#endif`` lines resolved against ``defined`` (nothing else is allowed in a signature)."""
    out, stack = [], []  # stack of (this branch active, parent active)
    for line in body.split("\n"):
        s = line.strip()
        if not s.startswith("#"):
            if all(a for a, _ in stack):
                out.append(line)
            continue
        m = re.fullmatch(r"#\s*(ifdef|ifndef|if|else|endif)\b\s*(.*)", s)
        if m is None:
            raise ValueError(f"{where}: unsupported preprocessor line in a kernel signature: {s!r}")
        op, arg = m.group(1), m.group(2).strip()
        parent = all(a for a, _ in stack)
        if op in ("ifdef", "ifndef", "if"):
            if op == "if":
                mm = re.fullmatch(r"(!?)\s*defined\s*\(?\s*(\w+)\s*\)?", arg)
                if mm is None:
                    raise ValueError(f"{where}: only '#if defined(X)' / '#if !defined(X)' are supported in a kernel "
                                     f"signature, got {s!r}")
                on = (mm.group(2) in defined) != bool(mm.group(1))
            else:
                on = (arg in defined) == (op == "ifdef")
            stack.append((on, parent))
        elif not stack:
            raise ValueError(f"{where}: #{op} without #if in a kernel signature")
        elif op == "else":
            on, par = stack.pop()
            stack.append((not on, par))
        else:
            stack.pop()
    if stack:
        raise ValueError(f"{where}: unterminated #if in a kernel signature")
    return "\n".join(out)


@functools.cache
def kernel_params(file: str, kernel: str, defined: frozenset = frozenset()) -> tuple[KernelParam, ...]:
    """The parameters of ``__kernel void <kernel>(...)`` in ``kernels_cl/<file>.cl``, parsed from the
    source once per set of ``defined`` names (conditional parameters: ``#ifdef NAME`` inside the
    signature). Raises ``ValueError`` when the kernel or a parameter type is not understood."""
    from ..device import kernel_dir

    path = kernel_dir() / f"{file}.cl"
    src = _strip_comments(path.read_text())
    m = re.search(r"__kernel\s+void\s+" + re.escape(kernel) + r"\s*\(", src)
    if m is None:
        raise ValueError(f"kernel {kernel!r} not found in {path}")
    depth, i = 1, m.end()
    while depth:
        if i >= len(src):
            raise ValueError(f"{path}: unbalanced parentheses in the signature of {kernel!r}")
        depth += {"(": 1, ")": -1}.get(src[i], 0)
        i += 1
    where = f"{path.name}:{kernel}"
    text = _signature_text(src[m.end():i - 1], defined, where)
    params = []
    for raw in (p.strip() for p in text.split(",")):
        if not raw or raw == "void":
            continue
        words = re.findall(r"\w+|\*", raw)
        name = words[-1]
        space = next((_ADDRESS_SPACES[w] for w in words if w in _ADDRESS_SPACES), None)
        if "*" in words:
            kind, ctype = space or "buffer", " ".join(w for w in words[:-1] if w not in _ADDRESS_SPACES)
        else:
            types = [w for w in words[:-1] if w not in _QUALIFIERS]
            ctype = ("u" if "unsigned" in words else "") + (types[-1] if types else "int")
            if ctype not in _SCALAR_TYPES:
                raise ValueError(f"{where}: parameter {name!r} has type {ctype!r}, which launch() cannot pass "
                                 f"(scalars: {', '.join(_SCALAR_TYPES)}; anything else as a buffer)")
            kind = "scalar"
        if name in LAUNCH_RESERVED:
            raise ValueError(f"{where}: parameter name {name!r} is reserved by launch()")
        params.append(KernelParam(name, kind, ctype))
    names = [p.name for p in params]
    if len(set(names)) != len(names):
        raise ValueError(f"{where}: duplicate parameter names {names}")
    return tuple(params)


def _converters(params: Sequence[KernelParam], real) -> tuple[tuple[str, type | None], ...]:
    """``(name, numpy scalar type or None for a buffer)`` per parameter, for :func:`bind_args`."""
    real = np.dtype(real)
    return tuple((p.name, None if p.kind != "scalar" else
                  (real.type if _SCALAR_TYPES[p.ctype] is None else np.dtype(_SCALAR_TYPES[p.ctype]).type))
                 for p in params)


@functools.cache
def _binding(file: str, kernel: str, defined: frozenset, real: str):
    """The parameters and their converters, once per (file, kernel, defined names, REAL)."""
    params = kernel_params(file, kernel, defined)
    return params, _converters(params, real)


def bind_args(params: Sequence[KernelParam], args: dict, real, queue: cl.CommandQueue, where: str = "kernel") -> list:
    """The positional argument list of a kernel call from ``args`` keyed by parameter name.

    Buffers take a device array (its buffer; ``None`` or an empty array: a 1-element placeholder,
    as :func:`buf`), a ``cl.MemoryObject`` or a ``cl.LocalMemory``; scalars take a number (or bool),
    converted to the parameter's C type (``REAL``: ``real``). Every parameter must be given, and
    nothing else (a ``ValueError`` lists the missing and unknown names and the signature).
    """
    return _bind(params, _converters(params, real), args, queue, where)


def _bind(params, conv, args: dict, queue, where: str) -> list:
    if len(args) != len(conv) or any(name not in args for name, _ in conv):
        missing = [p.name for p in params if p.name not in args]
        extra = sorted(set(args) - {p.name for p in params})
        sig = ", ".join(f"{p.ctype} {p.name}" for p in params)  # a pointer's ctype holds its '*'
        raise ValueError(f"{where}: missing arguments {missing}, unknown arguments {extra}; signature ({sig})")
    out = []
    for name, t in conv:
        v = args[name]
        if t is not None:
            if v is None:
                raise ValueError(f"{where}: scalar argument {name!r} is None")
            out.append(t(v))
        elif isinstance(v, cla.Array) and v.size:
            out.append(v.data)
        elif v is None or isinstance(v, cla.Array):
            out.append(buf(v, queue))
        elif isinstance(v, cl.MemoryObjectHolder | cl.LocalMemory):
            out.append(v)
        else:
            raise ValueError(f"{where}: argument {name!r} must be a device array, a cl buffer or None, "
                             f"got {type(v).__name__}")
    return out


def launch(device, file: str, kernel: str, global_size, local_size, /, defines: dict | None = None,
           real=np.float32, **args):
    """Run ``kernel`` of ``kernels_cl/<file>.cl`` with its arguments bound by name.

    ``launch(dev, "binning", "bin_count", *grid_1d(M), defines={"TILE": 8}, real=real, vs=vs, F=F, m=M, ...)``
    builds (or reuses) the program as ``device.kernel(file, kernel, defines, real)`` does, looks up
    the signature (:func:`kernel_params`, parsed once per file, kernel and set of defined names, so
    a parameter under ``#ifdef NAME`` exists only in builds that define ``NAME``) and passes
    ``args`` in its order, converted as :func:`bind_args` says. No argument order to keep in step
    with the ``.cl`` file by hand, and a missing or misspelt name is an error, not a wrong result.
    Any op may use it (kernel parameter names ``defines`` and ``real`` are reserved). Returns the
    ``cl.Event``.
    """
    params, conv = _binding(file, kernel, _defined(defines), np.dtype(real).str)
    k = device.kernel(file, kernel, defines, real)
    return k(device.queue, global_size, local_size, *_bind(params, conv, args, device.queue, f"{file}.cl:{kernel}"))
