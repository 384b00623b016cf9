"""The mesh stage (docs/ARCHITECTURE.md §1, §9): extract a connected mesh from a trained soup and keep
optimising it as a mesh, then export the PBR assets.

One round: soup (or the previous round's mesh) → :func:`~triplet_cl.mesh.extract.extract_scene`
(connected, opaque, raw parameters transferred by nearest neighbour) → ``iterations`` steps of the
soup stage's loop with **area-weighted vertex normals**, the soft coverage window on the
**silhouette edges only** (on every edge it would open seams along the shared interior edges of a
connected mesh; on none the outline gets no gradient), 3×3 supersampling (test renders at 4×4), a few
fragments per pixel, and the mesh regularisers (face-normal consistency, uniform Laplacian of the positions, graph TV of
the materials); every ``remesh_every`` steps the faces with the largest accumulated position
gradients are subdivided and the smallest simplified (:mod:`~triplet_cl.mesh.remesh`), with every
vertex parameter and its Adam moments carried across. ``rounds > 1`` repeats extraction → refine
from the refined mesh (the method's iterative loop).

Outputs in the run directory: ``mesh.glb``, ``mesh.obj`` (+ ``mesh.mtl`` and textures),
``mesh.ply``, ``envmap.exr`` (with an SH environment light), ``lights.json``, ``mesh_stage.npz``
(the refined mesh and raw parameters: ``triplet export`` reads it), ``renders/mesh/*.png`` and a
``"mesh"`` entry in ``metrics.json`` (test PSNR/SSIM of mesh and soup, faces, Chamfer distance to
the dataset's ``gt_mesh.ply`` when there is one).
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from ..activations import logit, sigmoid
from ..autodiff import Param, Tape
from ..datasets.base import render_files, resolve_background
from ..io import atomic_write_bytes, write_json
from ..losses import (
    exact_device_loss_available,
    loss_backend,
    photometric_loss_and_grad,
    photometric_loss_and_grad_exact,
)
from ..materials import copy_ambient, get_brdf, tie_ambient_gradient
from ..optim import Adam, ExponentialDecay
from ..regularizers import FaceNormalConsistency, MaterialGTV, RestLaplacian, UniformLaplacian
from ..render import FragmentCache, RenderSettings, render
from ..scene import Scene
from .asset import MeshAsset

MESH_STATE = "mesh_stage.npz"
AO_MODES = ("auto", "learned", "computed")  # MeshConfig.ao


def face_mean_norm(g: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``[M]``: the mean over each face's corners of its vertices' gradient norms, the bits of
    ``np.linalg.norm(g, axis=1)[F].mean(axis=1)`` (numpy sums a last axis of 3 as ``(x0 + x1) + x2``) from columns:
    2.1 -> 0.3 ms a mesh step on spot's 61k faces (``tests/test_mesh_stage.py``)."""
    c = [np.ascontiguousarray(g[:, j]) for j in range(3)]
    n = np.sqrt((c[0] * c[0] + c[1] * c[1]) + c[2] * c[2])
    return ((n[F[:, 0]] + n[F[:, 1]]) + n[F[:, 2]]) / 3


def supersample_for(width: int, height: int, factor: int, max_pixels: int) -> int:
    """``factor`` lowered (to 1 at least) until a ``width × height`` render supersampled by it holds at most
    ``max_pixels`` pixels."""
    f = max(int(factor), 1)
    while f > 1 and width * height * f * f > max_pixels:
        f -= 1
    return f


# the metal gauge's factor stays within this range (MeshStage.metal_gauge)
METAL_GAUGE_RANGE = (0.25, 4.0)
# the two hypotheses of MeshConfig.metallic_trial (a sigmoid's value: 0 and 1 are out of reach)
METALLIC_TRIAL_VALUES = (0.01, 0.99)
# a metal hypothesis fitted rougher than this is refused (metallic_trial)
MAX_METAL_ROUGHNESS = 0.8
NORMAL_KAPPA_START = 10.0  # the robust normal term's κ at a round's first step: ρ'(x) within 0.9–1.1 of the plain
# term's slope up to 60°, 1.9 at 90° (every bend of the extracted surface smoothed, folds resisted)


@dataclass
class MeshConfig:
    """Settings of the mesh stage (saved in ``config.json`` under ``"mesh"``)."""

    method: str = "tsdf"  # "tsdf" (TSDF fusion + marching cubes) or "weld" (merge coincident vertices)
    resolution: int | None = None  # TSDF voxels along the longest side of the soup's bounds (None: a voxel ≈ a pixel)
    extract_faces: int | None = 50_000  # QEM-simplify the extracted mesh to at most this many faces (None: keep all)
    photo_masks: bool = True  # the photos' alpha also carves free space in the TSDF (when the dataset has alpha)
    photo_hull: bool = True  # ... and whatever lies outside the photos' visual hull is outside (overrides the soup)
    # the soup's depth fused by the TSDF: where its accumulated alpha reaches this (its median lies ~1 px inside the
    # surface). Spot, 3000-it. soup, mesh PSNR (soup 31.59) / Chamfer, both with the visual hull, 2×2 supersampling:
    # median 30.58 / 0.0094, 0.1: 32.31 / 0.0063
    depth_quantile: float = 0.1
    rounds: int = 1  # extraction → refine rounds
    iterations: int = 600  # refinement steps per round (0: extract and export only)
    faces_per_pixel: int = 4  # K of the mesh renders (an opaque mesh needs few)
    # render at this × resolution and box-filter down: antialiased silhouettes, as the photos. Measured (test PSNR,
    # Chamfer, per-step time; evaluated at 4): spot 2 → 32.92 dB, 0.0063, 0.12 s; 3 → 33.70 dB, 0.0059, 0.19 s;
    # spot 6000-it. soup 33.16 → 33.68 dB; bob_env 32.99 → 33.69 dB
    supersample: int = 3
    # the test renders (metrics, renders/mesh): 4×4 samples approach the pixel-area coverage of the photos' renderer
    # (spot, the same refined mesh trained at 2: evaluated at 2 → 32.31 dB, at 4 → 32.92 dB); None: as ``supersample``
    eval_supersample: int | None = 4
    # the supersampled renders' size cap (pixels): a factor that would pass it is lowered (supersample_for). An
    # 800² capture's refinement rendered 2400² (6-8 GB a step on PoCL, 2.5 s) and its test views 3200² (12 GB);
    # every capture up to 666² keeps its factors
    max_render_pixels: int = 4_000_000
    # the capture's pixel filter (RenderSettings.pixel_sigma: a Gaussian's standard deviation in pixels; 0: a box over
    # each pixel; None: read from the photos' alpha edges after the first extraction, mesh/pixel_filter.py, and saved
    # resolved). Measured (same soups, bench/results/pixel_filter_pocl_2026-11-26.txt): the box → 0.5 mesh NVS spot
    # 35.83 → 38.63, bob_env 35.37 → 37.26, gadget 29.73 → 30.91 dB; the photos (Mitsuba 3's film) use 0.5
    pixel_sigma: float | None = None
    # soft window on the silhouette edges only, 1 − exp(−sigma·d) at d supersampled pixels inside the edge: gradients
    # that move the outline; None: hard edges (no silhouette gradients). The window only takes coverage away (a
    # rendered outline 1/sigma supersampled pixels thinner than the geometry's, on average over the edges' positions
    # in the pixel grid): at 1 and 3×3 supersampling a third of a photo pixel, a thin part's (gadget's rods, ~1.2 px
    # wide) coverage short by half. Measured (session 41,
    # the same soups, bench/results/mesh_window_pocl_2026-11-27.txt), 1 → 6: mesh NVS spot 38.61 → 39.77, bob_env
    # 39.31 → 40.35, gadget 31.25 → 32.38 dB; surface Chamfer 0.00477 → 0.00458, gadget 0.00848 → 0.00812
    sigma: float | None = 6.0
    lr_position: float = 2e-4  # × scene extent, decays ×0.1 over the round
    lr_material: float = 0.05  # as the soup stage (spot: 0.02 → 30.0 dB, 0.05 → 30.2 dB test PSNR after 600 steps)
    lr_vertex_sh: float = 0.002
    lr_lights: float = 0.005
    # regulariser weights, measured on spot (trained soup → 50k-face TSDF mesh, test PSNR at 150/300/450 steps):
    # Laplacian 2, normals 0.02: 30.4 → 29.0 → 27.9 dB (the surface grows noise that the vertex normals show);
    # 20 / 0.1: 29.1 → 30.3 → 30.7 dB; 100 / 0.3: 27.1 → 28.1 → 28.5 dB (too stiff to follow the silhouettes)
    normal_weight: float = 0.1  # face-normal consistency
    # ... robust: each edge's bend x = 1 − cos(n_a, n_b) costs κ·log(1 + x/κ) + x⁵/5
    # (regularizers.FaceNormalConsistency): small bends are smoothed as by the plain 1 − cos, bends of ~25–75° are
    # pulled weakly (κ = 0.05: a sixth of the plain slope at 45–60°), a right angle about as hard as by the plain
    # term and a fold past it harder. κ falls from NORMAL_KAPPA_START (the extracted surface's facets smoothed first)
    # to normal_kappa over the first normal_kappa_anneal of each round's steps.
    # Measured (session 42, the same soups, bench/results/normal_kappa_pocl_2026-11-27.txt): gadget surface Chamfer
    # 0.00784 → 0.00761 (seed 1: 0.00805 → 0.00782), mesh NVS +0.45 / +0.61 dB, relight +0.15 to +0.29 dB; spot NVS
    # 39.32 → 39.66, relight −0.1 to −0.3; bob_env NVS 40.29 → 39.68, relight −0.1 to −0.5, albedo −0.3 (its spots'
    # colour edges crease the surface a little). κ held at 0.05 from the start, without the x⁵/5 term: gadget 0.00720,
    # bob_env 37.91 dB, 2 % of its edges folded past 100° (with it: 0.00738, 39.18 dB, 0.3 %; the anneal: 0.2 %, the
    # plain term 0.02 %); the plain term at weight 0.02 instead: gadget 0.00765, bob_env 38.45
    normal_kappa: float | None = 0.05  # None: the plain 1 − cos
    normal_kappa_anneal: float = 0.5
    laplacian_weight: float = 20.0  # uniform Laplacian of the positions (mean |δ|², δ in world units; at the dev
    # scenes' size: / Trainer.length_scale² elsewhere, Regularizers)
    # "uniform": |L x|² (its gradient, the bi-Laplacian, rounds edges and corners, a thin part's first); "rest":
    # |L x − L x₀|², x₀ the positions at the extraction and after each remesh (keeps the extracted shape's
    # curvature, damps the noise the steps grow). Measured, same soups (bench/results/parts_pocl_2026-11-24b.txt):
    # before issue 18's light phase, gadget 29.49 → 29.57 dB, cable 0.35 → 0.45 and rungs 0.80 → 0.88 of their
    # surface within 1 %, spot 34.61 → 34.56 dB; with it, gadget (repair rings 0) 29.77 → 29.82 dB but the cable
    # 0.47 → 0.43: a tie, so the rule before stays the default
    laplacian: str = "uniform"
    # graph TV of the raw materials over the mesh's edges. Measured (session 41, the same soups, mesh stage with
    # sigma 6; bench/results/mesh_window_pocl_2026-11-27.txt), 0.002 → 0.005 → 0.01: albedo bob_env 26.64 → 26.93 →
    # 27.07, spot 29.90 → 30.29 → 30.58, gadget 18.29 → 18.24 → 18.28; relight mean bob_env +0.33 / +0.60, spot
    # −0.09 / −0.26 (env_rotated −0.29 / −0.61), gadget −0.08 / −0.18; mesh NVS bob_env −0.15 / −0.76 dB
    gtv_weight: float = 0.005
    # the mesh stage's light phase (issue 18): every material channel but the albedo (roughness, metallic, AO; Blinn-
    # Phong's ks, shininess; its ka follows kd, TrainConfig.blinn_phong_ka) starts each round at its mean over the
    # mesh and stays one value for this many steps (the mean of the per-vertex gradients; the metallic is held at
    # the metallic_trial's choice instead), the lights learning, then per vertex again. The soup's per-vertex AO
    # and roughness hold shading painted in while its normals were noisy; on the mesh, with clean normals, one
    # value each lets the highlights and the lights explain it. spot_small (1500-it. soup): albedo (scaled) 20.75 →
    # 24.57 dB, relight +0.5 / +0.5 / +1.4 dB (AO alone set to 1: 23.20 dB)
    material_tie: int = 300
    # metal or dielectric (Cook-Torrance's metallic channel) decided before round 0's light phase by a trial fit of
    # each hypothesis, this many steps each at one sample per pixel (``MeshStage.choose_metallic``); the light
    # phase then holds it, and it goes per vertex with the other channels after. 0: no trial, the metallic is tied
    # with the others (the rule before: a tied value that Adam steps goes wherever its mean gradient's sign points;
    # measured, the metal capture's mesh ended at 0.98 or 0.11 depending on the lights' path). 200 since Mitsuba's
    # BSDF (session 38): the metal hypothesis refits its albedo as F0 from the soup's dielectric state and, at 120
    # steps, ended 0.3 % behind the dielectric over the second half on the metal capture (ahead over the last
    # quarter): the dielectric won and the mesh came out 24.2 dB for 29.1; at 200 the metal wins by 0.6 %
    metallic_trial: int = 200
    # Cook-Torrance's AO on the mesh: "learned" per vertex (tied in the light phase, as the soup's), or "computed":
    # traced from the mesh's geometry (visibility.vertex_ambient_occlusion, ao_directions rays per vertex, at the
    # start of each round and after each remesh) and held, so that the albedo alone answers for the colour; or
    # "auto": computed where the AO the soup learned follows the extracted mesh's traced occlusion (their Spearman
    # rank correlation over the vertices at least ao_auto_correlation: the photos' dark ambient-lit parts are then
    # the occlusion, which the trace gives without baking light into the material), learned elsewhere (the learned
    # AO also carries what point + ambient lights miss: an environment's up/down gradient, interreflection).
    # Measured (session 36, bench/results/ao_auto_pocl_2026-11-26.txt): the correlation is 0.33 on gadget (200²),
    # 0.21 at 100², 0.27 lit by an environment, |ρ| ≤ 0.07 on spot, Bob and five spot_small captures, −0.29 on the
    # metal; computed AO relights gadget at 27.74 / 27.82 / 27.81 instead of 27.42 / 27.55 / 25.87 (albedo −0.45 dB)
    # and its environment capture 0.4-1.1 dB better; on bob_env it relit 1.4–3.8 dB worse, on spot_small 0.2-1.5
    ao: str = "auto"
    ao_directions: int = 32
    ao_auto_correlation: float = 0.15
    # the lights read again from the extracted mesh's shading (mesh/light_fit.py) before round 0's light phase:
    # "auto" when the lights are point lights and an ambient one and learning; for a metal (the metallic trial's
    # choice: it shows no diffuse shading) from its highlights, which also sets the tied roughness; the number of
    # point lights (up to light_fit_max) is then the data's, the light phase refits the albedo under them. "off":
    # the soup's lights go on.
    # Measured from scratch (bench/results/light_fit_pocl_2026-11-26.txt §8; relight mean, albedo): spot_small
    # under two point lights 22.5 -> 28.7 dB, 14.2 -> 25.5 dB; under sun and sky 27.2 -> 30.1, 19.9 -> 25.1; under
    # an HDR environment 29.8 -> 31.6, 24.4 -> 27.6; the one-light dev scenes keep the soup's lights (margin below)
    light_fit: str = "auto"
    light_fit_max: int = 3
    # Cook-Torrance's ambient light becomes an SH environment of this degree after the light fit (round 0; whether
    # the fit was kept, refused or off): the same radiance in band 0 (a dielectric's renders unchanged at the switch;
    # a metal's reflection takes its lobe's weight, shade_brdf.h), the higher bands learned from 0 with the
    # lights: what a sky brighter above than below, or a room, gives a mesh beside its point lights. The soup keeps
    # its ambient light: as its default the environment took the point light's share on spot (albedo -2.0 / -2.8 dB
    # over two seeds) and the mesh stage's light fit reads only point and ambient lights. Measured on the mesh stage
    # of the same soups (session 39, bench/results/mesh_env_pocl_2026-11-27.txt). 0: keep the ambient light (runs
    # saved before it)
    env_degree: int = 2
    # the same for a metal (the metallic trial's verdict, else a mean metallic above 0.5): a dielectric's diffuse
    # reflection of an environment keeps only its bands 0-2 (Lambert's A_l is 0 at l = 3 and under 0.05 above), a
    # metal's reflection is the environment filtered by its specular lobe, which keeps the higher bands; with degree 2
    # a metal's reflections cannot sharpen and its roughness goes unconstrained. Measured on the mesh stage of the same
    # soups (session 45, bench/results/env_degree_pocl_2026-11-27.txt): spot_small as a metal under the HDR
    # environment, relight 27.07 / 26.74 / 31.77 -> 28.76 / 28.88 / 34.76, albedo 25.75 -> 27.78 (roughness median
    # 0.65 -> 0.57, truth 0.35); the three other metal captures -0.03 to +0.27 dB of relight; degree 8 costs a mesh
    # stage ~45 % more time (spot, all degree 8: 80 s at degree 2 -> 116 s with shade_bwd's chunked sums), metals only
    env_degree_metal: int = 8
    # the SH environment's occlusion by the mesh itself (visibility.vertex_occlusion, env_occlusion_directions rays
    # per vertex, traced when the mesh's faces change: round start, remesh): bands 1 .. this degree of every SH
    # environment light (the learned one, a relit one) see only the sky each vertex sees; band 0 is the AO's, bands
    # above it are left unoccluded (their irradiance share is small: A_3 = 0). Off by default: measured on the mesh
    # stage of the same soups at 2 (session 40, bench/results/env_occlusion_pocl_2026-11-27.txt) it moved relight
    # and albedo by -0.5 to +0.3 dB (spot +0.3 albedo, bob_env -0.2, gadget under an HDR environment -0.5 dB of
    # env_rotated, -0.2 of albedo: its photos' crevices also get the light their walls reflect, which the occluded
    # model without interreflection leaves dark) for 15-22 s of traces. 0: off
    env_occlusion: int = 0
    env_occlusion_directions: int = 64
    # kept only when its robust fit is this much better than the soup's lights' (their scale refitted): the fit's
    # model is cruder than the renderer that trained them (no highlights, the photos' median per vertex), so a
    # lighting it finds only a little better is not worth the soup's; measured objective ratios (fit / soup's): two
    # point lights 0.69, environment 0.77-0.83, sun and sky 0.92, spot_small 0.93-0.94, spot 0.95, gadget at 100²
    # 0.96-0.98, bob_env 0.98, gadget 1.0 (with no margin, bob_env's mesh relit 0.2-1.2 dB worse)
    light_fit_margin: float = 0.06
    # the same for the metal's fit (its own objective, the highlights' view consistency): measured ratios two point
    # lights 0.849-0.859, an environment 0.813-0.838 (both relit better), one point light 0.935 (its ambient 1.35x
    # the soup's, the AO darkened to match: env_rotated -2.4 dB; bench/results/metal_light_fit_pocl_2026-11-26.txt §6)
    light_fit_margin_metal: float = 0.10
    # a metal's lights are scaled so that the median F0 (luminance) they imply over its vertices is this, when its
    # lights are fitted (fit_lights) and again at the end of each round (metal_gauge: albedo x s, the lights / s): a
    # metal shows no diffuse shading, so nothing in its photos fixes the lights' brightness against its F0 but the
    # weak Fresnel rise at grazing angles, and the soup's lights (fitted to a dielectric in its light phase) left it
    # 2.2x too dark with the highlights painted in; the mesh stage's steps drift it darker again (0.70 -> 0.54).
    # 0.75: what real metals reflect, the median F0 luminance of published tables of measured metals (Filament's
    # material guide, eight metals from iron 0.51 to silver 0.95: median 0.74; Adobe's Substance metal references,
    # thirteen from titanium 0.41 to silver 0.98: median 0.78): a physical prior, not a capture's truth. Measured
    # on three metal captures, bench/results/metal_f0_prior_pocl_2026-11-27.txt. 0: the mesh's own F0 (runs saved
    # before it)
    metal_f0: float = 0.75
    # the metal's fit (mesh/light_fit.py fit_metal_lights) reads every view of this many vertices (a fixed random
    # sample): its matrices hold observations × 512 atoms
    light_fit_samples: int = 2000
    # interreflection: "traced" lights every vertex also with one diffuse bounce of the lights off the rest of the
    # mesh (visibility.vertex_bounce, bounce_directions rays per vertex, a constant re-traced with the cast shadows
    # and after each remesh; lights.BounceLight), "off" without. States saved before it read "off"
    bounce: str = "off"
    bounce_directions: int = 32
    # cast shadows as the soup stage (``--shadows vertex``): per-vertex visibility towards the point / directional
    # lights, traced through the mesh every ``shadow_every`` steps of the run and after each remesh; the ray start
    # offset × the mesh's bounding-box diagonal (an opaque mesh needs less than the soup's layers: 0.01, as
    # bench/relight.py --gt-ceiling on the true meshes)
    shadow_eps: float = 0.01
    remesh_every: int = 200  # steps between subdivision / simplification (0: never)
    # (measured, not kept: also subdividing where the albedo's gradient is large, a face ranked by the larger of its
    # position- and albedo-gradient ranks: bob_env and spot even, gadget's mesh NVS -1.4 dB;
    # bench/results/ao_pocl_2026-11-26.txt)
    # the final repair's first neighbourhood (rings around the crossing faces' vertices that are smoothed; it grows
    # by a ring per round): 0 smooths fewer vertices (gadget, 838 crossing pairs: 1185 moved instead of 2804, the
    # test PSNR lost to the repair 0.50 → 0.20 dB; with issue 18's light phase 29.71 → 29.77 dB; spot −0.02 dB,
    # bob_env +0.01 dB, both still free of crossings)
    repair_rings: int = 0
    subdivide_fraction: float = 0.03  # faces with the largest position gradients, subdivided
    simplify_fraction: float = 0.05  # faces with the smallest, simplified away
    max_faces: int = 300_000
    texture_size: int = 1024
    formats: tuple = ("glb", "obj", "ply")
    # the object of a capture with a background (photos without alpha): "auto" crops the extraction to the box
    # found from the cameras' look-at point, the ground plane and the sparse points (mesh/roi.py) when the dataset
    # has no alpha; "none" never crops. ``bbox`` (XMIN, YMIN, ZMIN, XMAX, YMAX, ZMAX, world units) overrides both.
    crop: str = "auto"
    bbox: tuple | None = None

    def normal_kappa_at(self, it: int) -> float | None:
        """The robust normal term's κ at step ``it`` of a round: geometric from ``NORMAL_KAPPA_START`` to
        ``normal_kappa`` over the first ``normal_kappa_anneal`` of the steps (None: the plain term)."""
        if self.normal_kappa is None:
            return None
        span = self.normal_kappa_anneal * max(self.iterations, 1)
        t = 1.0 if span == 0 else min(it / span, 1.0)
        return float(np.exp((1.0 - t) * np.log(NORMAL_KAPPA_START) + t * np.log(self.normal_kappa)))

    def validate(self) -> None:
        if self.normal_kappa is not None and (isinstance(self.normal_kappa, bool) or not (
                isinstance(self.normal_kappa, int | float | np.floating)
                and 0 < self.normal_kappa <= NORMAL_KAPPA_START)):
            raise ValueError(f"mesh normal_kappa must be None (the plain normal term) or a number in (0, "
                             f"{NORMAL_KAPPA_START}], got {self.normal_kappa!r}")
        if isinstance(self.normal_kappa_anneal, bool) or not (
                isinstance(self.normal_kappa_anneal, int | float | np.floating) and 0 <= self.normal_kappa_anneal <= 1):
            raise ValueError(f"mesh normal_kappa_anneal must be a number in [0, 1], got {self.normal_kappa_anneal!r}")
        if self.method not in ("tsdf", "weld"):
            raise ValueError(f"mesh method must be 'tsdf' or 'weld', got {self.method!r}")
        if self.rounds < 1:
            raise ValueError(f"mesh rounds must be >= 1, got {self.rounds}")
        if self.iterations < 0:
            raise ValueError(f"mesh iterations must be >= 0, got {self.iterations}")
        if not (np.isfinite(self.shadow_eps) and self.shadow_eps >= 0):
            raise ValueError(f"mesh shadow_eps must be a finite number >= 0, got {self.shadow_eps!r}")
        if not isinstance(self.material_tie, int) or self.material_tie < 0:
            raise ValueError(f"mesh material_tie must be an integer >= 0, got {self.material_tie!r}")
        if self.ao not in AO_MODES:
            raise ValueError(f"mesh ao must be one of {AO_MODES}, got {self.ao!r}")
        if not (isinstance(self.ao_auto_correlation, int | float) and -1 <= self.ao_auto_correlation <= 1):
            raise ValueError(f"mesh ao_auto_correlation must be a number in [-1, 1], got {self.ao_auto_correlation!r}")
        if self.light_fit not in ("auto", "off"):
            raise ValueError(f"mesh light_fit must be 'auto' or 'off', got {self.light_fit!r}")
        for name in ("light_fit_margin", "light_fit_margin_metal"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0.0 <= v < 1.0):
                raise ValueError(f"mesh {name} must be a number in [0, 1), got {v!r}")
        for name in ("env_degree", "env_degree_metal"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= 8:
                raise ValueError(f"mesh {name} must be an integer in [0, 8] (0: keep the ambient light), got {v!r}")
        if isinstance(self.env_occlusion, bool) or not isinstance(self.env_occlusion, int) or \
                not 0 <= self.env_occlusion <= 4:
            raise ValueError(f"mesh env_occlusion must be an integer in [0, 4] (the occluded SH bands' degree; 0: "
                             f"off), got {self.env_occlusion!r}")
        if not isinstance(self.env_occlusion_directions, int) or not 1 <= self.env_occlusion_directions <= 1024:
            raise ValueError(f"mesh env_occlusion_directions must be an integer in [1, 1024], got "
                             f"{self.env_occlusion_directions!r}")
        if isinstance(self.metal_f0, bool) or not (isinstance(self.metal_f0, int | float) and 0 <= self.metal_f0 <= 1):
            raise ValueError(f"mesh metal_f0 must be a number in [0, 1] (0: the mesh's own F0), got {self.metal_f0!r}")
        if isinstance(self.light_fit_max, bool) or not isinstance(self.light_fit_max, int) \
                or not 1 <= self.light_fit_max <= 8:
            raise ValueError(f"mesh light_fit_max must be an integer in [1, 8], got {self.light_fit_max!r}")
        if isinstance(self.light_fit_samples, bool) or not isinstance(self.light_fit_samples, int) \
                or not 64 <= self.light_fit_samples <= 100000:
            raise ValueError(f"mesh light_fit_samples must be an integer in [64, 100000], got "
                             f"{self.light_fit_samples!r}")
        if self.bounce not in ("traced", "off"):
            raise ValueError(f"mesh bounce must be 'traced' or 'off', got {self.bounce!r}")
        if not isinstance(self.bounce_directions, int) or not 1 <= self.bounce_directions <= 1024:
            raise ValueError(f"mesh bounce_directions must be an integer in [1, 1024], got {self.bounce_directions!r}")
        if not isinstance(self.ao_directions, int) or not 1 <= self.ao_directions <= 1024:
            raise ValueError(f"mesh ao_directions must be an integer in [1, 1024], got {self.ao_directions!r}")
        if not isinstance(self.metallic_trial, int) or self.metallic_trial < 0:
            raise ValueError(f"mesh metallic_trial must be an integer >= 0, got {self.metallic_trial!r}")
        if not 1 <= self.supersample <= 4:
            raise ValueError(f"mesh supersample must be in [1, 4], got {self.supersample}")
        if isinstance(self.max_render_pixels, bool) or not isinstance(self.max_render_pixels, int) \
                or self.max_render_pixels < 4096:
            raise ValueError(f"mesh max_render_pixels must be an integer >= 4096, got {self.max_render_pixels!r}")
        if self.eval_supersample is not None and not 1 <= self.eval_supersample <= 8:
            raise ValueError(f"mesh eval_supersample must be None or in [1, 8], got {self.eval_supersample}")
        if self.pixel_sigma is not None:
            from ..ops.downsample import check_pixel_sigma

            check_pixel_sigma("mesh pixel_sigma (--mesh-pixel-filter; None: auto)", self.pixel_sigma)
        if not 0 < self.depth_quantile < 1:
            raise ValueError(f"mesh depth_quantile must lie in (0, 1), got {self.depth_quantile}")
        if not 1 <= self.faces_per_pixel <= 1024:
            raise ValueError(f"mesh faces_per_pixel must be in [1, 1024], got {self.faces_per_pixel}")
        if self.crop not in ("auto", "none"):
            raise ValueError(f"mesh crop must be 'auto' or 'none', got {self.crop!r}")
        if self.bbox is not None:
            from .roi import ROI

            ROI.from_bbox(self.bbox)
        bad = [f for f in self.formats if f not in ("glb", "obj", "ply")]
        if bad or not self.formats:
            raise ValueError(f"export formats must be a non-empty subset of glb, obj, ply; got {list(self.formats)}")
        if self.extract_faces is not None and self.extract_faces < 100:
            raise ValueError(f"mesh extract_faces (--mesh-faces) must be None or >= 100, got {self.extract_faces}")
        if self.resolution is not None and not 16 <= self.resolution <= 1024:
            raise ValueError(f"mesh resolution (--mesh-resolution) must be in [16, 1024], got {self.resolution}")
        if not 16 <= self.texture_size <= 16384:
            raise ValueError(f"texture_size (--texture-size) must be in [16, 16384], got {self.texture_size}")
        if self.laplacian not in ("uniform", "rest"):
            raise ValueError(f"mesh laplacian (--mesh-laplacian) must be 'uniform' or 'rest', got {self.laplacian!r}")
        if self.repair_rings < 0:
            raise ValueError(f"mesh repair_rings must be >= 0, got {self.repair_rings}")
        if self.remesh_every < 0:
            raise ValueError(f"mesh remesh_every (--remesh-every) must be >= 0, got {self.remesh_every}")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["formats"] = list(self.formats)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> MeshConfig:
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown mesh config fields: {sorted(unknown)}")
        d = dict(d)
        d.setdefault("bounce", "off")  # saved before the traced interreflection: trained without it
        d.setdefault("pixel_sigma", 0.0)  # saved before the pixel filter: trained with the box
        d.setdefault("metal_f0", 0.0)  # saved before the metal's F0 prior: scaled to the mesh's own F0
        d.setdefault("env_degree", 0)  # saved before the mesh's SH environment: its ambient light kept
        d.setdefault("env_degree_metal", d["env_degree"])  # saved before a metal's own degree: the one degree for all
        d.setdefault("env_occlusion", 0)  # saved before the environment's occlusion: rendered without it
        d.setdefault("normal_kappa", None)  # saved before the robust normal term: refined with the plain one
        if "formats" in d:
            d["formats"] = tuple(d["formats"])
        if d.get("bbox") is not None:
            d["bbox"] = tuple(d["bbox"])
        return cls(**d)


class Regularizers:
    """The mesh regularisers of one topology, their weighted sum and gradients (into ``.grad``). ``length_scale``:
    the capture's size against the dev scenes' (``Trainer.length_scale``: its frame radius / 1.165); the Laplacian,
    an energy in squared world units, is weighted by ``laplacian_weight / length_scale²``, so that an object in
    other units or framed with another lens is smoothed as the same object in a dev scene (the normal and material
    terms are scale-free)."""

    def __init__(self, scene: Scene, cfg: MeshConfig, length_scale: float = 1.0):
        n = scene.V.shape[0]
        self.cfg = cfg
        if not (np.isfinite(length_scale) and length_scale > 0):
            raise ValueError(f"length_scale must be finite and > 0, got {length_scale!r}")
        self.lap_weight = cfg.laplacian_weight / length_scale**2
        self.normal = FaceNormalConsistency(scene.F, n, kappa=cfg.normal_kappa) if cfg.normal_weight > 0 else None
        self.lap = None
        if cfg.laplacian_weight > 0:
            self.lap = (RestLaplacian(scene.F, n, np.asarray(scene.V.data)) if cfg.laplacian == "rest"
                        else UniformLaplacian(scene.F, n))
        self.gtv = MaterialGTV(scene.F, n) if cfg.gtv_weight > 0 else None

    def __call__(self, scene: Scene) -> float:
        total = 0.0
        for fn, x, w in ((self.normal, scene.V, self.cfg.normal_weight), (self.lap, scene.V, self.lap_weight),
                         (self.gtv, scene.material, self.cfg.gtv_weight)):
            if fn is None:
                continue
            with Tape() as tape:
                e = fn(x)
            tape.backward(e, np.asarray(w, np.float64))
            total += w * float(np.asarray(e.data))
        return total

    def compute(self, V: np.ndarray, material: np.ndarray) -> tuple[float, list]:
        """What :meth:`__call__` computes, without a tape and without touching the scene: ``(weighted sum,
        [("V" | "material", gradient), ...])`` in :meth:`__call__`'s order. Pure numpy on arrays the step only reads,
        so the refinement runs it on a worker thread while the device renders and differentiates the view (the
        regularisers were ~18 ms of a ~76 ms spot step on the host, the device idle meanwhile); :meth:`apply` then adds
        the gradients as the tape would have (the same values in the same order: bit for bit)."""
        from ..autodiff.arrays import like
        from ..autodiff.function import Context

        total, grads = 0.0, []
        for fn, name, x, w in ((self.normal, "V", V, self.cfg.normal_weight),
                               (self.lap, "V", V, self.lap_weight),
                               (self.gtv, "material", material, self.cfg.gtv_weight)):
            if fn is None:
                continue
            ctx = Context((True,))
            e = fn.forward(ctx, x)
            g = fn.backward(ctx, like(np.asarray(w, np.float64), e))
            grads.append((name, g[0] if isinstance(g, tuple) else g))
            total += w * float(np.asarray(e))
        return total, grads

    @staticmethod
    def apply(scene: Scene, computed: tuple[float, list]) -> float:
        """Add :meth:`compute`'s gradients to the scene's parameters; returns the weighted sum."""
        total, grads = computed
        for name, g in grads:
            (scene.V if name == "V" else scene.material).accumulate_grad(g)
        return total


def photometric_backward(r, target: np.ndarray, lam: float) -> float:
    """The photometric loss of the render ``r`` against ``target`` and its backward pass; the loss's value.

    From ``DEVICE_LOSS_RESIDENT_MIN_PIXELS`` on, the losses.cl kernels on the filtered image where it already is (only
    the target goes up, the adjoint seeds the backward on the device: as the soup's steps); below, the numpy loss's
    values computed on the device bit for bit (``photometric_loss_and_grad_exact``, as the soup's small steps: the
    soup's metallic probe at 96² spent a third of its trial in scipy's SSIM filters), or numpy on the host image
    where that is not available (no fp64). Either way the loss and its adjoint are those of
    ``photometric_loss_and_grad`` on the host image (the same kernels on the same values: the device paths save the
    image's upload and its adjoint's download and upload)."""
    if loss_backend(target.shape, resident=True) == "opencl":
        img = r.device_image
        loss, v_img = photometric_loss_and_grad(img, cla.to_device(img.queue, np.ascontiguousarray(target, img.dtype)),
                                                lam=lam)
        r.backward_device(v_img)
        return float(loss)
    img, device = (r.device_image if r.image_var is not None else None), r.state.device
    if exact_device_loss_available(device, img, lam):
        loss, v_img = photometric_loss_and_grad_exact(device, img, r.image, target, lam=lam)
        r.backward_device(v_img)
        return loss.value()
    loss, v_img = photometric_loss_and_grad(r.image, target, lam=lam, backend=loss_backend(target.shape))
    r.backward(v_img)
    return float(loss)


class MeshStage:
    """Runs the mesh stage on a trained (or resumed) :class:`~triplet_cl.train.Trainer`."""

    def __init__(self, trainer, cfg: MeshConfig | None = None, quiet: bool | None = None):
        self.trainer = trainer
        self.cfg = cfg or MeshConfig()
        self.cfg.validate()
        self.quiet = trainer.quiet if quiet is None else quiet
        self.run_dir = trainer.run_dir
        self.device = trainer.device
        self.ds = trainer.ds
        self.rng = np.random.default_rng(trainer.cfg.seed + 7)
        self.scene: Scene | None = None
        self.history: list[dict] = []
        self.metallic_choice: dict | None = None  # choose_metallic's trial, when it ran
        self.ao_choice: dict | None = None  # choose_ao's decision, when MeshConfig.ao is "auto"
        self._ao_traced: tuple | None = None  # (scene, its traced AO) from choose_ao, for set_computed_ao
        self.light_fit: dict | None = None  # fit_lights's record, when it was asked for
        self.metal_gauge_rec: list[dict] = []  # metal_gauge's record per round, for a metal
        self.environment: dict | None = None  # ambient_to_environment's record, when it switched
        self._env_occ: tuple | None = None  # (the faces, vertex count, U) of the last environment-occlusion trace
        self.env_occlusion_traces: list[dict] = []  # each trace's vertices, seconds and U's size (metrics.json)
        self.pixel_filter: dict | None = None  # resolve_pixel_filter's estimate, when it ran
        self._roi = False  # not computed yet
        self.renderer = "raster"  # of every render of the stage (relighting may ask for "hybrid")

    # ---- one round -----------------------------------------------------------------------------
    def extract(self, source: Scene, downscale: int = 1) -> Scene:
        """The mesh of ``source`` (a soup, or a previous round's mesh): ``MeshConfig.method`` over the training views,
        their depth rendered at the photos' size, or ``downscale`` times smaller (the soup's metallic probe at large
        photos: a coarser mesh, fused from fewer pixels and voxels, is enough to tell a metal)."""
        from ..train import _downsample
        from .extract import extract_scene

        views = self.ds.train
        f = int(downscale)
        # the cameras and masks of f x f pixel blocks, as the trainer's targets at 1 / f (Targets.get)
        cams = [v.camera if f == 1 else v.camera.block_averaged(f) for v in views]
        masks = None
        if self.cfg.photo_masks and self.cfg.method == "tsdf":
            masks = [_downsample(v.alpha, f) if v.alpha is not None and v.alpha.shape == (v.camera.height,
                                                                                          v.camera.width) else None
                     for v in views]
            masks = masks if any(m is not None for m in masks) else None
        t = time.perf_counter()
        roi = self.roi()
        # a later round extracts from the previous round's mesh: opaque triangles that tile the surface, whose soft
        # coverage window (the soup's, 1/px from every edge) would leave each small face half transparent (the demo's
        # mesh: accumulated alpha at most 0.51, "no surface" found); its depth is rendered with hard coverage
        sigma = None if source is not self.trainer.scene else 1.0
        scene = extract_scene(source, cams, self.cfg.method, resolution=self.cfg.resolution,
                              max_faces=self.cfg.extract_faces, device=self.device, masks=masks,
                              hull_views=1 if self.cfg.photo_hull else None, depth_quantile=self.cfg.depth_quantile,
                              roi=roi, sigma=sigma)
        self.trainer.log.info(f"mesh extraction ({self.cfg.method}): {len(scene.F)} faces, "
                              f"{scene.V.shape[0]} vertices, {time.perf_counter() - t:.1f} s")
        return scene

    def roi(self):
        """The region of interest (:mod:`triplet_cl.mesh.roi`): ``--bbox``, else the automatic one for a
        dataset without alpha (photos with a background), else None."""
        from .roi import ROI, auto_roi

        if self._roi is not False:
            return self._roi
        roi = None
        if self.cfg.bbox is not None:
            roi = ROI.from_bbox(self.cfg.bbox)
        elif self.cfg.crop == "auto" and not self.ds.has_alpha:
            roi = auto_roi([v.camera for v in self.ds.train], self.ds.points)
            if roi is None:
                self.trainer.log.info("mesh crop: no region of interest found (too few sparse points)")
        if roi is not None:
            self.trainer.log.info(f"mesh crop ({roi.source}): {json.dumps(roi.to_dict())}")
        self._roi = roi
        return roi

    def build_optimizer(self, scene: Scene) -> Adam:
        tc, c = self.trainer.cfg, self.cfg
        opt = Adam()
        kw = {"betas": tuple(tc.betas), "eps": 1e-12}
        ext = self.trainer.extent
        steps = max(c.iterations, 1)
        opt.add_group("V", [scene.V], lr=ExponentialDecay(c.lr_position * ext, 0.1 * c.lr_position * ext, steps), **kw)
        opt.add_group("material", [scene.material], lr=c.lr_material, **kw)
        if scene.vertex_sh is not None:
            opt.add_group("vertex_sh", [scene.vertex_sh], lr=c.lr_vertex_sh, max_grad_norm=tc.sh_clip, **kw)
        if scene.light_params is not None:
            # the soup stage's light rates: "relative" steps each radiometric value by lr × its size at the start of
            # the stage (lights.relative_lr_scales; with one absolute rate a point light's intensity of ~20 moved by
            # 0.03 % a step and the ambient light by 2 %: the mesh stage could not move the intensity at all)
            from ..lights import relative_lr_scales

            scale = ([relative_lr_scales(scene.lights, extent=ext)]
                     if tc.lr_lights_mode == "relative" else None)
            opt.add_group("lights", [scene.light_params], lr=c.lr_lights, lr_scale=scale, **kw)
        return opt

    def settings(self, background, transfer: str | None = None, downsample: int = 1) -> RenderSettings:
        tc = self.trainer.cfg
        sh = self.trainer.scene.vertex_sh is not None
        return RenderSettings(K=self.cfg.faces_per_pixel, sigma=self.cfg.sigma, soft_edges="silhouette",
                              background=tuple(float(x) for x in background), normals="vertex",
                              sh_degree=tc.sh_degree if sh else None, transfer=transfer, renderer=self.renderer,
                              downsample=downsample, prune=True,
                              pixel_sigma=0.0 if self.cfg.pixel_sigma is None else self.cfg.pixel_sigma)

    def shadows_active(self) -> bool:
        """The mesh is shaded with cast shadows when its soup was (``--shadows vertex``) and it is rasterized."""
        return self.trainer.shadows_active() and self.renderer == "raster"

    def visibility(self, scene: Scene, lights=None, vertices=None, normals=None):
        """``[N, NV]`` per-vertex visibility of ``scene`` (of its ``vertices`` when given) towards ``lights``
        (default its own), or None without shadows (:meth:`shadows_active`); with ``normals`` (one per traced
        vertex) 1 without a ray towards a light behind a vertex's normal (for callers that weight it by
        ``max(0, n · l)``: :func:`~triplet_cl.visibility.vertex_visibility`)."""
        if not self.shadows_active():
            return None
        from ..visibility import vertex_visibility

        return vertex_visibility(scene, self.device, lights=lights, ray_eps=self.cfg.shadow_eps, vertices=vertices,
                                 normals=normals)

    def bounce_active(self, scene: Scene) -> bool:
        """The mesh is lit with the traced interreflection (``MeshConfig.bounce``): rasterized, without a vertex-SH
        light (its per-vertex light absorbs what a bounce would explain)."""
        return self.cfg.bounce == "traced" and self.renderer == "raster" and scene.vertex_sh is None

    def bounce(self, scene: Scene, vis=None, lights=None):
        """``[N, 3]`` per-vertex radiance of one bounce of ``lights`` (default the scene's) off the mesh
        (:func:`~triplet_cl.visibility.vertex_bounce`, shaded with the cast shadows ``vis`` towards them), or None
        when :meth:`bounce_active` is not."""
        if not self.bounce_active(scene):
            return None
        from ..visibility import vertex_bounce
        from .bake import vertex_normals

        return vertex_bounce(scene, vertex_normals(scene.V.data, scene.F), self.device, lights=lights, vis=vis,
                             directions=self.cfg.bounce_directions, ray_eps=self.cfg.shadow_eps)

    def env_occlusion(self, scene: Scene) -> np.ndarray | None:
        """``[N, (d + 1)² − 1]`` the environment's occlusion of ``scene``'s mesh (``MeshConfig.env_occlusion``;
        :func:`~triplet_cl.visibility.vertex_occlusion`), ``d`` the smaller of that degree and the largest SH
        environment light's, or None (off, no SH environment of degree ≥ 1, another renderer than "raster").
        Traced when the faces change (a new mesh, a remesh) and held while the vertices move, as the computed AO."""
        from ..lights import SHEnvironmentLight
        from ..visibility import vertex_occlusion
        from .bake import vertex_normals

        c = self.cfg
        deg = min(c.env_occlusion, max((lt.degree for lt in scene.lights if isinstance(lt, SHEnvironmentLight)),
                                       default=0))
        if deg < 1 or self.renderer != "raster" or len(scene.F) == 0:
            return None
        n, N = (deg + 1) ** 2 - 1, scene.V.shape[0]
        held = self._env_occ
        if held is None or held[0] is not scene.F or held[1] != N:
            t = time.perf_counter()
            _, U = vertex_occlusion(scene, vertex_normals(scene.V.data, scene.F), self.device,
                                    directions=c.env_occlusion_directions, degree=c.env_occlusion, ray_eps=c.shadow_eps)
            held = self._env_occ = (scene.F, N, U)
            rec = {"vertices": int(N), "seconds": round(time.perf_counter() - t, 2),
                   "occluded_share": round(float(np.mean(np.abs(U).max(axis=1) > 1e-6)) if N else 0.0, 4)}
            self.env_occlusion_traces.append(rec)
            self.trainer.log.info("mesh environment occlusion traced: " + json.dumps(rec))
        return held[2][:, :n]

    def render(self, scene: Scene, cam, background, supersample: int | None = None, vis=None, bounce=None,
               frag_cache=None):
        """Render at ``supersample`` (default: the config's) × the camera's resolution; returns ``(result,
        image [H, W, 3], alpha [H, W])`` filtered down to the camera's size on the device by the capture's pixel filter
        (``RenderSettings.downsample`` and ``pixel_sigma``: the linear premultiplied radiance and the alpha, as a camera
        integrates a pixel, then the run's transfer follows); ``result.backward(v_image)`` takes an image adjoint back
        through it all. An SH environment light is occluded by the mesh (:meth:`env_occlusion`: its columns follow
        the cast shadows' in ``vis``, transmittance 1 for them without shadows). ``frag_cache``: a
        :class:`~triplet_cl.render.FragmentCache` for renders of an unchanging geometry (the metallic trial)."""
        U = self.env_occlusion(scene)
        if U is not None:
            nv = sum(1 for lt in scene.lights if lt.CASTS_SHADOWS)
            vis = np.concatenate([np.ones((len(U), nv)) if vis is None else np.asarray(vis, np.float64), U], 1)
        f = supersample_for(cam.width, cam.height, supersample or self.cfg.supersample, self.cfg.max_render_pixels)
        big = cam.scaled(f) if f > 1 else cam
        if (big.width, big.height) != (cam.width * f, cam.height * f):
            raise ValueError(f"supersampling needs an integer-scalable camera, got {cam.width}x{cam.height} × {f}")
        r = render(scene, big, self.settings(background, self.trainer.transfer, f), self.device, vis=vis,
                   bounce=bounce, frag_cache=frag_cache)
        return r, r.image, r.alpha

    def light_phase_ties(self, scene: Scene) -> list[int]:
        """The material columns the light phase ties (``MeshConfig.material_tie``: all but the albedo, Blinn-Phong's
        ka that follows kd and the held ones), each set to its mean over the mesh: the light phase starts from one
        value per tied channel. Also where the soup's metallic probe starts its trial (``Trainer.probe_metallic``)."""
        amb = self.trainer.ambient_pairs
        held = self.held_columns(scene)
        tied = [k for k in tied_channels(scene.brdf) if k not in amb[1] and k not in held] \
            if self.cfg.material_tie > 0 else []
        copy_ambient(scene.material, amb)
        if tied:
            m = np.asarray(scene.material.data)
            m[:, tied] = m[:, tied].mean(axis=0, keepdims=True)
        return tied

    def choose_metallic(self, scene: Scene, tied: list[int], col: int, downscale: int = 1,
                        max_metal_roughness: float = MAX_METAL_ROUGHNESS) -> dict:
        """Metal or dielectric for the whole mesh (:func:`metallic_trial`, ``MeshConfig.metallic_trial`` steps per
        hypothesis at one sample per pixel, the same views and backgrounds for each, the photos ``downscale`` times
        smaller: the soup's probe at large photos; a metal fitted rougher than ``max_metal_roughness`` refused: the
        soup's probe passes ``TrainConfig.metal_probe_max_roughness``); the winner is kept in the column ``col`` of
        ``scene.material`` and the trial in ``self.metallic_choice`` (metrics.json's ``mesh.metallic_trial``)."""
        from ..lights import balanced_lights, relative_lr_scales

        c, tc = self.cfg, self.trainer.cfg
        rng = np.random.default_rng(tc.seed + 11)
        n = c.metallic_trial
        held = self.held_columns(scene)
        vis = self.visibility(scene)  # the run's cast shadows (the geometry is fixed through the trial)
        bounce = self.bounce(scene, vis)
        views = rng.integers(0, len(self.ds.train), n)
        bgs = (rng.uniform(0, 1, (n, 3)) if tc.background == "random"
               else np.tile(np.asarray(resolve_background(tc.background), np.float64), (n, 1)))
        # both hypotheses step through the same views of the same geometry: each view's fragments are rasterized
        # once (the renders and gradients bit for bit the same; the probe's trial 13.1 -> 10.3 s on the demo)
        frags = FragmentCache(device=self.device)

        def loss_and_backward(k: int) -> float:
            cam, target = self.trainer.targets.get(int(views[k]), 1.0 / downscale, np.asarray(bgs[k], np.float32))
            r, img, _ = self.render(scene, cam, bgs[k], supersample=1, vis=vis, bounce=bounce, frag_cache=frags)
            loss = photometric_backward(r, target, tc.ssim_lambda)
            if held and scene.material.grad is not None:
                scene.material.grad[:, held] = 0.0
            return float(loss)

        def after_step(lights_before) -> None:
            scene.light_params.data[...] = balanced_lights(tc.white_light, scene.lights, scene.light_params.data,
                                                           self.trainer.priors.center,
                                                           before=lights_before if tc.hold_irradiance else None,
                                                           min_distance=self.trainer.light_min_radius)

        light_scale = (relative_lr_scales(scene.lights, extent=self.trainer.extent)
                       if scene.light_params is not None
                       and tc.lr_lights_mode == "relative" else None)
        t = time.perf_counter()
        out = metallic_trial(scene, tied, col, loss_and_backward, n, lr_material=c.lr_material,
                             rough_col=get_brdf(scene.brdf).column("roughness"),
                             max_metal_roughness=max_metal_roughness,
                             betas=tuple(tc.betas), lr_lights=c.lr_lights, light_scale=light_scale,
                             after_step=after_step if scene.light_params is not None else None)
        out["seconds"] = time.perf_counter() - t
        self.metallic_choice = out
        self.trainer.log.info("mesh metallic trial: " + json.dumps({k: v for k, v in out.items() if k != "curves"}))
        return out

    def fit_lights(self, scene: Scene) -> dict | None:
        """``MeshConfig.light_fit``: the scene's lights replaced by point lights and an ambient one fitted to the
        mesh's shading (:func:`~triplet_cl.mesh.light_fit.fit_lights`), or for a metal (the metallic trial's choice,
        or the mean metallic without a trial) to its highlights (:func:`~triplet_cl.mesh.light_fit.fit_metal_lights`,
        which also sets the tied roughness), scaled by the median over the vertices of the albedo they imply over the
        mesh's (the photos fix only albedo × light) or, for a metal with ``MeshConfig.metal_f0``, so that the median
        F0 they imply is that, the mesh's albedo then brought to it (× ``metal_f0`` / its median F0, within
        :data:`METAL_GAUGE_RANGE`); the light phase then refits the albedo under them. Skipped (None, the reason
        logged and recorded) when off, when the lights are held (``lr_lights`` 0) or are not point lights with
        falloff and ambient ones, when the fit fails (too few observed vertices, no direction), or when its objective
        is not ``light_fit_margin`` (``light_fit_margin_metal``) better than the lights before. The record goes to
        ``metrics.json``'s ``mesh.light_fit``."""
        from ..lights import AmbientLight, PointLight, lights_to_json, pack_lights

        c = self.cfg

        def log(msg: str) -> None:  # the train log, and the user's terminal (the stage's other decisions print too)
            self.trainer.log.info(msg)
            if not self.quiet:
                print(msg)

        if c.light_fit == "off":
            return None
        lights = scene.current_lights()
        mat = np.asarray(scene.material.data)
        metal = self.metallic_value(scene)
        why = None
        if c.lr_lights == 0:
            why = "the lights are held (lr_lights 0)"
        elif not any(isinstance(x, PointLight) for x in lights) or any(
                type(x) not in (PointLight, AmbientLight) or (isinstance(x, PointLight) and not x.falloff)
                for x in lights):
            why = "the lights are not point lights (with falloff) and ambient ones"
        if why is not None:
            log(f"mesh light fit skipped: {why}")
            self.light_fit = {"applied": False, "reason": why}
            return None
        t = time.perf_counter()
        ao_col = get_brdf(scene.brdf).column("ao")  # Cook-Torrance's ambient term is AO × (albedo or F0) × La
        ao = float(np.mean(sigmoid(mat[:, ao_col].astype(np.float64)))) if ao_col is not None else 1.0
        fitter = self._fit_metal_lights if metal > 0.5 else self._fit_diffuse_lights
        try:
            fit, scale, radiance = fitter(scene, lights, ao)
        except ValueError as exc:  # the photos show too little to fit: the soup's lights go on
            log(f"mesh light fit not possible: {exc}")
            self.light_fit = {"applied": False, "reason": str(exc)}
            return None
        kind = "metal (highlights)" if metal > 0.5 else "diffuse shading"
        rec = {k: fit[k] for k in ("objective", "objective_current", "distance", "weights", "vertices", "ambient")}
        rec.update({k: fit[k] for k in ("tv", "roughness", "observations", "f0_median") if k in fit}, model=kind)
        rec["seconds"] = time.perf_counter() - t
        margin = c.light_fit_margin_metal if metal > 0.5 else c.light_fit_margin
        if fit["objective_current"] is not None and fit["objective"] > (1.0 - margin) * fit["objective_current"]:
            log(f"mesh light fit ({kind}) not kept: {fit['objective']:.4f}, the lights before "
                f"{fit['objective_current']:.4f} (a gain under {margin:.0%})")
            why = f"not {margin:.0%} better than the lights before"
            self.light_fit = {"applied": False, "reason": why, **rec}
            return None
        new_lights = [PointLight(p, np.full(3, scale * i))
                      for p, i in zip(fit["positions"], fit["intensities"], strict=True)]
        new_lights.append(AmbientLight(np.full(3, scale * radiance)))
        scene.lights = new_lights
        scene.light_params = Param(pack_lights(new_lights).params.astype(mat.dtype), "light_params")
        rough_col = get_brdf(scene.brdf).column("roughness")
        if "roughness" in fit and rough_col is not None:  # the lobe the lights were fitted with (tied in the phase)
            mat[:, rough_col] = logit(fit["roughness"])
        if metal > 0.5 and c.metal_f0 > 0:  # the albedo brought to the F0 the lights were scaled to: the light phase
            # starts from renders as bright as the photos (else 0.35x on the demo's forced metal), as the old rule's
            a = float(np.clip(c.metal_f0 / max(self._f0_median(scene), 1e-6), *METAL_GAUGE_RANGE))
            rec.update(albedo_scale=a, albedo_saturated=self._scale_albedo(scene, a))
        rec.update(applied=True, lights=lights_to_json(new_lights)["lights"], scale=scale)
        before = "none" if fit["objective_current"] is None else f"{fit['objective_current']:.4f}"
        log(f"mesh light fit ({kind}): {len(new_lights) - 1} point light(s) at {fit['distance']} extents, "
            f"objective {fit['objective']:.4f} (lights before {before}), {rec['seconds']:.1f} s")
        self.light_fit = rec
        return rec

    def ambient_to_environment(self, scene: Scene) -> dict | None:
        """``MeshConfig.env_degree`` (``env_degree_metal`` for a metal: :meth:`metallic_value` above 0.5): each ambient
        light of a Cook-Torrance mesh replaced by an SH environment of that degree with the same radiance in band 0
        and 0 above (Cook-Torrance's ambient term is the environment term of a constant radiance: the renders are the
        same at the switch), its higher bands then learned with the lights.
        None (nothing done) when that degree is 0, for Blinn-Phong (its ambient term is ``La ka``, not the
        environment's), when the lights are held (``lr_lights`` 0) or have no ambient light. Recorded in
        ``metrics.json``'s ``mesh.environment``."""
        from ..lights import AmbientLight, SHEnvironmentLight, pack_lights

        c = self.cfg
        lights = scene.current_lights()
        metal = scene.brdf == "cook_torrance" and self.metallic_value(scene) > 0.5
        degree = c.env_degree_metal if metal else c.env_degree
        if (degree == 0 or scene.brdf != "cook_torrance" or c.lr_lights == 0 or scene.light_params is None
                or not any(isinstance(x, AmbientLight) for x in lights)):
            return None
        new = [SHEnvironmentLight.constant(x.color, degree=degree) if isinstance(x, AmbientLight) else x
               for x in lights]
        scene.lights = new
        scene.light_params = Param(pack_lights(new).params.astype(scene.light_params.data.dtype), "light_params")
        self.environment = {"degree": degree, "metal": metal, "from": "ambient",
                            "radiance": [float(np.mean(x.color)) for x in lights if isinstance(x, AmbientLight)]}
        self.trainer.log.info("mesh environment: " + json.dumps(self.environment))
        return self.environment

    def metallic_value(self, scene: Scene) -> float:
        """The metallic the stage treats the object with: the metallic trial's choice, else the mean metallic (0
        without a metallic channel); above 0.5 a metal (its lights from its highlights, the F0 gauge)."""
        if self.metallic_choice is not None:
            return float(self.metallic_choice["metallic"])
        met_col = get_brdf(scene.brdf).column("metallic")
        if met_col is None:
            return 0.0
        return float(np.mean(sigmoid(np.asarray(scene.material.data)[:, met_col].astype(np.float64))))

    def metal_gauge(self, scene: Scene) -> dict | None:
        """A metal's brightness gauge (``MeshConfig.metal_f0``), at the end of each round: the albedo × ``s`` (each
        channel at most 1 - 1e-4) and every light / ``s``, ``s`` = ``metal_f0`` / the median F0 luminance over the
        vertices (0.04 (1 - metallic) + metallic × albedo), within [1/4, 4] (:data:`METAL_GAUGE_RANGE`: a nearly
        black soup would otherwise send every vertex to 1). The photos fix only F0 × light on a metal (up to the
        Fresnel rise at grazing angles), so the renders keep but for the vertices whose albedo reaches 1. None
        (nothing done) for a dielectric, without a metallic channel, when ``metal_f0`` is 0 or the lights are held
        (``lr_lights`` 0: they are the user's). The record goes to ``metrics.json``'s ``mesh.metal_gauge``."""
        from ..lights import scale_lights

        c = self.cfg
        if (c.metal_f0 <= 0 or get_brdf(scene.brdf).column("metallic") is None or c.lr_lights == 0
                or scene.light_params is None or self.metallic_value(scene) <= 0.5):
            return None
        before = self._f0_median(scene)
        s = float(np.clip(c.metal_f0 / max(before, 1e-6), *METAL_GAUGE_RANGE))
        saturated = self._scale_albedo(scene, s)
        lp = scene.light_params
        lp.data[...] = scale_lights(scene.lights, lp.data, 1.0 / s)
        rec = {"scale": s, "f0_median_before": before, "f0_median": self._f0_median(scene), "saturated": saturated}
        self.trainer.log.info("mesh metal gauge: " + json.dumps(rec))
        self.metal_gauge_rec.append(rec)
        return rec

    @staticmethod
    def _f0_luminance(scene: Scene, idx=slice(None)) -> np.ndarray:
        """``[n]`` the F0 luminance of the vertices ``idx``, 0.04 (1 - metallic) + metallic × albedo (metallic 1
        without a metallic channel)."""
        from .light_fit import LUMA

        mat = np.asarray(scene.material.data)
        met_col = get_brdf(scene.brdf).column("metallic")
        met = sigmoid(mat[idx, met_col].astype(np.float64))[:, None] if met_col is not None else 1.0
        return (0.04 * (1.0 - met) + met * sigmoid(mat[idx, 0:3].astype(np.float64))) @ LUMA

    @classmethod
    def _f0_median(cls, scene: Scene) -> float:
        """The median over the vertices of the F0 luminance (:meth:`_f0_luminance`)."""
        return float(np.median(cls._f0_luminance(scene)))

    @staticmethod
    def _scale_albedo(scene: Scene, s: float) -> float:
        """The albedo × ``s`` in place (each channel within [1e-4, 1 - 1e-4]); returns the share of the vertices
        that reached the top."""
        mat = np.asarray(scene.material.data)
        alb = sigmoid(mat[:, 0:3].astype(np.float64)) * s
        mat[:, 0:3] = logit(np.clip(alb, 1e-4, 1.0 - 1e-4)).astype(mat.dtype)
        return float(np.mean(alb.max(axis=1) > 1.0 - 1e-4))

    def _photos(self):
        """The training views as ``(camera, rgb, alpha)`` in the renderer's radiance: decoded where the run renders
        linear radiance and encodes after (the linear pipeline on sRGB photos); as stored for linear data and for
        the sRGB-valued pipeline."""
        from ..ops.color import srgb_decode

        decode = self.trainer.transfer is not None
        return [(v.camera, srgb_decode(v.rgb) if decode else v.rgb, v.alpha) for v in self.ds.train]

    def _seen(self, scene: Scene, vertices=None, normals=None) -> np.ndarray:
        """``[N, views]``: which training camera sees which vertex (shadow rays towards the camera centres); with
        ``normals`` (one per vertex asked), no ray (1) towards a camera behind a vertex's normal: the observations
        (:func:`~triplet_cl.mesh.light_fit.vertex_observations`) need ``n · to camera > min_cos`` anyway."""
        from ..lights import PointLight
        from ..visibility import vertex_visibility

        return vertex_visibility(scene, self.device, lights=[PointLight(v.camera.center, np.ones(3))
                                                             for v in self.ds.train],
                                 ray_eps=self.cfg.shadow_eps, vertices=vertices, normals=normals)

    def _point_visibility(self, scene: Scene, n: int, vertices=None, normals=None):
        """``visibility(P, rows=None) -> [n, len(P)]``: the transmittance of point lights at ``P`` from the ``n``
        vertices ``vertices`` (default all), with the mesh's cast shadows where the run's renders have them
        (:meth:`visibility`), else 1; ``rows`` (indices into those ``n``): only their rows, traced from them alone.
        ``normals`` ``[n, 3]``: no ray (1) towards a light behind a vertex's normal, where the light fit's atoms
        weigh it by ``max(0, n · l) = 0``."""
        from ..lights import PointLight

        def visibility(P, rows=None):
            sel = vertices if rows is None else (np.asarray(rows) if vertices is None else np.asarray(vertices)[rows])
            m = n if rows is None else len(rows)
            nrm = None if normals is None else (normals if rows is None else np.asarray(normals)[np.asarray(rows)])
            vis = self.visibility(scene, [PointLight(p, np.ones(3)) for p in P], vertices=sel, normals=nrm)
            return np.ones((m, len(P))) if vis is None else vis
        return visibility

    @staticmethod
    def _current_lights(lights, ambient_factor: float):
        """``(positions, intensities, ambient)`` of the point and ambient ``lights`` in luminance, the ambient
        radiance × ``ambient_factor``."""
        from ..lights import AmbientLight, PointLight
        from .light_fit import LUMA

        points = [x for x in lights if isinstance(x, PointLight)]
        amb = sum(float(np.asarray(x.color) @ LUMA) for x in lights if isinstance(x, AmbientLight))
        return (np.array([x.position for x in points]).reshape(-1, 3),
                np.array([float(np.asarray(x.intensity) @ LUMA) for x in points]), ambient_factor * amb)

    def _fit_diffuse_lights(self, scene: Scene, lights, ao: float) -> tuple[dict, float, float]:
        """:func:`~triplet_cl.mesh.light_fit.fit_lights` on the mesh's per-vertex median radiance; the scale: the
        median over vertices of the albedo the new lights imply over the diffuse albedo the mesh keeps (albedo ×
        (1 - metallic)); the ambient light's radiance before that scale (the fit's ambient irradiance is π AO La).
        Measured (results §9-§10): the scale of the soup's lights' own robust fit relit two point lights 0.7-1.6 dB
        worse (those lights were fitted wrong); the ratio of the two medians put gadget's ambient 3x too bright
        (env_rotated -3.2 dB)."""
        from .bake import vertex_normals
        from .light_fit import LUMA, fit_lights, vertex_radiance

        V = np.asarray(scene.V.data, np.float64)
        normals = vertex_normals(V, scene.F)
        rad, count = vertex_radiance(V, normals, self._photos(), self._seen(scene, normals=normals))
        lo, hi = V.min(axis=0), V.max(axis=0)  # the atoms around the mesh itself, not the cameras' extent
        fit = fit_lights(V, scene.F, normals, rad, count, self._point_visibility(scene, len(V), normals=normals),
                         center=0.5 * (lo + hi), extent=0.5 * float(np.linalg.norm(hi - lo)),
                         max_lights=self.cfg.light_fit_max,
                         current=self._current_lights(lights, np.pi * ao))  # E = π AO La
        mat = np.asarray(scene.material.data)
        met_col = get_brdf(scene.brdf).column("metallic")
        good = fit["observed"]
        implied = np.pi * (rad[good] @ LUMA) / np.maximum(fit["irradiance"][good], 1e-12)
        diffuse = sigmoid(mat[good, 0:3].astype(np.float64)) @ LUMA
        if met_col is not None:
            diffuse = diffuse * (1.0 - sigmoid(mat[good, met_col].astype(np.float64)))
        return fit, float(np.median(implied / np.maximum(diffuse, 0.02))), fit["ambient"] / (np.pi * max(ao, 1e-3))

    def _fit_metal_lights(self, scene: Scene, lights, ao: float) -> tuple[dict, float, float]:
        """:func:`~triplet_cl.mesh.light_fit.fit_metal_lights` on the photo values of ``light_fit_samples`` vertices
        (a fixed random sample: the fit holds observations × atoms), with the mesh's F0 (0.04 (1 - metallic) +
        metallic × albedo) in Schlick's Fresnel (measured against F = F0 on the metal captures, results §7: two
        point lights relit +0.2 / +0.6 / +1.5 dB, albedo +1.2; the environment and one light the same); the scale:
        the median F0 the new lights imply over ``MeshConfig.metal_f0`` (a metal's typical F0; 0: the median over
        them of the implied F0 over the mesh's); the ambient light's radiance before that scale (the fit's ambient
        term is AO La, over F0)."""
        from .bake import vertex_normals
        from .light_fit import fit_metal_lights, vertex_observations

        V = np.asarray(scene.V.data, np.float64)
        normals = vertex_normals(V, scene.F)
        idx = np.arange(len(V))
        if len(V) > self.cfg.light_fit_samples:
            idx = np.sort(np.random.default_rng(0).choice(len(V), self.cfg.light_fit_samples, replace=False))
        obs = vertex_observations(V[idx], normals[idx], self._photos(), self._seen(scene, idx, normals[idx]))
        f0 = self._f0_luminance(scene, idx)
        lo, hi = V.min(axis=0), V.max(axis=0)
        fit = fit_metal_lights(V[idx], normals[idx], obs, self._point_visibility(scene, len(idx), idx, normals[idx]),
                               center=0.5 * (lo + hi), extent=0.5 * float(np.linalg.norm(hi - lo)),
                               max_lights=self.cfg.light_fit_max, f0=f0,
                               current=self._current_lights(lights, ao))  # AO × F0 × La
        good = np.isfinite(fit["implied"])
        if self.cfg.metal_f0 > 0:  # the lights' brightness from what metals reflect (MeshConfig.metal_f0)
            scale = float(np.median(fit["implied"][good])) / self.cfg.metal_f0
        else:
            scale = float(np.median(fit["implied"][good] / np.maximum(f0[good], 0.02)))
        fit["f0_median"] = float(np.median(fit["implied"][good])) / scale  # what the scaled lights imply
        return fit, scale, fit["ambient"] / max(ao, 1e-3)

    @property
    def ao_mode(self) -> str:
        """``MeshConfig.ao``, with "auto" as decided by :meth:`choose_ao` ("learned" until then)."""
        if self.cfg.ao != "auto":
            return self.cfg.ao
        return self.ao_choice["choice"] if self.ao_choice is not None else "learned"

    def choose_ao(self, scene: Scene) -> dict | None:
        """``MeshConfig.ao = "auto"``: trace the extracted mesh's AO and compare it with the AO the soup learned (as
        transferred to the mesh's vertices, before the light phase ties it): computed when their Spearman rank
        correlation reaches ``ao_auto_correlation``, else learned. Not decided (None) without a learned per-vertex
        AO (a BRDF without one, or the soup's held by ``TrainConfig.ao = "off"``). The record goes to
        ``metrics.json``'s ``mesh.ao_choice``."""
        from scipy.stats import spearmanr

        col = get_brdf(scene.brdf).column("ao")
        if self.cfg.ao != "auto" or col is None or col in self.trainer.held_ao:
            return None
        t = time.perf_counter()
        learned = sigmoid(np.asarray(scene.material.data[:, col], np.float64))
        traced = self.trace_ao(scene)
        self._ao_traced = (scene, traced)  # set_computed_ao at the round's start reuses it: the same vertices
        rho = float(spearmanr(traced, learned)[0]) if np.ptp(learned) > 0 and np.ptp(traced) > 0 else 0.0
        rho = rho if np.isfinite(rho) else 0.0
        choice = "computed" if rho >= self.cfg.ao_auto_correlation else "learned"
        self.ao_choice = {"choice": choice, "spearman": rho, "threshold": self.cfg.ao_auto_correlation,
                          "traced_p10_50_90": np.round(np.percentile(traced, [10, 50, 90]), 3).tolist(),
                          "learned_p10_50_90": np.round(np.percentile(learned, [10, 50, 90]), 3).tolist(),
                          "seconds": time.perf_counter() - t}
        msg = (f"mesh AO: {choice} (the soup's learned AO against the traced occlusion: Spearman {rho:.2f}, "
               f"{'at least' if choice == 'computed' else 'below'} {self.cfg.ao_auto_correlation})")
        self.trainer.log.info(msg)
        if not self.quiet:
            print(msg)
        return self.ao_choice

    def computed_ao_column(self, scene: Scene) -> int | None:
        """The AO column that ``MeshConfig.ao = "computed"`` (or "auto" decided so) sets from the geometry, or None
        (learned, or a BRDF without AO)."""
        return get_brdf(scene.brdf).column("ao") if self.ao_mode == "computed" else None

    def held_columns(self, scene: Scene) -> list[int]:
        """The material columns that take no step in the mesh stage: the AO held by ``TrainConfig.ao = "off"``
        or set from the geometry (``MeshConfig.ao = "computed"``)."""
        ao = self.computed_ao_column(scene)
        return list(self.trainer.held_ao) + ([ao] if ao is not None else [])

    def trace_ao(self, scene: Scene) -> np.ndarray:
        """``[N]`` the mesh's traced ambient occlusion (:func:`~triplet_cl.visibility.vertex_ambient_occlusion`,
        ``ao_directions`` rays per vertex)."""
        from ..visibility import vertex_ambient_occlusion
        from .bake import vertex_normals

        return vertex_ambient_occlusion(scene, vertex_normals(scene.V.data, scene.F), self.device,
                                        directions=self.cfg.ao_directions, ray_eps=self.cfg.shadow_eps)

    def set_computed_ao(self, scene: Scene, col: int | None) -> None:
        """The mesh's traced ambient occlusion (:func:`~triplet_cl.visibility.vertex_ambient_occlusion`) written into
        the AO column ``col`` (raw: the sigmoid's inverse, clipped to [0.02, 0.999])."""
        if col is None:
            return
        t = time.perf_counter()
        cached, self._ao_traced = self._ao_traced, None
        ao = cached[1] if cached is not None and cached[0] is scene else self.trace_ao(scene)
        scene.material.data[:, col] = logit(np.clip(ao, 0.02, 0.999), eps=None).astype(scene.material.data.dtype)
        pct = np.round(np.percentile(ao, [10, 50, 90]), 3).tolist()
        self.trainer.log.info(f"mesh AO traced: {len(ao)} vertices, p10/50/90 {pct}, {time.perf_counter() - t:.1f} s")

    def refine(self, scene: Scene, round_index: int) -> Scene:
        from tqdm import tqdm

        from ..lights import balanced_lights
        from ..train import psnr, tie_rows
        from .remesh import refine_scene

        c, tc = self.cfg, self.trainer.cfg
        amb = self.trainer.ambient_pairs  # Blinn-Phong's ka ≡ kd (TrainConfig.blinn_phong_ka): not tied on its own
        if round_index == 0:  # before anything ties the AO the soup learned
            self.choose_ao(scene)
        ao_col = self.computed_ao_column(scene)
        held_cols = self.held_columns(scene)
        tied = self.light_phase_ties(scene)
        # the metallic column is decided, not drifted: held through the light phase at the value choose_metallic
        # picked (round 0) or at its mean (later rounds)
        self.set_computed_ao(scene, ao_col)
        held = get_brdf(scene.brdf).column("metallic") if tied and c.metallic_trial > 0 else None
        if held is not None and round_index == 0:
            self.choose_metallic(scene, tied, held)
        if round_index == 0:
            self.fit_lights(scene)
            self.ambient_to_environment(scene)
        # the held metallic: each vertex's own gradient builds its Adam moments through the phase and the value is
        # put back after each step (as the soup's held lobes); with its gradient zeroed instead, its moments stayed 0
        # and, Adam's step count shared, it left the phase at up to 3× the rate, undoing the trial's choice
        phase_tied = [k for k in tied if k != held]
        opt = self.build_optimizer(scene)
        reg = Regularizers(scene, c, self.trainer.length_scale)
        shadows = None
        if self.shadows_active():
            from ..visibility import VisibilityCache

            shadows = VisibilityCache(every=tc.shadow_every, extent=self.trainer.extent, ray_eps=c.shadow_eps)
        grad_acc = np.zeros(len(scene.F))
        # the traced interreflection, re-traced every shadow_every steps (as the cast shadows) and after a remesh
        bounce, bounce_at, bounce_traces = None, 0, None
        bounce_every = max(tc.shadow_every, 1) if self.bounce_active(scene) else 0
        targets = self.trainer.targets
        order: list[int] = []
        bar = tqdm(total=c.iterations, desc=f"mesh {round_index + 1}/{c.rounds}", unit="it", disable=self.quiet,
                   dynamic_ncols=True)
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=1)  # the regularisers, beside each step's render and backward
        try:
            for it in range(c.iterations):
                if not order:
                    order = list(self.rng.permutation(len(self.ds.train)))
                i = int(order.pop())
                bg = self.rng.uniform(0, 1, 3) if tc.background == "random" else resolve_background(tc.background)
                cam, target = targets.get(i, 1.0, np.asarray(bg, np.float32))
                t0 = time.perf_counter()
                if reg.normal is not None:  # its crease scale this step (the previous step's job is done)
                    reg.normal.kappa = c.normal_kappa_at(it)
                reg_job = pool.submit(reg.compute, np.asarray(scene.V.data), np.asarray(scene.material.data))
                vis = None if shadows is None else shadows.get(scene, it, self.device)
                # re-traced every shadow_every steps, and whenever the cast shadows were (a light moved: the cache
                # re-traces early) or the topology changed (bounce None)
                traces = None if shadows is None else shadows.traces
                if bounce_every and (bounce is None or it - bounce_at >= bounce_every or traces != bounce_traces):
                    bounce, bounce_at, bounce_traces = self.bounce(scene, vis), it, traces
                r, img, _ = self.render(scene, cam, bg, vis=vis, bounce=bounce)
                loss = photometric_backward(r, target, tc.ssim_lambda)
                gV = np.asarray(scene.V.grad, np.float64)
                grad_acc += face_mean_norm(gV, scene.F)
                reg_loss = reg.apply(scene, reg_job.result())
                tie_ambient_gradient(scene.material, amb)
                if held_cols and scene.material.grad is not None:
                    scene.material.grad[:, held_cols] = 0.0
                kept = None
                if it < c.material_tie and tied:
                    tie_rows(scene.material, phase_tied)
                    if held is not None:
                        kept = np.array(scene.material.data[:, held])
                lights_before = (np.array(scene.light_params.data)
                                 if scene.light_params is not None and tc.hold_irradiance else None)
                opt.step()
                opt.zero_grad()
                if kept is not None:
                    scene.material.data[:, held] = kept
                copy_ambient(scene.material, amb)
                if scene.light_params is not None:  # the soup stage's white-light rule (and its irradiance hold)
                    scene.light_params.data[...] = balanced_lights(tc.white_light, scene.lights,
                                                                   scene.light_params.data, self.trainer.priors.center,
                                                                   before=lights_before,
                                                                   min_distance=self.trainer.light_min_radius)
                rec = {"round": round_index, "it": it + 1, "loss": float(loss), "reg": reg_loss,
                       "psnr": psnr(img, target), "faces": len(scene.F), "time": time.perf_counter() - t0}
                self.history.append(rec)
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{rec['psnr']:.2f}", faces=str(len(scene.F)))
                last = it + 1 == c.iterations
                if c.remesh_every and (it + 1) % c.remesh_every == 0 and not last:
                    hi = c.subdivide_fraction if len(scene.F) < c.max_faces else 0.0
                    rep = refine_scene(scene, opt, grad_acc, fraction_hi=hi, fraction_lo=c.simplify_fraction)
                    self.trainer.log.info(f"mesh remesh at {it + 1}: faces {rep.faces_before} -> {rep.faces_after} "
                                          f"({rep.subdivided} subdivided, {rep.simplified} simplified)")
                    reg = Regularizers(scene, c, self.trainer.length_scale)
                    grad_acc = np.zeros(len(scene.F))
                    self.set_computed_ao(scene, ao_col)
                    bounce = None  # the topology changed: re-traced at the next step
                    self.device.release_memory()  # buffers of the old sizes (RSS grew 6.8 -> 12.8 GB at 800²)
                if (it + 1) % 100 == 0:
                    self.trainer.log.info(json.dumps(rec))
        finally:
            pool.shutdown(wait=True)
            bar.close()
        self.metal_gauge(scene)
        return scene

    # ---- the whole stage -----------------------------------------------------------------------
    def run(self) -> dict:
        """Extract → refine (``rounds`` times) → evaluate → export. Returns the ``"mesh"`` metrics."""
        t = time.perf_counter()
        # what the soup's training no longer needs goes back before the stage allocates (an 800² capture's train
        # --mesh-stage was killed at 24 GB here): its targets at other scales, the pool's and the C heap's free memory
        self.trainer.targets.keep_only(1.0)
        self.device.release_memory()
        source = self.trainer.scene
        # the refinement compares renders of the mesh alone with the photos: with a background in them (no alpha)
        # and the mesh cropped to the object, it would grow the mesh over the background; extraction only then
        refine = self.cfg.iterations > 0 and not (self.roi() is not None and not self.ds.has_alpha)
        if self.cfg.iterations and not refine:
            msg = ("mesh refinement skipped: the photos have a background (no alpha) and the mesh is cropped to the "
                   "object; the mesh is extracted, its materials transferred from the soup")
            self.trainer.log.info(msg)
            if not self.quiet:
                print(msg)
        for k in range(self.cfg.rounds):
            scene = self.extract(source)
            if self.cfg.pixel_sigma is None:
                self.resolve_pixel_filter(scene)
            if refine:
                scene = self.refine(scene, k)
            source = scene
        self.scene = source
        topology = self.repair()
        self.save_state()
        metrics = self.evaluate()
        metrics["topology"] = topology
        if self.metallic_choice is not None:
            metrics["metallic_trial"] = self.metallic_choice
        if self.ao_choice is not None:
            metrics["ao_choice"] = self.ao_choice
        if self.light_fit is not None:
            metrics["light_fit"] = self.light_fit
        if self.metal_gauge_rec:
            metrics["metal_gauge"] = self.metal_gauge_rec
        if self.environment is not None:
            metrics["environment"] = self.environment
        if self.env_occlusion_traces:
            metrics["environment_occlusion"] = {"degree": self.cfg.env_occlusion, "traces": self.env_occlusion_traces}
        metrics["wall_time_s"] = time.perf_counter() - t
        if self.roi() is not None:
            metrics["roi"] = self.roi().to_dict()
        if self.pixel_filter is not None:
            metrics["pixel_filter"] = self.pixel_filter
        self._write_metrics(metrics)  # before the export: a failing export loses no result
        metrics["files"] = [str(p.name) for p in self.export()]
        self._write_metrics(metrics)
        return metrics

    def resolve_pixel_filter(self, scene: Scene) -> None:
        """``MeshConfig.pixel_sigma`` None (auto): read from the photos' alpha edges against renders of the extracted
        ``scene`` (:func:`~triplet_cl.mesh.pixel_filter.estimate_pixel_sigma`); the config then holds the value (saved
        with the state: the test renders and relighting use it)."""
        from dataclasses import replace

        from .pixel_filter import estimate_pixel_sigma

        t = time.perf_counter()
        est = estimate_pixel_sigma(self, scene)
        self.cfg = replace(self.cfg, pixel_sigma=round(float(est["sigma"]), 3))
        self.cfg.validate()
        est["seconds"] = time.perf_counter() - t
        self.pixel_filter = est
        ratio = "" if est["photo_ratio"] is None else f", photos' edge ratio {est['photo_ratio']:.3f}"
        self.trainer.log.info(f"pixel filter: Gaussian sigma {self.cfg.pixel_sigma} px ({est['source']}{ratio}, "
                              f"{est['seconds']:.1f} s)")

    def repair(self) -> dict:
        """Remove the final mesh's self-intersections (:func:`~triplet_cl.mesh.repair.repair_self_intersections`:
        QEM simplification and the refinement's vertex steps can make faces cross) and report its topology
        before and after (genus, watertightness, crossing face pairs) for ``metrics.json``."""
        from dataclasses import asdict

        from .repair import mesh_topology, repair_self_intersections

        t = time.perf_counter()
        V, F = np.asarray(self.scene.V.data), np.asarray(self.scene.F)
        before = mesh_topology(V, F, intersections=False)
        Vn, rep = repair_self_intersections(V, F, rings=self.cfg.repair_rings)
        if rep.before:
            self.scene.V.data = Vn.astype(V.dtype)
        after = mesh_topology(self.scene.V.data, F, intersections=False)
        before["self_intersections"], after["self_intersections"] = rep.before, rep.after
        out = {"before_repair": before, "after_repair": after, "repair": {**asdict(rep),
                                                                            "seconds": time.perf_counter() - t}}
        self.trainer.log.info(f"mesh repair: {rep.before} -> {rep.after} self-intersecting face pairs "
                              f"({rep.moved_vertices} vertices moved, at most {rep.max_displacement:.2g}); genus "
                              f"{after['genus']}, watertight {after['watertight']}, {time.perf_counter() - t:.1f} s")
        return out

    def evaluate(self) -> dict:
        """Test-view PSNR/SSIM of the mesh (and of the soup, for comparison), Chamfer to ``gt_mesh.ply`` and to its
        outer surface (``chamfer_surface_to_gt``: :mod:`~triplet_cl.mesh.metrics`)."""
        from .metrics import chamfer_distance, load_reference_mesh

        tr = self.trainer
        soup = tr.evaluate()
        mesh = self._evaluate_scene(self.scene, write_renders=True)
        out = {"faces": len(self.scene.F), "vertices": self.scene.V.shape[0], "method": self.cfg.method,
               "psnr": mesh["psnr"], "ssim": mesh["ssim"], "soup_psnr": soup["psnr"], "soup_ssim": soup["ssim"],
               "soup_faces": len(tr.scene.F), "views": mesh["views"]}
        if self.roi() is not None and not self.ds.has_alpha:
            # the mesh is the object alone and the photos show the ground and the sky around it: its PSNR against
            # them measures the missing background, not the mesh (the command says so beside the number)
            out["cropped_to_object"] = True
        ref = load_reference_mesh(tr.data) if Path(tr.data).is_dir() else None
        if ref is not None:
            cd = chamfer_distance(self.scene.V.data, self.scene.F, *ref)
            out["gt_buried_fraction"] = cd.pop("buried_fraction")  # metrics.py: the reference's hidden faces
            out.update({f"{k}_to_gt": v for k, v in cd.items()})
        return out

    def _evaluate_scene(self, scene: Scene, write_renders: bool) -> dict:
        from ..io import write_png
        from ..losses import ssim
        from ..runs import view_progress
        from ..train import psnr

        tr = self.trainer
        views = tr.ds["test"] or tr.ds.train
        if tr.cfg.max_test_views:
            views = views[: tr.cfg.max_test_views]
        bg = np.asarray(resolve_background("white" if tr.cfg.background == "random" else tr.cfg.background),
                        np.float32)
        vis = self.visibility(scene)
        bounce = self.bounce(scene, vis)
        per = []
        for v, fname in view_progress(zip(views, render_files(views), strict=True), "render mesh",
                                      not tr.view_progress):
            _, img, alpha = self.render(scene, v.camera, bg, self.cfg.eval_supersample, vis=vis, bounce=bounce)
            target = v.target(bg)
            img = np.clip(img, 0, 1)
            per.append({"name": v.name, "psnr": psnr(img, target),
                        "ssim": float(ssim(img.astype(np.float64), target.astype(np.float64), padding="valid"))})
            if write_renders:
                a = np.clip(alpha, 0, 1)
                rgb = np.where(a[..., None] > 1e-4, (img - bg * (1 - a[..., None])) / np.maximum(a[..., None], 1e-4),
                               0.0)
                write_png(self.run_dir / "renders" / "mesh" / fname, rgb, a)
        return {"psnr": float(np.mean([p["psnr"] for p in per])), "ssim": float(np.mean([p["ssim"] for p in per])),
                "views": per}

    def export(self) -> list[Path]:
        return export_run_mesh(self.run_dir, self.asset(), self.cfg.formats, self.cfg.texture_size,
                               albedo_space=albedo_space(self.trainer.cfg.color))

    def asset(self) -> MeshAsset:
        return MeshAsset.from_scene(self.scene)

    # ---- persistence ---------------------------------------------------------------------------
    def save_state(self) -> Path:
        save_mesh_state(self.run_dir / MESH_STATE, self.scene, self.cfg)
        self.state_saved = True  # (an interruption after this: the new state beside the previous exports)
        return self.run_dir / MESH_STATE

    def _write_metrics(self, mesh_metrics: dict) -> None:
        from ..runs import read_metrics

        path = self.run_dir / "metrics.json"
        metrics = read_metrics(self.run_dir, "extract")
        metrics["mesh"] = mesh_metrics
        write_json(path, metrics)
        self.trainer.log.info("mesh metrics: " + json.dumps({k: v for k, v in mesh_metrics.items() if k != "views"}))




def metallic_trial(scene: Scene, tied: list[int], col: int, loss_and_backward, steps: int, *, lr_material: float,
                   betas=(0.9, 0.999), lr_lights: float = 0.0, light_scale=None, after_step=None,
                   values=METALLIC_TRIAL_VALUES, rough_col: int | None = None,
                   max_metal_roughness: float = MAX_METAL_ROUGHNESS) -> dict:
    """Metal or dielectric: the metallic column ``col`` of ``scene.material`` set to each of ``values`` in turn on
    every vertex and held there, the same short fit run from the same start for each (``steps`` calls of
    ``loss_and_backward(k)``, which renders step ``k``'s view, returns its loss and leaves the gradients in the
    scene's parameters; Adam on the materials, the ``tied`` columns one value, and on the lights when the scene
    has any, ``after_step(lights_before)`` after each step with the light parameters before it (None without
    lights); the geometry fixed); the value whose fit has the lower mean loss over its second half wins. The
    scene is put back as it was, but for the column set to the winner. Returns ``{"metallic", "loss" (per value),
    "steps", "curves" (per value, the loss of every step), "tied" (per value, the tied columns' raw values at the
    end of its fit), "refused" (the metal value refused by the roughness rule, or None)}``.

    Why a trial: a metallic value tied over the mesh and stepped by Adam goes wherever the sign of its mean
    gradient points, at full rate however weak the evidence; measured, the metal capture's mesh ended at metallic
    0.98 or 0.11 depending on the lights' path, and gadget's (a dielectric) at 0.48. The trial starts from the
    soup's state, fitted as a near-dielectric (metallic 0.1): the metal hypothesis has to refit its albedo in
    the same steps, a bias towards the dielectric, as a prior that keeps metallic at 0 unless the photos need it.

    A metal that wins with its (tied) roughness ``rough_col`` fitted above ``max_metal_roughness`` is refused (the
    lowest value wins): so rough a metal is a near-Lambertian reflector that a dielectric explains as well, and its
    small gain in loss comes from absorbing what the light model misses. Measured (96² captures, 200-step trials):
    the metal hypothesis won on the metal capture at roughness 0.65 (truth 0.35), and on two dielectric ones (two
    point lights; gadget) at 0.92 and 0.91; on spot_small the dielectric won outright (its metal at 0.93)."""
    from ..train import tie_rows

    m0 = np.array(scene.material.data)
    lp = scene.light_params
    params = [p for p in (scene.V, scene.alpha, scene.vertex_sh, scene.material, lp) if p is not None]
    l0 = None if lp is None else np.array(lp.data)
    curves, ends = {}, {}
    # not optimised here: held, the renders' backward skips their adjoints (the geometry's)
    with held_params([p for p in (scene.V, scene.alpha, scene.vertex_sh) if p is not None]):
        for value in values:
            scene.material.data[...] = m0
            scene.material.data[:, col] = logit(value)
            if l0 is not None:
                lp.data[...] = l0
            opt = Adam()
            opt.add_group("material", [scene.material], lr=lr_material, betas=tuple(betas), eps=1e-12)
            if l0 is not None:
                opt.add_group("lights", [lp], lr=lr_lights, lr_scale=None if light_scale is None else [light_scale],
                              betas=tuple(betas), eps=1e-12)
            losses = []
            for k in range(steps):
                for p in params:
                    p.grad = None
                losses.append(loss_and_backward(k))
                tie_rows(scene.material, tied)
                if scene.material.grad is not None:
                    scene.material.grad[:, col] = 0.0
                lights_before = None if lp is None else np.array(lp.data)
                opt.step()
                if after_step is not None:
                    after_step(lights_before)
            for p in params:
                p.grad = None
            curves[value] = losses
            ends[value] = np.asarray(scene.material.data)[0, tied].tolist()
    scores = {v: float(np.mean(c[len(c) // 2:])) for v, c in curves.items()}
    best = min(scores, key=scores.get)
    refused = None
    if best > 0.5 and rough_col is not None and rough_col in tied:
        # a near-Lambertian metal: what a dielectric explains as well, the prior wins
        if sigmoid(ends[best][tied.index(rough_col)]) > max_metal_roughness:
            refused, best = best, min(values)
    scene.material.data[...] = m0
    scene.material.data[:, col] = logit(best)
    if l0 is not None:
        lp.data[...] = l0
    return {"metallic": best, "loss": {str(v): x for v, x in scores.items()}, "steps": steps,
            "curves": {str(v): c for v, c in curves.items()}, "tied": {str(v): e for v, e in ends.items()},
            "refused": refused}


@contextlib.contextmanager
def held_params(params):
    """``requires_grad`` off for ``params`` inside the block, each put back as it was after it (also on an error)."""
    before = [p.requires_grad for p in params]
    for p in params:
        p.requires_grad = False
    try:
        yield
    finally:
        for p, b in zip(params, before, strict=True):
            p.requires_grad = b


def tied_channels(brdf: str) -> list[int]:
    """The material columns the mesh stage's light phase ties (``MeshConfig.material_tie``): all but the albedo."""
    return [i for i, n in enumerate(get_brdf(brdf).channel_names) if not n.startswith(("albedo_", "kd_"))]


def save_mesh_state(path: Path, scene: Scene, cfg: MeshConfig) -> None:
    """The refined mesh (V, F, raw parameters, lights) as one ``.npz`` (atomic)."""
    import io as _io

    from ..lights import lights_to_json

    arrays = {"V": scene.V.data, "F": scene.F, "material": scene.material.data, "alpha": scene.alpha.data}
    if scene.vertex_sh is not None:
        arrays["vertex_sh"] = scene.vertex_sh.data
    meta = {"brdf": scene.brdf, "lights": lights_to_json(scene.current_lights(), check_finite=False)["lights"],
            "mesh": cfg.to_dict()}
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = _io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_mesh_state(path) -> Scene:
    """The :class:`Scene` saved by :func:`save_mesh_state`."""
    import zipfile

    from ..errors import RunError
    from ..lights import lights_from_json

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no mesh-stage result at {path}: run `triplet extract` on the run first")
    try:
        with np.load(path, allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
        meta = json.loads(bytes(a.pop("meta")).decode())
        lights = lights_from_json(meta["lights"])
        return Scene.from_arrays(a["V"], a["F"], material=a["material"], alpha=a["alpha"], lights=lights,
                                 vertex_sh=a.get("vertex_sh"), brdf=meta["brdf"])
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise RunError(path, f"damaged mesh-stage result ({type(exc).__name__}: {exc}): run `triplet extract` "
                             "again") from None


def albedo_space(color: str) -> str:
    """The ``albedo_space`` of the exports of a run with colour pipeline ``color`` (``TrainConfig.color``):
    the linear pipeline learns linear reflectance (encoded with the sRGB transfer for the base-colour textures),
    the old encoded one fitted the photos' encoded values (stored unchanged)."""
    return "linear" if color == "linear" else "srgb"


def run_color(run_dir) -> str:
    """``TrainConfig.color`` of the run in ``run_dir`` (``"encoded"`` for a run saved before the linear pipeline)."""
    cfg = json.loads((Path(run_dir) / "config.json").read_text())
    return cfg.get("train", {}).get("color", "encoded")


def export_run_mesh(run_dir, asset: MeshAsset, formats=("glb", "obj", "ply"), texture_size: int = 1024,
                    albedo_space: str = "srgb") -> list[Path]:
    """Write the mesh assets of a run (``mesh.glb/.obj/.ply``, ``envmap.exr``, ``lights.json``);
    ``albedo_space``: see :func:`albedo_space`."""
    from .export import export_asset

    written = export_asset(asset, run_dir, formats=tuple(formats), texture_size=texture_size,
                           albedo_space=albedo_space)
    paths = []
    for v in written.values():
        paths += [Path(p) for p in v] if isinstance(v, list | tuple) else [Path(v)]
    return paths
