"""The op graph: Function (forward/backward), Tape and gradcheck (installed as ``triplet_cl.autodiff``).

Dependencies run ``cli → triplet_cl → autodiff``: nothing here imports ``triplet_cl``.
"""

from .arrays import accumulate, is_device_array, like, ones_like, to_host
from .function import Context, Function, Node
from .gradcheck import EntryError, GradcheckReport, InputCheck, assert_gradcheck, gradcheck
from .tape import Tape, active_tape
from .variable import Param, Variable

__all__ = [
    "Context",
    "EntryError",
    "Function",
    "GradcheckReport",
    "InputCheck",
    "Node",
    "Param",
    "Tape",
    "Variable",
    "accumulate",
    "active_tape",
    "assert_gradcheck",
    "gradcheck",
    "is_device_array",
    "like",
    "ones_like",
    "to_host",
]
