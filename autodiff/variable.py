"""Variables: named arrays that flow through recorded :class:`~.function.Function` calls."""

from __future__ import annotations

from .arrays import accumulate, shape_of


class Variable:
    """A named array in the graph (numpy array or ``pyopencl.array.Array``).

    Attributes:
        data: the value, any shape.
        name: a label used in error messages and gradcheck reports.
        requires_grad: whether adjoints should be propagated to (and, for leaves, stored in) it.
        grad: the accumulated adjoint ``v_data`` of a leaf after :meth:`Tape.backward`, same shape
            and kind (host/device) as ``data``; ``None`` before any backward pass.
        creator: the recorded node that produced it, ``None`` for a leaf.
    """

    __slots__ = ("data", "name", "requires_grad", "grad", "creator", "__weakref__")

    def __init__(self, data, name: str | None = None, requires_grad: bool = False):
        self.data = data
        self.name = name
        self.requires_grad = bool(requires_grad)
        self.grad = None
        self.creator = None

    @property
    def shape(self) -> tuple[int, ...]:
        return shape_of(self.data)

    @property
    def is_leaf(self) -> bool:
        return self.creator is None

    def zero_grad(self) -> None:
        """Forget the accumulated adjoint."""
        self.grad = None

    def accumulate_grad(self, v) -> None:
        """``grad += v`` (out of place; host/device kind follows ``data``)."""
        self.grad = accumulate(self.grad, v, self.data)

    def __repr__(self) -> str:
        kind = type(self.data).__module__.split(".")[0]
        return (f"{type(self).__name__}({self.name!r}, shape={list(self.shape)}, {kind}, "
                f"requires_grad={self.requires_grad})")


class Param(Variable):
    """A leaf :class:`Variable` that is optimised: ``requires_grad`` is on, ``name`` is required."""

    __slots__ = ()

    def __init__(self, data, name: str):
        if not name:
            raise ValueError("name must be a non-empty string for a Param")
        super().__init__(data, name=name, requires_grad=True)
