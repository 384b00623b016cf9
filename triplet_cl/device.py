"""The OpenCL device layer: device selection, one object holding context, queue and program cache.

Selection order (docs/ARCHITECTURE.md §4):

1. an explicit specification (``--device`` on the command line, the ``spec`` argument here),
2. else the ``TRIPLET_DEVICE`` environment variable,
3. else the first GPU of any platform, else the first CPU, else the first device of any kind.

A specification is either ``"P:D"`` (platform index, device index, as ``triplet devices`` prints
them) or a case-insensitive substring of ``"<platform name> <device name>"`` (``"pocl"``,
``"nvidia"``, ``"intel cpu"`` ...).

Programs are built from ``kernels_cl/<name>.cl`` with ``-I kernels_cl/common`` and ``-D`` defines
(always ``-DREAL=float|double``), memoised per (file, options) on each :class:`Device` and cached on
disk by PyOpenCL (its cache key covers the source, the options, the device and every header found
on the ``-I`` path).
"""

from __future__ import annotations

import functools
import os
import re
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DeviceSelectionError, KernelBuildError, NoOpenCLPlatformError

try:  # pyopencl is a hard dependency; import lazily-tolerant so that `--help` still works
    import pyopencl as cl
except ImportError as exc:  # pragma: no cover - only without the dependency installed
    raise ImportError(
        "triplet_cl needs pyopencl (pip install pyopencl) and an OpenCL driver"
    ) from exc


ENV_VAR = "TRIPLET_DEVICE"


@functools.cache
def kernel_dir() -> Path:
    """The folder holding the ``.cl`` sources and ``common/`` headers (looked up once: every kernel
    fetch builds its options from it, thousands of times per training run).

    Installed from a wheel the kernels live inside the package (``triplet_cl/kernels_cl``); in a
    source checkout (editable install) they live at the repository root (``kernels_cl/``).
    """
    here = Path(__file__).resolve().parent
    for cand in (here / "kernels_cl", here.parent / "kernels_cl"):
        if (cand / "common").is_dir():
            return cand
    raise FileNotFoundError(
        f"OpenCL kernel sources not found: looked for kernels_cl/ in {here} and {here.parent}"
    )


# ----------------------------------------------------------------------------------------------
# Enumeration
# ----------------------------------------------------------------------------------------------


POOL_HELD_LIMIT = 1 << 30  # bytes of freed device buffers the pool may keep for reuse (Device.release_held)


@dataclass(frozen=True)
class DeviceInfo:
    """What ``triplet devices`` prints about one OpenCL device."""

    platform_index: int
    device_index: int
    platform_name: str
    device_name: str
    type: str  # "GPU", "CPU", "ACCELERATOR", ...
    compute_units: int
    global_mem_bytes: int
    max_alloc_bytes: int
    fp64: bool
    opencl_c_version: str
    driver_version: str

    @property
    def index(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    @property
    def full_name(self) -> str:
        return f"{self.platform_name} {self.device_name}"


def _type_name(dev) -> str:
    t = dev.type
    for flag, name in (
        (cl.device_type.GPU, "GPU"),
        (cl.device_type.CPU, "CPU"),
        (cl.device_type.ACCELERATOR, "ACCELERATOR"),
    ):
        if t & flag:
            return name
    return "OTHER"


def _platforms():
    try:
        plats = cl.get_platforms()
    except cl.Error as exc:  # PLATFORM_NOT_FOUND_KHR when no ICD is registered
        raise NoOpenCLPlatformError(str(exc)) from exc
    if not plats:
        raise NoOpenCLPlatformError("pyopencl.get_platforms() returned no platform")
    return plats


def _enumerate():
    """[(DeviceInfo, cl.Platform, cl.Device)] for every device of every platform."""
    out = []
    for pi, plat in enumerate(_platforms()):
        try:
            devs = plat.get_devices()
        except cl.Error:  # a broken platform (e.g. a mis-installed ICD) must not hide the others
            continue
        for di, dev in enumerate(devs):
            info = DeviceInfo(
                platform_index=pi,
                device_index=di,
                platform_name=plat.name.strip(),
                device_name=dev.name.strip(),
                type=_type_name(dev),
                compute_units=int(dev.max_compute_units),
                global_mem_bytes=int(dev.global_mem_size),
                max_alloc_bytes=int(dev.max_mem_alloc_size),
                fp64=bool(dev.double_fp_config) or "cl_khr_fp64" in dev.extensions,
                opencl_c_version=str(getattr(dev, "opencl_c_version", dev.version)).strip(),
                driver_version=str(dev.driver_version).strip(),
            )
            out.append((info, plat, dev))
    if not out:
        raise NoOpenCLPlatformError("OpenCL platforms exist but none reports a device")
    return out


def list_devices() -> list[DeviceInfo]:
    """Every OpenCL device visible to this process, in (platform, device) index order."""
    return [info for info, _, _ in _enumerate()]


def _describe(entries) -> str:
    return "\n".join(
        f"  {info.index}  [{info.type}] {info.platform_name} / {info.device_name}" for info, _, _ in entries
    )


def resolve_spec(spec: str | None = None):
    """Pick a device; returns ``(DeviceInfo, cl.Platform, cl.Device)``.

    ``spec`` None falls back to ``$TRIPLET_DEVICE``, then to the first GPU, then the first CPU.
    Raises :class:`DeviceSelectionError` (listing every device) when the spec matches nothing.
    """
    entries = _enumerate()
    source = "--device"
    if spec is None or str(spec).strip() == "":
        spec = os.environ.get(ENV_VAR, "").strip() or None
        source = f"${ENV_VAR}"
    if spec is None:
        for wanted in ("GPU", "CPU"):
            for e in entries:
                if e[0].type == wanted:
                    return e
        return entries[0]

    spec = str(spec).strip()
    m = re.fullmatch(r"(\d+):(\d+)", spec)
    if m:
        p, d = int(m.group(1)), int(m.group(2))
        for e in entries:
            if e[0].platform_index == p and e[0].device_index == d:
                return e
        raise DeviceSelectionError(
            f"device index {spec!r} ({source}) does not exist; expected 'P:D' from this list:\n{_describe(entries)}"
        )
    if re.fullmatch(r"\d+", spec):  # a model number ("4090") as a whole number of a device's name; "1" matched
        # "OpenCL C 1.2" or "avx512" as a substring (battery 10): on two GPUs `--device 1` picked whichever held a 1
        for e in entries:
            if re.search(rf"(?<![\d.]){spec}(?![\d.])", e[0].full_name):
                return e
    if re.fullmatch(r"\d+", spec) or len(spec) < 2:  # "a": any name
        raise DeviceSelectionError(
            f"{spec!r} ({source}) is not a device: give 'P:D' (platform and device indices, e.g. '0:{spec}' if "
            f"{spec!r} meant a device of platform 0), a part of a device's name (a number only as a whole number "
            "in it, a model's), 'gpu' or 'cpu'; available "
            f"devices:\n{_describe(entries)}")
    needle = spec.lower()
    for e in entries:
        if needle in e[0].full_name.lower() or needle == e[0].type.lower():
            return e
    for e in entries:  # then the OpenCL C version: PoCL's platform is "Portable Computing Language", its "OpenCL C
        # 1.2 PoCL" (the README's `TRIPLET_DEVICE=pocl` matched nothing, a battery found)
        if needle in e[0].opencl_c_version.lower():
            return e
    raise DeviceSelectionError(
        f"no OpenCL device matches {spec!r} ({source}: a substring of the platform or device name or of its OpenCL C "
        "version, a type "
        f"'gpu'/'cpu', or 'P:D' indices); available devices:\n{_describe(entries)}"
    )


# ----------------------------------------------------------------------------------------------
# Device: context + queue + program cache
# ----------------------------------------------------------------------------------------------


def _format_define(key: str, value) -> str:
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", key):
        raise ValueError(f"kernel define name {key!r} is not a valid C identifier")
    if value is None or value is True:
        return f"-D{key}"
    if value is False:
        return ""
    return f"-D{key}={value}"


def declare_scalar_types(k: cl.Kernel, name: str, kernel_name: str, defines: dict | None, real) -> bool:
    """Declare the by-value parameters' types of ``kernel_name`` (``kernels_cl/<name>.cl``) to PyOpenCL, from its
    signature as :func:`~triplet_cl.ops.common.kernel_params` parses it (``REAL``: ``real``). Why: without them PyOpenCL
    hands each numpy scalar to ``clSetKernelArg`` through the buffer protocol, ~7 µs an argument on every launch
    (PoCL, this machine: a launch with 8 scalars and 12 buffers 88 µs, declared 9 µs, the same argument bytes). A
    signature the parser does not read, or whose parameter count is not the built kernel's, is left undeclared (the
    plain path, as before). Returns whether the types were declared."""
    from .ops.common import _converters, _defined, kernel_params

    try:
        params = kernel_params(name, kernel_name, _defined(defines))
    except (ValueError, OSError):
        return False
    if len(params) != k.get_info(cl.kernel_info.NUM_ARGS):
        return False
    k.set_scalar_arg_dtypes([t for _, t in _converters(params, real)])
    return True


class Device:
    """One OpenCL device with its context, in-order queue and program/kernel memo.

    Attributes:
        info: the :class:`DeviceInfo` of the device.
        ctx, queue: the ``pyopencl`` context and command queue.
        fp64: whether ``-DREAL=double`` programs can be built here.
        build_count: how many programs this object has built (each (file, options) once).
    """

    def __init__(self, info: DeviceInfo, platform, device):
        self.info = info
        self.platform = platform
        self.cl_device = device
        self.ctx = cl.Context([device])
        self.queue = cl.CommandQueue(self.ctx)
        self.fp64 = info.fp64
        self._programs: dict[tuple[str, tuple[str, ...]], cl.Program] = {}
        self._kernels: dict[tuple[str, tuple[str, ...], str], cl.Kernel] = {}
        self._by_defines: dict[tuple, cl.Kernel] = {}
        self._lock = threading.Lock()
        self.build_count = 0
        self._cache: dict = {}
        self._allocator = None

    # ---- properties ---------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return self.info.full_name

    @property
    def is_cpu(self) -> bool:
        return self.info.type == "CPU"

    def __repr__(self) -> str:
        return f"Device({self.info.index} {self.info.type} {self.name!r})"

    # ---- building -----------------------------------------------------------------------------
    def build_options(self, defines: dict | None = None, real=np.float32) -> tuple[str, ...]:
        """The compiler options for a program: include path, ``REAL`` and user defines."""
        real = np.dtype(real)
        if real == np.float64:
            if not self.fp64:
                raise KernelBuildError(
                    "<REAL=double>", [], f"device {self.name!r} has no fp64 (cl_khr_fp64) support"
                )
            rdef = "double"
        elif real == np.float32:
            rdef = "float"
        else:
            raise ValueError(f"real must be float32 or float64, got {real}")
        opts = ["-I", str(kernel_dir() / "common"), f"-DREAL={rdef}"] + (["-DREAL_FP64"] if rdef == "double" else [])
        if self.info.type == "CPU":
            opts.append("-DTRIPLET_CPU")  # CPU-only code paths (e.g. raster_lists.h's prefetch builtin)
        for k in sorted(defines or {}):
            d = _format_define(k, defines[k])
            if d:
                opts.append(d)
        return tuple(opts)

    def program(self, name: str, defines: dict | None = None, real=np.float32) -> cl.Program:
        """The built program ``kernels_cl/<name>.cl`` for these defines (memoised)."""
        opts = self.build_options(defines, real)
        key = (name, opts)
        prg = self._programs.get(key)
        if prg is not None:
            return prg
        with self._lock:
            prg = self._programs.get(key)
            if prg is None:
                prg = self._build(name, opts)
                self._programs[key] = prg
                self.build_count += 1
        return prg

    def build_source(self, source: str, options: tuple[str, ...], label: str) -> cl.Program:
        """Build OpenCL C ``source``; a failure raises :class:`KernelBuildError` with the log."""
        prg = cl.Program(self.ctx, source)
        try:
            prg.build(options=list(options), devices=[self.cl_device])
        except (cl.RuntimeError, cl.LogicError, cl.Error) as exc:
            log = ""
            try:
                log = prg.get_build_info(self.cl_device, cl.program_build_info.LOG)
            except Exception:  # noqa: BLE001 - the log is best effort; the exception text has it too
                pass
            raise KernelBuildError(label, list(options), (log or "").strip() or str(exc), self.name) from exc
        return prg

    def _build(self, name: str, options: tuple[str, ...]) -> cl.Program:
        path = kernel_dir() / f"{name}.cl"
        if not path.is_file():
            raise FileNotFoundError(f"kernel source {path} does not exist (op {name!r})")
        return self.build_source(path.read_text(), options, str(path))

    def kernel(self, name: str, kernel_name: str, defines: dict | None = None, real=np.float32) -> cl.Kernel:
        """The ``cl.Kernel`` ``kernel_name`` of ``kernels_cl/<name>.cl`` (fetched once, reused)."""
        # bool values are keyed apart from ints: False omits a define, 0 defines it as 0
        fast = (name, kernel_name, real, tuple(sorted((k, v, type(v) is bool) for k, v in defines.items()))
                if defines else ())
        k = self._by_defines.get(fast)  # skips formatting the options on every fetch (many defines)
        if k is not None:
            return k
        opts = self.build_options(defines, real)
        key = (name, opts, kernel_name)
        k = self._kernels.get(key)
        if k is None:
            k = cl.Kernel(self.program(name, defines, real), kernel_name)
            declare_scalar_types(k, name, kernel_name, defines, real)
            self._kernels[key] = k
        self._by_defines[fast] = k
        return k

    def cached(self, key, factory):
        """Memoise a per-device object (a scan kernel, a constant buffer ...) under ``key``."""
        obj = self._cache.get(key)
        if obj is None:
            obj = self._cache[key] = factory()
        return obj

    # ---- memory -------------------------------------------------------------------------------
    @property
    def allocator(self):
        """A pooled allocator: device buffers are recycled by size class across iterations."""
        if self._allocator is None:
            from pyopencl.tools import ImmediateAllocator, MemoryPool

            self._allocator = MemoryPool(ImmediateAllocator(self.queue))
        return self._allocator

    def release_held(self, limit_bytes: int = POOL_HELD_LIMIT) -> int:
        """Give the pool's held buffers (freed, kept for reuse) back to the driver when they exceed
        ``limit_bytes``; returns the bytes released. Why: the pool keeps one free list per size class, and a
        render's buffers change size with its fragment count, so at large sizes (an 800² capture's mesh stage
        renders 2400²) each view left blocks of new classes behind: 24 GB held, the process killed. Below the
        limit (every 200² run) nothing changes."""
        pool = self._allocator
        if pool is None:
            return 0
        held = int(pool.managed_bytes) - int(pool.active_bytes)
        if held <= limit_bytes:
            return 0
        pool.free_held()
        return held

    def release_memory(self, min_resident: int = 0) -> None:
        """Between phases (the soup's training and the mesh stage, each remesh): every held pool buffer given back,
        Python's garbage collected, and the C heap's free pages returned to the system (glibc's ``malloc_trim``;
        PoCL's buffers live on that heap). Measured: an 800² capture's ``train --mesh-stage`` was killed at 24 GB in
        its mesh stage, while ``triplet extract`` of the same soup in a fresh process peaked at 12.8 GB. Skipped
        while the process holds less than ``min_resident`` bytes (the training loop's densifications: 37 ms a call,
        0.4 s of the demo's 21 s, for a process of 0.5 GB)."""
        import gc

        if min_resident and resident_bytes() < min_resident:
            return
        # nothing in flight while buffers (and objects the collector frees) go back: a 200k-face mesh stage died once
        # in 2 identical runs with a worker thread jumping to a heap address after its last remesh (session 37)
        self.queue.finish()
        gc.collect()
        self.release_held(0)
        try:
            import ctypes

            ctypes.CDLL("libc.so.6").malloc_trim(0)
        except (OSError, AttributeError):  # not glibc: nothing to trim this way
            pass

    def check_alloc(self, nbytes: int, what: str) -> None:
        """Raise a clear ``MemoryError`` when one buffer would exceed the device's limits."""
        if nbytes > self.info.max_alloc_bytes:
            raise MemoryError(
                f"{what} needs a buffer of {nbytes / 2**20:.1f} MiB, larger than the device's maximum "
                f"allocation ({self.info.max_alloc_bytes / 2**20:.1f} MiB on {self.name!r}); "
                "reduce the resolution, the face count or K"
            )


def resident_bytes() -> int:
    """The process's resident memory in bytes (``/proc/self/statm``; 0 where unknown)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


_DEVICES: dict[tuple[int, int], Device] = {}
_DEVICES_LOCK = threading.Lock()


def get_device(spec: str | None = None) -> Device:
    """The :class:`Device` for ``spec`` (see module docstring); one object per device per process."""
    info, plat, dev = resolve_spec(spec)
    key = (info.platform_index, info.device_index)
    with _DEVICES_LOCK:
        d = _DEVICES.get(key)
        if d is None:
            d = Device(info, plat, dev)
            _DEVICES[key] = d
    return d
