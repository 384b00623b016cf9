"""triplet_cl: mesh-based inverse rendering (Triplet / Triangle Patchlets) on OpenCL.

Geometry (a triangle soup, then a connected mesh), physically based materials and lights are
recovered from multi-view photos; every heavy step is an OpenCL kernel with a hand-derived adjoint.
"""

from .device import Device, DeviceInfo, get_device, list_devices, resolve_spec
from .errors import DeviceSelectionError, KernelBuildError, NoOpenCLPlatformError, TripletError

__version__ = "0.1.0"

__all__ = [
    "Device",
    "DeviceInfo",
    "DeviceSelectionError",
    "KernelBuildError",
    "NoOpenCLPlatformError",
    "TripletError",
    "get_device",
    "list_devices",
    "resolve_spec",
    "__version__",
]
