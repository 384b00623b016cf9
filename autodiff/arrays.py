"""Array helpers that let numpy and ``pyopencl.array.Array`` data flow through the same graph.

Nothing here copies device data to the host unless two adjoints of different kinds must be added
(a host adjoint reaching a device variable is uploaded once; a device adjoint reaching a host
variable is downloaded once).
"""

from __future__ import annotations

import numpy as np

try:  # pyopencl is a dependency of the distribution; autodiff still works on numpy without it
    import pyopencl.array as cla
except ImportError:  # pragma: no cover
    cla = None


def is_device_array(a) -> bool:
    """True for a ``pyopencl.array.Array``."""
    return cla is not None and isinstance(a, cla.Array)


def is_array(a) -> bool:
    """True for data that can carry an adjoint: numpy arrays, numpy/python floats, device arrays."""
    return is_device_array(a) or isinstance(a, np.ndarray | np.floating | float | Deferred)


def shape_of(a) -> tuple[int, ...]:
    """The shape of an array or scalar (``()`` for python floats)."""
    return tuple(getattr(a, "shape", ()))


def to_host(a) -> np.ndarray:
    """A numpy view/copy of ``a`` (device arrays are downloaded, :class:`Deferred` values resolved)."""
    if isinstance(a, Deferred):
        return a.resolve()
    return a.get() if is_device_array(a) else np.asarray(a)


def like(value, reference):
    """``value`` converted to the kind (host/device) and dtype of ``reference``."""
    if is_device_array(reference):
        if is_device_array(value):
            return value if value.dtype == reference.dtype else value.astype(reference.dtype)
        host = np.ascontiguousarray(np.broadcast_to(np.asarray(value, reference.dtype), reference.shape))
        return cla.to_device(reference.queue, host)
    host = to_host(value)
    dtype = np.result_type(getattr(reference, "dtype", np.float64), np.float32)
    return np.asarray(host, dtype=dtype)


def ones_like(a):
    """An array of ones of the shape/kind/dtype of ``a`` (the default seed of a backward pass)."""
    if is_device_array(a):
        out = cla.empty_like(a)
        out.fill(1)
        return out
    return np.ones_like(np.asarray(a, dtype=np.result_type(getattr(a, "dtype", np.float64), np.float32)))


def accumulate(acc, new, reference):
    """``acc + new`` in the kind of ``reference`` (``acc`` may be None). Never mutates ``acc``."""
    new = like(new, reference)
    if acc is None:
        return new
    return acc + new


class Deferred:
    """An adjoint whose host value is not there yet (a non-blocking download, e.g. per-work-group partials still
    to be summed): ``shape`` is known, :meth:`resolve` waits and returns the numpy value. The tape adds it to a
    leaf's ``.grad`` at the end of the backward pass (in the order it came), so the host need not wait for the
    device in the middle of queueing the pass; anywhere else it is resolved on the spot."""

    __slots__ = ("shape", "_fn")

    def __init__(self, shape, fn):
        self.shape, self._fn = tuple(shape), fn

    def resolve(self) -> np.ndarray:
        return self._fn()


def download_deferred(a) -> Deferred:
    """A device array's host copy as a :class:`Deferred` (the copy is queued now, not waited for)."""
    if not a.flags.forc:
        return Deferred(a.shape, a.get)
    host, event = a.get_async()

    def done(host=host, event=event, keep=a):
        event.wait()
        return host

    return Deferred(a.shape, done)
