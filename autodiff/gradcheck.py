"""Central-difference gradient checks in float64 with a readable report of the worst entries.

``gradcheck(func, {"x": x, "w": w})`` calls ``func(x_var, w_var)`` (inputs as :class:`Param` in
dict order) on a :class:`Tape`, runs the adjoint with a cotangent ``v`` (1 for a scalar output, a
seeded standard normal otherwise, i.e. it checks the VJP of ``sum(out * v)``), and compares every
(or a sampled subset of) input entries with ``(f(x + eps) - f(x - eps)) / (2 eps)``. An entry
passes when ``|analytic - numeric| <= atol + rtol * |numeric|``; rtol/atol may be given per input.
Device inputs (``pyopencl.array.Array``, float64) are perturbed on the host and uploaded for each
evaluation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .arrays import is_device_array, to_host
from .tape import Tape
from .variable import Param, Variable


@dataclass
class EntryError:
    """One checked entry: its index in the input, both derivatives and their absolute difference."""

    index: tuple[int, ...]
    analytic: float
    numeric: float
    error: float


@dataclass
class InputCheck:
    """The result for one input."""

    name: str
    ok: bool
    checked: int
    total: int
    rtol: float
    atol: float
    max_error: float
    worst: list[EntryError] = field(default_factory=list)


@dataclass
class GradcheckReport:
    """All inputs' results; ``str(report)`` is the readable table, ``report.ok`` the verdict."""

    inputs: list[InputCheck]
    eps: float

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.inputs)

    def __getitem__(self, name: str) -> InputCheck:
        for c in self.inputs:
            if c.name == name:
                return c
        raise KeyError(name)

    def __str__(self) -> str:
        lines = [f"gradcheck (central differences, eps={self.eps:g}): {'PASS' if self.ok else 'FAIL'}"]
        for c in self.inputs:
            lines.append(
                f"  {c.name}: {'ok' if c.ok else 'FAILED'}  checked {c.checked}/{c.total} entries, "
                f"max |analytic-numeric| = {c.max_error:.3e} (rtol={c.rtol:g}, atol={c.atol:g})"
            )
            if c.worst:
                lines.append(f"    {'index':>18} {'analytic':>14} {'numeric':>14} {'error':>11}")
                for e in c.worst:
                    lines.append(f"    {str(e.index):>18} {e.analytic:14.6e} {e.numeric:14.6e} {e.error:11.3e}")
        return "\n".join(lines)


def _per_input(value, name: str, default: float) -> float:
    if isinstance(value, dict):
        return float(value.get(name, default))
    return float(value)


def _as_float64(name: str, a):
    if is_device_array(a):
        if a.dtype != np.float64:
            raise ValueError(f"input {name!r} must be a float64 device array for gradcheck, got {a.dtype}")
        return a
    a = np.asarray(a)
    if a.dtype.kind != "f":
        raise ValueError(f"input {name!r} must be floating point, got dtype {a.dtype}")
    return np.array(a, dtype=np.float64)


def _evaluate(func, values: list):
    out = func(*[Variable(v) for v in values])
    return to_host(out.data if isinstance(out, Variable) else out).astype(np.float64)


def gradcheck(
    func,
    inputs: dict,
    *,
    eps: float = 1e-6,
    rtol: float | dict = 1e-5,
    atol: float | dict = 1e-8,
    v_output=None,
    max_checks: int | None = None,
    worst: int = 5,
    seed: int = 0,
) -> GradcheckReport:
    """Compare the tape's adjoints of ``func`` with central finite differences.

    Args:
        func: ``func(*variables) -> Variable`` built from :class:`Function` calls (constants are
            closed over); inputs arrive as :class:`Variable` in the order of ``inputs``.
        inputs: ``{name: array}``, floating host arrays (copied to float64) or float64 device arrays.
        eps: the finite-difference step (applied as ``x ± eps``).
        rtol, atol: tolerances, a float or ``{name: float}`` (missing names use the defaults).
        v_output: the output cotangent (same shape as the output); default 1 for a scalar output,
            else a standard normal drawn from ``seed``.
        max_checks: check at most this many entries per input (a seeded random subset), else all.
        worst: how many worst entries to list per input in the report.
        seed: seeds the cotangent and the entry subset.

    Returns:
        A :class:`GradcheckReport`; see also :func:`assert_gradcheck`.
    """
    rng = np.random.default_rng(seed)
    names = list(inputs)
    values = [_as_float64(n, inputs[n]) for n in names]
    params = [Param(v, n) for n, v in zip(names, values, strict=True)]

    with Tape() as tape:
        out = func(*params)
    if not isinstance(out, Variable):
        raise ValueError("func must return a Variable built from the inputs by recorded Function calls")
    out_shape = out.shape
    if v_output is None:
        v = np.ones(out_shape) if int(np.prod(out_shape)) == 1 else rng.standard_normal(out_shape)
    else:
        v = np.asarray(v_output, dtype=np.float64)
    tape.backward(out, v)

    checks = []
    for k, (name, p) in enumerate(zip(names, params, strict=True)):
        host = to_host(values[k]).astype(np.float64)
        analytic = np.zeros_like(host) if p.grad is None else to_host(p.grad).astype(np.float64)
        flat_idx = np.arange(host.size)
        if max_checks is not None and host.size > max_checks:
            flat_idx = np.sort(rng.choice(host.size, size=max_checks, replace=False))
        r, a = _per_input(rtol, name, 1e-5), _per_input(atol, name, 1e-8)
        numeric = np.empty(len(flat_idx))
        for j, fi in enumerate(flat_idx):
            vals = []
            for sign in (1.0, -1.0):
                pert = host.copy()
                pert.flat[fi] += sign * eps
                trial = list(values)
                trial[k] = _upload_like(pert, values[k])
                vals.append(float(np.sum(_evaluate(func, trial) * v)))
            numeric[j] = (vals[0] - vals[1]) / (2.0 * eps)
        an = analytic.reshape(-1)[flat_idx]
        err = np.abs(an - numeric)
        excess = err / (a + r * np.abs(numeric))
        order = np.argsort(-excess)[:worst]
        entries = [
            EntryError(tuple(int(i) for i in np.unravel_index(flat_idx[o], host.shape)), float(an[o]),
                       float(numeric[o]), float(err[o]))
            for o in order
        ]
        checks.append(InputCheck(name, bool(np.all(excess <= 1.0)), len(flat_idx), host.size, r, a,
                                 float(err.max()) if err.size else 0.0, entries))
    return GradcheckReport(checks, eps)


def _upload_like(host: np.ndarray, reference):
    if is_device_array(reference):
        import pyopencl.array as cla

        return cla.to_device(reference.queue, host)
    return host


def assert_gradcheck(func, inputs: dict, **kwargs) -> GradcheckReport:
    """:func:`gradcheck`, raising ``AssertionError`` with the report when any entry fails."""
    report = gradcheck(func, inputs, **kwargs)
    if not report.ok:
        raise AssertionError(str(report))
    return report
