"""``render(scene, camera, settings)``: the differentiable image formation of the method, on the tape.

Graph (every box a :class:`~triplet_cl.autodiff.Function` with a hand-derived adjoint)::

    V ─┬─ Normals ───────────────┐
       ├─ VertexSH(V, vsh) ──────┤ (optional)
    material ─ MaterialActivation┤
    alpha ─ Sigmoid ─────────────┤
       └─────────────────────────┴─ Concat → attr [N, C]
       (settings.attributes == "device", the default: one VertexAttributes op builds the same attr
        on the device, normals included, and takes its adjoint apart there; the chain above is
        its reference and the fallback for layouts it does not handle)
    RasterInterpolate(V, attr)  → fragment attributes [P, C], coverage window [P] (packed fragments)
    ShadeFragments(…, light_params) → rgb [P, 3], alpha [P]
    Composite(rgb, alpha, win)  → image [H, W, 3], accumulated alpha [H, W]

Renderers (``RenderSettings.renderer``): ``"raster"`` (the graph above); ``"raytrace"``: the
fragments come from the K nearest hits of camera rays through a BVH (``ops/trace.py``; same
``Fragments``, so every op and adjoint after it is shared), and shading adds ray-traced shadows
(transmittance ``Π(1−α)`` towards point/directional lights) and one mirror reflection bounce;
``"hybrid"``: rasterized primary visibility with the ray-traced shadows and bounce. The traced terms
live in :class:`TracedShadeFragments`, which also takes the packed attributes so that occluders and
bounce hits receive their gradients.

One packed per-vertex attribute array is interpolated once and its adjoint, together with those of
the barycentrics and the coverage window, comes back in one fused pass
(:func:`~triplet_cl.ops.raster.fragments_backward`).
"""

from __future__ import annotations

from contextlib import nullcontext as _nullcontext
from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from .activations import sigmoid, sigmoid_bwd, softplus, softplus_bwd
from .autodiff import Function, Tape, Variable, active_tape, to_host
from .autodiff.arrays import Deferred
from .camera import Camera
from .device import Device, get_device
from .lights import BounceLight, pack_lights
from .materials import get_brdf
from .ops import columns
from .ops import downsample as downsample_op
from .ops import normals as normals_op
from .ops import shade as shade_op
from .ops import trace as trace_op
from .ops import vertex_attr as vattr_op
from .ops import vertex_sh as vsh_op
from .ops.bvh import BVH, build_bvh, refit
from .ops.color import SRGBComposite
from .ops.common import device_empty
from .ops.composite import composite, composite_backward, coverage
from .ops.interpolate import interpolate
from .ops.mesh import DeviceMesh
from .ops.prune import prune_fragments
from .ops.raster import fragments_backward, project, project_backward, rasterize
from .ops.silhouette import silhouette_bits
from .scene import Scene

RENDERERS = ("raster", "raytrace", "hybrid")
TRANSFERS = (None, "srgb", "srgb-clip")


@dataclass
class RenderSettings:
    """How a view is rendered (every field is a run-time setting)."""

    K: int = 30  # fragments kept per pixel (the method: 150 in warm-up, then 30)
    sigma: float | None = 1.0  # soft-coverage sharpness in 1/pixels; None = hard edges (original method)
    soft_edges: str = "all"  # window on "all" edges (a soup) or the "silhouette" only (a connected mesh: no seams)
    background: tuple = (1.0, 1.0, 1.0)  # RGB behind the scene
    t_min: float = 1e-4  # compositing stops below this transmittance
    normals: str = "face"  # "face": per-face normal of each triplet; "vertex": area-weighted vertex normals
    two_sided: bool = True  # flip normals facing away from the camera (right for a soup)
    cull_backface: bool = False  # drop back-facing triangles in the rasterizer
    sh_degree: int | None = None  # active vertex-SH degree (None: all bands of the coefficients)
    real: type = np.float32  # float32 in production; float64 for gradient checks
    renderer: str = "raster"  # "raster" | "raytrace" (BVH primary rays) | "hybrid" (raster primary)
    shadows: bool = True  # raytrace/hybrid: ray-traced shadows of point and directional lights
    reflections: bool = True  # raytrace/hybrid: one mirror reflection bounce (glossy weight of env_scales)
    # ray start offset, × the scene's bounding-box diagonal: past the soup's own layer of overlapping triplets
    # (measured on spot_small, hybrid, 800 it.: 1e-4 → 30.45 dB and more baked shadow than raster, 1e-2 → 31.06 dB)
    ray_eps: float = 1e-2
    # the image formation after compositing: None = the composite of the shaded values over ``background`` is the
    # image (values in whatever space the scene was fitted in); "srgb" = shading and compositing are linear
    # radiance (over black), then ``A·s(C/A) + (1−A)·background`` with s the sRGB transfer (ops/color.py): the
    # model of straight-alpha sRGB-encoded photos composited over ``background`` in encoded space; "srgb-clip" the
    # same with the encoded colour saturating at 1 (8/16-bit photos clip there: TrainConfig.sensor_clip)
    transfer: str | None = None
    # where the per-vertex attribute array (positions, normals, activated materials and alpha) is built:
    # "device" (one kernel, ops/vertex_attr.py; the default) or "host" (the numpy chain Normals →
    # MaterialActivation → SigmoidHost → Concat: the reference the device op is tested against)
    attributes: str = "device"
    # the camera renders ``downsample ×`` the output's resolution and each block is averaged (the linear premultiplied
    # radiance and the alpha, before the transfer: as a camera integrates a pixel; ops/downsample.py, on the device):
    # the mesh stage's supersampling. The camera given to render() is the supersampled one
    downsample: int = 1
    # the capture's pixel filter, in output pixels: 0 averages each downsample block (a box); > 0 weights the samples
    # by a Gaussian of this standard deviation between their centres and the pixel's, truncated at 4 sigma (a film's
    # reconstruction filter; ops/downsample.py), also with downsample 1 (it then blurs the render)
    pixel_sigma: float = 0.0
    # drop the fragments behind each pixel's t_min cut-off before shading (ops/prune.py; raster only): the image and
    # every gradient are the full list's, the shading and its adjoints run on fewer fragments. The mesh stage's
    # renders (an opaque mesh: one fragment per covered pixel instead of its front and back faces); the soup's
    # training keeps the full list, which its density statistics read
    prune: bool = False

    def __post_init__(self):
        from .ops.raster import K_LIMIT

        if isinstance(self.K, bool) or not isinstance(self.K, int | np.integer) or not 1 <= self.K <= K_LIMIT:
            raise ValueError(f"K must be in [1, {K_LIMIT}] (an integer: fragments kept per pixel), got {self.K!r}")
        self.background = settings_background(self.background)
        if self.attributes not in ("device", "host"):
            raise ValueError(f"attributes must be 'device' or 'host', got {self.attributes!r}")
        if self.transfer not in TRANSFERS:
            raise ValueError(f"transfer must be one of {TRANSFERS}, got {self.transfer!r}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        if not (np.isfinite(self.ray_eps) and self.ray_eps >= 0):
            raise ValueError(f"ray_eps must be a finite number >= 0, got {self.ray_eps}")
        if self.normals not in ("face", "vertex"):
            raise ValueError(f"normals must be 'face' or 'vertex', got {self.normals!r}")
        if self.soft_edges not in ("all", "silhouette"):
            raise ValueError(f"soft_edges must be 'all' or 'silhouette', got {self.soft_edges!r}")
        if self.renderer == "raytrace" and self.soft_edges != "all" and self.sigma is not None:
            raise ValueError("renderer='raytrace' supports soft_edges='all' only (its primary hits take the window "
                             "of every edge); use renderer='hybrid' for soft_edges='silhouette'")
        if self.sigma is not None and not (np.isfinite(self.sigma) and self.sigma > 0):
            raise ValueError(f"sigma must be positive or None, got {self.sigma}")
        if not isinstance(self.downsample, (int, np.integer)) or not 1 <= self.downsample <= 16:
            raise ValueError(f"downsample must be an integer in [1, 16], got {self.downsample!r}")
        downsample_op.check_pixel_sigma("pixel_sigma", self.pixel_sigma)


def settings_background(background) -> tuple:
    """``RenderSettings.background`` as three finite floats: ``"white"`` / ``"black"`` (the names the dataset and
    training options use), one number (grey) or three; anything else a ``ValueError`` naming the field."""
    if isinstance(background, str):
        named = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}
        if background not in named:
            raise ValueError(f"background must be 'white', 'black' or three numbers (RGB), got {background!r}")
        return named[background]
    try:
        rgb = np.asarray(background, np.float64).reshape(-1)
    except (TypeError, ValueError):
        rgb = None
    if rgb is not None and rgb.shape == (1,):  # one number: grey (as the datasets' resolve_background)
        rgb = np.repeat(rgb, 3)
    if rgb is None or rgb.shape != (3,) or not np.isfinite(rgb).all():
        raise ValueError(f"background must be 'white', 'black' or three finite numbers (RGB), got {background!r}")
    return tuple(float(x) for x in rgb)


def _upload(device: Device, a: np.ndarray) -> cla.Array:
    """A host array of the forward pass on the device without waiting: a blocking write waits for every kernel
    queued before it (the shading's light table waited for the whole rasterization), a non-blocking one is
    ordered by the in-order queue alone. The host array must not change until the write is done: every caller
    hands a fresh copy or an array that stays unchanged until :func:`render` returns, and render ends with a
    blocking read (:class:`Stack`), by which the writes are done."""
    return cla.to_device(device.queue, a, async_=True)


class RenderState:
    """The state one :func:`render` call shares between its ops (device, camera, fragments ...); the
    ops hold it as ``self.view``. Not a dataset view (that is :class:`triplet_cl.datasets.View`).

    ``info`` is what the render reports to its caller (:attr:`RenderResult.info`, after gsplat's
    ``info`` dict): ``"frags"`` the :class:`~triplet_cl.ops.fragments.Fragments` of the forward pass
    (their ``face`` ids are the visible faces), ``"vs"`` ``[N, 3]`` the projected vertices (u, v, z)
    and ``"v_vs"`` ``[N, 3]`` their adjoint, set by the backward pass (None until then): the
    screen-space gradient density control accumulates. Device arrays.
    """

    def __init__(self, device: Device, mesh: DeviceMesh, camera: Camera, settings: RenderSettings):
        self.device, self.mesh, self.camera, self.settings = device, mesh, camera, settings
        self.frags = None  # Fragments of the forward pass
        self.bvh: BVH | None = None  # ray-traced renderers: the hierarchy, refitted to this view's V
        self.ray_eps = 0.0  # world-space ray offset
        self.traced: dict = {}  # ray-traced renderers: the discrete choices of the last forward pass
        self.win = None  # [P] coverage window of the forward pass (sigma set)
        self.info: dict = {"frags": None, "vs": None, "v_vs": None}
        self._V_src = self._Vd = None  # the vertex positions on the device, uploaded once per render
        self.frag_cache: FragmentCache | None = None  # render(frag_cache=...): fragments of unchanged geometry

    def device_V(self, V) -> cla.Array:
        """``V [N, 3]`` (host) on the device in the settings' REAL: uploaded once per render call and
        shared by the ops that read it (the same host array object)."""
        if self._Vd is None or self._V_src is not V:
            self._Vd = _upload(self.device, np.ascontiguousarray(V, self.settings.real))
            self._V_src = V
        return self._Vd


class FragmentCache:
    """The rasterized fragments of views whose geometry stays put, for renders that only change materials and
    lights: the metallic trial (``mesh/refine.py`` ``MeshStage.choose_metallic``: positions, faces and opacities
    fixed through its 2 × 200 steps over the same views). :func:`render` with ``frag_cache`` takes a view's
    fragments (projected, rasterized, their coverage windows and, with ``RenderSettings.prune``, pruned) from
    here when it saw the same camera with the same positions, opacities and faces, and interpolates the attributes
    on them: the render and every gradient are the same bit for bit, the geometry's forward runs once per view.
    Any change of ``V``, ``alpha`` or ``F`` empties it. Raster renders only; at most ``max_bytes`` of fragments
    are kept (views past it are rendered as without a cache), by default 768 MiB or an eighth of ``device``'s
    memory, the smaller."""

    def __init__(self, max_bytes: int | None = None, device: Device | None = None):
        if max_bytes is None:
            mem = device.info.global_mem_bytes if device is not None else 1 << 40
            max_bytes = min(768 << 20, mem // 8)
        self.max_bytes = int(max_bytes)
        self.entries: dict = {}
        self.bytes = 0
        self.hits = self.misses = 0
        self._geometry = None  # (V, alpha, F) copies the entries were made with

    def validate(self, scene: Scene) -> None:
        """Empty the cache unless ``scene``'s positions, opacities and faces are those of its entries."""
        g = self._geometry
        V, a, F = (np.asarray(x) for x in (scene.V.data, scene.alpha.data, scene.F))
        if g is None or not (np.array_equal(g[0], V) and np.array_equal(g[1], a) and np.array_equal(g[2], F)):
            self.entries.clear()
            self.bytes = 0
            self._geometry = (V.copy(), a.copy(), F.copy())

    @staticmethod
    def key(camera: Camera, settings: RenderSettings) -> tuple:
        return (camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy, camera.near, camera.far,
                np.asarray(camera.w2c, np.float64).tobytes(), settings.K, settings.sigma, settings.soft_edges,
                settings.cull_backface, settings.prune, settings.t_min, np.dtype(settings.real).str)

    def get(self, key):
        hit = self.entries.get(key)
        if hit is None:
            self.misses += 1
        else:
            self.hits += 1
        return hit

    def put(self, key, frags, win, vs) -> None:
        arrays = {id(a): a for a in (*vars(frags).values(), win, vs) if isinstance(a, cla.Array)}  # win: frags.win
        size = sum(a.nbytes for a in arrays.values())
        if self.bytes + size <= self.max_bytes:
            self.entries[key] = (frags, win, vs)
            self.bytes += size


# ---------------------------------------------------------------------------------------------- per vertex


class Normals(Function):
    """``V [N, 3] → n [N, 3]``: per-face normal of each vertex's triangle (soup) or area-weighted
    vertex normals (connected mesh). Uses the :class:`DeviceMesh` (faces and vertex→corner table
    already on the device, built once per topology)."""

    def __init__(self, mesh: DeviceMesh, mode: str, real, device: Device):
        self.mesh, self.mode, self.real, self.device = mesh, mode, real, device
        F = mesh.faces
        if mode == "face" and F.size and np.bincount(F.reshape(-1)).max() > 1:
            raise ValueError("normals='face' needs a soup (each vertex in one face); use normals='vertex'")

    def forward(self, ctx, V):
        d, m = self.device, self.mesh
        ctx.Vd = cla.to_device(d.queue, np.ascontiguousarray(V, self.real))
        n = np.zeros((V.shape[0], 3), self.real)
        if m.num_faces == 0:
            return n
        if self.mode == "vertex":
            return normals_op.vertex_forward(d, ctx.Vd, m.F, m.csr_off, m.csr_corner, self.real).get()
        fn = normals_op.face_forward(d, ctx.Vd, m.F, True, self.real).get()
        if m.corners_are_vertices:  # the training layout (face f on 3f, 3f + 1, 3f + 2): no scatter
            return np.repeat(fn, 3, axis=0)
        n[m.faces.reshape(-1)] = np.repeat(fn, 3, axis=0)  # each soup vertex takes its face's normal
        return n

    def backward(self, ctx, v_n):
        d, m = self.device, self.mesh
        v_n = np.asarray(v_n, self.real)
        if m.num_faces == 0:
            return np.zeros_like(v_n)
        if self.mode == "vertex":
            return normals_op.vertex_backward(d, ctx.Vd, m.F, cla.to_device(d.queue, v_n), m.csr_off, m.csr_corner,
                                              self.real).get()
        # adjoint of the per-corner copy (the training layout: a reshape, the same sums as the gather)
        v_c = v_n.reshape(m.num_faces, 3, 3) if m.corners_are_vertices else v_n[m.faces]
        v_fn = np.ascontiguousarray(v_c.sum(axis=1))
        return normals_op.face_backward(d, ctx.Vd, m.F, cla.to_device(d.queue, v_fn), m.csr_off, m.csr_corner,
                                        True, self.real, corners_are_vertices=m.corners_are_vertices).get()


class MaterialActivation(Function):
    """Raw ``[N, Cm]`` → activated materials: sigmoid, except the BRDF's softplus channels
    (``materials.BRDF.channels``; e.g. Blinn-Phong shininess)."""

    def __init__(self, brdf: str):
        self.softplus_cols = get_brdf(brdf).softplus_columns

    def forward(self, ctx, raw):
        y = sigmoid(raw)
        for c in self.softplus_cols:
            y[:, c] = softplus(raw[:, c])
        ctx.save(raw, y)
        return y

    def backward(self, ctx, v_y):
        raw, y = ctx.saved
        v = sigmoid_bwd(y, v_y)
        for c in self.softplus_cols:
            v[:, c] = softplus_bwd(raw[:, c], v_y[:, c])
        return v


class SigmoidHost(Function):
    """``[N, k] → [N, k]`` logistic activation of raw per-vertex values (alpha)."""

    def forward(self, ctx, x):
        y = sigmoid(x)
        ctx.save(y)
        return y

    def backward(self, ctx, v_y):
        (y,) = ctx.saved
        return sigmoid_bwd(y, v_y)


class VertexSH(Function):
    """``(V [N, 3], coeffs [N, 6, (D+1)²]) → [N, 6]`` per-vertex SH light along the view direction."""

    def __init__(self, cam_center, degree, device, real):
        self.cam, self.degree, self.device, self.real = cam_center, degree, device, real

    def forward(self, ctx, V, coeffs):
        ctx.save(V, coeffs)
        return vsh_op.vertex_sh(V, coeffs, self.cam, self.degree, device=self.device, real=self.real)

    def backward(self, ctx, v_out):
        V, coeffs = ctx.saved
        v_c, v_V = vsh_op.vertex_sh_backward(V, coeffs, self.cam, np.asarray(v_out), self.degree, device=self.device,
                                             real=self.real)
        return v_V, v_c


class Concat(Function):
    """Per-vertex blocks ``[N, c_i]`` → ``[N, Σ c_i]`` (host)."""

    def forward(self, ctx, *blocks):
        ctx.sizes = [b.shape[1] for b in blocks]
        return np.ascontiguousarray(np.concatenate(blocks, axis=1))

    def backward(self, ctx, v):
        v = np.asarray(v)
        out, c0 = [], 0
        for s in ctx.sizes:
            out.append(np.ascontiguousarray(v[:, c0:c0 + s]))
            c0 += s
        return tuple(out)


class VertexAttributes(Function):
    """``(V [N, 3], material raw [N, Cm], alpha raw [N, 1][, vlight [N, 6]]) → attr [N, C]`` (a device
    array, layout ``pos | nrm | mat | alpha [| vlight]``): what ``Concat(V, Normals(V),
    MaterialActivation(material), SigmoidHost(alpha)[, vlight])`` computes, as one kernel on the device
    (``ops/vertex_attr.py``) with the normals kept there; the adjoint takes ``v_attr`` apart on the
    device and downloads only the parameters' gradients. Applies to a soup in the training layout
    (``normals="face"``, face f on vertices 3f … 3f + 2) and to ``normals="vertex"``
    (:func:`use_device_attributes`). ``const`` (``[N, k]``, optional): constant per-vertex columns
    appended last (a block that ``Concat`` would take as a plain array: no adjoint)."""

    def __init__(self, view: RenderState, brdf: str, const: np.ndarray | None = None):
        self.view, self.softplus = view, get_brdf(brdf).softplus_columns
        self.const = None if const is None else np.asarray(const)

    def forward(self, ctx, V, material, alpha, *vl):
        v, s = self.view, self.view.settings
        d, m, real = v.device, v.mesh, s.real
        Vd = v.device_V(V)
        ctx.face = s.normals == "face"
        if ctx.face:
            nrm = normals_op.face_forward(d, Vd, m.F, True, real)  # [M, 3]: vertex i takes face i // 3
        else:
            nrm = normals_op.vertex_forward(d, Vd, m.F, m.csr_off, m.csr_corner, real)
        ctx.Vd = Vd
        ctx.mat = _upload(d, np.ascontiguousarray(material, real))
        ctx.alpha = _upload(d, np.ascontiguousarray(alpha, real).reshape(-1))
        vld = _upload(d, np.ascontiguousarray(vl[0], real)) if vl else None
        ctx.has_vl = bool(vl)
        cst = None if self.const is None else _upload(d, np.ascontiguousarray(self.const, real))
        ctx.nconst = 0 if cst is None else cst.shape[1]
        ctx.attr = vattr_op.vertex_attr(d, Vd, nrm, ctx.mat, ctx.alpha, vld, self.softplus, ctx.face, real,
                                        const=cst)
        return ctx.attr

    def backward(self, ctx, v_attr):
        v, s = self.view, self.view.settings
        d, m, real = v.device, v.mesh, s.real
        if not isinstance(v_attr, cla.Array) or v_attr.dtype != real:
            v_attr = cla.to_device(d.queue, np.ascontiguousarray(to_host(v_attr), real))
        v_pos, v_nrm, v_mat, v_alpha, v_vl = vattr_op.vertex_attr_backward(d, ctx.mat, ctx.attr, v_attr,
                                                                             self.softplus, ctx.has_vl, real,
                                                                             ctx.nconst)
        def rest():  # read back after every kernel is queued (one wait)
            return (v_mat.get(), v_alpha.get().reshape(-1, 1)) + ((v_vl.get(),) if ctx.has_vl else ())

        if not ctx.needs_input_grad[0]:  # positions held: no normals' adjoint
            return (None,) + rest()
        if ctx.face:
            v_Vn = normals_op.face_backward(d, ctx.Vd, m.F, vattr_op.face_sum3(d, v_nrm, real), m.csr_off,
                                            m.csr_corner, True, real, corners_are_vertices=True)
        else:
            v_Vn = normals_op.vertex_backward(d, ctx.Vd, m.F, v_nrm, m.csr_off, m.csr_corner, real)
        v_V = v_pos + v_Vn
        return (v_V.get(),) + rest()


def use_device_attributes(settings: RenderSettings, mesh: DeviceMesh) -> bool:
    """Whether :func:`render` builds the attribute array with :class:`VertexAttributes` (else the
    host chain): ``settings.attributes == "device"``, at least one face, and normals the device op
    handles (``"vertex"``, or ``"face"`` on a soup whose corners are its vertices)."""
    if settings.attributes != "device" or mesh.num_faces == 0:
        return False
    return settings.normals == "vertex" or mesh.corners_are_vertices


# ---------------------------------------------------------------------------------------------- per fragment


class RasterInterpolate(Function):
    """``(V [N, 3], attr [N, C]) → (frag_attr [P, C][, win [P]])`` (device arrays, packed fragments).
    ``alpha_col``: the opacity's column of ``attr``, for ``RenderSettings.prune`` (None: no pruning)."""

    def __init__(self, view: RenderState, alpha_col: int | None = None):
        self.view, self.alpha_col = view, alpha_col

    def forward(self, ctx, V, attr):
        v, s = self.view, self.view.settings
        d, cam = v.device, v.camera
        ctx.Vd = v.device_V(V)
        ctx.attr = attr if isinstance(attr, cla.Array) and attr.dtype == s.real else \
            cla.to_device(d.queue, np.ascontiguousarray(to_host(attr), s.real))
        cache = v.frag_cache if s.renderer == "raster" else None
        key = None if cache is None else FragmentCache.key(cam, s)
        hit = None if cache is None else cache.get(key)
        if hit is not None:  # the same view of the same geometry: only the attributes are interpolated again
            fr, win, vs = hit
            fa = interpolate(d, ctx.attr, fr)
        else:
            fr, fa, win, vs = self._fragments(ctx)
            if cache is not None:
                cache.put(key, fr, win, vs)
        v.frags = ctx.frags = fr
        v.info.update(frags=fr, vs=vs)
        if s.sigma is None:
            return fa
        v.win = win
        return fa, win

    def _fragments(self, ctx):
        """``(frags, frag_attr, win, vs)`` of this view: projected, rasterized (or traced), interpolated, windowed and,
        with ``RenderSettings.prune``, pruned."""
        v, s = self.view, self.view.settings
        d, cam = v.device, v.camera
        vs = project(d, ctx.Vd, cam)
        if s.renderer == "raytrace":
            fr = trace_op.trace_primary(d, v.bvh, ctx.Vd, vs, cam, s.K, s.cull_backface)
        else:
            soft = None
            if s.sigma is not None and s.soft_edges == "silhouette":
                soft = silhouette_bits(d, ctx.Vd, v.mesh, cam.center)
            fr = rasterize(d, vs, v.mesh, cam.width, cam.height, s.K, cam.near, cam.far, s.cull_backface,
                           sigma=s.sigma, soft_edges=soft)
        fa = interpolate(d, ctx.attr, fr)
        win = None if s.sigma is None else coverage(d, fr, s.sigma)
        if s.prune and self.alpha_col is not None and s.renderer == "raster" and s.t_min > 0:
            fr, fa, win = prune_fragments(d, fr, fa, self.alpha_col, win, s.t_min)
        return fr, fa, win, vs

    def backward(self, ctx, v_fa, v_win=None):
        d, s = self.view.device, self.view.settings
        if not ctx.needs_input_grad[0]:  # positions held (the metallic trial): the attributes' adjoint alone
            v_attr, _ = fragments_backward(d, ctx.frags, ctx.attr, v_fa, geometry=False)
            return None, v_attr
        v_attr, v_vs, _ = fragments_backward(d, ctx.frags, ctx.attr, v_fa, v_win=v_win,
                                             sigma=s.sigma or 0.0, want_sigma=False)  # no read-back: not used
        self.view.info["v_vs"] = v_vs  # screen-space vertex adjoint: density control's view-space gradient
        return project_backward(d, ctx.Vd, self.view.camera, v_vs), v_attr


class ShadeFragments(Function):
    """``(frag_attr [P, C][, light_params]) → (rgb [P, 3], alpha [P])``.

    The fragments are packed (``[P, C]``), so shading and its adjoint cost per fragment; the shading
    inputs are column blocks of the packed attribute array, read in place by the shading kernels, and the
    adjoint is written into the blocks of ``v_frag_attr`` by them (``ops.shade.forward_packed`` /
    ``backward_packed``: no per-block copies; :class:`TracedShadeFragments` splits the blocks out with
    ``ops.columns``, as this op did before).
    """

    #: the layout's blocks by their names in shade.cl
    PACKED_BLOCKS = {"pos": "POS", "nrm": "NRM", "mat": "MAT", "vlight": "VL", "vis": "VIS", "alpha": "ALPHA"}

    def __init__(self, view: RenderState, lights, brdf: str, layout: dict):
        self.view, self.lights, self.brdf, self.layout = view, list(lights), brdf, layout

    def _blocks(self, comp, fa, keys=("pos", "nrm", "mat", "vlight")) -> dict:
        """The shading inputs' columns of the packed fragment attributes, compacted to ``[P, c]``
        (one pass over the fragments: ``columns.split_columns``)."""
        L = self.layout
        keys = [k for k in keys if k in L]
        return dict(zip(keys, columns.split_columns(comp.device, comp.frags, fa, [L[k] for k in keys]), strict=True))

    def _prepare(self, blk: dict, face, light_params=None):
        """``shade_op`` inputs of shaded points ``blk`` (faces ``face``), with the current light parameters."""
        v, s = self.view, self.view.settings
        _, inp = shade_op.prepare(blk["pos"], blk["nrm"], blk["mat"], face, v.camera.center, self.lights,
                                  brdf=self.brdf, vlight=blk.get("vlight"), two_sided=s.two_sided, device=v.device,
                                  real=s.real)
        if light_params is not None and len(inp.table.params):
            inp.lt_f = cla.to_device(v.device.queue, np.ascontiguousarray(light_params, s.real))
        if "vis" in blk:  # cached per-vertex visibility, interpolated (a constant: no adjoint)
            inp.vis = blk["vis"]
        return inp

    def _outputs(self, ctx, comp, inp, fa, n_rest, alpha=None):
        """Shade (``[P, 3]``), take alpha's column (unless split already); keep the backward's state."""
        d, fr = self.view.device, self.view.frags
        P = fr.P
        rgb = shade_op.forward(d, inp).reshape(P, 3)  # the fragments are packed: [P, 3] as they come
        if alpha is None:
            alpha = device_empty(d.queue, (max(P, 1), 1), fr.real, allocator=d.allocator)[:P]
            columns.copy_columns(d, fr, fa, self.layout["alpha"][0], alpha, 0, 1)
        ctx.comp, ctx.inp, ctx.C, ctx.n_rest = comp, inp, fa.shape[-1], n_rest
        return rgb, alpha.reshape(P)

    def forward(self, ctx, fa, *rest):
        v, s = self.view, self.view.settings
        d, P = v.device, v.frags.P
        table = pack_lights(self.lights)
        lt_i = table.ints if len(table.ints) else np.zeros((1, 4), np.int32)
        params = rest[0] if rest and len(table.params) else table.params
        lt_f = np.asarray(params, s.real) if len(table.params) else np.zeros(1, s.real)
        blocks = {self.PACKED_BLOCKS[k]: self.layout[k] for k in self.PACKED_BLOCKS if k in self.layout}
        if fa.shape != (P, sum(n for _, n in self.layout.values())) or not fa.flags.c_contiguous:
            fa = cla.to_device(d.queue, np.ascontiguousarray(to_host(fa), s.real))
        inp = shade_op.packed_inputs(d, fa, blocks, v.camera.center, table, _upload(d, lt_i),
                                     _upload(d, np.ascontiguousarray(lt_f)), self.brdf, s.two_sided,
                                     s.real)
        rgb, alpha = shade_op.forward_packed(d, inp)
        ctx.inp, ctx.n_rest = inp, len(rest)
        return rgb, alpha

    def backward(self, ctx, v_rgb, v_alpha):
        d, fr = self.view.device, self.view.frags
        P = fr.P
        v_rgb = _as_device(d, v_rgb, (P, 3), fr.real)
        v_alpha = _as_device(d, v_alpha, (P,), fr.real)
        # every column of the layout in the shading adjoint's one pass; the cached visibility's per-vertex values
        # are constants, but their interpolation moves with the barycentrics (V): its adjoint goes back too
        if not ctx.n_rest:
            return (shade_op.backward_packed(d, ctx.inp, v_rgb, v_alpha)[0],)
        # the light parameters' gradient (a leaf's: the tape adds it after the pass) without a wait here: the host
        # goes on queueing the fragment adjoint while the device runs the shading's
        real = self.view.settings.real
        v_fa, v_params = shade_op.backward_packed(d, ctx.inp, v_rgb, v_alpha, deferred=True)
        if isinstance(v_params, Deferred):
            return v_fa, Deferred(v_params.shape, lambda: v_params.resolve().astype(real))
        return v_fa, v_params.astype(real)


class TracedShadeFragments(ShadeFragments):
    """``(frag_attr [P, C], attr [N, C][, light_params]) → (rgb [P, 3], alpha [P])``:
    :class:`ShadeFragments` plus ray-traced shadows and one reflection bounce (``ops/trace.py``).

    * shadows: per shaded fragment and point/directional light, ``T = Π(1 − α)`` over the triplets
      the segment to the light crosses (own face skipped, start offset ``view.ray_eps``); T scales
      the light's intensity. Adjoints: occluders' vertex alphas and positions, the fragment position,
      the light position/direction.
    * bounce: the nearest hit along the mirror direction, shaded with the same lights (seen from the
      reflecting point, no shadows), ``L_r = α_hit · rgb_hit``, added as ``s_g · L_r`` (``s_g`` the
      glossy weight of ``env_scales``). Adjoints: the hit's interpolated attributes (materials,
      normal, position, alpha, vertex light) and the light parameters; the reflecting surface's
      materials and normal through ``s_g``; and the bounce geometry (the hit point moves with the
      reflecting point, its normal and the hit face's vertices; the hit face itself is discrete).
    ``attr`` is the packed per-vertex attribute array (positions in its ``pos`` columns).
    """

    def forward(self, ctx, fa, attr, *rest):
        v, s = self.view, self.view.settings
        d, fr = v.device, v.frags
        comp = columns.Compaction(d, fr)
        L = self.layout
        blk = self._blocks(comp, fa)
        face_c = fr.face  # [P] face ids, in the fragments' packed order (read only)
        # rays only for fragments that composite with weight (t_min cut-off, as Composite)
        face_r = trace_op.ray_mask(d, fr, comp.offsets, face_c, comp.pack(fa, L["alpha"][0], 1), v.win, s.t_min) \
            if s.t_min > 0 else face_c
        inp = self._prepare(blk, face_c, rest[0] if rest else None)
        attr_h = np.ascontiguousarray(to_host(attr), s.real)
        attr_d = attr if isinstance(attr, cla.Array) and attr.dtype == s.real else cla.to_device(d.queue, attr_h)
        p0 = L["pos"][0]
        Vd = cla.to_device(d.queue, np.ascontiguousarray(attr_h[:, p0:p0 + 3]))
        ctx.shadow = ctx.hits = None
        if s.shadows and trace_op.num_shadowed_lights(inp.table) and comp.P:
            # early_out: a ray stops once its T is below 1e-4 (its adjoint walks the same hits: trace.cl)
            ctx.shadow = trace_op.shadow_forward(d, v.bvh, Vd, attr_d, L["alpha"][0], blk["pos"], face_r, inp.lt_i,
                                                 inp.lt_f, inp.table, v.ray_eps, nrm=blk["nrm"],
                                                 cam_center=v.camera.center, two_sided=s.two_sided, early_out=True)
            inp.vis = ctx.shadow.vis
        if s.reflections and comp.P:
            hf, hb = trace_op.bounce(d, v.bvh, Vd, blk["pos"], blk["nrm"], face_r, v.camera.center, s.two_sided,
                                     v.ray_eps)
            hblk = {k: trace_op.gather_hits(d, attr_d, *L[k], v.mesh.F, hf, hb)
                    for k in ("pos", "nrm", "mat", "vlight", "alpha") if k in L}
            hinp = self._prepare(hblk, hf)
            hinp.lt_f, hinp.eye = inp.lt_f, blk["pos"]
            hrgb = shade_op.forward(d, hinp).get()
            ha = hblk["alpha"].get()
            inp.refl = cla.to_device(d.queue, np.ascontiguousarray(hrgb * ha, s.real))
            ctx.hits = (hf.get(), hb.get(), hinp, hrgb, ha)
            ctx.bounce_dev = (Vd, attr_d, blk["pos"], blk["nrm"], hf, hb)
        v.traced = {"shadow_hits": None if ctx.shadow is None else ctx.shadow.nhit.get(),
                    "bounce_face": None if ctx.hits is None else ctx.hits[0]}  # discrete choices (tests, tools)
        ctx.N = attr_h.shape[0]
        return self._outputs(ctx, comp, inp, fa, len(rest))

    def backward(self, ctx, v_rgb, v_alpha):
        v, s = self.view, self.view.settings
        d, fr = v.device, v.frags
        P = fr.P
        comp, L, inp = ctx.comp, self.layout, ctx.inp
        v_rgb = _as_device(d, v_rgb, (P, 3), fr.real)
        g = shade_op.backward(d, inp, v_rgb)
        v_pos, v_nrm, v_mat, v_vl, v_params = g.v_pos, g.v_nrm, g.v_mat, g.v_vlight, g.v_light_params
        v_attr = np.zeros((ctx.N, ctx.C))
        if ctx.shadow is not None:
            sg = trace_op.shadow_backward(d, v.bvh, ctx.shadow, g.v_vis)
            v_attr[:, L["alpha"][0]] += sg.v_alpha
            v_attr[:, L["pos"][0]:L["pos"][0] + 3] += sg.v_V
            v_pos = v_pos + sg.v_pos
            for j, off in enumerate(inp.table.shadow_ray_offsets):  # each caster's SHADOW_RAY_PARAM
                v_params[off:off + 3] += sg.v_light[:, j].sum(axis=0)
        if ctx.hits is not None:
            hf, hb, hinp, hrgb, ha = ctx.hits
            gr = g.v_refl.get().astype(np.float64)
            v_hrgb = cla.to_device(d.queue, np.ascontiguousarray(gr * ha, s.real))
            hg = shade_op.backward(d, hinp, v_hrgb)
            v_params = v_params + hg.v_light_params
            v_hit = np.zeros((len(hf), ctx.C))
            for key, gk in (("pos", hg.v_pos), ("nrm", hg.v_nrm), ("mat", hg.v_mat), ("vlight", hg.v_vlight)):
                if key in L:
                    v_hit[:, L[key][0]:L[key][0] + L[key][1]] = gk.get()
            v_hit[:, L["alpha"][0]] = (gr * hrgb).sum(axis=1)
            v_attr += trace_op.scatter_hits(v.mesh.faces, ctx.N, hf, hb, v_hit)
            Vd, attr_d, bpos, bnrm, hf_d, hb_d = ctx.bounce_dev
            bp, bn, bV = trace_op.bounce_backward(d, Vd, attr_d, bpos, bnrm, hf_d, hb_d, v_hit, hg.v_eye, v.mesh,
                                                  v.camera.center, s.two_sided)
            v_pos, v_nrm = v_pos + bp, v_nrm + bn
            v_attr[:, L["pos"][0]:L["pos"][0] + 3] += bV
        v_fa = device_empty(d.queue, (max(P, 1), ctx.C), fr.real, allocator=d.allocator)[:P]
        for key, gk in (("pos", v_pos), ("nrm", v_nrm), ("mat", v_mat), ("vlight", v_vl)):
            if key in L:
                comp.unpack(gk, v_fa, L[key][0])
        v_alpha = _as_device(d, v_alpha, (P,), fr.real)
        columns.copy_columns(d, fr, v_alpha.reshape(P, 1), 0, v_fa, L["alpha"][0], 1)
        out = (v_fa, v_attr.astype(s.real))
        return out + ((v_params.astype(s.real),) if ctx.n_rest else ())


def _is_zero_scalar(b) -> bool:
    return b is None or (not hasattr(b, "shape")) or b.shape == ()


def _as_device(d: Device, x, shape, real) -> cla.Array:
    """An adjoint as a device array of ``shape`` (the tape hands unused outputs a scalar 0)."""
    if isinstance(x, cla.Array):
        return x.reshape(shape)
    x = np.asarray(x, real)
    if x.shape != tuple(shape):
        x = np.broadcast_to(x, shape)
    return cla.to_device(d.queue, np.ascontiguousarray(x))


class Composite(Function):
    """``(rgb [P, 3], alpha [P][, win [P]]) → (image [H, W, 3], acc [H, W])`` over ``background`` (default: the
    settings' background)."""

    def __init__(self, view: RenderState, background=None):
        self.view = view
        self.bg = np.asarray(view.settings.background if background is None else background, np.float64)

    def forward(self, ctx, rgb, alpha, win=None):
        v = self.view
        fr = v.frags
        a = alpha.reshape(fr.P)
        img, trans, ncon = composite(v.device, fr, rgb, a, self.bg, win=win, t_min=v.settings.t_min)
        ctx.save(rgb, a, win, trans, ncon)
        return img, 1.0 - trans

    def backward(self, ctx, v_img, v_acc):
        rgb, a, win, trans, ncon = ctx.saved
        v = self.view
        fr = v.frags
        if _is_zero_scalar(v_acc) or (isinstance(v_acc, np.ndarray) and not v_acc.any()):
            v_acc = None
        v_feat, v_alpha, v_win, _ = composite_backward(v.device, fr, rgb, a, self.bg, ncon, trans, v_img, v_acc,
                                                       win=win)
        out = (v_feat, v_alpha)
        return out + ((v_win,) if win is not None else ())


# ---------------------------------------------------------------------------------------------- render


class PixelFilterRGBA(Function):
    """``(image [H f, W f, 3], acc [H f, W f]) → (image [H, W, 3], acc [H, W])`` (device arrays, ``ops/downsample.py``):
    a render's radiance and alpha filtered down together, by the Gaussian pixel filter of standard deviation ``sigma``
    output pixels (one four-channel pass per axis, ``downsample.gauss_down_rgba``) or, ``sigma`` 0, the mean of each
    ``f × f`` block (``downsample.box_down``). The tape hands the adjoint device arrays for both outputs (a device
    zero for one the loss does not read)."""

    def __init__(self, device: Device, f: int, sigma: float = 0.0):
        self.device, self.f, self.sigma = device, int(f), float(sigma)

    def forward(self, ctx, img, acc):
        if self.sigma > 0:
            return downsample_op.gauss_down_rgba(self.device, img, acc, self.f, self.sigma)
        return downsample_op.box_down(self.device, img, self.f), downsample_op.box_down(self.device, acc, self.f)

    def backward(self, ctx, v_img, v_acc):
        if self.sigma > 0:
            return downsample_op.gauss_up_rgba(self.device, v_img, v_acc, self.f, self.sigma)
        return downsample_op.box_up(self.device, v_img, self.f), downsample_op.box_up(self.device, v_acc, self.f)


class Stack(Function):
    """``(image [H, W, 3], acc [H, W]) → [H, W, 4]`` on the host: the RGBA the losses see."""

    def forward(self, ctx, img, acc):
        img = img.get() if isinstance(img, cla.Array) else np.asarray(img)
        acc = acc.get() if isinstance(acc, cla.Array) else np.asarray(acc)
        return np.concatenate([img, acc[..., None]], axis=-1)

    def backward(self, ctx, v):
        v = np.asarray(v)
        return np.ascontiguousarray(v[..., :3]), np.ascontiguousarray(v[..., 3])


@dataclass
class RenderResult:
    """Outputs of :func:`render`: ``rgba`` ``[H, W, 4]`` (numpy; RGB and accumulated alpha) on the tape,
    and :attr:`info`."""

    rgba: Variable
    tape: Tape
    scene: Scene
    state: RenderState
    #: ``[H, W, 3]`` the image on the device before :class:`Stack` downloads it (the same values as
    #: :attr:`image`): the training loop's device loss reads it and seeds :meth:`backward_device` there
    image_var: Variable | None = None

    @property
    def info(self) -> dict:
        """What the render reports besides the image (after gsplat's ``info``): ``"frags"`` the
        fragments of the forward pass (``frags.face``: the visible faces), ``"vs"`` ``[N, 3]`` the
        projected vertices, ``"v_vs"`` ``[N, 3]`` their adjoint once :meth:`backward` ran (None
        before): the statistics density control reads. Device arrays."""
        return self.state.info

    @property
    def out_size(self) -> tuple[int, int]:
        """``(H, W)`` of the image: the camera's, divided by ``RenderSettings.downsample``."""
        f = self.state.settings.downsample
        return self.state.camera.height // f, self.state.camera.width // f

    @property
    def image(self) -> np.ndarray:
        """``[H, W, 3]`` rendered colour."""
        return self.rgba.data[..., :3]

    @property
    def alpha(self) -> np.ndarray:
        """``[H, W]`` accumulated alpha."""
        return self.rgba.data[..., 3]

    def backward(self, v_image, v_alpha=None) -> dict[str, np.ndarray]:
        """Propagate ``v_image [H, W, 3]`` (and optionally ``v_alpha [H, W]``) to every scene
        parameter; returns ``{param name: gradient}`` (also accumulated into each ``Param.grad``)."""
        s = self.state.settings
        H, W = self.out_size
        v = np.zeros((H, W, 4), s.real)
        v_image = np.asarray(v_image)
        if v_image.shape != (H, W, 3):
            raise ValueError(f"v_image must have shape [{H}, {W}, 3], got {list(v_image.shape)}")
        v[..., :3] = v_image
        if v_alpha is not None:
            v_alpha = np.asarray(v_alpha)
            if v_alpha.shape != (H, W):
                raise ValueError(f"v_alpha must have shape [{H}, {W}], got {list(v_alpha.shape)}")
            v[..., 3] = v_alpha
        self.tape.backward(self.rgba, v)
        return {p.name: None if p.grad is None else to_host(p.grad) for p in self.scene.params}

    @property
    def device_image(self) -> cla.Array:
        """``[H, W, 3]`` rendered colour on the device (what :attr:`image` was downloaded from)."""
        return self.image_var.data

    def backward_device(self, v_image: cla.Array) -> None:
        """:meth:`backward` for a device cotangent ``v_image [H, W, 3]`` of :attr:`device_image` (e.g. the
        device photometric loss's adjoint): the tape is seeded at the device image, so no host round trip
        (the accumulated alpha gets no cotangent, as ``backward(v_image)``). Gradients land in each
        ``Param.grad``."""
        s = self.state.settings
        H, W = self.out_size
        if not isinstance(v_image, cla.Array) or v_image.shape != (H, W, 3) or v_image.dtype != s.real:
            raise ValueError(f"v_image must be a device array of shape [{H}, {W}, 3] and dtype "
                             f"{np.dtype(s.real).name}, got {type(v_image).__name__} "
                             f"{list(getattr(v_image, 'shape', ()))} {getattr(v_image, 'dtype', '')}")
        from .ops.common import check_contiguous

        check_contiguous("v_image", v_image)  # a strided view gave wrong gradients without a word (battery 10)
        self.tape.backward(self.image_var, v_image)


_MESH_CACHE: dict = {}
_BVH_CACHE: dict = {}


def scene_bvh(device: Device, mesh: DeviceMesh, V: np.ndarray, real) -> BVH:
    """The :class:`BVH` of a topology: built when the topology (or dtype) changes, refitted to ``V``
    on every call (positions move after every optimiser step)."""
    key = (id(device), id(mesh), np.dtype(real).str)
    b = _BVH_CACHE.get(key)
    Vr = np.ascontiguousarray(V, real)
    if b is None or b.mesh is not mesh:
        _BVH_CACHE.clear()
        b = _BVH_CACHE[key] = build_bvh(device, Vr, mesh)
    else:
        refit(device, b, Vr)
    return b


def device_mesh(device: Device, F: np.ndarray, n: int) -> DeviceMesh:
    """The :class:`DeviceMesh` of a topology, cached while the topology (array identity) is unchanged."""
    key = (id(device), id(F), F.shape, n)
    m = _MESH_CACHE.get(key)
    if m is None or m.faces is not F and not np.array_equal(m.faces, F):
        _MESH_CACHE.clear()
        m = _MESH_CACHE[key] = DeviceMesh(device, F, n)
    return m


def render(scene: Scene, camera: Camera, settings: RenderSettings | None = None,
           device: Device | None = None, vis: np.ndarray | None = None,
           bounce: np.ndarray | None = None, frag_cache: FragmentCache | None = None) -> RenderResult:
    """Render ``scene`` from ``camera``, recording on the active tape (or a new one).

    ``vis`` (optional, ``renderer="raster"`` only): ``[N, NV]`` per-vertex transmittance towards each
    shadow-casting light of ``scene.lights`` in light order (``visibility.vertex_visibility``), interpolated
    per fragment and scaling each light's term: cached cast shadows. Optionally followed by ``(d + 1)² − 1``
    columns of the environment's occlusion (``visibility.vertex_occlusion``: SH bands 1 .. d, shared by the SH
    environment lights). The per-vertex values are constants (no gradient through the shadow boundary); their
    interpolation moves with the barycentrics like any attribute.

    ``bounce`` (optional, ``renderer="raster"``, a scene without a vertex-SH light): ``[N, 3]`` per-vertex radiance
    of one interreflection bounce (``visibility.vertex_bounce``), interpolated per fragment and lit as a
    :class:`~triplet_cl.lights.BounceLight` appended to the scene's lights; a constant, as ``vis``.

    ``frag_cache`` (optional, ``renderer="raster"``): a :class:`FragmentCache` the fragments of this view come from
    when it holds them for the scene's current geometry (else they are rasterized and put there).

    Returns:
        :class:`RenderResult` with ``image [H, W, 3]`` and ``alpha [H, W]`` (numpy);
        ``result.backward(v_image)`` returns the gradient of every scene parameter.
    """
    s = RenderSettings() if settings is None else settings
    if not isinstance(s, RenderSettings):
        raise TypeError(f"settings must be a RenderSettings (e.g. RenderSettings(**{{...}}) for a dict), got "
                        f"{type(s).__name__}")
    if device is not None and not isinstance(device, Device):
        raise TypeError(f"device must be a Device (triplet_cl.device.get_device(...) takes a name or an index), got "
                        f"{type(device).__name__} {device!r}")
    if not isinstance(scene, Scene) or not isinstance(camera, Camera):
        raise TypeError(f"render takes a Scene and a Camera, got {type(scene).__name__} and {type(camera).__name__}")
    d = device or get_device()
    d.release_held()  # the pool's free lists kept bounded: the last render's buffers are back in it by now
    N = scene.V.shape[0]
    if vis is not None:
        nv = sum(1 for lt in scene.lights if lt.CASTS_SHADOWS)
        vis = np.asarray(vis)
        if vis.ndim != 2 or vis.shape[0] != N or vis.shape[1] < nv:
            raise ValueError(f"vis must have shape [{N}, {nv} (+ environment occlusion)] (vertices, shadow-casting "
                             f"lights), got {list(vis.shape)}")
        shade_op.env_occlusion_columns(pack_lights(scene.lights), vis.shape[1])
        if s.renderer != "raster":
            raise ValueError(f"vis (cached visibility) needs renderer='raster', got {s.renderer!r} (its own shadows)")
        if vis.shape[1] == 0:
            vis = None
    if bounce is not None:
        bounce = np.asarray(bounce, np.float64)
        if bounce.shape != (N, 3):
            raise ValueError(f"bounce must have shape [{N}, 3] (vertices, rgb), got {list(bounce.shape)}")
        if s.renderer != "raster":
            raise ValueError(f"bounce (traced interreflection) needs renderer='raster', got {s.renderer!r}")
        if scene.vertex_sh is not None:
            raise ValueError("bounce cannot be combined with a vertex-SH light (both are per-vertex light rows)")
    if s.downsample > 1 and (camera.width % s.downsample or camera.height % s.downsample):
        raise ValueError(f"downsample {s.downsample} needs a camera whose size it divides, got "
                         f"{camera.width}x{camera.height}")
    mesh = device_mesh(d, scene.F, N)
    view = RenderState(d, mesh, camera, s)
    if frag_cache is not None and s.renderer == "raster":
        frag_cache.validate(scene)
        view.frag_cache = frag_cache
    if s.renderer != "raster":
        Vh = np.asarray(scene.V.data, np.float64)
        view.bvh = scene_bvh(d, mesh, Vh, s.real)
        diag = float(np.linalg.norm(Vh.max(0) - Vh.min(0))) if len(Vh) else 1.0
        view.ray_eps = s.ray_eps * max(diag, 1e-12)
    cm = scene.material.shape[1]
    outer = active_tape()
    tape = outer if outer is not None else Tape()
    with tape if outer is None else _nullcontext():
        sizes = [3, 3, cm, 1] + ([6] if scene.vertex_sh is not None else [])
        names = ["pos", "nrm", "mat", "alpha"] + (["vlight"] if scene.vertex_sh is not None else [])
        vl = [VertexSH(camera.center, s.sh_degree, d, s.real)(scene.V, scene.vertex_sh)] \
            if scene.vertex_sh is not None else []
        const = None
        blocks = []  # constant blocks, last: interpolated with the rest, no adjoint of their own
        if bounce is not None:  # the bounce light's rows: radiance | 3 unused columns (vlight's layout)
            blocks.append(np.concatenate([bounce, np.zeros_like(bounce)], 1))
            sizes.append(6)
            names.append("vlight")
        if vis is not None:
            blocks.append(vis)
            sizes.append(vis.shape[1])
            names.append("vis")
        if blocks:
            const = np.ascontiguousarray(np.concatenate(blocks, 1), s.real)
        if use_device_attributes(s, mesh):
            attr = VertexAttributes(view, scene.brdf, const=const)(scene.V, scene.material, scene.alpha, *vl)
        else:  # the host chain (the reference of VertexAttributes)
            nrm = Normals(mesh, s.normals, s.real, d)(scene.V)
            mat = MaterialActivation(scene.brdf)(scene.material)
            alpha = SigmoidHost()(scene.alpha)
            attr = Concat()(scene.V, nrm, mat, alpha, *vl, *([const] if const is not None else []))
        ri = RasterInterpolate(view, alpha_col=6 + cm)(scene.V, attr)  # pos | nrm | mat | alpha
        fa, win = (ri, None) if s.sigma is None else ri
        offsets = np.concatenate([[0], np.cumsum(sizes)])
        layout = {k: (int(offsets[i]), int(sizes[i])) for i, k in enumerate(names)}
        lp = [scene.light_params] if scene.light_params is not None else []
        # the bounce light last: the packed light parameters (and their gradient) are those of the scene's lights
        lights = list(scene.lights) + ([BounceLight()] if bounce is not None else [])
        if s.renderer == "raster" or not (s.shadows or s.reflections):
            rgb, alpha_f = ShadeFragments(view, lights, scene.brdf, layout)(fa, *lp)
        else:
            rgb, alpha_f = TracedShadeFragments(view, scene.lights, scene.brdf, layout)(fa, attr, *lp)
        f = s.downsample
        if s.transfer in ("srgb", "srgb-clip"):  # linear radiance over black, then the photos' encoding and background
            img, acc = Composite(view, np.zeros(3))(rgb, alpha_f, *([win] if win is not None else []))
            if f > 1 or s.pixel_sigma > 0:
                img, acc = PixelFilterRGBA(d, f, s.pixel_sigma)(img, acc)
            img = SRGBComposite(d, s.background, s.real, clip=s.transfer == "srgb-clip")(img, acc)
        else:
            img, acc = Composite(view)(rgb, alpha_f, *([win] if win is not None else []))
            if f > 1 or s.pixel_sigma > 0:
                img, acc = PixelFilterRGBA(d, f, s.pixel_sigma)(img, acc)
        rgba = Stack()(img, acc)
    return RenderResult(rgba, tape, scene, view, image_var=img)
