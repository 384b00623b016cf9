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


class UsageError(TripletError):
    """A command-line option or an input/output path is invalid; raised before any work is done.

    ``option`` is the option (``--init-points``) or the path the message is about."""

    def __init__(self, option: str, problem: str):
        self.option = str(option)
        self.problem = problem
        super().__init__(self.option, problem)

    def __str__(self) -> str:
        return f"{self.option}: {self.problem}"


class RunError(TripletError):
    """A run directory or one of its files (config.json, a checkpoint, mesh_stage.npz) is missing,
    damaged or belongs to another configuration; names the file."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(self.path, problem)

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}"


class NonFiniteError(TripletError):
    """Training produced a NaN/Inf: names the iteration, the parameter group and the likely cause."""

    def __init__(self, iteration: int, group: str, what: str, cause: str):
        self.iteration, self.group, self.what, self.cause = int(iteration), group, what, cause
        super().__init__(iteration, group, what, cause)

    def __str__(self) -> str:
        return (f"non-finite {self.what} in parameter group {self.group!r} at iteration {self.iteration}: "
                f"{self.cause}")


def is_utf8(text: str) -> bool:
    """Whether ``text`` (a path or name from the OS) is UTF-8 text: bytes of another encoding reach Python as
    surrogates, which OpenImageIO cannot take (battery 10)."""
    try:
        text.encode("utf-8")
        return True
    except UnicodeEncodeError:
        return False


def shown_text(text: str) -> str:
    """``text`` printable in a message, a non-UTF-8 byte as ``\\xNN``."""
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
