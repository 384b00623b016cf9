"""Image losses with adjoints (docs/ARCHITECTURE.md §8). Images are ``[H, W, C]``.

===================  ======================================================================
loss                 definition
===================  ======================================================================
``l1_loss``          ``mean |pred - target|`` over all ``H·W·C`` entries
``ssim``             mean SSIM map, 11×11 Gaussian window (σ = 1.5), C1 = 0.01², C2 = 0.03²
``photometric_loss`` ``(1 − λ)·L1 + λ·(1 − SSIM)``, λ = 0.2 (the method's and 3DGS's loss)
``image_tv``         ``Σ_c Σ_{i<H-1, j≥1} sqrt((x[i,j−1] − x[i,j])² + (x[i+1,j] − x[i,j])² + eps)``
``normal_consistency`` ``mean_pixels Σ_k w_k (1 − n_kᵀ N)`` (soup fragments vs rendered normal)
===================  ======================================================================

SSIM follows 3D Gaussian Splatting's ``ssim()``: per channel, the local means, variances and
covariance are Gaussian-filtered with an 11-tap separable window (σ = 1.5, normalised to 1),
"same"-size output with **zero padding** (3DGS's ``conv2d(padding=5)``), the map
``((2μxμy + C1)(2σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2))`` (population moments,
``σx² = G*x² − μx²``) averaged over every pixel and channel (``padding="zero"``).
``padding="valid"`` averages only over pixels at least 5 px from the border: that is what
``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)`` returns (skimage filters with
reflect padding and then crops 5 px, so the padding never reaches the pixels it averages).
The data range is 1 (images in [0, 1]).

Adjoint of SSIM: with ``A1 = 2μxμy + C1``, ``A2 = 2(sxy − μxμy) + C2``, ``B1 = μx² + μy² + C1``,
``B2 = sxx − μx² + syy − μy² + C2`` (``s·· = G * (··)`` raw second moments) and the map
``m = A1 A2 / (B1 B2)``, each pixel's weight ``g = v / count`` (0 outside the averaged region)
gives ``∂A1 = g A2/(B1 B2)``, ``∂A2 = g A1/(B1 B2)``, ``∂B1 = −g m/B1``, ``∂B2 = −g m/B2``,
``∂μx = 2μy(∂A1 − ∂A2) + 2μx(∂B1 − ∂B2)``, ``∂sxx = ∂B2``, ``∂sxy = 2∂A2``; because the
zero-padded symmetric Gaussian filter is its own transpose, ``v_x = G*∂μx + 2x·G*∂sxx + y·G*∂sxy``
(and symmetrically for ``v_y``).

Backends (L1 / SSIM / photometric): ``"numpy"`` (scipy.ndimage separable filters, vectorised numpy)
and ``"opencl"`` (``kernels_cl/losses.cl``; host images are uploaded to the default device and their
adjoints downloaded). ``backend=None`` (default) follows the kind of ``pred``: device arrays run on
their device, host arrays in numpy, so the default never copies. ``bench/losses.py`` at 800×800×3
float32 on PoCL (2 shared CPU cores), forward + backward: numpy 56–89 ms, OpenCL on device arrays
61–79 ms, OpenCL from host arrays 60–148 ms (noisy, the cores were shared) — a tie on this CPU, so
the rule above; on a GPU the device path avoids the copies of the rendered image. Image TV and
normal consistency are numpy only (device inputs are downloaded; the tape uploads their adjoints
where a device variable needs them).

Every function validates its inputs and raises ``ValueError`` naming the argument (shape, dims,
dtype, NaN/Inf on host data).
"""

from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import scipy.ndimage

from triplet_cl.autodiff import Function, to_host
from triplet_cl.ops.common import device_empty, round_up

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
SSIM_RADIUS = SSIM_WINDOW // 2
DEFAULT_LAMBDA = 0.2
TV_EPS = 1e-8


# ---------------------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------------------
def _check_array(name: str, a, ndim: int | None = None):
    """A floating host array (finite) or device array; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(a, cla.Array):
        if a.dtype not in (np.float32, np.float64):
            raise ValueError(f"{name} must be a float32/float64 device array, got {a.dtype}")
        out = a
    else:
        out = np.asarray(a)
        if out.dtype.kind != "f":
            raise ValueError(f"{name} must be a floating-point array, got dtype {out.dtype}")
        if out.size and not np.isfinite(out).all():
            raise ValueError(f"{name} must be finite, found {int((~np.isfinite(out)).sum())} NaN/Inf value(s)")
    if ndim is not None and len(out.shape) != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {list(out.shape)}")
    return out


def _check_image(name: str, img, min_size: int = 1):
    img = _check_array(name, img, ndim=3)
    h, w, c = img.shape
    if h < min_size or w < min_size or c < 1:
        raise ValueError(f"{name} must have shape [H>={min_size}, W>={min_size}, C>=1], got {list(img.shape)}")
    return img


def _check_pair(pred, target, min_size: int = 1):
    pred = _check_image("pred", pred, min_size)
    target = _check_image("target", target, min_size)
    if tuple(pred.shape) != tuple(target.shape):
        raise ValueError(f"target must have the shape of pred {list(pred.shape)}, got {list(target.shape)}")
    if isinstance(pred, cla.Array) != isinstance(target, cla.Array):
        raise ValueError("pred and target must both be host arrays or both device arrays")
    return pred, target


def _float_dtype(*arrays):
    return np.result_type(*[a.dtype for a in arrays], np.float32)


# ---------------------------------------------------------------------------------------------
# L1
# ---------------------------------------------------------------------------------------------
def _l1_fwd(pred, target):
    return np.asarray(np.mean(np.abs(pred - target), dtype=np.float64))


def _l1_bwd(pred, target, v):
    v_pred = np.sign(pred - target) * (float(v) / pred.size)
    return v_pred.astype(_float_dtype(pred, target), copy=False)


# ---------------------------------------------------------------------------------------------
# SSIM (numpy)
# ---------------------------------------------------------------------------------------------
def gaussian_window_1d(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    """``[size]`` float64 Gaussian taps ``exp(−(k − size//2)² / 2σ²)`` normalised to sum 1 (3DGS)."""
    k = np.arange(size, dtype=np.float64) - size // 2
    g = np.exp(-(k**2) / (2.0 * sigma**2))
    return g / g.sum()


def gaussian_filter_zero(x: np.ndarray, window: np.ndarray | None = None) -> np.ndarray:
    """``[H, W, ...] -> [H, W, ...]``: separable Gaussian over axes 0 and 1, zero padding, same size.

    Symmetric taps + zero padding make this linear map its own transpose (used by the adjoints).
    """
    w = gaussian_window_1d() if window is None else window
    w = w.astype(x.dtype)
    out = scipy.ndimage.correlate1d(x, w, axis=0, mode="constant", cval=0.0)
    return scipy.ndimage.correlate1d(out, w, axis=1, mode="constant", cval=0.0)


def _ssim_mask(shape, padding: str) -> tuple[tuple[slice, slice], int]:
    """The averaged region (rows, cols) and its entry count for ``padding`` ("zero" or "valid")."""
    h, w, c = shape
    if padding == "zero":
        return (slice(0, h), slice(0, w)), h * w * c
    if padding == "valid":
        r = SSIM_RADIUS
        if h <= 2 * r or w <= 2 * r:
            raise ValueError(f"padding='valid' needs images larger than {2 * r}×{2 * r}, got {list(shape)}")
        return (slice(r, h - r), slice(r, w - r)), (h - 2 * r) * (w - 2 * r) * c
    raise ValueError(f"padding must be 'zero' (3DGS) or 'valid' (skimage), got {padding!r}")


def _ssim_fwd(pred: np.ndarray, target: np.ndarray, padding: str):
    """SSIM value and what the adjoint needs (the filtered moments and the A/B factors)."""
    region, count = _ssim_mask(pred.shape, padding)
    c = pred.shape[2]
    dtype = _float_dtype(pred, target)
    x, y = pred.astype(dtype, copy=False), target.astype(dtype, copy=False)
    f = gaussian_filter_zero(np.concatenate([x, y, x * x, y * y, x * y], axis=2))
    mu_x, mu_y, s_xx, s_yy, s_xy = (f[..., k * c:(k + 1) * c] for k in range(5))
    mu_xy = mu_x * mu_y
    a1 = 2.0 * mu_xy + SSIM_C1
    a2 = 2.0 * (s_xy - mu_xy) + SSIM_C2
    b1 = mu_x * mu_x + mu_y * mu_y + SSIM_C1
    b2 = (s_xx + s_yy - mu_x * mu_x - mu_y * mu_y) + SSIM_C2
    ssim_map = (a1 * a2) / (b1 * b2)
    value = np.asarray(np.sum(ssim_map[region], dtype=np.float64) / count)
    return value, (x, y, mu_x, mu_y, a1, a2, b1, b2, ssim_map, region, count)


def _ssim_bwd(saved, v, need_target: bool = True):
    """``(v_pred, v_target)`` of the mean SSIM for the scalar adjoint ``v`` (see module docstring)."""
    x, y, mu_x, mu_y, a1, a2, b1, b2, ssim_map, region, count = saved
    g = np.zeros_like(ssim_map)
    g[region] = float(v) / count
    d = g / (b1 * b2)
    d_a1, d_a2 = d * a2, d * a1  # ∂m/∂A1, ∂m/∂A2 (times g)
    d_b1, d_b2 = -g * ssim_map / b1, -g * ssim_map / b2
    # A1, A2, B1, B2 through μx, μy, sxx (=syy share ∂B2), sxy
    d_mu_x = 2.0 * (mu_y * (d_a1 - d_a2) + mu_x * (d_b1 - d_b2))
    maps = [d_mu_x, d_b2, 2.0 * d_a2]
    if need_target:
        maps.append(2.0 * (mu_x * (d_a1 - d_a2) + mu_y * (d_b1 - d_b2)))
    c = x.shape[2]
    f = gaussian_filter_zero(np.concatenate(maps, axis=2))
    f_mu_x, f_ss, f_xy = (f[..., k * c:(k + 1) * c] for k in range(3))
    v_x = f_mu_x + 2.0 * x * f_ss + y * f_xy
    v_y = f[..., 3 * c:] + 2.0 * y * f_ss + x * f_xy if need_target else None
    return v_x, v_y


# ---------------------------------------------------------------------------------------------
# image TV
# ---------------------------------------------------------------------------------------------
def _tv_terms(img: np.ndarray, eps: float):
    dx = img[:-1, :-1] - img[:-1, 1:]  # x[i, j-1] - x[i, j]  for i < H-1, j >= 1
    dy = img[1:, 1:] - img[:-1, 1:]  # x[i+1, j] - x[i, j]
    return dx, dy, np.sqrt(dx * dx + dy * dy + eps)


def _tv_bwd(img: np.ndarray, eps: float, scale: float) -> np.ndarray:
    dx, dy, t = _tv_terms(img, eps)
    a = scale / t
    v = np.zeros_like(img)
    v[:-1, :-1] += a * dx
    v[:-1, 1:] -= a * (dx + dy)
    v[1:, 1:] += a * dy
    return v


def reduction_scale(reduction: str, count: int) -> float:
    """The factor of a ``reduction`` (``"mean"``: 1 / count, ``"sum"``: 1) over ``count`` terms."""
    if reduction == "mean":
        return 1.0 / max(count, 1)
    if reduction == "sum":
        return 1.0
    raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")


# ---------------------------------------------------------------------------------------------
# normal consistency
# ---------------------------------------------------------------------------------------------
def _check_normal_inputs(normals, weights, rendered_normal):
    normals = to_host(_check_array("normals", normals))
    weights = to_host(_check_array("weights", weights))
    rendered_normal = to_host(_check_array("rendered_normal", rendered_normal))
    if normals.ndim < 2 or normals.shape[-1] != 3:
        raise ValueError(f"normals must have shape [..., K, 3], got {list(normals.shape)}")
    if tuple(weights.shape) != tuple(normals.shape[:-1]):
        raise ValueError(f"weights must have shape {list(normals.shape[:-1])} (normals without the 3), "
                         f"got {list(weights.shape)}")
    if tuple(rendered_normal.shape) != tuple(normals.shape[:-2]) + (3,):
        raise ValueError(f"rendered_normal must have shape {list(normals.shape[:-2]) + [3]}, "
                         f"got {list(rendered_normal.shape)}")
    return normals, weights, rendered_normal


# ---------------------------------------------------------------------------------------------
# tape functions
# ---------------------------------------------------------------------------------------------
def _resolve_backend(backend: str | None, data) -> str:
    if backend is None:  # the kind of the data: no host<->device copy (bench/losses.py: a tie on PoCL)
        return "opencl" if isinstance(data, cla.Array) else "numpy"
    if backend not in ("numpy", "opencl"):
        raise ValueError(f"backend must be None, 'numpy' or 'opencl', got {backend!r}")
    return backend


class PhotometricLoss(Function):
    """Tape op ``(pred [H,W,C], target [H,W,C]) -> (1 − λ)·mean|pred − target| + λ·(1 − SSIM)``.

    ``lam=0`` is the L1 loss, ``lam=1`` the D-SSIM loss. ``padding``: "zero" (3DGS) or "valid"
    (skimage's cropped mean). ``backend``: None (the kind of ``pred``), "numpy" or "opencl".
    """

    def __init__(self, lam: float = DEFAULT_LAMBDA, padding: str = "zero", backend: str | None = None):
        if not 0.0 <= float(lam) <= 1.0:
            raise ValueError(f"lam must lie in [0, 1], got {lam}")
        _ssim_mask((100, 100, 1), padding)  # validates the name
        self.lam, self.padding, self.backend = float(lam), padding, backend

    def forward(self, ctx, pred, target):
        pred, target = _check_pair(pred, target, min_size=2 * SSIM_RADIUS + 1 if self.padding == "valid" else 1)
        ctx.backend = _resolve_backend(self.backend, pred)
        if ctx.backend == "opencl":
            return _cl_photometric_fwd(ctx, pred, target, self.lam, self.padding)
        pred, target = to_host(pred), to_host(target)
        value = 0.0
        ctx.l1 = ctx.ssim = None
        if self.lam < 1.0:
            ctx.l1 = (pred, target)
            value += (1.0 - self.lam) * float(_l1_fwd(pred, target))
        if self.lam > 0.0:
            s, ctx.ssim = _ssim_fwd(pred, target, self.padding)
            value += self.lam * (1.0 - float(s))
        return np.asarray(value)

    def backward(self, ctx, v):
        if ctx.backend == "opencl":
            return _cl_photometric_bwd(ctx, v)
        need_t = ctx.needs_input_grad[1]
        v_pred = v_target = None
        if ctx.l1 is not None:
            v_pred = _l1_bwd(*ctx.l1, (1.0 - self.lam) * float(v))
            v_target = -v_pred if need_t else None
        if ctx.ssim is not None:
            sx, sy = _ssim_bwd(ctx.ssim, -self.lam * float(v), need_t)
            v_pred = sx if v_pred is None else v_pred + sx
            if need_t:
                v_target = sy if v_target is None else v_target + sy
        return v_pred, v_target


class L1Loss(PhotometricLoss):
    """Tape op ``(pred [H,W,C], target [H,W,C]) -> mean |pred − target|`` (scalar)."""

    def __init__(self, backend: str | None = None):
        super().__init__(lam=0.0, backend=backend)


class SSIM(Function):
    """Tape op ``(pred [H,W,C], target [H,W,C]) -> mean SSIM`` (scalar; see module docstring)."""

    def __init__(self, padding: str = "zero", backend: str | None = None):
        self.dssim = PhotometricLoss(lam=1.0, padding=padding, backend=backend)

    def forward(self, ctx, pred, target):
        return np.asarray(1.0 - float(self.dssim.forward(ctx, pred, target)))

    def backward(self, ctx, v):
        return self.dssim.backward(ctx, -v)


class ImageTV(Function):
    """Tape op ``img [H,W,C] -> TV`` (scalar): ``Σ sqrt(dx² + dy² + eps)`` over the ``(H−1)(W−1)C``
    pixels with both neighbours (``dx = x[i,j−1] − x[i,j]``, ``dy = x[i+1,j] − x[i,j]``), divided
    by their count when ``reduction="mean"`` (default; the scale the method's 0.01 weight expects)."""

    def __init__(self, eps: float = TV_EPS, reduction: str = "mean"):
        if eps <= 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        reduction_scale(reduction, 1)
        self.eps, self.reduction = float(eps), reduction

    def forward(self, ctx, img):
        img = to_host(_check_image("img", img))
        h, w, c = img.shape
        ctx.img, ctx.scale = img, reduction_scale(self.reduction, (h - 1) * (w - 1) * c)
        return np.asarray(np.sum(_tv_terms(img, self.eps)[2], dtype=np.float64) * ctx.scale)

    def backward(self, ctx, v):
        return _tv_bwd(ctx.img, self.eps, ctx.scale * float(v))


class NormalConsistencyLoss(Function):
    """Tape op for the soup's normal consistency (mean over pixels of ``Σ_k w_k (1 − n_kᵀ N)``).

    Inputs (``P...`` = any pixel shape, e.g. ``[H, W]``; ``K`` fragments per pixel):
        normals ``[P..., K, 3]``: unit normal of the face in fragment slot k (anything where w = 0),
        weights ``[P..., K]``: its blend weight ``w_k = α_k Π_{j<k}(1 − α_j)`` (0 for empty slots),
        rendered_normal ``[P..., 3]``: the rendered normal ``N`` (e.g. ``normalize(Σ_k w_k n_k)``).
    Adjoints: ``v_w_k = (1 − n_k·N)/P``, ``v_n_k = −w_k N/P``, ``v_N = −Σ_k w_k n_k / P`` with ``P``
    the pixel count; pass ``N`` as a constant to treat it as a target (stop-gradient).
    """

    def forward(self, ctx, normals, weights, rendered_normal):
        n, w, big_n = _check_normal_inputs(normals, weights, rendered_normal)
        pixels = max(int(np.prod(w.shape[:-1])), 1)
        cos = np.einsum("...kd,...d->...k", n, big_n)
        ctx.save(n, w, big_n, cos, 1.0 / pixels)
        return np.asarray(np.sum(w * (1.0 - cos), dtype=np.float64) / pixels)

    def backward(self, ctx, v):
        n, w, big_n, cos, inv_p = ctx.saved
        s = float(v) * inv_p
        v_n = -s * w[..., None] * big_n[..., None, :] if ctx.needs_input_grad[0] else None
        v_w = s * (1.0 - cos) if ctx.needs_input_grad[1] else None
        v_big_n = -s * np.einsum("...k,...kd->...d", w, n) if ctx.needs_input_grad[2] else None
        return v_n, v_w, v_big_n


# ---------------------------------------------------------------------------------------------
# functional forms (arrays or Variables)
# ---------------------------------------------------------------------------------------------
def l1_loss(pred, target, backend: str | None = None):
    """``mean |pred − target|`` of ``[H,W,C]`` images; a 0-d array (a Variable for Variable inputs)."""
    return L1Loss(backend)(pred, target)


def ssim(pred, target, padding: str = "zero", backend: str | None = None):
    """Mean SSIM of ``[H,W,C]`` images in [0, 1] (see module docstring for ``padding``)."""
    return SSIM(padding, backend)(pred, target)


def dssim_loss(pred, target, padding: str = "zero", backend: str | None = None):
    """``1 − SSIM`` of ``[H,W,C]`` images."""
    return PhotometricLoss(1.0, padding, backend)(pred, target)


def photometric_loss(pred, target, lam: float = DEFAULT_LAMBDA, padding: str = "zero", backend: str | None = None):
    """``(1 − λ)·L1 + λ·(1 − SSIM)`` of ``[H,W,C]`` images (λ = 0.2 by default)."""
    return PhotometricLoss(lam, padding, backend)(pred, target)


# host images above this many pixels go through the losses.cl kernels in the training loop: measured on
# PoCL (2 cores, loaded), loss + adjoint numpy vs OpenCL: 48² 1.5 vs 4.8 ms, 96² 5.0 vs 5.0 ms, 128² 12.9 vs
# 7.0 ms, 200² 56 vs 26 ms, 400² 197 vs 85 ms
DEVICE_LOSS_MIN_PIXELS = 96 * 96 + 1


# the same choice when the rendered image is already on the device (RenderResult.device_image: no upload of the
# prediction, no download of its adjoint, the backward seeded there). Measured in the training loop (PoCL, 2 cores,
# loaded; loss + backward per step, median of 28 steps, host vs device alternating, spot_small / spot): 24² 19.1 vs
# 18.0 ms, 48² 21.9 vs 20.1 and 30.0 vs 26.3, 96² 38.5 vs 39.9 and 40.3 vs 39.4 (25th percentiles 31.7 vs 19.8
# and 38.5 vs 35.7), 100² 48.8 vs 42.4: a tie up to 96², faster above. The threshold stays the host images' one: below
# it the float32 kernels would change the small-image trajectories (the demo: test PSNR +0.16 and -0.24 dB in two
# back-to-back runs, inside its 0.4 dB seed spread, for no measurable time) where numpy keeps them bit for bit
DEVICE_LOSS_RESIDENT_MIN_PIXELS = DEVICE_LOSS_MIN_PIXELS


def loss_backend(shape, resident: bool = False) -> str:
    """The faster backend for images of ``shape [H, W, ...]``: "opencl" from :data:`DEVICE_LOSS_MIN_PIXELS`
    pixels on for host images (upload, kernels, download), from :data:`DEVICE_LOSS_RESIDENT_MIN_PIXELS` for a
    prediction already on the device (``resident``), else "numpy"."""
    n = int(shape[0]) * int(shape[1])
    return "opencl" if n >= (DEVICE_LOSS_RESIDENT_MIN_PIXELS if resident else DEVICE_LOSS_MIN_PIXELS) else "numpy"


def photometric_loss_and_grad(pred, target, lam: float = DEFAULT_LAMBDA, padding: str = "zero",
                              backend: str | None = None):
    """``(loss: float, v_pred [H,W,C])`` without a tape (the training loop's one-liner)."""
    from triplet_cl.autodiff import Context

    fn = PhotometricLoss(lam, padding, backend)
    ctx = Context((True, False))
    value = fn.forward(ctx, pred, target)
    return float(value), fn.backward(ctx, np.asarray(1.0))[0]


def image_tv(img, eps: float = TV_EPS, reduction: str = "mean"):
    """Total variation of an ``[H,W,C]`` image (see :class:`ImageTV`)."""
    return ImageTV(eps, reduction)(img)


def normal_consistency(normals, weights, rendered_normal):
    """Soup normal consistency (see :class:`NormalConsistencyLoss` for shapes)."""
    return NormalConsistencyLoss()(normals, weights, rendered_normal)


# ---------------------------------------------------------------------------------------------
# OpenCL backend (kernels_cl/losses.cl)
# ---------------------------------------------------------------------------------------------
_CL_SCRATCH: dict = {}  # (context, dtype, shape) -> [tmp [5,H,W,C], tmp2 [4,H,W,C], window [11]]


def _cl_device(arr):
    """The :class:`triplet_cl.device.Device` owning ``arr``'s context."""
    from triplet_cl import device as devmod

    dev = devmod.get_device()
    if dev.ctx == arr.context:
        return dev
    for d in list(devmod._DEVICES.values()):
        if d.ctx == arr.context:
            return d
    raise ValueError("pred must live in the context of a triplet_cl Device (get_device()) for backend='opencl'")


def _ch_defines(c: int) -> dict | None:
    """``CH3`` for three channels: losses.cl takes a pixel's channels as one vector (the same bits)."""
    return {"CH3": True} if c == 3 else None


def _lanes(dev, c: int) -> bool:
    """Whether the photometric passes run as losses.cl's ``*8`` kernels (eight pixels of a row per work-item in
    vector lanes, the same operations per pixel in the same order): on a CPU device, for colour images (PoCL
    vectorises the one-pixel kernels neither across work-items nor over the taps; a GPU keeps one pixel per
    work-item)."""
    return c == 3 and dev.is_cpu


#: values of slack past the end of the SSIM scratch maps (tmp, d, tmp2): one work-item's 8 pixels x 3 channels
NV_SLACK = 24


def _pass_grid(dev, h: int, w: int, c: int):
    """``(global size, local size, the size arguments, kernel-name suffix)`` of a photometric pass over ``[h, w, c]``
    images: the ``*8`` kernels (:func:`_lanes`) in fixed 8 x 8 work-groups over (ceil(w / 8), h) rounded up (left to
    the runtime, PoCL picked groups of one work-item for an odd width: 4x slower than the one-pixel kernels), with no
    channel argument; else one work-item per pixel, the runtime's choice of group."""
    if _lanes(dev, c):
        return (round_up(-(-w // 8), 8), round_up(h, 8)), (8, 8), (np.int32(h), np.int32(w)), "8"
    return (w, h), None, (np.int32(h), np.int32(w), np.int32(c)), ""


def _cl_scratch(dev, dtype, shape):
    key = (dev.ctx, np.dtype(dtype), tuple(shape))
    sc = _CL_SCRATCH.get(key)
    if sc is None:
        n = int(np.prod(shape))
        dev.check_alloc(5 * n * np.dtype(dtype).itemsize, "the SSIM scratch buffer")
        window = cla.to_device(dev.queue, gaussian_window_1d().astype(dtype))
        # NV_SLACK values past the end: the *8 kernels' vertical taps read a row's last eight pixels in place, past the
        # image's end on its last row (values only lanes that are never stored see)
        sc = (device_empty(dev.queue, (5 * n + NV_SLACK,), dtype), device_empty(dev.queue, (4 * n + NV_SLACK,), dtype),
              window)
        _CL_SCRATCH.clear()  # keep one size class (the training resolution) alive
        _CL_SCRATCH[key] = sc
    return sc


def _cl_photometric_fwd(ctx, pred, target, lam, padding):
    """Device forward: two filter passes + a sum; saves the unit-seed SSIM maps for the adjoint."""
    ctx.download = not isinstance(pred, cla.Array)
    if ctx.download:  # host images: upload to the default device, hand host adjoints back
        from triplet_cl.device import get_device

        queue = get_device().queue
        pred = cla.to_device(queue, np.ascontiguousarray(pred))
        target = cla.to_device(queue, np.ascontiguousarray(target, dtype=pred.dtype))
    if pred.dtype != target.dtype:
        raise ValueError(f"target must have the dtype of pred ({pred.dtype}), got {target.dtype}")
    if not (pred.flags.c_contiguous and target.flags.c_contiguous):
        raise ValueError("pred and target must be C-contiguous device arrays")
    dev = _cl_device(pred)
    real = pred.dtype.type
    h, w, c = pred.shape
    region, count = _ssim_mask(pred.shape, padding)
    border = region[0].start
    tmp, _, window = _cl_scratch(dev, pred.dtype, pred.shape)
    with_ssim = lam > 0.0
    term = cla.empty_like(pred)
    d = device_empty(dev.queue, (4 * pred.size + NV_SLACK,), pred.dtype) if with_ssim else tmp  # (tmp: unused)
    gsize, lsize, hwc, sfx = _pass_grid(dev, h, w, c)
    if with_ssim:
        dev.kernel("losses", "photometric_h_fwd" + sfx, _ch_defines(c), real=pred.dtype)(
            dev.queue, gsize, lsize, pred.data, target.data, window.data, *hwc, tmp.data)
    dev.kernel("losses", "photometric_v_fwd" + sfx, _ch_defines(c), real=pred.dtype)(
        dev.queue, gsize, lsize, pred.data, target.data, tmp.data, window.data, *hwc, real(lam), np.int32(with_ssim),
        np.int32(border), real(1.0 / count), term.data, d.data)
    ctx.dev, ctx.lam, ctx.with_ssim, ctx.saved_cl = dev, lam, with_ssim, (pred, target, d)
    # the [H, W, C] terms summed in float64 on the host: download + numpy's pairwise sum measured 4x faster than
    # pyopencl's float64 reduction on PoCL (200²: 0.25 -> 0.06 ms, 800²: 4.2 -> 1.1 ms); the same float64 sum of
    # the same float32 terms up to the summation order (the value only: the adjoint seeds with v, not with it)
    return np.asarray(lam + float(term.get().sum(dtype=np.float64)))


def _cl_photometric_bwd(ctx, v):
    """Device adjoint: two filter passes; returns device ``(v_pred, v_target | None)``."""
    dev, lam = ctx.dev, ctx.lam
    pred, target, d = ctx.saved_cl
    real = pred.dtype.type
    h, w, c = pred.shape
    _, tmp2, window = _cl_scratch(dev, pred.dtype, pred.shape)
    want_t = bool(ctx.needs_input_grad[1])
    v_pred = cla.empty_like(pred)
    v_target = cla.empty_like(pred) if want_t else v_pred
    gsize, lsize, hwc, sfx = _pass_grid(dev, h, w, c)
    if ctx.with_ssim:
        dev.kernel("losses", "photometric_h_bwd" + sfx, _ch_defines(c), real=pred.dtype)(
            dev.queue, gsize, lsize, d.data, window.data, *hwc, tmp2.data)
    dev.kernel("losses", "photometric_v_bwd" + sfx, _ch_defines(c), real=pred.dtype)(
        dev.queue, gsize, lsize, pred.data, target.data, tmp2.data, window.data, *hwc, real(lam),
        np.int32(ctx.with_ssim), real(float(v)), np.int32(want_t), v_pred.data, v_target.data)
    if ctx.download:
        return v_pred.get(), (v_target.get() if want_t else None)
    return v_pred, (v_target if want_t else None)


# ---------------------------------------------------------------------------------------------
# the numpy loss's adjoint on the device, bit for bit (kernels_cl/ssim_exact.cl)
# ---------------------------------------------------------------------------------------------
# its work-groups: 8 work-items of 8 lanes each along a padded row (bench/results/ssim_exact_lanes_pocl_2026-11-29.txt)
SSIM_LANES_GROUP = 8


def exact_device_loss_available(device, pred, lam: float) -> bool:
    """Whether :func:`photometric_loss_and_grad_exact` serves ``pred`` (``[H, W, C]`` float32 device array) on
    ``device``: the kernels widen to double (cl_khr_fp64), as scipy's filter loop does."""
    return bool(device.fp64) and isinstance(pred, cla.Array) and pred.dtype == np.float32 and pred.ndim == 3 \
        and pred.flags.c_contiguous and 0.0 < float(lam) < 1.0


class ExactLoss:
    """The value of :func:`photometric_loss_and_grad_exact`: the SSIM map comes down without a wait, and
    :meth:`value` sums it (and the L1 term) on the host as the numpy reference does, once it is there."""

    def __init__(self, pred_host, target, ssim_map, event, lam: float, count: int):
        self.pred_host, self.target, self.ssim_map, self.event = pred_host, target, ssim_map, event
        self.lam, self.count = lam, count

    def value(self) -> float:
        self.event.wait()
        value = 0.0  # PhotometricLoss.forward's numpy branch, padding "zero"
        value += (1.0 - self.lam) * float(_l1_fwd(self.pred_host, self.target))
        s = np.asarray(np.sum(self.ssim_map, dtype=np.float64) / self.count)
        value += self.lam * (1.0 - float(s))
        return float(np.asarray(value))


def photometric_loss_and_grad_exact(device, pred, pred_host, target, lam: float = DEFAULT_LAMBDA):
    """``(ExactLoss, v_pred [H, W, C] device array)``: :func:`photometric_loss_and_grad` with
    ``backend="numpy"`` (padding "zero") for a rendered image ``pred`` already on ``device`` (``pred_host`` its
    host copy, ``target`` the host target), computed by ``ssim_exact.cl`` **bit for bit** as the numpy reference
    (every float32 operation in its order, the Gaussian passes in double as scipy's ``correlate1d``): the
    training loop's small images keep their trajectories (a float32 device loss moved the demo's test PSNR by up
    to 0.24 dB), and the host neither computes the loss nor uploads its adjoint. The loss value is summed on the
    host from the SSIM map (:meth:`ExactLoss.value`). Needs :func:`exact_device_loss_available`."""
    import pyopencl as cl

    from .ops.common import const_array, round_up

    if not exact_device_loss_available(device, pred, lam):
        raise ValueError("the exact device loss needs a C-contiguous float32 [H, W, C] device image, an fp64 device "
                         "and 0 < lam < 1")
    h, w, c = pred.shape
    target = np.ascontiguousarray(target, np.float32)
    if target.shape != (h, w, c):
        raise ValueError(f"target must have the shape of pred {[h, w, c]}, got {list(target.shape)}")
    n = h * w * c
    q, alloc = device.queue, device.allocator
    target_d = cla.to_device(q, target, allocator=alloc)  # the queue is idle here (the render read its image)
    win = gaussian_window_1d().astype(np.float32).astype(np.float64)
    taps = const_array(device, np.ascontiguousarray(win[SSIM_RADIUS::-1]))  # w0 (centre), w1 … w5
    # the maps' padded layout (ssim_exact.cl): rows of S values (R·C zeros, the row, zeros up to a multiple of 8),
    # R rows of zeros above and below; one work-item per 8 values of a padded row, on fixed work-groups (one build)
    r = SSIM_RADIUS
    S = round_up(2 * r * c + w * c, 8)
    rows = h + 2 * r
    src = device_empty(q, (5 * rows * S,), np.float32, allocator=alloc)
    tmp = device_empty(q, (5 * h * S + 2 * r * c,), np.float32, allocator=alloc)  # R·C margin either side
    dmaps = device_empty(q, (3 * rows * S,), np.float32, allocator=alloc)
    smap = device_empty(q, (h, w, c), np.float32, allocator=alloc)
    v_pred = device_empty(q, (h, w, c), np.float32, allocator=alloc)
    lanes_x = round_up(S // 8, SSIM_LANES_GROUP)
    lsize = (SSIM_LANES_GROUP, 1)
    i32 = np.int32
    device.kernel("ssim_exact", "ssim_x_maps8")(q, (lanes_x, rows), lsize, pred.data, target_d.data, i32(h), i32(w),
                                                i32(c), i32(S), src.data)
    device.kernel("ssim_exact", "ssim_x_rows8", {"KMAPS": 5})(q, (lanes_x, h), lsize, src.data, taps.data, i32(h),
                                                               i32(c), i32(S), tmp.data)
    g = np.float32(-lam * 1.0 / n)  # _ssim_bwd's seed: float(v) / count with v = -λ·1, rounded to float32
    device.kernel("ssim_exact", "ssim_x_fwd8")(q, (lanes_x, rows), lsize, tmp.data, taps.data, i32(h), i32(w), i32(c),
                                               i32(S), np.float32(SSIM_C1), np.float32(SSIM_C2), g, smap.data,
                                               dmaps.data)
    host_map = np.empty((h, w, c), np.float32)
    ev = cl.enqueue_copy(q, host_map, smap.data, is_blocking=False)
    device.kernel("ssim_exact", "ssim_x_rows8", {"KMAPS": 3})(q, (lanes_x, h), lsize, dmaps.data, taps.data, i32(h),
                                                               i32(c), i32(S), tmp.data)
    l1 = np.float32((1.0 - lam) * 1.0 / n)  # _l1_bwd's factor float(v) / size with v = (1 − λ)·1
    device.kernel("ssim_exact", "ssim_x_bwd8")(q, (lanes_x, h), lsize, pred.data, target_d.data, tmp.data, taps.data,
                                               i32(h), i32(w), i32(c), i32(S), l1, v_pred.data)
    # the scratch arrays go back to the pool only once their kernels are done: keep them with the value
    loss = ExactLoss(pred_host, target, host_map, ev, float(lam), n)
    loss._keep = (target_d, src, tmp, dmaps, smap)
    return loss, v_pred
