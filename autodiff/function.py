"""``Function``: one differentiable op, a forward that saves what its adjoint needs and a backward.

Write an op as a subclass::

    class Scale(Function):
        def __init__(self, factor):            # non-differentiable settings go to the constructor
            self.factor = factor

        def forward(self, ctx, x):             # x: plain arrays (numpy or pyopencl), never Variables
            return x * self.factor

        def backward(self, ctx, v_y):          # one adjoint per output, in the output's kind
            return v_y * self.factor           # one adjoint per input (None: not differentiable)

and call an instance: ``y = Scale(2.0)(x)``. With ``Variable`` inputs inside an active
:class:`~.tape.Tape` the call is recorded and returns ``Variable`` outputs; with plain arrays it just
returns the forward value, so the same class serves the training loop and plain evaluation.
"""

from __future__ import annotations

from .arrays import is_array, shape_of
from .variable import Variable


class Context:
    """Per-call scratch space: ``forward`` stores what ``backward`` needs as attributes or via
    :meth:`save`; ``needs_input_grad[i]`` says whether input ``i`` wants an adjoint (so a backward
    may skip work and return ``None`` there)."""

    def __init__(self, needs_input_grad: tuple[bool, ...]):
        self.needs_input_grad = needs_input_grad
        self.saved: tuple = ()

    def save(self, *values) -> None:
        """Keep ``values`` for the backward pass (available as ``ctx.saved``)."""
        self.saved = values


class Node:
    """One recorded call: the function object, its context, its inputs and its outputs."""

    __slots__ = ("function", "ctx", "inputs", "outputs")

    def __init__(self, function, ctx, inputs, outputs):
        self.function = function
        self.ctx = ctx
        self.inputs = inputs  # list: Variable or constant
        self.outputs = outputs  # list[Variable]

    @property
    def name(self) -> str:
        return type(self.function).__name__


class Function:
    """Base class of differentiable ops; see the module docstring for the protocol."""

    def forward(self, ctx: Context, *inputs):
        """Compute the output(s) from plain arrays; store in ``ctx`` what :meth:`backward` needs."""
        raise NotImplementedError

    def backward(self, ctx: Context, *v_outputs):
        """Given one adjoint per output, return one adjoint per input (``None`` where an input is
        not differentiable or ``ctx.needs_input_grad`` is False). A single input may return a bare
        array instead of a 1-tuple."""
        raise NotImplementedError

    def __call__(self, *inputs):
        from .tape import active_tape  # local import: tape imports this module

        raw = [x.data if isinstance(x, Variable) else x for x in inputs]
        needs = tuple(isinstance(x, Variable) and x.requires_grad for x in inputs)
        tape = active_tape()
        record = tape is not None and any(needs)
        ctx = Context(needs)
        out = self.forward(ctx, *raw)
        if not any(isinstance(x, Variable) for x in inputs):
            return out
        multi = isinstance(out, tuple)
        outs = [Variable(o, name=f"{type(self).__name__}.out{i}", requires_grad=record)
                for i, o in enumerate(out if multi else (out,))]
        if record:
            node = Node(self, ctx, list(inputs), outs)
            for o in outs:
                o.creator = node
            tape.record(node)
        return tuple(outs) if multi else outs[0]

    # -- helpers for subclasses -----------------------------------------------------------------
    @staticmethod
    def check_adjoint(name: str, v, data) -> None:
        """Raise ``ValueError`` when an adjoint's shape differs from its variable's."""
        if v is not None and is_array(data) and shape_of(v) != shape_of(data):
            raise ValueError(f"adjoint of {name} has shape {list(shape_of(v))}, expected {list(shape_of(data))}")
