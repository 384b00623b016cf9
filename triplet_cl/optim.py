"""Adam on numpy parameters, with parameter groups, learning-rate schedules, per-group gradient
clipping, checkpointable state and row remapping for density control (docs/ARCHITECTURE.md §8).

A group is a name, a list of parameters (objects with ``.data`` — a numpy array, updated in
place — and ``.grad`` — numpy or device array, or None; e.g. :class:`triplet_cl.autodiff.Param`)
and its own hyper-parameters. One ``step()``:

1. ``t += 1`` (one **global** step count shared by every group and every row, like 3D Gaussian
   Splatting: rows created by ``remap`` start with zero moments but the current ``t``, so their
   first bias-corrected update is ``(1 − β1)/(1 − β1^t)`` of the full-length one — no per-row
   counters to keep aligned);
2. per group: ``lr = schedule(t − 1)`` (the schedule sees the 0-based index of this step);
   when ``max_grad_norm`` is set and the global norm ``‖g‖ = sqrt(Σ_params Σ g²)`` of the group
   exceeds it, every gradient of the group is scaled by ``max_grad_norm / (‖g‖ + 1e-6)``
   (``torch.nn.utils.clip_grad_norm_``);
3. per parameter with a gradient: ``m = β1 m + (1 − β1) g``, ``v = β2 v + (1 − β2) g²``,
   ``x −= lr · (m / (1 − β1^t)) / (sqrt(v / (1 − β2^t)) + eps)`` (PyTorch's Adam); with the group's
   optional ``lr_scale`` for the parameter, ``lr`` is multiplied elementwise by it.

Parameters whose ``.grad`` is None are skipped (their moments do not decay).

``Adam(device=...)`` runs step 3 as one OpenCL kernel per parameter (``kernels_cl/adam.cl``:
upload x, m, v and the gradient, one fused pass, download x, m, v into the same numpy arrays), bit
for bit the numpy update on PoCL (``tests/test_optim.py``); parameters, moments, ``state_dict`` and
``remap`` stay numpy, so checkpoints and density control are unchanged. Parameters under
``device_min_size`` elements (:data:`DEVICE_MIN_SIZE`) keep the numpy update, which is faster there. Without a device
(the default) the update is numpy.

Schedules: :class:`Constant`, :class:`ExponentialDecay` (3DGS ``get_expon_lr_func``: log-linear
from ``lr_init`` at step 0 to ``lr_final`` at ``max_steps``, optional sine-eased delay) and
:class:`StepUp` (multiplies a base schedule by ``factor`` from each milestone on). They serialise to
plain dicts so ``state_dict()`` can be written to a checkpoint (npz/pickle/JSON + arrays).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from .autodiff.arrays import to_host

# ---------------------------------------------------------------------------------------------
# schedules
# ---------------------------------------------------------------------------------------------


@dataclass
class Constant:
    """``lr(step) = lr``."""

    lr: float

    def __call__(self, step: int) -> float:
        return float(self.lr)


@dataclass
class ExponentialDecay:
    """3DGS ``get_expon_lr_func``: ``exp(lerp(log lr_init, log lr_final, clip(step / max_steps, 0, 1)))``,
    times ``delay_mult + (1 − delay_mult)·sin(π/2·clip(step / delay_steps, 0, 1))`` when
    ``delay_steps > 0``."""

    lr_init: float
    lr_final: float
    max_steps: int
    delay_steps: int = 0
    delay_mult: float = 1.0

    def __post_init__(self):
        if self.lr_init < 0 or self.lr_final < 0 or self.max_steps <= 0:
            raise ValueError(f"ExponentialDecay needs lr_init, lr_final >= 0 and max_steps > 0, got {self}")
        if (self.lr_init == 0) != (self.lr_final == 0):
            raise ValueError("ExponentialDecay: lr_init and lr_final must both be > 0 (log-linear) or both 0")

    def __call__(self, step: int) -> float:
        if step < 0 or self.lr_init == 0.0:
            return 0.0
        delay = 1.0
        if self.delay_steps > 0:
            delay = self.delay_mult + (1.0 - self.delay_mult) * math.sin(
                0.5 * math.pi * min(max(step / self.delay_steps, 0.0), 1.0))
        t = min(max(step / self.max_steps, 0.0), 1.0)
        return delay * math.exp(math.log(self.lr_init) * (1.0 - t) + math.log(self.lr_final) * t)


@dataclass
class StepUp:
    """``lr(step) = base(step) · Π_{milestone ≤ step} factor`` (e.g. materials ×5 from 10 000)."""

    base: Constant | ExponentialDecay
    milestones: dict[int, float] = field(default_factory=dict)  # {step: factor}

    def __call__(self, step: int) -> float:
        lr = self.base(step)
        for at, factor in self.milestones.items():
            if step >= int(at):
                lr *= float(factor)
        return lr


Schedule = Constant | ExponentialDecay | StepUp


def schedule_to_dict(s: Schedule) -> dict:
    """A plain dict ``{"type": ..., fields...}`` for checkpoints."""
    if isinstance(s, StepUp):
        return {"type": "StepUp", "base": schedule_to_dict(s.base),
                "milestones": {str(k): float(v) for k, v in s.milestones.items()}}
    return {"type": type(s).__name__, **asdict(s)}


def schedule_from_dict(d: dict) -> Schedule:
    """Inverse of :func:`schedule_to_dict`."""
    d = dict(d)
    kind = d.pop("type", None)
    if kind == "Constant":
        return Constant(**d)
    if kind == "ExponentialDecay":
        return ExponentialDecay(**d)
    if kind == "StepUp":
        return StepUp(schedule_from_dict(d["base"]), {int(k): float(v) for k, v in d["milestones"].items()})
    raise ValueError(f"unknown schedule type {kind!r} (expected Constant, ExponentialDecay or StepUp)")


def _as_schedule(lr) -> Schedule:
    if isinstance(lr, Constant | ExponentialDecay | StepUp):
        return lr
    if isinstance(lr, int | float) and lr >= 0:
        return Constant(float(lr))
    raise ValueError(f"lr must be a float >= 0 or a schedule (Constant, ExponentialDecay, StepUp), got {lr!r}")


# ---------------------------------------------------------------------------------------------
# Adam
# ---------------------------------------------------------------------------------------------


@dataclass
class ParamGroup:
    """One group: its parameters, hyper-parameters and first/second moments (one per parameter)."""

    name: str
    params: list
    schedule: Schedule
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8
    max_grad_norm: float | None = None
    exp_avg: list[np.ndarray] = field(default_factory=list)
    exp_avg_sq: list[np.ndarray] = field(default_factory=list)
    last_grad_norm: float = 0.0  # the group's gradient norm before clipping at the last step
    #: per parameter, None or an array broadcasting to its shape: the update is multiplied by it (elementwise
    #: learning rates, e.g. each light parameter relative to its magnitude); not part of ``state_dict``
    lr_scale: list | None = None

    @property
    def num_rows(self) -> int:
        return int(self.params[0].data.shape[0]) if self.params and self.params[0].data.ndim else 0


class NonFiniteStep(ArithmeticError):
    """A NaN/Inf gradient (before the update: nothing changed) or parameter (after it) in ``group``."""

    def __init__(self, group: str, what: str):
        self.group, self.what = group, what
        super().__init__(f"non-finite {what} in parameter group {group!r}")


def _squared_norm(gr: np.ndarray, exact: bool) -> float:
    """``Σ gr²``. ``exact`` (a group that clips by its norm: the value scales the step) in float64; else with one BLAS
    dot product in the gradient's dtype (8x faster on 0.5M float32 values; the value is only the finiteness guard and
    ``last_grad_norm``), in float64 again when that is not finite, so that only a NaN/Inf gradient, not a float32
    overflow, reads as one."""
    if not exact:
        x = gr.reshape(-1)
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is checked below
            v = float(np.dot(x, x))
        if math.isfinite(v):
            return v
    return float(np.sum(np.square(gr, dtype=np.float64)))


# the smallest parameter (elements) whose update runs as the adam.cl kernel: below it the kernel's fixed cost (four
# host-pointer buffers, the launch, four maps, a finish: ~0.75 ms on PoCL) exceeds numpy's passes (medians on this
# 2-core machine, session 58: 100k elements 1.0 ms kernel / 0.43 numpy, 260k 1.44 / 1.44, 500k 2.3 / 3.1, 1M 4.4 / 8.0;
# bench/results/adam_device_size_pocl_2026-11-29.txt); either way the same bits
DEVICE_MIN_SIZE = 1 << 18


class Adam:
    """Adam with named parameter groups (see the module docstring for the exact update).

    Example::

        opt = Adam()
        opt.add_group("xyz", [positions], lr=ExponentialDecay(1.6e-4 * extent, 1.6e-6 * extent, 30_000),
                      betas=(0.5, 0.999), eps=1e-15)
        opt.add_group("albedo", [albedo_raw], lr=StepUp(Constant(0.01), {10_000: 5.0}))
        ... tape.backward(loss); opt.step(); opt.zero_grad()
    """

    def __init__(self, device=None, device_min_size: int = DEVICE_MIN_SIZE):
        self.groups: dict[str, ParamGroup] = {}
        self.t = 0  # completed steps
        self.device = device  # a triplet_cl Device: the update runs as the adam.cl kernel there
        self.device_min_size = int(device_min_size)  # for parameters of at least this many elements
        self._work: dict = {}  # dtype -> two flat scratch buffers of the numpy update (_workspace)

    # ---- groups -------------------------------------------------------------------------------
    def add_group(self, name: str, params: list, lr=1e-3, betas=(0.9, 0.999), eps: float = 1e-8,
                  max_grad_norm: float | None = None, lr_scale: list | None = None) -> ParamGroup:
        """Register ``params`` (each with ``.data`` a float numpy array, ``.grad``) as group ``name``.

        ``lr``: a float or a schedule; ``betas`` in [0, 1); ``max_grad_norm``: None or > 0; ``lr_scale``:
        None or one entry per parameter (None or a finite ``>= 0`` array broadcasting to its shape) multiplying
        its update elementwise (such a parameter is updated by numpy, also with a device).
        """
        if not name or name in self.groups:
            raise ValueError(f"name must be a new non-empty group name, got {name!r}")
        params = list(params)
        if not params:
            raise ValueError(f"params of group {name!r} must not be empty")
        for p in params:
            if not (isinstance(getattr(p, "data", None), np.ndarray) and p.data.dtype.kind == "f"):
                raise ValueError(f"params of group {name!r} must have .data a floating numpy array, got {p!r}")
        b1, b2 = (float(b) for b in betas)
        if not (0 <= b1 < 1 and 0 <= b2 < 1):
            raise ValueError(f"betas must lie in [0, 1), got {betas}")
        if eps < 0:
            raise ValueError(f"eps must be >= 0, got {eps}")
        if max_grad_norm is not None and max_grad_norm <= 0:
            raise ValueError(f"max_grad_norm must be None or > 0, got {max_grad_norm}")
        if lr_scale is not None:
            lr_scale = list(lr_scale)
            if len(lr_scale) != len(params):
                raise ValueError(f"lr_scale of group {name!r} must hold one entry per parameter ({len(params)}), "
                                 f"got {len(lr_scale)}")
            for i, (sc, p) in enumerate(zip(lr_scale, params, strict=True)):
                if sc is None:
                    continue
                sc = np.asarray(sc, np.float64)
                if not (np.isfinite(sc).all() and (sc >= 0).all()):
                    raise ValueError(f"lr_scale[{i}] of group {name!r} must be finite and >= 0")
                try:
                    np.broadcast_to(sc, p.data.shape)
                except ValueError:
                    raise ValueError(f"lr_scale[{i}] of group {name!r} has shape {list(sc.shape)}, which does not "
                                     f"broadcast to the parameter's {list(p.data.shape)}") from None
                lr_scale[i] = sc.astype(p.data.dtype)
        g = ParamGroup(name, params, _as_schedule(lr), (b1, b2), float(eps), max_grad_norm,
                       [np.zeros_like(p.data) for p in params], [np.zeros_like(p.data) for p in params],
                       lr_scale=lr_scale)
        self.groups[name] = g
        return g

    def group(self, name: str) -> ParamGroup:
        if name not in self.groups:
            raise ValueError(f"group_name {name!r} is not a group of this optimizer ({sorted(self.groups)})")
        return self.groups[name]

    def lr(self, name: str, step: int | None = None) -> float:
        """The learning rate group ``name`` uses at 0-based ``step`` (default: the next step)."""
        return self.group(name).schedule(self.t if step is None else step)

    # ---- update -------------------------------------------------------------------------------
    def zero_grad(self) -> None:
        """Set every parameter's ``.grad`` to None."""
        for g in self.groups.values():
            for p in g.params:
                p.grad = None

    def step(self) -> None:
        """One Adam update of every parameter that has a gradient.

        Finiteness guard: a NaN/Inf gradient (seen in the group's gradient norm, which is computed
        anyway) raises :class:`NonFiniteStep` before **any** parameter is updated; a parameter that
        becomes NaN/Inf by the update raises it after the step (``what == "parameter"``)."""
        per_group = []
        for g in self.groups.values():
            grads = [None if p.grad is None else to_host(p.grad) for p in g.params]
            for p, gr in zip(g.params, grads, strict=True):
                if gr is not None and gr.shape != p.data.shape:
                    raise ValueError(f"gradient of {getattr(p, 'name', 'a parameter')} in group {g.name!r} has shape "
                                     f"{list(gr.shape)}, expected {list(p.data.shape)}")
            exact = g.max_grad_norm is not None
            norm = math.sqrt(sum(_squared_norm(gr, exact) for gr in grads if gr is not None))
            if not math.isfinite(norm):
                raise NonFiniteStep(g.name, "gradient")
            per_group.append((g, grads, norm))
        self.t += 1
        bad = None
        for g, grads, norm in per_group:
            lr = g.schedule(self.t - 1)
            g.last_grad_norm = norm
            coef = 1.0
            if g.max_grad_norm is not None and norm > g.max_grad_norm:
                coef = g.max_grad_norm / (norm + 1e-6)
            b1, b2 = g.betas
            bc1, bc2 = 1.0 - b1**self.t, 1.0 - b2**self.t
            for k, (p, gr) in enumerate(zip(g.params, grads, strict=True)):
                if gr is None:
                    continue
                scale = None if g.lr_scale is None else g.lr_scale[k]
                if scale is None and self._on_device(p.data, g.exp_avg[k], g.exp_avg_sq[k]):
                    finite = self._step_device(p.data, g.exp_avg[k], g.exp_avg_sq[k], gr, coef, b1, b2, lr / bc1,
                                               bc2, g.eps)
                    if bad is None and not finite:
                        bad = g.name
                    continue
                gr = gr.astype(p.data.dtype, copy=False)
                m, v = g.exp_avg[k], g.exp_avg_sq[k]
                # with lr_scale the step size is the array (lr / bc1) · scale, as ``(lr / bc1) * scale * m`` rounds it
                step = lr / bc1 if scale is None else (lr / bc1) * scale
                self._update_numpy(p.data, m, v, gr, coef, b1, b2, step, bc2, g.eps)
                if bad is None and not np.isfinite(p.data).all():
                    bad = g.name
        if bad is not None:
            raise NonFiniteStep(bad, "parameter")

    def _workspace(self, like: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Two scratch arrays of ``like``'s shape and dtype: views of two flat buffers per dtype kept between
        steps and shared by every parameter (no allocation, no fresh pages per step; the buffers grow to the
        largest parameter, e.g. after density control, and hold 2 × its size in all)."""
        w = self._work.get(like.dtype.str)
        if w is None or w[0].size < like.size:
            w = self._work[like.dtype.str] = (np.empty(like.size, like.dtype), np.empty(like.size, like.dtype))
        return w[0][:like.size].reshape(like.shape), w[1][:like.size].reshape(like.shape)

    def _update_numpy(self, x, m, v, gr, coef, b1, b2, step_size, bc2, eps) -> None:
        """Step 3 in place with two scratch arrays: the operations and their order of the textbook
        expressions ``g = grad·coef; m = β1 m + (1 − β1) g; v = β2 v + (1 − β2) g g;
        x −= (lr / bc1) m / (sqrt(v / bc2) + eps)`` as numpy evaluates them (python-float scalars
        rounded to the array's dtype, ``g·1`` skipped: it is ``g`` exactly), so bit for bit the same
        (``tests/test_optim.py``), in about half the memory passes and no temporaries. ``step_size``: ``lr / bc1``,
        or with ``lr_scale`` the array ``(lr / bc1) · scale`` (broadcasting to ``x``; ``step · m`` is the
        product ``(lr / bc1) * scale * m`` evaluates)."""
        w0, w1 = self._workspace(x)
        if coef != 1.0:
            gr = gr * coef
        m *= b1
        np.multiply(gr, 1.0 - b1, out=w0)
        m += w0
        v *= b2
        np.multiply(gr, 1.0 - b2, out=w0)
        w0 *= gr
        v += w0
        np.divide(v, bc2, out=w1)
        np.sqrt(w1, out=w1)
        w1 += eps
        np.multiply(m, step_size, out=w0)
        w0 /= w1
        x -= w0

    def _on_device(self, *arrays) -> bool:
        """Whether this update runs as the kernel: a device is set, the arrays hold at least ``device_min_size``
        elements (and at least one), C-contiguous float32 (or float64 on a device with fp64); otherwise numpy."""
        if self.device is None or not arrays[0].size or arrays[0].size < self.device_min_size:
            return False
        dt = arrays[0].dtype
        if dt != np.float32 and not (dt == np.float64 and self.device.fp64):
            return False
        return all(a.dtype == dt and a.flags.c_contiguous for a in arrays)

    def _step_device(self, x, m, v, gr, coef, b1, b2, step_size, bc2, eps) -> bool:
        """The update of one parameter as the ``adam_step`` kernel; ``x``, ``m``, ``v`` (numpy) are
        updated in place. Scalars are rounded to the parameter's dtype on the host first, as numpy
        does with a python float against an array of that dtype. Returns whether every updated
        parameter is finite (the kernel flags NaN/Inf results: the finiteness guard without a host pass)."""
        import pyopencl as cl

        from .ops.common import run_1d

        d, real = self.device, x.dtype.type
        q, mf = d.queue, cl.mem_flags
        gr = np.ascontiguousarray(to_host(gr), dtype=x.dtype)
        # the numpy arrays themselves as buffers (USE_HOST_PTR: no copy on a CPU device); mapping
        # them after the kernel hands the results back on any device
        bufs = [cl.Buffer(d.ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=a) for a in (x, m, v)]
        gbuf = cl.Buffer(d.ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=gr)
        flag = np.zeros(1, np.int32)
        bufs.append(cl.Buffer(d.ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=flag))
        run_1d(d, d.kernel("adam", "adam_step", real=x.dtype), x.size, *bufs[:3], gbuf, np.int32(x.size),
               real(coef), real(b1), real(1.0 - b1), real(b2), real(1.0 - b2), real(step_size), real(bc2), real(eps),
               bufs[3])
        for host, buf in zip((x, m, v, flag), bufs, strict=True):
            mapped, _ = cl.enqueue_map_buffer(q, buf, cl.map_flags.READ, 0, host.shape, host.dtype)
            mapped.base.release(q)
        q.finish()
        return not flag[0]

    # ---- density control ----------------------------------------------------------------------
    def remap(self, group_name: str, index_map, new_rows=None) -> None:
        """Resize the rows of every parameter of a group together with its moments.

        Args:
            group_name: the group whose parameters all have ``R_old`` rows (leading axis).
            index_map: ``[R_new]`` int; entry ``r`` is the old row that new row ``r`` comes from
                (kept, duplicated or split rows), or ``-1`` for a brand-new row. Pruning is a map
                that omits rows. Moments are gathered the same way; ``-1`` rows get zero moments.
            new_rows: the new parameter values, one array per parameter (a list in group order or a
                ``{name: array}`` dict): either the full ``[R_new, ...]`` arrays (e.g. children of a
                split moved to new positions) or ``[count(-1), ...]`` values for the ``-1`` rows only
                (other rows are gathered). None gathers every row (then no ``-1`` is allowed).

        Each parameter's ``.data`` is replaced by the new array and its ``.grad`` reset to None.
        """
        g = self.group(group_name)
        r_old = g.num_rows
        idx = np.asarray(index_map)
        if idx.dtype.kind not in "iu" or idx.ndim != 1:
            raise ValueError(f"index_map must be a 1-D integer array, got dtype {idx.dtype} shape {list(idx.shape)}")
        if idx.size and (idx.min() < -1 or idx.max() >= r_old):
            raise ValueError(f"index_map values must lie in [-1, {r_old - 1}], found [{idx.min()}, {idx.max()}]")
        for p in g.params:
            if p.data.shape[0] != r_old:
                raise ValueError(f"every parameter of group {group_name!r} must have {r_old} rows to be remapped")
        fresh = idx < 0
        n_new = int(fresh.sum())
        values = self._new_rows_list(g, new_rows)
        if values is None and n_new:
            raise ValueError(f"new_rows is required: index_map has {n_new} brand-new (-1) rows")
        src = np.where(fresh, 0, idx)
        for k, p in enumerate(g.params):
            data = p.data[src] if r_old else np.zeros((len(idx),) + p.data.shape[1:], p.data.dtype)
            if values is not None:
                val = np.asarray(values[k], dtype=p.data.dtype)
                tail = p.data.shape[1:]
                if val.shape == (len(idx),) + tail:
                    data = val.copy()
                elif val.shape == (n_new,) + tail:
                    data[fresh] = val
                else:
                    raise ValueError(f"new_rows[{k}] must have shape {[len(idx), *tail]} or {[n_new, *tail]}, "
                                     f"got {list(val.shape)}")
            p.data = np.ascontiguousarray(data)
            p.grad = None
            for moments in (g.exp_avg, g.exp_avg_sq):
                old = moments[k]
                new = old[src] if r_old else np.zeros_like(data)
                new[fresh] = 0
                moments[k] = np.ascontiguousarray(new)

    @staticmethod
    def _new_rows_list(g: ParamGroup, new_rows):
        if new_rows is None:
            return None
        if isinstance(new_rows, dict):
            names = [getattr(p, "name", None) for p in g.params]
            missing = [n for n in names if n not in new_rows]
            if missing:
                raise ValueError(f"new_rows lacks parameters {missing} of group {g.name!r}")
            return [new_rows[n] for n in names]
        if isinstance(new_rows, np.ndarray) and len(g.params) == 1:
            return [new_rows]
        new_rows = list(new_rows)
        if len(new_rows) != len(g.params):
            raise ValueError(f"new_rows must hold {len(g.params)} arrays (one per parameter), got {len(new_rows)}")
        return new_rows

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """``{"t": int, "groups": {name: {hyper-parameters, "exp_avg": [arrays], "exp_avg_sq": [...]}}}``
        (copies; parameter values are not included — save them with the scene)."""
        return {
            "t": self.t,
            "groups": {
                name: {
                    "schedule": schedule_to_dict(g.schedule),
                    "betas": list(g.betas),
                    "eps": g.eps,
                    "max_grad_norm": g.max_grad_norm,
                    "exp_avg": [m.copy() for m in g.exp_avg],
                    "exp_avg_sq": [v.copy() for v in g.exp_avg_sq],
                }
                for name, g in self.groups.items()
            },
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore step count, hyper-parameters and moments saved by :meth:`state_dict`. The groups
        must already exist with the same names and parameter shapes (restore the parameters first)."""
        groups = state.get("groups", {})
        if set(groups) != set(self.groups):
            raise ValueError(f"state has groups {sorted(groups)}, this optimizer has {sorted(self.groups)}")
        for name, s in groups.items():
            g = self.groups[name]
            for key in ("exp_avg", "exp_avg_sq"):
                arrs = s[key]
                if len(arrs) != len(g.params) or any(np.shape(a) != p.data.shape for a, p in zip(arrs, g.params,
                                                                                                   strict=False)):
                    raise ValueError(f"state[{name!r}][{key!r}] does not match the shapes of the group's parameters "
                                     f"{[list(p.data.shape) for p in g.params]}")
        for name, s in groups.items():
            g = self.groups[name]
            g.schedule = schedule_from_dict(s["schedule"])
            g.betas = tuple(float(b) for b in s["betas"])
            g.eps = float(s["eps"])
            g.max_grad_norm = None if s["max_grad_norm"] is None else float(s["max_grad_norm"])
            g.exp_avg = [np.array(a, dtype=p.data.dtype) for a, p in zip(s["exp_avg"], g.params, strict=True)]
            g.exp_avg_sq = [np.array(a, dtype=p.data.dtype) for a, p in zip(s["exp_avg_sq"], g.params, strict=True)]
        self.t = int(state["t"])


def owning_groups(optimizer, vparams) -> dict[str, list]:
    """``{group name: params}`` of the groups holding per-vertex parameters (matched by identity)."""
    if optimizer is None:
        return {}
    ids = {id(p) for p in vparams}
    out, seen = {}, set()
    for name, g in optimizer.groups.items():
        hit = [id(p) in ids for p in g.params]
        if not any(hit):
            continue
        if not all(hit):
            raise ValueError(f"optimizer group {name!r} mixes per-vertex parameters with others; it cannot be remapped")
        for p in g.params:
            if id(p) in seen:
                raise ValueError(f"parameter {p.name!r} is in more than one optimizer group")
            seen.add(id(p))
        out[name] = list(g.params)
    return out
