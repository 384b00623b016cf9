"""Exceptions raised by triplet_cl.

Every error names the thing that is wrong, what was expected and what was found.
"""

from __future__ import annotations


class TripletError(Exception):
    """Base class of every triplet_cl error."""


class NoOpenCLPlatformError(TripletError):
    """No OpenCL platform (driver / ICD) is installed on this machine."""

    HINT = (
        "No OpenCL platform was found. Install an OpenCL driver: a GPU vendor's driver, or on any "
        "Debian/Ubuntu machine the CPU runtime PoCL:\n"
        "    sudo apt-get install -y pocl-opencl-icd ocl-icd-libopencl1\n"
        "(do not use PyPI's pocl-binary-distribution: its LLVM cannot target many current CPUs)."
    )

    def __init__(self, detail: str = ""):
        super().__init__(self.HINT + (f"\nDetail: {detail}" if detail else ""))


class DeviceSelectionError(TripletError):
    """A device specification (``--device`` / ``TRIPLET_DEVICE``) matched nothing."""


class KernelBuildError(TripletError):
    """An OpenCL program failed to build; carries the file, the options and the full build log."""

    def __init__(self, path: str, options: list[str], log: str, device_name: str = ""):
        self.path = path
        self.options = list(options)
        self.log = log
        self.device_name = device_name
        msg = (
            f"OpenCL build of {path} failed"
            + (f" on device {device_name!r}" if device_name else "")
            + f"\noptions: {' '.join(self.options)}\nbuild log:\n{log}"
        )
        super().__init__(msg)


class DatasetError(TripletError):
    """A dataset on disk is missing or malformed; names the file (or folder) and the problem."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(self.path, problem)  # args stay (path, problem): the error pickles

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}"
