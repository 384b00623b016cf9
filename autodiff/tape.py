"""``Tape``: records :class:`~.function.Function` calls and runs their adjoints in reverse.

Usage::

    with Tape() as tape:
        y = Sigmoid()(x_param)            # recorded
        loss = L1Loss()(y, target)        # recorded
    tape.backward(loss)                   # x_param.grad now holds d loss / d x

Calls are recorded in execution order, which is a topological order of the graph (a call's inputs
exist before it runs), so walking the record backwards visits every node after all of its
consumers: its output adjoints are complete when its backward runs. Adjoints of intermediates are
summed with ``+`` in a dictionary and freed as soon as they are consumed; adjoints of leaves
(variables made by no recorded call) are added to their ``.grad``. Host (numpy) and device
(``pyopencl.array``) arrays may be mixed: an adjoint is converted to the kind of its variable's
data only when the two differ.
"""

from __future__ import annotations

from .arrays import Deferred, accumulate, download_deferred, is_array, is_device_array, like, ones_like, shape_of
from .function import Node
from .variable import Variable

_STACK: list[Tape] = []


def active_tape() -> Tape | None:
    """The innermost tape whose ``with`` block is running, else ``None``."""
    return _STACK[-1] if _STACK else None


class Tape:
    """A record of :class:`~.function.Node` calls (see the module docstring)."""

    def __init__(self):
        self.nodes: list[Node] = []

    def __enter__(self) -> Tape:
        _STACK.append(self)
        return self

    def __exit__(self, *exc) -> None:
        _STACK.remove(self)

    def __len__(self) -> int:
        return len(self.nodes)

    def record(self, node: Node) -> None:
        self.nodes.append(node)

    def clear(self) -> None:
        """Drop every recorded call (and the arrays their contexts saved). Each node is emptied too: an output
        keeps its ``creator`` (so it is still known as not a leaf), and without this the node and its outputs
        referenced each other, a cycle only Python's collector frees: a training step's device arrays stayed
        allocated until it ran, so the memory pool could not hand them to the next step and allocated anew
        (PoCL then allocates at a buffer's first kernel, a millisecond or more per kernel; the pool grew
        ~6 MB a step at spot 200²)."""
        for node in self.nodes:
            node.ctx = None
            node.inputs = []
            node.outputs = []
        self.nodes.clear()

    def backward(self, output: Variable, v_output=None, retain: bool = False) -> None:
        """Propagate ``v_output`` (default: ones, i.e. d output / d leaves for a scalar) from
        ``output`` to every leaf with ``requires_grad``, adding into their ``.grad``.

        Args:
            output: a :class:`Variable` produced by a call on this tape (or a leaf).
            v_output: the adjoint of ``output``, same shape; ``None`` means ones.
            retain: keep the record (to call ``backward`` again); by default it is cleared.
        """
        if not isinstance(output, Variable):
            raise ValueError(f"output must be a Variable, got {type(output).__name__}")
        seed = ones_like(output.data) if v_output is None else like(v_output, output.data)
        if shape_of(seed) != output.shape:
            raise ValueError(f"v_output must have shape {list(output.shape)}, got {list(shape_of(seed))}")
        if output.creator is None:
            if output.requires_grad:
                output.accumulate_grad(seed)
            return
        if output.creator not in self.nodes:
            raise ValueError("output was not produced by a call recorded on this tape")

        adjoints: dict[int, object] = {id(output): seed}
        # leaves' adjoints, added to their .grad after the pass in the order they came: a device adjoint of a host
        # leaf is downloaded without waiting (the host goes on queueing the rest of the pass instead of waiting
        # for the device at each leaf), the same values added in the same order
        leaf_adjoints: list = []
        for node in reversed(self.nodes):
            v_outs = [adjoints.pop(id(o), None) for o in node.outputs]
            if all(v is None for v in v_outs):
                continue  # does not lead to `output`
            v_outs = [like(0.0, o.data) if v is None else v for v, o in zip(v_outs, node.outputs, strict=True)]
            v_ins = node.function.backward(node.ctx, *v_outs)
            if not isinstance(v_ins, tuple):
                v_ins = (v_ins,)
            if len(v_ins) != len(node.inputs):
                raise ValueError(f"{node.name}.backward returned {len(v_ins)} adjoints for {len(node.inputs)} inputs")
            for i, (inp, v) in enumerate(zip(node.inputs, v_ins, strict=True)):
                if v is None or not (isinstance(inp, Variable) and inp.requires_grad):
                    continue
                if is_array(inp.data) and shape_of(v) != inp.shape:
                    raise ValueError(
                        f"{node.name}.backward: adjoint of input {i} ({inp.name}) has shape {list(shape_of(v))}, "
                        f"expected {list(inp.shape)}"
                    )
                if inp.creator is None:
                    if is_device_array(v) and not is_device_array(inp.data):
                        v = download_deferred(v)
                    leaf_adjoints.append((inp, v))
                else:
                    if isinstance(v, Deferred):
                        v = v.resolve()
                    adjoints[id(inp)] = accumulate(adjoints.get(id(inp)), v, inp.data)
        for inp, v in leaf_adjoints:
            inp.accumulate_grad(v.resolve() if isinstance(v, Deferred) else v)
        if not retain:
            self.clear()
