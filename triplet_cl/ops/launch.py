"""Kernels called by name: keyword arguments bound to a kernel's parameters by their names.

``launch(kernel, queue, global_size, local_size, pos=..., P=..., ...)`` reads the parameter names,
address qualifiers and types of the built kernel (OpenCL kernel-argument info; every program is
built with ``-cl-kernel-arg-info``, see :meth:`~triplet_cl.device.Device.build_options`), orders
the keywords to match, and converts each value to what the parameter takes:

* ``__global`` pointer: a ``pyopencl.array.Array`` (its ``.data``) or a ``cl.MemoryObject``;
* ``__local`` pointer: a ``cl.LocalMemory``;
* scalar ``int``/``uint``/``long``/``float``/``double``: any Python or numpy number, converted to
  the parameter's exact C type (``REAL`` parameters follow the program's ``-DREAL``).

A missing or unknown name raises ``TypeError`` naming the kernel and the names, before any launch:
the order of the ``.cl`` signature is no longer repeated by hand. Optional inputs are compiled in or
out with defines (``#if HAS_VIS`` around the parameter), so an absent input is simply not passed.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

_SCALARS = {"int": np.int32, "uint": np.uint32, "unsigned int": np.uint32, "long": np.int64, "ulong": np.uint64,
            "float": np.float32, "double": np.float64, "short": np.int16, "char": np.int8, "uchar": np.uint8}
_SIGNATURES: dict[int, tuple] = {}


def signature(kernel: cl.Kernel) -> tuple[tuple[str, str, int], ...]:
    """``((name, type name, address qualifier), ...)`` of the kernel's parameters, in order (cached)."""
    sig = _SIGNATURES.get(id(kernel))
    if sig is None or sig[0] is not kernel:
        n = kernel.get_info(cl.kernel_info.NUM_ARGS)
        try:
            params = tuple((kernel.get_arg_info(i, cl.kernel_arg_info.NAME),
                            kernel.get_arg_info(i, cl.kernel_arg_info.TYPE_NAME).strip(),
                            kernel.get_arg_info(i, cl.kernel_arg_info.ADDRESS_QUALIFIER)) for i in range(n))
        except cl.Error as exc:  # built without -cl-kernel-arg-info
            raise RuntimeError(f"kernel {kernel.function_name}: no argument info (build it with "
                               "-cl-kernel-arg-info, as Device.build_options does)") from exc
        sig = (kernel, params)
        _SIGNATURES[id(kernel)] = sig
    return sig[1]


def _convert(kname: str, name: str, tname: str, aq: int, value):
    if tname.endswith("*"):
        if aq == cl.kernel_arg_address_qualifier.LOCAL:
            if not isinstance(value, cl.LocalMemory):
                raise TypeError(f"kernel {kname}: {name} is __local memory, pass a cl.LocalMemory")
            return value
        if isinstance(value, cla.Array):
            return value.data
        if isinstance(value, cl.MemoryObjectHolder) or value is None:
            return value
        raise TypeError(f"kernel {kname}: {name} is a buffer, got {type(value).__name__}")
    t = _SCALARS.get(tname)
    if t is None:  # a struct or vector passed by value: the caller gives the numpy value
        return value
    return t(value)


def launch(kernel: cl.Kernel, queue: cl.CommandQueue, global_size, local_size, /, **args) -> cl.Event:
    """Enqueue ``kernel`` with its parameters bound by name from ``args`` (see the module docstring)."""
    sig = signature(kernel)
    names = [s[0] for s in sig]
    missing = [n for n in names if n not in args]
    unknown = [k for k in args if k not in names]
    if missing or unknown:
        raise TypeError(f"kernel {kernel.function_name}: missing arguments {missing}, unknown arguments {unknown} "
                        f"(parameters: {names})")
    fn = kernel.function_name
    values = [_convert(fn, n, t, aq, args[n]) for n, t, aq in sig]
    return kernel(queue, global_size, local_size, *values)
