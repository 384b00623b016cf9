"""Training: initialise a triangle soup, optimise it against the photos, write a run directory.

One iteration: pick a training view (a seeded permutation per epoch), render it at the scheduled
resolution and K, compare with the target (``(1−λ)·L1 + λ·D-SSIM``), back-propagate through the
tape, step Adam, accumulate density statistics and, on schedule, split / clone / prune / reset
alpha. Everything is a :class:`TrainConfig` field, saved to ``config.json``; checkpoints hold the
scene, the optimizer, the density statistics and the random state, so ``resume`` continues
bit-for-bit.

Run directory: ``config.json``, ``checkpoints/ckpt_<it>.npz`` (+ ``latest``), ``triplets.ply``,
``lights.json``, ``renders/test/*.png`` (RGBA, straight alpha), ``metrics.json``, ``train.log``.
"""

from __future__ import annotations

import errno
import io as _io
import json
import logging
import math
import os
import signal
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import pyopencl.array as cla
from scipy.spatial import cKDTree

from .camera import Camera
from .datasets import images as dataset_images
from .datasets import load_dataset
from .datasets.base import REFERENCE_EXTENT, Dataset, DatasetWarning, render_files, resolve_background
from .density import (
    DensityConfig,
    DensityStats,
    densify_and_prune,
    face_alpha,
    front_faces,
    reorder_faces,
    reset_alpha,
    visible_faces,
)
from .device import Device, get_device
from .errors import DatasetError, NonFiniteError, RunError
from .io import atomic_write_bytes, write_json, write_png, write_soup_ply
from .lights import LIGHT_KINDS as _LIGHT_CLASSES_BY_KIND
from .lights import (
    WHITE_LIGHT_MODES,
    LightInit,
    SHEnvironmentLight,
    balanced_lights,
    hold_irradiance,
    lights_kept_out,
    lights_to_json,
    pack_lights,
    relative_lr_scales,
    unpack_lights,
)
from .lights import initial_lights as _initial_lights
from .losses import (
    ExactLoss,
    exact_device_loss_available,
    loss_backend,
    photometric_loss_and_grad,
    photometric_loss_and_grad_exact,
    ssim,
)
from .materials import DEFAULT_BRDF, ambient_pairs, copy_ambient, get_brdf, tie_ambient_gradient
from .ops.common import check_faces
from .optim import Adam, Constant, ExponentialDecay, NonFiniteStep, StepUp
from .priors import Priors
from .render import RENDERERS, RenderSettings, render
from .scene import Scene
from .topology import morton_order
from .visibility import SHADOW_MODES, VisibilityCache

LIGHT_KINDS = tuple(_LIGHT_CLASSES_BY_KIND)  # the CLI kinds of the registered lights (lights.py)
# TrainConfig fields that may change when a run is resumed (the others fix what the checkpoint holds)
REFERENCE_ITERATIONS = 3000  # the run length the schedules' defaults are tuned for (TrainConfig.with_iterations)
DEMO_ITERATIONS = 1500  # `triplet train --demo` without --iterations (spot_small 96²: ~20 s here)
LIGHT_PHASE_LOBES = ("held", "tied")  # TrainConfig.light_phase_lobes
RESUMABLE_FIELDS = ("iterations", "checkpoint_every", "keep_checkpoints", "max_test_views")
COLOR_PIPELINES = ("linear", "encoded")
LR_LIGHTS_MODES = ("absolute", "relative")
Y00 = 0.28209479177387814  # the constant real SH basis function


@dataclass
class TrainConfig:
    """Every setting of a run (saved as ``config.json``; the CLI maps its options onto these)."""

    iterations: int = 3000  # optimisation steps
    seed: int = 0  # seeds the initial points, view order and random backgrounds
    brdf: str = DEFAULT_BRDF  # a name of materials.BRDFS
    lights: tuple = ("point", "ambient")  # any mix of LIGHT_KINDS
    light_distance: float = 0.6  # point lights start this many scene extents from the centre (PointLight.initial)
    sh_degree: int = 2  # max degree of the vertex-SH / SH-environment light
    sh_band_every: int = 1000  # one more SH band every this many iterations (until sh_degree)
    init_points: int = 20_000  # random initial triangles (when the dataset has no sparse points)
    # half-size of the random-point box, × the frame radius (frame_radius: the half-width the cameras see at the
    # look-at centre, 3.2 × tan 20° = 1.165 on the dev scenes → ±1.28, the method's ±1.3 on NeRF-synthetic objects).
    # Before, × the mean camera distance (0.4): a capture framed with a longer lens (spot_small re-rendered with its
    # cameras 2.5× farther and a 2.5× narrower field) started with 97 % of its triplets outside the object's frame:
    # soup 27.9 dB, mesh 30.7 dB, Chamfer 0.24 against 34.0 / 40.1 / 0.0048 (bench/results/framing_pocl_2026-11-27.txt)
    init_box: float = 1.1
    init_box_frame: bool = True  # init_box is × the frame radius (False: × the mean camera distance, runs before)
    # the scene extent that sets every world-size default (position rates, the density thresholds, the lights' start
    # and rate): the cameras' extent, or the frame radius × EXTENT_PER_FRAME_RADIUS where that is smaller (scene_extent;
    # False: the cameras' extent alone, runs before)
    extent_frame: bool = True
    init_size: float = 0.5  # triangle radius, × mean distance to the 3 nearest initial points
    # photos with a background (no alpha): this many extra triangles on a sphere of radius background_radius × the
    # mean camera distance around the look-at point, for the sky / far walls that SfM gives no points for (0: none).
    # "auto": AUTO_BACKGROUND_SHELL for photos without alpha trained over the random background with SfM points to
    # crop the mesh by (auto_background_shell), else 0 (resolved by the Trainer and saved in config.json as the
    # number). Measured on shared/data/photos/spot_ground (320x240, 3000 it.; together with
    # the random background that "auto" also chooses there, bench/results/photos_defaults_pocl_2026-11-28.txt):
    # test PSNR 27.34 -> 28.72 dB, the cropped mesh's Chamfer 0.0414 -> 0.0265 of the cow's radius
    background_shell: int | str = "auto"
    background_radius: float = 3.0
    faces_per_pixel: int = 30  # K after the warm-up
    warmup_faces_per_pixel: int = 150  # K during the warm-up
    warmup_until: int = 200  # warm-up length (¼ resolution and warm-up K)
    half_res_until: int = 600  # ½ resolution until this iteration, then full
    sigma: float | None = 2.0  # soft-coverage sharpness (1/px); None = hard edges (measured: much worse)
    renderer: str = "raster"  # "raster", "raytrace" (BVH primary rays) or "hybrid" (raster + ray-traced
    #                           shadows and reflection bounce); see render.RenderSettings
    # cast shadows with renderer "raster" (visibility.py): "vertex" = transmittance from every vertex towards each
    # point / directional light, ray-traced through the soup every shadow_every steps (and after density control
    # or when a light moved), interpolated per fragment, a constant for the gradient; "off" = none. Measured
    # (soup, seed 0, one run each, README "Cached shadows"): spot_small / spot / gadget / bob_env novel-view PSNR
    # +0.18 / +0.18 / +0.23 / +0.19 dB, relight (relit alike) up on all 12 sets (+0.03 to +0.29 dB), albedo
    # -0.21 / +0.01 / +0.12 / -0.03 dB, the step 0.91-1.09x a raster step (bench/shadow_step.py): the default
    shadows: str = "vertex"
    shadow_every: int = 100
    shadow_from: int = 600  # no shadows before (the warm-up soup is a half-transparent cloud)
    # shadow-ray start offset, × the soup's bounding-box diagonal: past the soup's own layers. Measured on the
    # spot_small demo soup against the ground-truth mesh's visibility (facing points): 0.003 / 0.01 / 0.03 →
    # 41 / 21 / 15 % shadowed against the truth's 14 % (agreement 73 / 93 / 98 %)
    shadow_eps: float = 0.03
    # "white", "black", "random" (a new colour per iteration) or "auto": random for photos without alpha with SfM
    # points (a real capture: the background is in the picture, and a soup that turned transparent anywhere would
    # show the random colour, so it stays opaque over the ground and the sky; white without SfM points, a flat
    # backdrop's colour on one); for photos with alpha white, unless at
    # least AUTO_BACKGROUND_FRACTION of their object pixels are white themselves (auto_background): a pixel the colour
    # of the background gives its alpha no gradient, and a soup there turns transparent (spot re-rendered under a
    # bright environment, bench/make_scene.py --lights env: 19 % of its object pixels white, the soup lost them and
    # the mesh stage extracted 370 faces, mesh NVS 19.3 dB; random: 35.7 dB). The dev scenes hold 0-0.5 %, and
    # random there measured worse at 200² (soup 33.56 -> 32.63 dB on spot, 32.32 -> 31.83 on gadget, H200, seed 0:
    # fewer triplets grow), so white stays their background. The resolved value is saved in config.json.
    background: str = "auto"
    ssim_lambda: float = 0.2  # loss = (1 − λ)·L1 + λ·(1 − SSIM)
    # × scene extent, decays exponentially to lr_position_final. The method's 1.1e-4 is tuned for 18k
    # iterations; measured on spot_small (300 it.): 1.1e-4 → 16 dB, 1e-3 → 29.7 dB, 3e-3 → 28.0 dB
    lr_position: float = 1e-3
    lr_position_final: float = 1e-5
    lr_position_steps: int = 30_000
    lr_material: float = 0.05  # the method: 0.01 (measured here: 0.05 learns faster at equal final quality)
    # × lr_material for the BRDF's roughness / metallic channels (materials.BRDF.lobe_columns; issue 18, README
    # "Roughness and metallic"); 1 = the material rate (runs before)
    lr_lobe_scale: float = 1.0
    lr_alpha: float = 0.1  # the method: 0.05
    lr_vertex_sh: float = 0.005
    lr_lights: float = 0.01
    # "relative" (issue 18): the radiometric light parameters (colours, intensities, SH radiance) step by lr_lights ×
    # their initial magnitude (lights.relative_lr_scales: an ambient light of 0.1 by 0.001, a point light of intensity
    # extent² ≈ 12 by 0.12); "absolute": lr_lights in the parameters' units (runs before). Measured on spot_small /
    # bob_env at 100² (1500 it.): relight +0.2/+0.1/+0.2 and +0.4/+1.5/+0.2 dB, albedo (scaled) +1.1 / +1.4 dB; at 200²,
    # 3000 it.: spot +1.2/+1.5/+1.9 dB (albedo +1.6), gadget -0.1/0.0/+0.8 (+0.3), bob_env -0.0/+0.2/-1.0 (+0.5)
    lr_lights_mode: str = "relative"
    # × lr_lights for the point lights' positions (world units per step at the reference extent, scaled by extent /
    # datasets.base.REFERENCE_EXTENT; "relative" mode). At 1 (0.01 per step, ~0.2°
    # of arc at spot's light distance) the light was still moving when the light phase ended and the per-vertex albedo
    # then kept whatever direction it had reached: spot_small's recovered light 0.7° off the truth with seed 0 but
    # 28.8° / 11.5° with seeds 1 / 2 (the initial light is jittered by 0.3 extent). At 10: 8.2° / 3.0°, soup relight
    # +1.2 to +5.0 dB on those seeds and level on seed 0 (bench/results/light_position_pocl_2026-11-26.txt)
    lr_light_position_scale: float = 10.0
    # a point light's step does not change its irradiance at the look-at centre (lights.hold_irradiance: its intensity
    # × (d / d_before)² after each step of the soup, the mesh stage and the metallic trials): the photos fix albedo ×
    # irradiance, and the gauge drifted with the distance the photos constrain least. False: runs before
    hold_irradiance: bool = True
    # point lights are kept at least this many frame radii (frame_radius: the half-width the cameras see at the look-at
    # centre, 1.165 on the dev scenes) from the centre, after each step of the soup, the mesh stage and the metallic
    # trials (lights.lights_kept_out), and start there if placed closer (initial_lights; the radius at most the
    # cameras' mean distance: light_keep_out_radius): a light inside the object lights nothing the photos show. On
    # spot_small's photos flattened on white a gradient spike threw the light inside the cow at iteration 244: test
    # PSNR 30.40 dB, the light ending below the object; with this 34.18
    # (bench/results/light_inside_pocl_2026-11-28.txt). 0: off (runs saved before)
    light_min_distance: float = 1.0
    lr_boost_at: int = 10_000  # material / vertex-SH learning rates × lr_boost from here (the method: 10k, ×5)
    lr_boost: float = 5.0
    betas: tuple = (0.5, 0.999)  # Adam betas (the method's)
    adam_eps: float = 1e-15
    sh_clip: float = 1.0  # gradient-norm clipping of the vertex-SH coefficients
    # density control; grad_threshold in NDC units (× W/2). Measured on spot_small (2500 it., 96²) in pixel
    # units: 2e-4 / 1e-4 / 5e-5 → 6k / 8k / 12k faces, 1e-4 best (34.8 dB) = 4.8e-3 in NDC; on spot (200²)
    # 5e-3 → 32.1 dB with 3.3k faces, 2e-3 → 31.0 dB with 8.2k. Alpha resets every 1000 it. with pruning
    # at alpha <= 0.05 collapsed the soup (a white object on a white background gives no gradient that
    # restores alpha: 29.4 dB), without them 34.8 dB; the screen-size prune at the method's 0.1 % of the
    # image removed most faces at 200² (1 % kept)
    density: DensityConfig = field(default_factory=lambda: DensityConfig(
        interval=100, densify_from=300, densify_until=2500, grad_threshold=5e-3, alpha_reset_interval=3000,
        prune_screen_frac=0.01, max_faces=200_000, min_faces=100, error_threshold=0.1, error_min_pixels=16.0,
        max_prune_fraction=0.5, inherit_moments=True, error_resplit_ratio=0.9))
    # error_resplit_ratio 0.9 (session 49; configs saved before keep theirs, None = off): a face split by the error
    # criterion is split by it again only once its error dropped 10 % (density.py). Measured from scratch with
    # --mesh-stage, the three dev scenes back to back (bench/results/resplit_pocl_2026-11-28.txt): soups of a fifth
    # to a sixth of the triplets, whole runs 21-28 % faster (spot 275 -> 199 s, bob_env 325 -> 257 s, gadget 232 ->
    # 179 s: issue 19's bob_env row was 1.18x its filing time), soup -0.4 to -0.8 dB, mesh -0.2 to +0.2 dB, surface
    # Chamfer +5 %, relight -0.1 to -0.6 dB, albedo -0.3 to +0.3 dB
    alpha_reset_grace: int = 500  # no pruning for this many iterations after an alpha reset
    checkpoint_every: int = 1000  # also at the end and on Ctrl-C
    keep_checkpoints: int = 3  # keep the newest N checkpoints (0: keep all)
    # dataset images reduced by this integer factor at load time; "auto": the smallest factor that brings the training
    # photos' longer side to at most datasets.images.AUTO_MAX_SIDE (1600) px (3D Gaussian Splatting's rule; 1 for
    # every dev scene and NeRF-synthetic's 800²). The factor chosen is what config.json keeps (a resume reads it)
    downscale: int | str = "auto"
    max_test_views: int | None = None  # evaluate only the first N test views (None: all)
    # "linear": shading, lights and compositing in linear radiance, the photos' sRGB transfer after compositing
    # (8/16-bit datasets; linear EXR/HDR datasets skip it), albedo = linear reflectance. "encoded": the renderer
    # fits the photos' encoded values directly (every run before the linear pipeline; a config.json without
    # this key is such a run)
    color: str = "linear"
    # the camera's saturation in the photo model (render.RenderSettings.transfer "srgb-clip", color.cl SRGB_CLIP):
    # an 8/16-bit photo clips at 1, so a clipped pixel says only "at least 1" and a render above it is not pulled
    # down. Without it the lights and albedo were fitted to the clipped values: spot re-rendered under the HDR
    # environment (bench/make_scene.py --lights env) has 54 % of its object pixels clipped, bob_env 76 %
    # (bench/results/light_models_pocl_2026-11-26.txt). Linear (EXR/HDR) data have no transfer and no clip.
    sensor_clip: bool = True
    # material / light priors (priors.py; 0 disables a term); README "Material and light priors": why each default.
    # Every term is off by default (`--priors lights` sets priors.LIGHT_WEIGHTS, `--priors all` those and
    # priors.MATERIAL_WEIGHTS). Measured at the end of 2026-11-24 with the other defaults of that day
    # (bench/results/final_defaults_pocl_2026-11-24.txt): the light priors cost bob_env (environment-lit)
    # 3.3 / 5.1 / 4.5 dB of relight PSNR, an ambient-share penalty being wrong where the light IS the
    # environment; on spot they were mixed; the material terms cost spot 0.75 dB of novel-view PSNR.
    prior_smooth: float = 0.0  # Charbonnier smoothness of albedo / roughness / metallic over kNN triplets
    prior_k: int = 8  # neighbours of the smoothness graph
    prior_metallic: float = 0.0  # mean metallic (L1 towards 0)
    prior_roughness: float = 0.0  # mean (roughness − prior_roughness_target)²
    prior_roughness_target: float = 0.5
    prior_ambient: float = 0.0  # ambient share (--priors lights: 0.02) of the irradiance at the scene centre
    prior_chroma: float = 0.0  # (--priors lights: 0.01) scale-free colour variance of each light (white-ish lights)
    prior_from: int = 600  # the priors act from this iteration (full resolution, the soup pruned once)
    # the light phase (issue 18): until this iteration every material channel is one value for the whole soup (each
    # step applies the mean of the per-vertex material gradients), so the lights, not per-vertex albedo / AO /
    # metallic, must explain the shading; then each vertex goes its own way from there. Photos of a Lambertian
    # object fix only albedo × irradiance per point: with free per-vertex albedo from the first step, the lights
    # stay wherever the first steps left them (ambient 3x the truth on spot)
    material_tie_until: int = 1200
    # the specular lobe's channels (roughness, metallic; Blinn-Phong's shininess: materials.BRDF.lobe_columns) in the
    # light phase: "held" (each vertex's Adam moments follow its own gradient, but the values are put back after
    # each step: they stay at their initial values, then go per vertex with moments that know their gradients'
    # size) or "tied" (one learning value, as the other channels; runs before). Tied, one roughness and one metallic
    # for the whole object followed the sign of the mean of their gradients at Adam's full step, however weak the
    # evidence: on gadget (black frame and tracks) metallic 0.1 -> 0.64 and roughness 0.5 -> 0.06 in 100 steps, and
    # the mesh stage took it for one rough metal (metallic 1.00, roughness 0.9; truth 0 / 0.4). "frozen" (no gradient
    # in the phase, fresh moments after it) sent the per-vertex lobes to extremes once free (bob_env: mesh NVS 35.1 ->
    # 31.1 dB). Measured at the mesh (the asset), 200², 3000 it., seed 0, tied -> held, relight point_left /
    # sun_and_sky / env_rotated, albedo scaled (bench/results/lobes_pocl_2026-11-26.txt): spot 29.91/29.49/29.61,
    # 24.94 -> 30.98/30.64/30.55, 26.59 dB; gadget 26.28/26.13/23.81, 17.34 -> 27.13/27.48/26.17, 17.76 (mesh NVS
    # 29.76 -> 30.21); bob_env 29.48/28.98/32.02, 24.42 -> 29.43/28.91/31.49, 23.73 (mesh NVS 35.12 -> 34.34)
    light_phase_lobes: str = "held"
    # metal or dielectric, decided in the soup (issue 18): at iteration metallic_probe_at (in the light phase, scaled
    # with the run) a mesh is extracted from the soup and the mesh stage's own trial decides on it
    # (MeshStage.choose_metallic: a fit of each hypothesis, the lower loss wins, a metal rougher than 0.8 refused);
    # a metal restarts the soup from iteration 0 held at 0.99 instead of the initial 0.1. A soup held as a dielectric
    # put a metal's surface where its highlights were: spot_small re-rendered as a metal (96², two point lights),
    # surface Chamfer 0.0260 -> 0.0093, relight +1.6 to +2.6 dB; every dielectric capture's verdict dielectric, its
    # soup unchanged (bench/results/soup_metallic_pocl_2026-11-27.txt). The trial on the soup itself (not on a
    # mesh) could not tell the metal from gadget's smooth-shaded dielectric. 0: no probe.
    metallic_probe_at: int = 360
    # the probe refuses a metal whose tied roughness fits above this (the mesh stage's own trial: MAX_METAL_ROUGHNESS
    # 0.8). The probe's mesh comes from a soup at a tenth of its run, whose coarser surface widens every lobe: over the
    # probes of sessions 45-48 (bench/results/metal_probe_pocl_2026-11-28.txt) the metal captures fitted 0.72-0.81
    # and the dielectrics that the metal hypothesis won on loss (gadget, a capture at 1e-4 scale, a dimmed one)
    # 0.90-0.94; at 0.8 the metal capture under two point lights (0.81 with the irradiance hold) was refused and its
    # soup trained as a dielectric (surface Chamfer 0.0106 -> 0.0169). 0.85 sits between the two groups
    metal_probe_max_roughness: float = 0.85
    # Blinn-Phong's ambient reflectance ka: "diffuse" keeps it equal to kd (one reflectance lights the diffuse and
    # the ambient term, as Cook-Torrance's albedo does; materials.tie_ambient_gradient / copy_ambient); "free": its
    # own per-vertex channel (runs before 2026-11-26), where shadows and ambient occlusion were painted into ka
    # while kd, seen only under the point light, drifted where it was dark
    blinn_phong_ka: str = "diffuse"
    # Cook-Torrance's ambient occlusion channel: "learned" per vertex, or "off" (held at its initial value, ≈ 1)
    ao: str = "learned"
    # "each": after each step every light's colour is made grey (its brightness kept; lights.grey_lights); "total":
    # the lights' colours rescaled per channel so that together they are white at the scene centre
    # (lights.white_balance; each light's colour relative to the others' free, each grey during the light phase);
    # "off": the lights may take any tint. Photos fix albedo × light per point: the tint common to every light is
    # the albedo's or the lights' alike (spot_small: the lights took the cow's pink), and with "total" the colours
    # relative to each other wandered as far (spot, bob_env: a red point light under a cyan ambient, bob_env 100²
    # novel views -2 to -4.8 dB); white lights are the usual reading where the photos cannot tell
    white_light: str = "each"

    def with_iterations(self, iterations: int) -> TrainConfig:
        """This configuration for a run of ``iterations`` steps, every schedule scaled with it: the defaults are
        tuned for :data:`REFERENCE_ITERATIONS` (3000), and a shorter or longer run keeps their shape — warm-up
        and half resolution (200 / 600 of 3000), one SH band per third, the position learning-rate decay
        (``lr_position_steps`` 10× the run: 1e-3 → 6.3e-4 × extent at the end), densification from 10 % to 83 %
        of the run (300 … 2500 of 3000: the last 17 % fine-tune a fixed soup), the alpha reset, the priors' start
        and the learning-rate boost. The densification ``interval`` stays 100 (the statistics need about one
        pass over the views) unless the window holds fewer than 5 of them. ``--iterations N`` on the command
        line is this (a resumed run keeps its saved schedules)."""
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        r = iterations / REFERENCE_ITERATIONS
        ref = TrainConfig()

        def sc(v: int, low: int = 0) -> int:
            return max(int(round(v * r)), low)

        d, rd = self.density, ref.density
        start, until = sc(rd.densify_from), sc(rd.densify_until)
        density = replace(d, densify_from=start, densify_until=until,
                          interval=max(1, min(rd.interval, (until - start) // 5)),
                          alpha_reset_interval=sc(rd.alpha_reset_interval, 1))
        return replace(self, iterations=int(iterations), warmup_until=sc(ref.warmup_until),
                       half_res_until=sc(ref.half_res_until), sh_band_every=sc(ref.sh_band_every, 1),
                       lr_position_steps=sc(ref.lr_position_steps, 1), prior_from=sc(ref.prior_from),
                       material_tie_until=sc(ref.material_tie_until), metallic_probe_at=sc(ref.metallic_probe_at),
                       lr_boost_at=sc(ref.lr_boost_at, 1), density=density)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["lights"] = list(self.lights)
        d["betas"] = list(self.betas)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        d = dict(d)
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        if "density" in d and isinstance(d["density"], dict):
            d["density"] = DensityConfig(**d["density"])
        for k in ("lights", "betas"):
            if k in d:
                d[k] = tuple(d[k])
        d.setdefault("color", "encoded")  # saved before the linear pipeline: it rendered encoded values
        d.setdefault("lr_lights_mode", "absolute")  # saved before the relative light learning rates
        d.setdefault("shadows", "off")  # saved before the cached shadows: none
        d.setdefault("lr_lobe_scale", 1.0)  # saved before the roughness / metallic learning-rate scale
        d.setdefault("material_tie_until", 0)  # saved before the light phase: none
        d.setdefault("metallic_probe_at", 0)  # saved before the soup's metallic probe: none
        d.setdefault("downscale", 1)  # (every config saved since 2026-11-22 has it: an int, what "auto" chose)
        d.setdefault("background_shell", 0)  # saved before the far shell: none (since then an int, what "auto" chose)
        d.setdefault("metal_probe_max_roughness", 0.8)  # saved before the probe's own roughness rule: the mesh stage's
        d.setdefault("light_phase_lobes", "tied")  # saved before the lobes were held in the light phase
        d.setdefault("blinn_phong_ka", "free")  # saved before ka was tied to kd
        d.setdefault("ao", "learned")  # saved before the AO could be held
        d.setdefault("lr_light_position_scale", 1.0)  # saved before the light positions' own rate
        d.setdefault("white_light", "off")  # saved before the white balance of the lights
        d.setdefault("sensor_clip", False)  # saved before the camera's saturation was modelled
        d.setdefault("init_box_frame", False)  # saved before the random box followed the frame: × camera distance
        d.setdefault("extent_frame", False)  # saved before the extent followed the frame: the cameras' extent
        d.setdefault("hold_irradiance", False)  # saved before a light's step kept its irradiance at the centre
        d.setdefault("light_min_distance", 0.0)  # saved before the lights were kept out of the object
        for k, v in Priors.off().items():
            d.setdefault(k, v)  # saved before the priors: none
        return cls(**d)

    def validate(self) -> None:
        for f in fields(self):  # a NaN / Inf number (an edited config.json) is named first, whatever the field
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{f.name} must be a finite number, got {v}")
        bad = [x for x in self.lights if x not in LIGHT_KINDS]
        if bad or not self.lights:
            raise ValueError(f"lights must be a non-empty mix of {LIGHT_KINDS}, got {list(self.lights)}")
        get_brdf(self.brdf)  # ValueError naming the BRDFs
        if self.white_light not in WHITE_LIGHT_MODES:
            raise ValueError(f"white_light must be one of {WHITE_LIGHT_MODES}, got {self.white_light!r}")
        if self.ao not in ("learned", "off"):
            raise ValueError(f"ao must be 'learned' or 'off', got {self.ao!r}")
        if self.blinn_phong_ka not in ("diffuse", "free"):
            raise ValueError(f"blinn_phong_ka must be 'diffuse' or 'free', got {self.blinn_phong_ka!r}")
        if self.light_phase_lobes not in LIGHT_PHASE_LOBES:
            raise ValueError(f"light_phase_lobes must be one of {LIGHT_PHASE_LOBES}, got {self.light_phase_lobes!r}")
        if isinstance(self.metallic_probe_at, bool) or not isinstance(self.metallic_probe_at, int) \
                or self.metallic_probe_at < 0:
            raise ValueError(f"metallic_probe_at must be an integer >= 0, got {self.metallic_probe_at!r}")
        if isinstance(self.metal_probe_max_roughness, bool) \
                or not isinstance(self.metal_probe_max_roughness, int | float) \
                or not 0.0 <= self.metal_probe_max_roughness <= 1.0:
            raise ValueError(f"metal_probe_max_roughness must be a number in [0, 1], got "
                             f"{self.metal_probe_max_roughness!r}")
        if not isinstance(self.material_tie_until, int) or self.material_tie_until < 0:
            raise ValueError(f"material_tie_until must be an integer >= 0, got {self.material_tie_until!r}")
        if self.renderer not in RENDERERS:
            raise ValueError(f"renderer must be one of {RENDERERS}, got {self.renderer!r}")
        # the library's own checks of what the CLI refuses up front (battery 10: faces_per_pixel=0 trained to the end
        # and failed at the final renders; iterations=2.5 was saved and then refused by eval and --resume)
        for name, lo in (("iterations", 1), ("faces_per_pixel", 1), ("init_points", 1), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < lo:
                raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
        if self.faces_per_pixel > 1024:
            raise ValueError(f"faces_per_pixel must be at most 1024, got {self.faces_per_pixel}")
        if self.sigma is not None and (isinstance(self.sigma, bool) or not isinstance(self.sigma, int | float)
                                       or not 0 < self.sigma < math.inf):  # (None: hard edges, `--sigma 0`)
            raise ValueError(f"sigma must be a finite number > 0 (or None: hard edges), got {self.sigma!r}")
        shell = self.background_shell
        if not (shell == "auto" or (isinstance(shell, (int, np.integer)) and not isinstance(shell, bool))):
            raise ValueError(f"background_shell must be a number of triangles (>= 0) or 'auto', got {shell!r}")
        if (shell != "auto" and shell < 0) or not self.background_radius > 0:
            raise ValueError(f"background_shell must be >= 0 and background_radius > 0, got {self.background_shell}, "
                             f"{self.background_radius}")
        if self.lr_lights_mode not in LR_LIGHTS_MODES:
            raise ValueError(f"lr_lights_mode must be one of {LR_LIGHTS_MODES}, got {self.lr_lights_mode!r}")
        if self.shadows not in SHADOW_MODES:
            raise ValueError(f"shadows must be one of {SHADOW_MODES}, got {self.shadows!r}")
        if self.shadow_every < 1 or self.shadow_from < 0 or not (np.isfinite(self.shadow_eps)
                                                                  and self.shadow_eps >= 0):
            raise ValueError(f"shadow_every must be >= 1, shadow_from >= 0 and shadow_eps >= 0, got "
                             f"{self.shadow_every}, {self.shadow_from} and {self.shadow_eps}")
        if not (np.isfinite(self.lr_light_position_scale) and self.lr_light_position_scale >= 0):
            raise ValueError(f"lr_light_position_scale must be finite and >= 0, got {self.lr_light_position_scale}")
        if not (np.isfinite(self.lr_lobe_scale) and self.lr_lobe_scale >= 0):
            raise ValueError(f"lr_lobe_scale must be finite and >= 0, got {self.lr_lobe_scale}")
        if self.color not in COLOR_PIPELINES:
            raise ValueError(f"color must be one of {COLOR_PIPELINES}, got {self.color!r}")
        if not (np.isfinite(self.light_distance) and self.light_distance > 0):
            raise ValueError(f"light_distance must be finite and > 0, got {self.light_distance}")
        if not 0 <= self.sh_degree <= 8:
            raise ValueError(f"sh_degree must be in [0, 8], got {self.sh_degree}")
        if self.downscale != "auto" and (isinstance(self.downscale, bool) or not isinstance(self.downscale, int)
                                         or not 1 <= self.downscale <= 64):
            raise ValueError(f"downscale must be an integer in [1, 64] or 'auto', got {self.downscale!r}")
        if self.checkpoint_every < 0 or self.keep_checkpoints < 0:
            raise ValueError(f"checkpoint_every and keep_checkpoints must be >= 0, got {self.checkpoint_every} "
                             f"and {self.keep_checkpoints}")
        if self.background != "auto":
            resolve_background(self.background)
        if not (np.isfinite(self.init_box) and self.init_box > 0) or not isinstance(self.init_box_frame, bool):
            raise ValueError(f"init_box must be finite and > 0 and init_box_frame a boolean, got {self.init_box!r} "
                             f"and {self.init_box_frame!r}")
        if isinstance(self.light_min_distance, bool) or not isinstance(self.light_min_distance, int | float) \
                or not (math.isfinite(self.light_min_distance) and 0 <= self.light_min_distance <= 1000):
            raise ValueError(f"light_min_distance must be a number in [0, 1000] (frame radii), got "
                             f"{self.light_min_distance!r}")
        if not isinstance(self.extent_frame, bool) or not isinstance(self.hold_irradiance, bool):
            raise ValueError(f"extent_frame and hold_irradiance must be booleans, got {self.extent_frame!r} and "
                             f"{self.hold_irradiance!r}")
        mf = self.density.max_faces
        # init_points counts only for a dataset without SfM points: the Trainer checks it once the dataset is read
        # (check_initial_budget); SfM points are thinned to what the shell leaves (initial_budget)
        if mf is not None and shell != "auto" and shell > mf:
            raise ValueError(f"background_shell ({shell}) exceeds the face budget max_faces ({mf}): density control "
                             "would prune it at once; give at most the budget, or raise max_faces")
        bad = {k: getattr(self, k) for k in Priors.off() if not getattr(self, k) >= 0}
        if bad or self.prior_k < 1 or not 0 <= self.prior_roughness_target <= 1:
            raise ValueError(f"prior weights must be >= 0, prior_k >= 1, prior_roughness_target in [0, 1]; got "
                             f"{bad or ''} prior_k={self.prior_k} prior_roughness_target={self.prior_roughness_target}")


# ------------------------------------------------------------------------------------------------ init


def look_at_center(ds: Dataset) -> np.ndarray:
    """The point nearest to every training camera's optical axis (least squares): the centre of an
    object-centric capture. Falls back to the mean camera centre when the axes are parallel."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for v in ds.train:
        c = v.camera.center
        d = v.camera.w2c[2, :3]  # optical axis (+z of the camera) in world space
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    if np.linalg.cond(A) > 1e8:
        return ds.scene_center()
    return np.linalg.solve(A, b)


# TrainConfig.background_shell "auto": the far shell's triangles for photos without alpha (the README's photo command
# gave 4000 by hand before it was the default; 2 % of the default face budget)
AUTO_BACKGROUND_SHELL = 4000
MIN_SHELL_POINTS = 10  # ... and only with SfM points (mesh.roi.auto_roi's minimum): they crop the shell away
MIN_INIT_POINTS = 4  # initial_scene starts from the SfM points when there are at least this many (else a random cloud)


def num_sfm_points(ds: Dataset) -> int:
    """How many sparse SfM points ``ds`` holds (0 without)."""
    return 0 if ds.points is None else len(ds.points)


AUTO_BACKGROUND_FRACTION = 0.05  # "auto" trains on random backgrounds from this share of white object pixels up
WHITE_LEVEL = 1.0 - 2.0 / 255.0  # a photo pixel this close to white in every channel is the white background's colour


def auto_background(ds: Dataset) -> tuple[str, float]:
    """``TrainConfig.background = "auto"`` resolved for ``ds``: ``("random", f)`` when the training photos have
    alpha and a share ``f`` >= :data:`AUTO_BACKGROUND_FRACTION` of their object pixels (alpha > 0.5) is white in
    every channel (>= :data:`WHITE_LEVEL`: what a white background looks like, so nothing there tells the soup to
    stay opaque), else ``("white", f)``. Photos without alpha (a real capture: the ground and the sky are in the
    picture) with SfM points get ``"random"``: wherever the soup turned transparent the render would show a new
    colour each step, so it stays opaque over the whole frame (README "Your own photos") — unless their borders are a
    backdrop (:func:`photo_backdrop`: a synthetic render saved without alpha), which stays their background; without
    SfM points they keep white. ``f`` is then the larger share of border pixels of one flat colour."""
    if ds.train and not ds.has_alpha:
        colour, share = photo_backdrop(ds)
        if colour is None and num_sfm_points(ds) < MIN_INIT_POINTS:
            # no SfM points (e.g. a transforms.json of real photos): the soup starts as a random cloud, and random
            # backgrounds measured worse there (spot_ground's cameras without its points, 320x240: test PSNR 18.72
            # against white's 20.62, 100k triplets against 20k; bench/results/photos_defaults_pocl_2026-11-28.txt)
            colour = "white"
        return (colour or "random"), share
    n = white = 0
    for v in ds.train:
        if v.alpha is None:
            continue
        m = np.asarray(v.alpha) > 0.5
        n += int(m.sum())
        white += int((np.asarray(v.rgb)[m].min(axis=-1) >= WHITE_LEVEL).sum())
    frac = white / n if n else 0.0
    return ("random" if n and frac >= AUTO_BACKGROUND_FRACTION else "white"), frac


def auto_background_reason(ds: Dataset, bg: str, frac: float) -> str:
    """Why :func:`auto_background` chose ``bg`` (with its share ``frac``) for ``ds``: the command's note."""
    if ds.has_alpha:
        return (f"{100 * frac:.1f} % of the photos' object pixels are white"
                + (": a white background would hide their alpha" if bg == "random" else ""))
    if bg == "random":
        return "photos without alpha"
    if frac >= BACKDROP_FRACTION:
        return f"photos without alpha, {100 * frac:.0f} % of their borders {bg}: a backdrop"
    return ("photos without alpha and without SfM points: the soup starts as a random cloud, where random "
            "backgrounds measured worse")


BACKDROP_FRACTION = 0.95  # photo_backdrop: this share of the border pixels one flat colour


def photo_backdrop(ds: Dataset) -> tuple[str | None, float]:
    """The flat backdrop of photos without alpha: ``("white", f)`` / ``("black", f)`` when a share ``f`` >=
    :data:`BACKDROP_FRACTION` of the training photos' border pixels (a frame of 2 pixels) is white (>=
    :data:`WHITE_LEVEL` in every channel) / black (<= 2/255), else ``(None, f)`` with ``f`` the larger share: a real
    capture, whose borders show the ground, the sky, a room."""
    n = white = black = 0
    for v in ds.train:
        rgb = np.asarray(v.rgb)
        if rgb.shape[0] < 5 or rgb.shape[1] < 5:
            continue
        border = np.concatenate([rgb[:2].reshape(-1, 3), rgb[-2:].reshape(-1, 3), rgb[2:-2, :2].reshape(-1, 3),
                                 rgb[2:-2, -2:].reshape(-1, 3)])
        n += len(border)
        white += int((border.min(axis=-1) >= WHITE_LEVEL).sum())
        black += int((border.max(axis=-1) <= 2.0 / 255.0).sum())
    if not n:
        return None, 0.0
    fw, fb = white / n, black / n
    if fw >= BACKDROP_FRACTION:
        return "white", fw
    if fb >= BACKDROP_FRACTION:
        return "black", fb
    return None, max(fw, fb)


def auto_background_shell(cfg: TrainConfig, ds: Dataset) -> int:
    """``TrainConfig.background_shell = "auto"`` resolved for ``ds`` and the resolved ``cfg.background``:
    :data:`AUTO_BACKGROUND_SHELL` triangles for photos without alpha trained over a random background (a real
    capture: SfM finds no points on the sky or far walls), none for photos with alpha, on a flat backdrop
    (:func:`photo_backdrop`) or over a background the user chose white or black (measured worse with the shell,
    bench/results/photos_defaults_pocl_2026-11-28.txt); none without SfM points either (:data:`MIN_SHELL_POINTS`):
    the mesh is cropped to the object only where they locate it (mesh/roi.py), and uncropped, the far shell would
    widen the extraction's volume to six camera distances. Never more than half the face budget: the soup starts
    from the SfM points (``init_points`` unused), thinned to what the shell leaves (:func:`initial_budget`)."""
    if not ds.train or ds.has_alpha or cfg.background != "random":
        return 0
    if num_sfm_points(ds) < MIN_SHELL_POINTS:
        return 0
    mf = cfg.density.max_faces
    # the soup starts from the SfM points (init_points unused), thinned to what the shell leaves of the budget: the
    # shell takes at most half of it
    return AUTO_BACKGROUND_SHELL if mf is None else int(min(AUTO_BACKGROUND_SHELL, mf // 2))


def auto_background_shell_note(cfg: TrainConfig, ds: Dataset) -> str | None:
    """The command's note on what ``background_shell = "auto"`` resolved to (``cfg`` resolved): the triangles, or
    why a real capture over a random background got none; None where no shell was to be expected."""
    n = cfg.background_shell
    if n:
        capped = ", half of --max-faces" if n < AUTO_BACKGROUND_SHELL else ""
        return (f"background shell: {n} triangles on a far sphere for the sky / walls (auto; photos without "
                f"alpha{capped}; --background-shell 0 for none)")
    if ds.has_alpha or cfg.background != "random":
        return None
    if num_sfm_points(ds) < MIN_SHELL_POINTS:
        return (f"background shell: none (auto: the dataset has {num_sfm_points(ds)} SfM points, fewer than the "
                f"{MIN_SHELL_POINTS} that locate the object to crop the mesh to; --background-shell N to add one "
                "anyway)")
    return (f"background shell: none (auto: --max-faces {cfg.density.max_faces} leaves no room for one; give "
            "--background-shell N)")


def check_initial_budget(cfg: TrainConfig, ds: Dataset) -> None:
    """A dataset without SfM points starts from ``init_points`` random triangles, and the background shell joins
    them: together they must fit the face budget (density control would prune them at once). A ``ValueError`` naming
    the fields and the command's options otherwise; nothing to check when the soup starts from SfM points (thinned to
    the budget, :func:`initial_budget`) or without a budget."""
    mf, shell = cfg.density.max_faces, cfg.background_shell
    if mf is None or num_sfm_points(ds) >= MIN_INIT_POINTS or shell == "auto":
        return
    if cfg.init_points + shell > mf:
        raise ValueError(f"init_points (--init-points, {cfg.init_points}) + background_shell (--background-shell, "
                         f"{shell}) exceed the face budget max_faces (--max-faces, {mf}): density control would "
                         "prune them at once; give at most the budget, or raise --max-faces")


def frame_radius(ds: Dataset) -> float:
    """The half-width the training cameras see at :func:`look_at_center`: the mean over the cameras of their
    distance from it × ``min(W / 2fx, H / 2fy)`` (the half-angle's tangent of the narrower side). An object framed
    by the photos is about this large whatever the lens and the units (spot_small: 3.2 × tan 20° = 1.165)."""
    c = look_at_center(ds)
    r = [float(np.linalg.norm(v.camera.center - c)) * min(0.5 * v.camera.width / v.camera.fx,
                                                          0.5 * v.camera.height / v.camera.fy) for v in ds.train]
    return float(np.mean(r)) if r else 1.0


# the dev scenes' frame radius (cameras 3.2 from the object, a 40° field): Trainer.length_scale = frame_radius / this
REFERENCE_FRAME_RADIUS = 1.165


# the dev scenes' camera extent per frame radius (3.91-3.94 / 1.165 = 3.36-3.38), rounded up so that they keep their
# camera extent (scene_extent); NeRF-synthetic's rig (cameras 4.03 away, a 39.6° field) is 3.0
EXTENT_PER_FRAME_RADIUS = 3.4


def scene_extent(ds: Dataset, frame: bool = True) -> float:
    """The scene's size in world units for every default given as a multiple of it (the soup's and the mesh stage's
    position rates, the density thresholds, the point lights' start and rate, the shadow cache's tolerance): the
    cameras' extent (:meth:`Dataset.scene_extent`, 3DGS's), or with ``frame`` :func:`frame_radius` ×
    :data:`EXTENT_PER_FRAME_RADIUS` where that is smaller. The cameras' extent measures where the cameras stand, not
    what they frame: spot_small re-rendered with its cameras 2.5× farther and a 2.5× narrower field (the cow filling
    the photos as before) had a 2.5× larger extent, so its triplets split and pruned at 2.5× the size and its light
    started and moved 2.5× as far: soup 32.70 dB, relight 31.60 / 29.71 / 27.62; with this soup 34.97, relight 34.80 /
    33.09 / 32.58 (the shipped lens: 33.93; 34.03 / 32.49 / 32.56; bench/results/framing_pocl_2026-11-27.txt).
    Cameras closer than the dev rig's keep their extent (the smaller)."""
    e = ds.scene_extent()
    if not frame or not ds.train:
        return e
    return min(e, frame_radius(ds) * EXTENT_PER_FRAME_RADIUS)


# with TrainConfig.init_box_frame, the random box's half-size is at most this × the mean camera distance (the rule
# before): cameras close to the object with a wide field (spot_small re-rendered 0.6x as far, a 62° field) frame a
# large half-width, and a box of 1.1 x that reaches the cameras: soup 30.7 dB against 33.0 with the cap
INIT_BOX_CAMERA = 0.4


def mean_camera_distance(ds: Dataset) -> float:
    """The training cameras' mean distance from :func:`look_at_center`."""
    return float(np.linalg.norm(ds.camera_centers() - look_at_center(ds), axis=1).mean())


def random_points(ds: Dataset, n: int, box: float, rng: np.random.Generator, frame: bool = True) -> np.ndarray:
    """``n`` uniform points in a cube around :func:`look_at_center`, half-size ``box`` × :func:`frame_radius`
    (``frame``; 1.1 × 1.165 ≈ the method's ±1.3 on NeRF-synthetic objects) but at most :data:`INIT_BOX_CAMERA` × the
    mean camera distance from it, or ``box`` × that distance (``frame`` False: runs before)."""
    dist = mean_camera_distance(ds)
    r = min(frame_radius(ds) * box, INIT_BOX_CAMERA * dist) if frame else dist * box
    return look_at_center(ds) + rng.uniform(-r, r, (n, 3))


def background_shell_points(ds: Dataset, n: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` points uniform on a sphere around :func:`look_at_center`, of radius ``radius`` × the mean camera
    distance from it: the far background of a capture (sky, walls) as part of the scene."""
    r = mean_camera_distance(ds) * radius
    d = rng.normal(size=(n, 3))
    return look_at_center(ds) + r * d / np.linalg.norm(d, axis=1, keepdims=True)


def triangles_from_points(points: np.ndarray, size: float, rng: np.random.Generator) -> np.ndarray:
    """One small independent triangle per point: ``[P, 3] → V [3P, 3]`` (equilateral, random
    orientation, radius ``size`` × the mean distance to the 3 nearest other points)."""
    p = np.asarray(points, np.float64)
    k = min(4, len(p))
    d, _ = cKDTree(p).query(p, k=k)
    r = size * (d[:, 1:].mean(1) if k > 1 else np.ones(len(p)))
    n = rng.normal(size=(len(p), 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    a = np.cross(n, rng.normal(size=(len(p), 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(n, a)
    ang = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    off = np.cos(ang)[None, :, None] * a[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :]
    return (p[:, None, :] + r[:, None, None] * off).reshape(-1, 3)


def initial_budget(cfg: TrainConfig) -> int | None:
    """How many initial triangles from sparse points fit the face budget: ``max_faces`` less the background
    shell (a number: :func:`initial_scene` resolves "auto" first; None: no budget)."""
    if cfg.density.max_faces is None:
        return None
    return max(cfg.density.max_faces - cfg.background_shell, 4)


# below this scene extent (world units) a capture trains worse: the kernels' guards (e.g. a point light's falloff
# |w|^2 >= 1e-6) are absolute (bench/results/scale_units_pocl_2026-11-27.txt); Trainer warns
MIN_EXTENT = 0.01


# float32, the device's number for positions, has a 24-bit significand: a coordinate at distance D from the origin is
# resolved to about D * 2^-24 = D * 6e-8. Past this many scene extents from the origin, that step is more than 6e-5 of
# the scene (a pixel's footprint is ~1e-3 of it at 1000 px), and the soup's positions, the cameras' rays and the
# gradients lose the bits they need. Measured (battery 9, the demo's cameras shifted, 60 iterations): +1e3 (280
# extents) 22.68 dB as at the origin (22.66), +1e5 (2.8e4 extents) 21.39, +1e6 14.17; georeferenced poses (UTM
# metres) sit at 1e5-1e7. Trainer warns (recentring is the user's: the poses' frame is theirs)
FAR_FROM_ORIGIN = 1e3


def warn_if_far_from_origin(ds: Dataset, extent: float, data=None) -> None:
    """A :class:`DatasetWarning` when the scene (the training cameras' mean position or :func:`look_at_center`, the
    farther) lies more than :data:`FAR_FROM_ORIGIN` × ``extent`` from the origin: float32 positions there are too
    coarse for it (battery 9: 14 dB against 23 without a word)."""
    if not ds.train or not extent > 0:
        return
    centres = [np.asarray(ds.scene_center(), np.float64), np.asarray(look_at_center(ds), np.float64)]
    far = max(centres, key=lambda c: float(np.linalg.norm(c)) if np.isfinite(c).all() else -1.0)
    dist = float(np.linalg.norm(far))
    if np.isfinite(dist) and dist > FAR_FROM_ORIGIN * extent:
        import warnings

        warnings.warn(DatasetWarning(
            f"{data or ds.root}: the scene lies {dist:.3g} from the origin (around {np.round(far, 1).tolist()}), "
            f"{dist / extent:.3g} times its extent ({extent:.3g}): the device's float32 positions are resolved to "
            f"about {dist * 6e-8:.2g} there (24 bits), too coarse for it, and it trains worse; recentre the poses "
            "(subtract the cameras' mean position from every camera's) for the best result"), stacklevel=3)


def light_keep_out_radius(cfg: TrainConfig, ds: Dataset) -> float:
    """How close to :func:`look_at_center` a point light may come (world units): ``cfg.light_min_distance`` ×
    :func:`frame_radius`, the frame radius at most the cameras' mean distance (a lens wider than 90° frames more
    than the cameras' own distance, and would push the lights behind them)."""
    if not cfg.light_min_distance > 0 or not ds.train:
        return 0.0
    return float(cfg.light_min_distance * min(frame_radius(ds), mean_camera_distance(ds)))


def initial_lights(cfg: TrainConfig, ds: Dataset, rng: np.random.Generator):
    """The configured lights, placed from the cameras (each light class's ``initial``: a point light
    above the scene, a directional light from the cameras' mean up direction, dim ambient, a
    constant SH environment). A point light whose jittered start falls within :func:`light_keep_out_radius` starts on
    it, its intensity × (d / d_start)² (the irradiance at the centre it was placed to give; about 4 % of seeds on the
    dev scenes, and every seed of a short ``--light-distance``), as the first step would have moved it."""
    c = look_at_center(ds)
    ext = scene_extent(ds, cfg.extent_frame)
    up = -np.mean([v.camera.w2c[1, :3] for v in ds.train], axis=0)  # average camera "up" (−y axis)
    up = up / (np.linalg.norm(up) + 1e-12)
    lights = _initial_lights(cfg.lights, LightInit(c, ext, up, cfg.sh_degree, rng, distance=cfg.light_distance))
    radius = light_keep_out_radius(cfg, ds)
    if radius > 0 and lights:
        p0 = pack_lights(lights).params.astype(np.float64)
        p1 = lights_kept_out(lights, p0, c, radius)
        if not np.array_equal(p0, p1):
            lights = unpack_lights(lights, hold_irradiance(lights, p0, p1, c))
    return lights


def warn_if_unseen(ds: Dataset, V: np.ndarray, data=None, sample: int = 2000) -> None:
    """A :class:`DatasetWarning` when fewer than half the training cameras see any of the initial soup's vertices
    ``V`` (in front, inside the image): cameras that look away from the object trained an unseen soup without a
    word (battery 8: the face count never moved). The usual cause is a camera convention: NeRF / Blender cameras look
    down their -z axis, OpenCV / COLMAP ones down +z."""
    import warnings

    n = len(ds.train)
    if not n or not len(V):
        return
    pts = np.asarray(V, np.float64)[:: max(1, len(V) // sample)]
    seeing = 0
    for v in ds.train:
        c = v.camera
        uvz = c.project_points(pts)
        ok = (uvz[:, 2] > c.near) & (uvz[:, 0] >= 0) & (uvz[:, 0] < c.width) & (uvz[:, 1] >= 0) & (uvz[:, 1] < c.height)
        seeing += bool(ok.any())
    if 2 * seeing < n:
        warnings.warn(DatasetWarning(
            f"{data or ds.root}: only {seeing} of the {n} training cameras see the initial soup (around "
            f"{np.round(np.asarray(V).mean(axis=0), 3).tolist()}, where the cameras' optical axes meet or the SfM "
            "points are): the cameras may look away from the object. NeRF / Blender transforms look down the camera's "
            "-z axis (OpenCV / COLMAP poses down +z): check the transform_matrix convention"), stacklevel=3)


def initial_scene(cfg: TrainConfig, ds: Dataset, rng: np.random.Generator) -> Scene:
    """The method's initialisation: COLMAP points when present, else random points in the bounds."""
    if cfg.background_shell == "auto":  # (the Trainer resolves both first; here for callers that did not)
        bg = auto_background(ds)[0] if cfg.background == "auto" else cfg.background
        cfg = replace(cfg, background_shell=auto_background_shell(replace(cfg, background=bg), ds))
    pts = ds.points if num_sfm_points(ds) >= MIN_INIT_POINTS else None
    if pts is None:
        pts = random_points(ds, cfg.init_points, cfg.init_box, rng, frame=cfg.init_box_frame)
    else:
        budget = initial_budget(cfg)
        if budget is not None and len(pts) > budget:
            # one triangle per sparse point: more points than the face budget would be pruned at once (and
            # cost memory and time until then); a uniform, seeded subsample keeps their spatial density
            pts = pts[np.sort(rng.choice(len(pts), size=budget, replace=False))]
    V = triangles_from_points(pts, cfg.init_size, rng)
    if cfg.background_shell:
        V = np.concatenate([V, triangles_from_points(background_shell_points(ds, cfg.background_shell,
                                                                             cfg.background_radius, rng),
                                                     cfg.init_size, rng)])
    F = np.arange(len(V)).reshape(-1, 3)
    lights = initial_lights(cfg, ds, rng)
    vsh = None
    if "vertex-sh" in cfg.lights:
        vsh = np.zeros((len(V), 6, (cfg.sh_degree + 1) ** 2))
        vsh[:, 0:3, 0] = 0.5 / Y00  # radiance = relu(Y00·c + 0.5) = 1
        vsh[:, 3:6, 0] = 0.1 * rng.normal(size=(len(V), 3))
    return Scene.from_arrays(V, F, lights=lights, vertex_sh=vsh, brdf=cfg.brdf)


def build_optimizer(cfg: TrainConfig, scene: Scene, extent: float, device=None) -> Adam:
    """Adam with one group per parameter family and the configured learning-rate schedules; with a CPU ``device``
    the update of each parameter without ``lr_scale`` runs as ``adam.cl`` there (bit for bit numpy's update)."""
    # on a CPU device the kernel reads and writes the numpy arrays in place (USE_HOST_PTR) in one vectorised pass
    # on the device's threads, where numpy makes eleven single-threaded passes: the update phase of a spot 200²
    # step 12.7-13.2 -> 11.5-11.9 ms in three interleaved pairs, the same bits (session 57; earlier, with more host
    # work around it, it had measured no faster); parameters under optim.DEVICE_MIN_SIZE elements keep numpy (the
    # kernel's fixed cost: the demo's 96² soup, session 58). A GPU would copy the parameters both ways every step:
    # unmeasured there, it keeps numpy
    opt = Adam(device=device if device is not None and device.is_cpu else None)
    kw = {"betas": tuple(cfg.betas), "eps": cfg.adam_eps}
    opt.add_group("V", [scene.V], lr=ExponentialDecay(cfg.lr_position * extent, cfg.lr_position_final * extent,
                                                      cfg.lr_position_steps), **kw)
    boost = {cfg.lr_boost_at: cfg.lr_boost}
    mscale = None
    if cfg.lr_lobe_scale != 1.0:
        brdf = get_brdf(scene.brdf)
        sc = np.ones((1, brdf.num_channels))
        sc[0, brdf.lobe_columns] = cfg.lr_lobe_scale
        mscale = [sc]
    opt.add_group("material", [scene.material], lr=StepUp(Constant(cfg.lr_material), boost), lr_scale=mscale, **kw)
    opt.add_group("alpha", [scene.alpha], lr=cfg.lr_alpha, **kw)
    if scene.vertex_sh is not None:
        opt.add_group("vertex_sh", [scene.vertex_sh], lr=StepUp(Constant(cfg.lr_vertex_sh), boost),
                      max_grad_norm=cfg.sh_clip, **kw)
    if scene.light_params is not None:
        scale = ([relative_lr_scales(scene.lights, position=cfg.lr_light_position_scale, extent=extent)]
                 if cfg.lr_lights_mode == "relative" else None)
        opt.add_group("lights", [scene.light_params], lr=cfg.lr_lights, lr_scale=scale, **kw)
    return opt


def tie_rows(param, columns=None) -> None:
    """Every row of ``param``'s gradient (in ``columns``, default all) replaced by their mean: the rows (equal at
    the start, with equal Adam moments) take the same step and stay one value (the light phases,
    ``TrainConfig.material_tie_until`` and ``MeshConfig.material_tie``)."""
    g = param.grad
    if g is None or not len(g):
        return
    # the mean of the rows as one BLAS product with a ones vector: 10x faster than numpy's mean over axis 0 of a
    # [60k, 6] float32 array (0.16 against 1.5 ms; it ran every step of the light phase) and closer to the float64
    # mean (numpy adds the rows one after another in float32: 1e-5 relative against 2e-6). OpenBLAS's threads may spin
    # beside the OpenCL CPU device's: the demo's metallic probe read 9.3-10.1 s in two runs against 7.2-7.9 s before,
    # and 7.5 s with OPENBLAS_NUM_THREADS=1, but the code before also read 11.6 s once: not settled (session 57)
    x = np.asarray(g) if columns is None else np.asarray(g[:, columns])
    mean = (np.ones(len(x), x.dtype) @ x.reshape(len(x), -1)).reshape(1, *x.shape[1:]) / x.dtype.type(len(x))
    if columns is None:
        g[...] = mean
    else:
        g[:, columns] = mean


# ------------------------------------------------------------------------------------------------ schedules


def schedule(cfg: TrainConfig, it: int) -> tuple[float, int, int]:
    """``(resolution factor, K, active SH degree)`` at iteration ``it`` (0-based)."""
    scale = 0.25 if it < cfg.warmup_until else (0.5 if it < cfg.half_res_until else 1.0)
    K = cfg.warmup_faces_per_pixel if it < cfg.warmup_until else cfg.faces_per_pixel
    deg = min(cfg.sh_degree, it // max(cfg.sh_band_every, 1))
    return scale, K, deg


# the soup's metallic probe works on photos of about this many pixels at most (probe_downscale): its verdicts were
# measured at 96² and 200² (bench/results/soup_metallic_pocl_2026-11-27.txt); at 800² its extraction's depth renders
# alone took 180 s and its trial 49 s (gadget upsampled to 800², bench/results/env_degree_pocl_2026-11-27.txt)
PROBE_PIXELS = 200 * 200


def probe_downscale(views) -> int:
    """The integer factor by which the soup's metallic probe shrinks the training photos: 1 up to about
    :data:`PROBE_PIXELS` (the sizes its verdicts were measured at: the dev scenes and captures), else the nearest
    factor that brings the largest view there (400² -> 2, 800² -> 4)."""
    px = max((v.camera.width * v.camera.height for v in views), default=0)
    return max(1, int(round(math.sqrt(px / PROBE_PIXELS)))) if px else 1


def _downsample(img: np.ndarray, f: int) -> np.ndarray:
    if f == 1:
        return img
    h, w = (img.shape[0] // f) * f, (img.shape[1] // f) * f
    x = img[:h, :w].reshape(h // f, f, w // f, f, *img.shape[2:])
    return x.mean(axis=(1, 3)).astype(np.float32)


def over_background(rgb: np.ndarray, alpha: np.ndarray, background: np.ndarray) -> np.ndarray:
    """``rgb [H, W, 3]`` (float32) over ``background [3]`` by ``alpha [H, W]``: ``rgb·a + bg·(1 − a)``, the same
    operations and bits as numpy's broadcast ``rgb * alpha[..., None] + bg * (1 - alpha[..., None])``, on flat arrays
    (alpha repeated per channel): a broadcast over a last axis of 3 runs numpy's inner loops 3 values at a time,
    2.0 -> 1.0 ms at 200² (a training step composites its target every step)."""
    background = np.asarray(background)
    if not rgb.dtype == alpha.dtype == background.dtype:  # numpy's promotions: its own expression
        return rgb * alpha[..., None] + background[None, None, :] * (1 - alpha[..., None])
    a3 = np.repeat(alpha.reshape(-1), 3)
    out = rgb.reshape(-1) * a3
    np.subtract(1, a3, out=a3)
    a3 *= np.tile(background, alpha.size)
    out += a3
    return out.reshape(rgb.shape)


class Targets:
    """Training images at each scheduled resolution (block-averaged once, cached)."""

    def __init__(self, ds: Dataset):
        self.ds = ds
        self.cache: dict = {}

    def get(self, i: int, scale: float, background: np.ndarray) -> tuple[Camera, np.ndarray]:
        v = self.ds.train[i]
        f = max(1, int(round(1 / scale)))
        key = (i, f)
        if key not in self.cache:
            rgb = _downsample(v.rgb, f)
            alpha = None if v.alpha is None else _downsample(v.alpha, f)
            cam = v.camera if f == 1 else v.camera.block_averaged(f)  # (W // f) x (H // f), as _downsample's
            self.cache[key] = (cam, rgb, alpha)
        cam, rgb, alpha = self.cache[key]
        if alpha is None:
            return cam, rgb
        return cam, over_background(rgb, alpha, background)

    def keep_only(self, scale: float) -> None:
        """Drop the images cached at every other scale (a phase that trains at ``scale`` only)."""
        f = max(1, int(round(1 / scale)))
        self.cache = {k: v for k, v in self.cache.items() if k[1] == f}


def training_views_id(ds: Dataset) -> dict:
    """What names the training views a run is trained on (in its checkpoints' metadata, compared on resume): a digest
    of their names, the first three, and their image size; their cameras go beside it (:func:`training_cameras`)."""
    import hashlib

    names = [str(v.name) for v in ds.train]
    first = ds.train[0] if len(ds.train) else None
    return {"names": hashlib.sha256("\n".join(names).encode()).hexdigest()[:16], "first_names": names[:3],
            "size": [first.width, first.height] if first is not None else None}


def training_cameras(ds: Dataset) -> np.ndarray:
    """``[n, 10]`` per training view: ``fx, fy, cx, cy``, the camera centre and its viewing axis (in the
    checkpoints, compared on resume with :func:`same_cameras`)."""
    rows = []
    for v in ds.train:
        c = v.camera
        R = np.asarray(c.w2c, np.float64)[:3, :3]
        rows.append([c.fx, c.fy, c.cx, c.cy, *np.asarray(c.center, np.float64), *R[2]])
    return np.asarray(rows, np.float64).reshape(-1, 10)


def same_cameras(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two :func:`training_cameras` arrays are the same captures' cameras: positions within 1e-5 of the
    cameras' spread, axes within 0.01°, intrinsics within 1 % (a COLMAP dataset undistorted again, e.g. by another
    pycolmap, may shift its pinhole focal length a little; another dataset's cameras differ far more)."""
    if a.shape != b.shape:
        return False
    if not len(a):
        return True
    spread = max(float(np.linalg.norm(a[:, 4:7] - a[:, 4:7].mean(axis=0), axis=1).max()), 1e-9)
    return bool(np.abs(a[:, 4:7] - b[:, 4:7]).max() <= 1e-5 * spread
                and (a[:, 7:10] * b[:, 7:10]).sum(axis=1).min() >= np.cos(np.radians(0.01))
                and np.abs(a[:, :4] - b[:, :4]).max() <= 1e-2 * np.abs(a[:, :2]).max())


def mean_abs_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``[H, W]``: ``|a − b|`` averaged over the 3 channels, the bits of ``np.abs(a - b).mean(axis=2)`` (numpy sums
    an axis of 3 as ``(d0 + d1) + d2`` and divides by 3) in a fifth of its time (1.5 -> 0.3 ms at 200²: a reduction
    over a last axis of 3 is slow in numpy)."""
    d = np.subtract(a, b)
    np.abs(d, out=d)
    s = d[..., 0] + d[..., 1]
    s += d[..., 2]
    s /= d.dtype.type(3)
    return s


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two ``[H, W, 3]`` images in [0, 1] (clipped)."""
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * math.log10(1.0 / mse) if mse > 0 else float("inf")


# ------------------------------------------------------------------------------------------------ trainer


RUN_FILES = ("config.json", "metrics.json", "lights.json", "triplets.ply", "train.log", "checkpoints", "renders")


def check_new_run_dir(run_dir) -> None:
    """A new run (the library's ``Trainer``, as the CLI's ``train --out``) is not started in a folder that is not a run
    and holds files of a run's names: the user's ``config.json``, ``metrics.json``, ``lights.json`` and
    ``triplets.ply`` were replaced (battery 10). A triplet run there is replaced (the CLI's ``--overwrite``)."""
    from .errors import RunError
    from .runs import is_run_dir, stillborn_run_leftovers

    run_dir = Path(run_dir)
    if not run_dir.is_dir() or is_run_dir(run_dir) or stillborn_run_leftovers(run_dir):  # (the CLI clears those)
        return
    found = [n for n in RUN_FILES if (run_dir / n).exists() or (run_dir / n).is_symlink()]
    if found:
        raise RunError(run_dir, f"is not a triplet run and holds {', '.join(found)}: a new run would replace them; "
                                "give an empty or new folder")


class Trainer:
    """Runs (or resumes) a training run in ``run_dir``; see the module docstring."""

    def __init__(self, data, run_dir, cfg: TrainConfig | None = None, device: Device | None = None,
                 resume: bool = False, data_format: str = "auto", quiet: bool = False):
        self.run_dir = Path(run_dir)
        self.device = device or get_device()
        self.quiet = quiet
        self.view_progress = not quiet  # a bar per rendered view on a terminal (render / eval / extract set it)
        if resume:
            from .runs import config_from_saved, read_run_config

            saved = read_run_config(self.run_dir)
            saved_cfg = config_from_saved(self.run_dir, saved)
            if cfg is not None:  # options that may change on resume (RESUMABLE_FIELDS); the rest must match
                cfg = replace(saved_cfg, **{k: getattr(cfg, k) for k in RESUMABLE_FIELDS})
            else:
                cfg = saved_cfg
            data = saved["data"] if data is None else data
            data_format = saved.get("format", data_format)
        self.cfg = cfg or TrainConfig()
        self.cfg.validate()
        if not resume:
            check_new_run_dir(self.run_dir)
        # the dataset's absolute path goes into config.json: render / eval / relight find it from any folder
        self.data, self.data_format = str(Path(data).absolute()), data_format
        auto_bg = self.cfg.background == "auto"
        self.ds = load_dataset(data, format=data_format, downscale=self.cfg.downscale,
                               background="white" if auto_bg else self.cfg.background)
        bg_note = None
        if auto_bg:
            bg, frac = auto_background(self.ds)
            self.cfg = replace(self.cfg, background=bg)
            self.ds.background = bg
            bg_note = f"background: {bg} (auto; {auto_background_reason(self.ds, bg, frac)})"
        shell_note = None
        if self.cfg.background_shell == "auto":
            self.cfg = replace(self.cfg, background_shell=auto_background_shell(self.cfg, self.ds))
            shell_note = auto_background_shell_note(self.cfg, self.ds)
        check_initial_budget(self.cfg, self.ds)  # init_points counts only without SfM points
        ds_note = None
        if self.cfg.downscale == "auto":
            self.cfg = replace(self.cfg, downscale=self.ds.downscale)
            if self.ds.downscale > 1:
                (w, h), f = self.ds.auto_downscale, self.ds.downscale
                ds_note = (f"downscale: {f} (auto: the photos are {w}x{h}, trained at {w // f}x{h // f}: at most "
                           f"{dataset_images.AUTO_MAX_SIDE} px on the longer side; --downscale N to choose)")
        from .validate import check_image_sizes, check_training_views

        if not self.ds.train:  # named with its test split's count (check_training_views), before the sizes' check
            check_training_views(self.ds, new_run=not resume)

        check_image_sizes(self.ds, self.cfg.downscale)  # before anything is written
        check_training_views(self.ds, new_run=not resume)  # a run trained already is not refused on loading
        self.check_device_budget()
        self.extent = scene_extent(self.ds, self.cfg.extent_frame)
        # the object's size against the dev scenes' (the mesh stage's Laplacian weight follows its square)
        self.length_scale = frame_radius(self.ds) / REFERENCE_FRAME_RADIUS
        # point lights stay this far from the look-at centre (world units; TrainConfig.light_min_distance)
        self.light_min_radius = light_keep_out_radius(self.cfg, self.ds)
        if self.extent < MIN_EXTENT:
            import warnings

            warnings.warn(DatasetWarning(
                f"{data}: the capture is very small in world units (scene extent {self.extent:.3g}; the dev scenes' "
                f"{REFERENCE_EXTENT}): below {MIN_EXTENT} the shading kernels' absolute guards bias the result "
                "(measured on spot_small: x 0.001 the mesh 1.5 dB worse, x 0.0001 4.4 dB); multiply the cameras' "
                "positions by a power of ten for the best result"), stacklevel=2)
        warn_if_far_from_origin(self.ds, self.extent, data)
        brdf = get_brdf(self.cfg.brdf)  # the light phase's columns: lobes held, the others tied (Trainer.step)
        self.lobe_columns = brdf.lobe_columns
        self.tied_columns = [c for c in range(brdf.num_channels) if c not in self.lobe_columns]
        # Blinn-Phong's ka ≡ kd (TrainConfig.blinn_phong_ka): the pairs, empty lists when off or Cook-Torrance
        self.ambient_pairs = ambient_pairs(brdf) if self.cfg.blinn_phong_ka == "diffuse" else ([], [])
        # TrainConfig.ao "off": the AO column takes no step (soup and mesh stage)
        self.held_ao = [brdf.column("ao")] if self.cfg.ao == "off" and brdf.column("ao") is not None else []
        self.start_soup()
        if not resume:
            warn_if_unseen(self.ds, np.asarray(self.scene.V.data), data)
        self.targets = Targets(self.ds)
        self.metallic_probe = None  # the soup's metal-or-dielectric probe (TrainConfig.metallic_probe_at), once run
        self._resumed_from: tuple | None = None  # (checkpoint, its number of training views) once one is loaded
        self._resumed_id: tuple = (None, None)  # the checkpoint's training_views_id and training_cameras
        self._views_id_cache: dict | None = None
        self.history: list[dict] = []
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self.log = _file_logger(self.run_dir / "train.log")
        self.background_note, self.shell_note, self.downscale_note = bg_note, shell_note, ds_note
        for note in (bg_note, shell_note, ds_note):
            if note:
                self.log.info(note)
        if resume:
            self.load_checkpoint(self.latest_checkpoint())
        else:
            write_json(self.run_dir / "config.json", {"data": self.data, "format": data_format,
                                                      "train": self.cfg.to_dict()})

    def start_soup(self, metallic: float | None = None) -> None:
        """The soup's initial state at iteration 0 (scene, optimiser, generator, density statistics, priors, shadow
        cache, view order); ``metallic``: every vertex's initial metallic (the probe's restart for a metal)."""
        self.rng = np.random.default_rng(self.cfg.seed)
        self.scene = initial_scene(self.cfg, self.ds, self.rng)
        if metallic is not None:
            from .activations import logit

            self.scene.material.data[:, get_brdf(self.scene.brdf).column("metallic")] = logit(metallic)
        copy_ambient(self.scene.material, self.ambient_pairs)
        self.opt = build_optimizer(self.cfg, self.scene, self.extent, self.device)
        self.split_error = np.full(len(self.scene.F), np.inf)  # per-face error records (error_resplit_ratio)
        self.spatial_sort()
        self.stats = DensityStats(len(self.scene.F))
        self.priors = Priors(self.cfg, look_at_center(self.ds))
        self.shadow_cache = VisibilityCache(self.cfg.shadow_every, self.cfg.shadow_from, self.extent,
                                            ray_eps=self.cfg.shadow_eps)
        self.it = 0
        self.last_alpha_reset: int | None = None
        self.order: list[int] = []

    def check_device_budget(self) -> None:
        """Refuse (``ValueError``, before any work) a schedule whose largest renders cannot fit the device
        (:func:`~triplet_cl.validate.check_device_budget`): the warm-up (¼ resolution, warm-up K) and the full
        resolution (K) of the largest training view, with up to ``max_faces`` faces."""
        from .validate import check_device_budget

        big = max(self.ds.train, key=lambda v: v.rgb.shape[0] * v.rgb.shape[1])
        h, w = big.rgb.shape[:2]
        c = self.cfg
        check_device_budget(self.device.info, [(max(w // 4, 1), max(h // 4, 1), c.warmup_faces_per_pixel,
                                                "the warm-up's fragments per pixel (warmup_faces_per_pixel)"),
                                               (w, h, c.faces_per_pixel, "--faces-per-pixel")],
                            c.density.max_faces)

    @property
    def transfer(self) -> str | None:
        """``RenderSettings.transfer`` of this run: ``"srgb"`` for the linear pipeline on sRGB-encoded photos,
        ``"srgb-clip"`` with ``sensor_clip`` (the default of new runs)."""
        return color_transfer(self.cfg.color, self.ds.color_space, self.cfg.sensor_clip)

    def spatial_sort(self) -> None:
        """Store the faces in Morton order of their centroids (coherent memory for the kernels)."""
        V = self.scene.V.data.reshape(-1, 3, 3)
        order = morton_order(V.mean(axis=1))
        reorder_faces(self.scene, self.opt, order)
        self.split_error = self.split_error[order]

    # ---- one step ------------------------------------------------------------------------------
    def next_view(self) -> int:
        if not self.order:
            self.order = list(self.rng.permutation(len(self.ds.train)))
        return int(self.order.pop())

    def step(self) -> dict:
        if 0 < self.cfg.metallic_probe_at == self.it < self.cfg.material_tie_until and self.metallic_probe is None:
            self.probe_metallic()  # (a metal's verdict restarts the soup: this step is then iteration 0)
        cfg, it = self.cfg, self.it
        scale, K, deg = schedule(cfg, it)
        self.set_env_degree(deg)
        if cfg.background == "random":
            bg = self.rng.uniform(0, 1, 3)
        else:
            bg = resolve_background(cfg.background)
        i = self.next_view()
        cam, target = self.targets.get(i, scale, np.asarray(bg, np.float32))
        settings = RenderSettings(K=K, sigma=cfg.sigma, background=tuple(float(x) for x in bg),
                                  sh_degree=deg if self.scene.vertex_sh is not None else None,
                                  renderer=cfg.renderer, transfer=self.transfer)
        t0 = time.perf_counter()
        vis = self.visibility(it)
        tv = time.perf_counter()
        r = render(self.scene, cam, settings, self.device, vis=vis)
        t1 = time.perf_counter()
        if not np.isfinite(r.image).all():
            raise NonFiniteError(it + 1, "render", "image", "the rendered image holds NaN/Inf (non-finite "
                                 f"lights or materials?); {self.checkpoint_hint()}")
        # from DEVICE_LOSS_RESIDENT_MIN_PIXELS on (every size on PoCL, measured: losses.py), the losses.cl kernels on
        # the rendered image where it already is (only the target goes up and the loss value comes down; the adjoint
        # seeds the backward on the device); below that threshold, the host (numpy) loss
        if loss_backend(target.shape, resident=True) == "opencl":
            target_d = cla.to_device(self.device.queue, np.ascontiguousarray(target, r.device_image.dtype))
            loss, v_img = photometric_loss_and_grad(r.device_image, target_d, lam=cfg.ssim_lambda)
            t2 = time.perf_counter()
            r.backward_device(v_img)
        elif exact_device_loss_available(self.device, r.device_image, cfg.ssim_lambda):
            # below it, the numpy loss's adjoint computed on the device bit for bit (ssim_exact.cl: the float32
            # operations in numpy's order, the Gaussian passes in double as scipy's): the same trajectories without
            # the host loss (~2.8 ms a step at 96² on PoCL) and without uploading its adjoint; the value is summed
            # on the host from the SSIM map, as numpy does, once the backward has been queued
            loss, v_img = photometric_loss_and_grad_exact(self.device, r.device_image, r.image, target,
                                                          lam=cfg.ssim_lambda)
            t2 = time.perf_counter()
            r.backward_device(v_img)
        else:
            loss, v_img = photometric_loss_and_grad(r.image, target, lam=cfg.ssim_lambda, backend="numpy")
            t2 = time.perf_counter()
            r.backward(v_img)
        prior_terms = self.priors.apply(self.scene, it)
        t3 = time.perf_counter()
        dens = cfg.density
        if it < dens.densify_until:
            fr = r.info["frags"]
            # gradients in NDC units (× W/2, as 3D Gaussian Splatting): the same face gets the same
            # statistic at ¼, ½ and full resolution, so one threshold serves the whole schedule; the
            # error criterion needs each pixel's error and nearest face (density.DensityStats.add)
            # visibility and the nearest faces from the fragments on the device (face_visibility.cl): only
            # [M] bytes and the [H, W] map come down, not the [P] face ids (density.py's host functions are
            # the reference, bit for bit)
            err = mean_abs_error(r.image, target) if dens.error_threshold is not None else None
            self.stats.add(r.info["v_vs"].get(), visible_faces(fr.face, len(self.scene.F), device=self.device),
                           self.scene.F, vs=r.info["vs"].get(), image_size=(cam.width, cam.height),
                           v_V=self.scene.V.grad, grad_scale=0.5 * cam.width, device=self.device, error=err,
                           front=None if err is None else front_faces(fr, face_alpha(self.scene.alpha.data,
                                                                                    self.scene.F),
                                                                      dens.error_min_alpha, device=self.device))
        held = None
        if it < cfg.material_tie_until:
            if cfg.light_phase_lobes == "held":  # the lobes' own per-vertex moments, their values put back below
                held = np.array(self.scene.material.data[:, self.lobe_columns])
                tie_rows(self.scene.material, self.tied_columns)
            else:
                tie_rows(self.scene.material)
        tie_ambient_gradient(self.scene.material, self.ambient_pairs)
        if self.held_ao and self.scene.material.grad is not None:
            self.scene.material.grad[:, self.held_ao] = 0.0
        lp = self.scene.light_params
        lights_before = np.array(lp.data) if lp is not None and cfg.hold_irradiance else None
        try:
            self.opt.step()  # the finiteness guard: see Adam.step
        except NonFiniteStep as exc:
            raise NonFiniteError(it + 1, exc.group, exc.what, self._nonfinite_cause(exc)) from None
        self.opt.zero_grad()
        if held is not None:
            self.scene.material.data[:, self.lobe_columns] = held
        copy_ambient(self.scene.material, self.ambient_pairs)
        self.priors.project(self.scene)
        self.balance_lights(lights_before)
        t4 = time.perf_counter()
        report = None
        if dens.densify_at(it):
            # after an alpha reset (alpha <= 0.01 everywhere) faces need time to regain opacity before
            # the alpha <= prune_alpha (0.05) test: measured on spot_small, pruning 100 iterations after
            # a reset removed 98 % of the faces (29 dB -> 20 dB); so no pruning during a grace period
            grace = self.last_alpha_reset is not None and it - self.last_alpha_reset < cfg.alpha_reset_grace
            report = densify_and_prune(self.scene, self.opt, self.stats, dens, self.extent, prune=not grace,
                                       prune_screen=it > dens.alpha_reset_interval, split_error=self.split_error)
            self.split_error = report.split_error
            self.spatial_sort()
            self.stats = DensityStats(len(self.scene.F))
            self.priors.invalidate()
            self.shadow_cache.invalidate()  # new rows, new order
            self.check_finite(f"after densification at iteration {it + 1}")
            self.device.release_memory(1 << 30)  # the old sizes' buffers and heap pages, once past 1 GiB (no effect
            # on the numbers)
        if dens.reset_alpha_at(it):
            reset_alpha(self.scene, self.opt, dens.alpha_reset_value)
            self.last_alpha_reset = it
        t5 = time.perf_counter()
        self.it += 1
        loss = loss.value() if isinstance(loss, ExactLoss) else float(loss)  # the exact device loss: summed here
        rec = {"it": self.it, "loss": loss, "psnr": psnr(r.image, target), "faces": len(self.scene.F),
               "render": t1 - t0, "shadow": tv - t0, "loss_t": t2 - t1, "backward": t3 - t2, "step": t4 - t3,
               "density": t5 - t4}
        if prior_terms:
            rec["priors"] = prior_terms
        if report is not None:
            rec["densify"] = {"split": report.split, "cloned": report.cloned, "pruned": report.pruned,
                              "pruned_alpha": report.pruned_alpha, "pruned_world": report.pruned_world_area,
                              "pruned_screen": report.pruned_screen, "by_error": report.by_error,
                              "error_blocked": report.error_blocked,
                              "spared": report.spared_min_faces, "skipped_budget": report.skipped_max_faces}
        return rec

    def probe_metallic(self) -> dict | None:
        """Metal or dielectric for the soup (``TrainConfig.metallic_probe_at``): a mesh extracted from it now, the
        mesh stage's trial on that mesh (:meth:`~triplet_cl.mesh.refine.MeshStage.choose_metallic`, from its light
        phase's start: :meth:`~triplet_cl.mesh.refine.MeshStage.light_phase_ties`). A dielectric leaves the soup as it
        is; a metal restarts it from iteration 0 with every metallic at 0.99, which the light phase then holds
        (:meth:`start_soup`). Deterministic (the stage's own seeded generators; the run's is not drawn from). Returns
        the trial's record (also in metrics.json and the checkpoints), or None (no metallic channel; skipped)."""
        from .mesh.refine import MeshConfig, MeshStage

        brdf = get_brdf(self.scene.brdf)
        col = brdf.column("metallic")
        if col is None:
            return None
        if not self.ds.has_alpha:  # photos with a background: a mesh of the object alone cannot be compared with them
            # (the mesh stage skips its refinement there for the same reason); the soup stays a dielectric
            self.metallic_probe = {"it": self.it, "skipped": "the photos have no alpha (a background)"}
            self.log.info("soup metallic probe skipped: the photos have no alpha (a background)")
            return None
        t = time.perf_counter()
        f = probe_downscale(self.ds.train)
        # photos shrunk by f are f x f block averages, next to which the capture's own pixel filter (a fraction of
        # a photo pixel) is negligible: no filter then, and no full-size renders to estimate one
        stage = MeshStage(self, MeshConfig(pixel_sigma=None if f == 1 else 0.0), quiet=True)
        cached = set(self.targets.cache)
        try:
            try:
                mesh = stage.extract(self.scene, downscale=f)
            except ValueError as exc:  # a soup with no surface yet (a very short run): the dielectric stays
                self.metallic_probe = {"it": self.it, "skipped": str(exc)}
                self.log.info(f"soup metallic probe skipped: {exc}")
                return None
            if stage.cfg.pixel_sigma is None:
                stage.resolve_pixel_filter(mesh)
            out = stage.choose_metallic(mesh, stage.light_phase_ties(mesh), col, downscale=f,
                                        max_metal_roughness=self.cfg.metal_probe_max_roughness)
        finally:  # the photos the probe shrank: not kept for the training (what it had cached stays)
            self.targets.cache = {k: v for k, v in self.targets.cache.items() if k in cached}
        rec = {"it": self.it, **{k: v for k, v in out.items() if k != "curves"}, "faces": len(mesh.F),
               "downscale": f, "seconds": time.perf_counter() - t, "restarted": bool(out["metallic"] > 0.5)}
        self.metallic_probe = rec
        self.log.info("soup metallic probe: " + json.dumps(rec))
        del stage, mesh
        self.device.release_memory()
        if rec["restarted"]:  # a metal: the soup again from its first step, held as one (its surface placed as one)
            self.start_soup(metallic=0.99)
            ck = self.run_dir / "checkpoints"  # the first pass's checkpoints: a resume must not take them for newer
            for p in [*ck.glob("ckpt_*.npz"), ck / "latest"]:
                p.unlink(missing_ok=True)
            if self.cfg.checkpoint_every:  # the restart's state, so that a resume from here does not probe again
                self.save_checkpoint()
            self.log.info("soup restarted from iteration 0 as a metal (metallic 0.99)")
        return rec

    def balance_lights(self, before=None) -> None:
        """The white-light rule (``TrainConfig.white_light``, :func:`lights.balanced_lights`) after each step, and
        with ``before`` (the light parameters before it) :func:`lights.hold_irradiance`."""
        lp = self.scene.light_params
        if lp is not None:
            lp.data[...] = balanced_lights(self.cfg.white_light, self.scene.lights, lp.data, self.priors.center,
                                           self.it < self.cfg.material_tie_until, before=before,
                                           min_distance=self.light_min_radius)

    def set_env_degree(self, deg: int) -> None:
        """The SH environment lights' active degree follows the band schedule (one band every ``sh_band_every``
        iterations up to ``sh_degree``), as the vertex-SH light's: before this, nothing raised it from the
        initial 0, so ``--lights sh-env`` trained a constant environment only."""
        for lt in self.scene.lights:
            if isinstance(lt, SHEnvironmentLight):
                lt.degree = min(int(deg), lt.stored_degree)

    def visibility(self, it: int | None = None) -> np.ndarray | None:
        """The cached per-vertex visibility (``[N, NV]``) for iteration ``it`` (default: the current one), or
        None (``shadows`` off, a ray-traced renderer with its own shadows, or before ``shadow_from``)."""
        if self.cfg.shadows != "vertex" or self.cfg.renderer != "raster":
            return None
        return self.shadow_cache.get(self.scene, self.it if it is None else it, self.device)

    def shadows_active(self) -> bool:
        """Whether this run's state was trained with the cached shadows (``--shadows vertex``, raster, past
        ``shadow_from``): its renders and relit images then have them."""
        return self.cfg.shadows == "vertex" and self.cfg.renderer == "raster" and self.it >= self.cfg.shadow_from

    def final_visibility(self) -> np.ndarray | None:
        """The per-vertex visibility of the current state, traced afresh (evaluation, relighting under the
        learned lights: the same images), or None without shadows; the training cache is left alone."""
        if not self.shadows_active():
            return None
        from .visibility import vertex_visibility

        return vertex_visibility(self.scene, self.device, ray_eps=self.cfg.shadow_eps)

    def _nonfinite_cause(self, exc: NonFiniteStep) -> str:
        last = self.checkpoint_hint()
        if exc.what == "gradient":
            why = ("the render/loss back-propagation produced NaN/Inf gradients (degenerate or huge triangles, "
                   f"overflowing lights?; the learning rate of this group is {self.opt.lr(exc.group):.3g}: a large "
                   "one makes the previous update diverge); nothing was updated")
        else:
            why = (f"the Adam update made it NaN/Inf: learning rate {self.opt.lr(exc.group, self.opt.t - 1):.3g} "
                   "of this group too large (diverging), or the parameters were already non-finite")
        return f"{why}; {last}"

    def checkpoint_hint(self) -> str:
        latest = self.run_dir / "checkpoints" / "latest"
        if latest.is_file():
            return f"the last good checkpoint is kept ({latest.read_text().strip()})"
        return "no checkpoint was written"

    def check_finite(self, where: str) -> None:
        """Every parameter finite, else NonFiniteError naming the group (after a load or densification)."""
        for name, g in self.opt.groups.items():
            for p in g.params:
                if not np.isfinite(p.data).all():
                    n = int((~np.isfinite(p.data)).sum())
                    raise NonFiniteError(self.it, name, "parameter", f"{n} NaN/Inf value(s) {where}; "
                                         f"{self.checkpoint_hint()}")

    # ---- loop ----------------------------------------------------------------------------------
    def train(self) -> dict:
        """Train to ``cfg.iterations`` (from the current iteration), then write the results."""
        from tqdm import tqdm

        cfg = self.cfg
        interrupted = []

        def on_sigint(signum, frame):
            interrupted.append(signum)

        from .runs import remove_stale_temp_files

        renders = self.run_dir / "renders"
        for folder in (self.run_dir, self.run_dir / "checkpoints",
                       *(sorted(renders.iterdir()) if renders.is_dir() else [])):
            remove_stale_temp_files(folder)
        self.check_resumable()
        from .validate import check_render_out, linked_within

        if self.ds["test"] and linked_within(self.run_dir, renders / "test"):  # the folder a link there points to
            check_render_out(self, "test", renders / "test", "RUN")  # is the user's (battery 9)
        self.check_finite("before training")
        old = signal.signal(signal.SIGINT, on_sigint)
        old_term = signal.signal(signal.SIGTERM, on_sigint)  # `kill PID`: the same clean stop as Ctrl-C
        bar = tqdm(total=cfg.iterations, initial=self.it, desc="train", unit="it", disable=self.quiet,
                   dynamic_ncols=True)
        t_start = time.perf_counter()
        try:
            while self.it < cfg.iterations:
                try:
                    rec = self.step()
                except NonFiniteError as exc:
                    self.log.info(f"stopped: {exc}")
                    raise
                self.history.append(rec)
                if self.it < bar.n:  # the soup restarted (a metal: probe_metallic)
                    bar.reset(total=cfg.iterations)
                bar.update(self.it - bar.n)
                bar.set_postfix(loss=f"{rec['loss']:.4f}", psnr=f"{rec['psnr']:.2f}", faces=str(rec["faces"]))
                if self.it % 100 == 0 or "densify" in rec:
                    self.log.info(json.dumps(rec))
                if cfg.checkpoint_every and self.it % cfg.checkpoint_every == 0:
                    self.save_checkpoint()
                if interrupted:
                    self.save_checkpoint()
                    self.log.info(f"interrupted at iteration {self.it}; checkpoint saved")
                    if interrupted[0] == signal.SIGTERM and callable(old_term):
                        old_term(signal.SIGTERM, None)  # the caller's own handler (the CLI's: exit status 143)
                    raise KeyboardInterrupt
        finally:
            bar.close()
            signal.signal(signal.SIGINT, old)
            signal.signal(signal.SIGTERM, old_term)
        wall = time.perf_counter() - t_start
        self.save_checkpoint()
        return self.finish(wall)

    def mesh_made_from(self) -> dict | None:
        """A mesh stage's record in this run (``mesh_stage.npz`` present): ``{"mesh": the metrics' "mesh" section or
        None, "iterations": the soup's iterations when it was made (metrics.json's, or None)}``; None without one."""
        from .mesh.refine import MESH_STATE

        if not (self.run_dir / MESH_STATE).is_file():
            return None
        try:
            old = json.loads((self.run_dir / "metrics.json").read_text())
        except (OSError, ValueError):
            old = {}
        if not isinstance(old, dict):
            old = {}
        mesh = old.get("mesh") if isinstance(old.get("mesh"), dict) else None
        its = old.get("iterations") if isinstance(old.get("iterations"), int) else None
        return {"mesh": mesh, "iterations": its}

    def finish(self, wall: float | None = None) -> dict:
        """Write triplets.ply, lights.json, test renders and metrics.json. In a run with a mesh stage (a resumed one)
        its metrics' "mesh" section is kept, marked ``stale`` when the soup trained on since it was made, and
        lights.json (the mesh's lights, which its exports carry) is left as the stage wrote it (battery 11: a resume
        dropped the mesh's metrics and put the soup's lights beside the mesh's files, without a word)."""
        made = self.mesh_made_from()
        self.export_scene(lights=made is None)
        metrics = self.evaluate(write_renders=True)
        metrics.update({"iterations": self.it, "faces": len(self.scene.F)})
        if made is not None and made["mesh"] is not None:
            metrics["mesh"] = dict(made["mesh"])
            if made["iterations"] != self.it:
                metrics["mesh"]["stale"] = {"made_from_iterations": made["iterations"], "soup_iterations": self.it}
        if self.metallic_probe is not None:  # (a resumed run's from its checkpoint)
            metrics["metallic_probe"] = self.metallic_probe
        if wall is not None:
            metrics["wall_time_s"] = wall
            steps = [h for h in self.history if "render" in h]
            if steps:
                metrics["seconds_per_iteration"] = {k: float(np.mean([h[k] for h in steps]))
                                                    for k in ("render", "loss_t", "backward", "step", "density")}
                shadow = [h.get("shadow", 0.0) for h in steps]  # the visibility traces, inside "render"
                metrics["shadows"] = {"mode": self.cfg.shadows, "traces": self.shadow_cache.traces,
                                      "trace_s": float(np.sum(shadow))}
        write_json(self.run_dir / "metrics.json", metrics)
        self.log.info(f"metrics: {json.dumps({k: v for k, v in metrics.items() if k != 'views'})}")
        return metrics

    # ---- outputs -------------------------------------------------------------------------------
    def export_scene(self, lights: bool = True) -> None:
        """triplets.ply and (``lights``) lights.json of the current soup."""
        from .activations import sigmoid

        s = self.scene
        brdf = get_brdf(s.brdf)
        attrs = {"alpha": sigmoid(s.alpha.data.astype(np.float64))}
        attrs.update(brdf.split(brdf.activate(s.material.data)))  # every attribute (Blinn-Phong's shininess too)
        write_soup_ply(self.run_dir / "triplets.ply", s.V.data, s.F, attrs,
                       albedo_space="linear" if self.cfg.color == "linear" else "srgb")
        if lights:
            write_json(self.run_dir / "lights.json", lights_to_json(s.current_lights(), check_finite=False))

    def evaluate(self, split: str = "test", write_renders: bool = False, out_dir=None) -> dict:
        """PSNR / SSIM of every view of ``split`` (rendered at full resolution, K after warm-up)."""
        views = self.ds[split]
        if not views:
            if split == "test" and self.ds.train:  # a dataset without test views: report on the training views
                views, split = self.ds.train, "train"
            else:
                raise DatasetError(self.ds.root, f"the dataset has no {split!r} views (splits with views: "
                                   f"{[s for s, v in self.ds.splits.items() if v]})")
        if self.cfg.max_test_views:
            views = views[: self.cfg.max_test_views]
        bg = np.asarray(resolve_background("white" if self.cfg.background == "random" else self.cfg.background),
                        np.float32)
        settings = RenderSettings(K=self.cfg.faces_per_pixel, sigma=self.cfg.sigma, background=tuple(bg),
                                  renderer=self.cfg.renderer, transfer=self.transfer,
                                  sh_degree=min(self.cfg.sh_degree, self.it // max(self.cfg.sh_band_every, 1))
                                  if self.scene.vertex_sh is not None else None)
        out_dir = Path(out_dir) if out_dir else self.run_dir / "renders" / split
        per = []
        vis = self.final_visibility()
        from .runs import view_progress

        for v, fname in view_progress(zip(views, render_files(views), strict=True), f"render {split}",
                                      not self.view_progress):
            r = render(self.scene, v.camera, settings, self.device, vis=vis)
            target = v.target(bg)
            img = np.clip(r.image, 0, 1)
            per.append({"name": v.name, "psnr": psnr(img, target),
                        "ssim": float(ssim(img.astype(np.float64), target.astype(np.float64), padding="valid"))})
            if write_renders:
                # straight alpha: un-composite the background from the rendered colour
                a = np.clip(r.alpha, 0, 1)
                rgb = np.where(a[..., None] > 1e-4, (img - bg * (1 - a[..., None])) / np.maximum(a[..., None], 1e-4),
                               0.0)
                write_png(out_dir / fname, rgb, a)
        return {"split": split, "psnr": float(np.mean([p["psnr"] for p in per])) if per else None,
                "ssim": float(np.mean([p["ssim"] for p in per])) if per else None, "views": per}

    # ---- checkpoints ---------------------------------------------------------------------------
    def latest_checkpoint(self) -> Path:
        from .runs import list_checkpoints

        latest = self.run_dir / "checkpoints" / "latest"
        try:  # a damaged `latest` (binary garbage, a NUL byte) counts as lost, as a missing one
            text = latest.read_text(encoding="utf-8").strip() if latest.is_file() else None
            # only a checkpoint of this run's own folder: `../../other/checkpoints/ckpt_*.npz` resumed another run
            # (a battery); such a name counts as lost too
            named = self.run_dir / "checkpoints" / text if text and Path(text).name == text else None
            if named is not None and named.is_file():
                return named
        except (OSError, UnicodeDecodeError, ValueError):
            pass
        found = list_checkpoints(self.run_dir)  # `latest` lost or pointing at a removed file: the newest one
        ck = self.run_dir / "checkpoints"
        if not found and (ck.exists() or ck.is_symlink()) and not ck.is_dir():
            raise FileNotFoundError(f"{ck} is a file, not the run's checkpoints folder: the run's trained state is "
                                    "not there (move the file away, or start again with --overwrite)")
        if not found:
            head = (f"no checkpoint in {self.run_dir / 'checkpoints'}: the run's trained state (every command that "
                    "reads a run loads it; triplets.ply alone is an export of it)")
            if (self.run_dir / "metrics.json").is_file():  # a finished run whose checkpoints were deleted (battery
                # 11: advised --overwrite, which would delete its mesh too)
                from .mesh.refine import MESH_STATE

                has_mesh = (self.run_dir / MESH_STATE).is_file()
                raise FileNotFoundError(
                    f"{head}: the run finished (metrics.json) but its checkpoints were removed, so eval, render, "
                    "relight and extract cannot load it; restore the checkpoints folder, or train it again into a "
                    "new --out (not --overwrite: it would delete this run" + (", mesh included" if has_mesh else "")
                    + ")" + ("; `triplet export` still works from its mesh (mesh_stage.npz)" if has_mesh else ""))
            raise FileNotFoundError(f"{head}; a run stopped before its first checkpoint starts again with --overwrite")
        return found[-1]

    def save_checkpoint(self) -> Path:
        s = self.scene
        self.check_finite(f"at iteration {self.it}: no checkpoint written")
        arrays = {"V": s.V.data, "F": s.F, "material": s.material.data, "alpha": s.alpha.data}
        if s.vertex_sh is not None:
            arrays["vertex_sh"] = s.vertex_sh.data
        if s.light_params is not None:
            arrays["light_params"] = s.light_params.data
        for k, v in vars(self.stats).items():
            if isinstance(v, np.ndarray):
                arrays[f"stats.{k}"] = v
        arrays["density.split_error"] = self.split_error
        arrays["views.cameras"] = training_cameras(self.ds)  # compared on resume (Trainer.check_resumable)
        sc = self.shadow_cache
        if sc.vis is not None:  # the cached visibility: a resumed run continues bit for bit
            arrays["shadow.vis"], arrays["shadow.rays"] = sc.vis, sc.rays
            arrays["shadow.at"] = np.array([sc.at], np.int64)
        opt_state = self.opt.state_dict()
        for g, st in opt_state["groups"].items():
            for j, (m, v) in enumerate(zip(st["exp_avg"], st["exp_avg_sq"], strict=True)):
                arrays[f"opt.{g}.{j}.m"], arrays[f"opt.{g}.{j}.v"] = m, v
        meta = {"it": self.it, "t": opt_state["t"], "order": [int(x) for x in self.order],
                "train_views": len(self.ds.train), "train_views_id": self._views_id(),
                "last_alpha_reset": self.last_alpha_reset,
                "metallic_probe": self.metallic_probe,
                "rng": self.rng.bit_generator.state,
                "config": {k: v for k, v in self.cfg.to_dict().items() if k not in RESUMABLE_FIELDS},
                "opt_hyper": {g: {k: v for k, v in st.items() if k not in ("exp_avg", "exp_avg_sq")}
                              for g, st in opt_state["groups"].items()}}
        arrays["meta"] = np.frombuffer(json.dumps(meta, default=_json_default).encode(), np.uint8)
        buf = _io.BytesIO()
        np.savez(buf, **arrays)
        name = f"ckpt_{self.it:07d}.npz"
        atomic_write_bytes(self.run_dir / "checkpoints" / name, buf.getvalue())
        atomic_write_bytes(self.run_dir / "checkpoints" / "latest", name.encode())
        from .runs import prune_checkpoints

        prune_checkpoints(self.run_dir, self.cfg.keep_checkpoints, protect=self.run_dir / "checkpoints" / name)
        return self.run_dir / "checkpoints" / name

    def load_checkpoint(self, path: Path) -> None:
        from .runs import read_checkpoint

        a, meta = read_checkpoint(path)
        self._check_checkpoint(path, a, meta)
        try:
            self._restore(a, meta)
        except (ValueError, TypeError, KeyError, IndexError) as exc:  # a hand-edited or damaged state: name the file
            raise RunError(path, f"damaged: {exc} (resume from an earlier checkpoint: edit checkpoints/latest; or "
                                 "start again)") from None

    def _restore(self, a: dict, meta: dict) -> None:
        """The run's state from a checked checkpoint's arrays and metadata."""
        s = self.scene
        s.V.data, s.F = a["V"], a["F"].astype(np.int32)
        s.material.data, s.alpha.data = a["material"], a["alpha"]
        if s.vertex_sh is not None:
            s.vertex_sh.data = a["vertex_sh"]
        if s.light_params is not None:
            s.light_params.data = a["light_params"]
        self.shadow_cache.invalidate()
        if "shadow.vis" in a and a["shadow.vis"].shape[0] == len(s.V.data):
            sc = self.shadow_cache
            sc.vis, sc.rays, sc.at, sc.F = a["shadow.vis"], a["shadow.rays"], int(a["shadow.at"][0]), s.F
        self.stats = DensityStats(len(s.F))
        se = a.get("density.split_error")
        self.split_error = se if se is not None and se.shape == (len(s.F),) else np.full(len(s.F), np.inf)
        for k in list(vars(self.stats)):
            if f"stats.{k}" in a:
                setattr(self.stats, k, a[f"stats.{k}"])
        groups = {}
        for g, hyper in meta["opt_hyper"].items():
            n = len(self.opt.groups[g].params)
            groups[g] = dict(hyper, exp_avg=[a[f"opt.{g}.{j}.m"] for j in range(n)],
                             exp_avg_sq=[a[f"opt.{g}.{j}.v"] for j in range(n)])
        self.opt.load_state_dict({"t": meta["t"], "groups": groups})
        self.it = int(meta["it"])
        self.set_env_degree(schedule(self.cfg, max(self.it - 1, 0))[2])  # the degree of the last step
        self.last_alpha_reset = meta.get("last_alpha_reset")
        self.metallic_probe = meta.get("metallic_probe")  # decided before the checkpoint: not again
        self.order = list(meta["order"])
        self.rng.bit_generator.state = meta["rng"]

    def close_log(self) -> None:
        """Close ``train.log`` (a run folder about to be removed: its logger, cached by path, must not keep writing to
        the deleted file)."""
        for h in list(self.log.handlers):
            h.close()
            self.log.removeHandler(h)

    def _views_id(self) -> dict:
        """:func:`training_views_id` of the dataset, computed once."""
        if self._views_id_cache is None:
            self._views_id_cache = training_views_id(self.ds)
        return self._views_id_cache

    def check_resumable(self, action: str = "resume") -> None:
        """Training may go on from the loaded checkpoint: the dataset has the training views it was made with (their
        number, and every view its order has left), else a :class:`RunError` naming the checkpoint. Training and the
        mesh stage (``action="extract"``: it refines against the training photos) need this; evaluating or rendering
        a run whose dataset changed is allowed."""
        if self._resumed_from is None:
            return
        path, saved_n = self._resumed_from
        n = len(self.ds.train)
        if (saved_n is not None and saved_n != n) or any(i >= n for i in self.order):
            was = f"{saved_n} training views" if saved_n is not None else "more training views"
            raise RunError(path, f"was trained on {was}, the dataset {self.data} now has {n} (another dataset, or "
                                 f"frames added or removed since): {action} with the dataset the run was made with "
                                 "(config.json's \"data\"), or start a new run")
        what = self._views_mismatch()
        if what is not None:
            raise self._other_views(path, what, f"{action} with the dataset the run was made with (config.json's "
                                                "\"data\"), or start a new run")

    def _other_views(self, path, what: str, advice: str) -> RunError:
        return RunError(path, f"was trained on other training views than the dataset {self.data} holds ({what}): "
                              f"{advice}")

    def _views_mismatch(self) -> str | None:
        """What differs between the loaded checkpoint's training views and the dataset's (their names, size,
        cameras), or None (the same, or a checkpoint from before they were saved)."""
        saved_id, saved_cams = self._resumed_id  # checkpoints written before they were saved: the count only
        what = None
        if isinstance(saved_id, dict):
            mine = self._views_id()
            if saved_id.get("names") != mine["names"]:
                what = (f"its training frames were {', '.join(map(str, saved_id.get('first_names') or []))}, ... and "
                        f"the dataset's are {', '.join(mine['first_names'])}, ...")
            elif saved_id.get("size") != mine["size"]:
                was, now = saved_id.get("size") or ["?", "?"], mine["size"]
                what = f"it was trained on {was[0]}x{was[1]} photos and the dataset's are {now[0]}x{now[1]}"
        if what is None and saved_cams is not None and not same_cameras(saved_cams, training_cameras(self.ds)):
            what = "the training views' cameras (poses or intrinsics) are not the ones it was trained with"
        return what

    def warn_if_dataset_changed(self) -> None:
        """Evaluating or rendering a run whose dataset's training split changed since it was trained is allowed (new
        test views), but its test split may then hold views it trained on (a battery: ``transforms_test.json``
        removed, the hold-out of the training views became the test split and metrics.json was rewritten from it):
        say so, one warning line. As many training views but not the same ones (their names, size or cameras:
        another capture put at the run's path) is refused (:class:`RunError`, before anything is written)."""
        import warnings

        from .datasets.base import DatasetWarning

        if self._resumed_from is None:
            return
        path, saved_n = self._resumed_from
        n = len(self.ds.train)
        if saved_n is not None and saved_n != n:
            warnings.warn(DatasetWarning(f"the run was trained on {saved_n} training views and the dataset "
                                         f"{self.data} now has {n}: its test split may hold views the run trained on "
                                         "(a transforms_test.json removed or added since?)"), stacklevel=2)
            return
        what = self._views_mismatch()  # as many views, but not the same: another dataset at the run's path (battery
        if what is not None:  # 11: eval scored another object, 9.8 dB, into metrics.json without a word)
            raise self._other_views(path, what, "its renders and scores would be of another capture; point the run "
                                                "at the dataset it was made with (config.json's \"data\", or "
                                                "`triplet train --resume` with DATA), or start a new run")

    def _check_checkpoint(self, path, a: dict, meta: dict) -> None:
        """The checkpoint belongs to this configuration and this dataset's training views, and holds what it needs,
        finite."""
        order = meta.get("order")
        if not isinstance(order, list) or any(not isinstance(i, int) or isinstance(i, bool) or i < 0 for i in order):
            raise RunError(path, f"damaged: its view order must be a list of integers >= 0, found {str(order)[:60]}")
        self._resumed_from = (path, meta.get("train_views"))
        cams = np.asarray(a["views.cameras"], np.float64) if "views.cameras" in a else None
        self._resumed_id = (meta.get("train_views_id"), cams)
        saved = meta.get("config")
        if saved is not None:
            mine = {k: v for k, v in self.cfg.to_dict().items() if k not in RESUMABLE_FIELDS}
            # a field added since the checkpoint was written: its value when absent from a saved config matches
            # (its default; "color": "encoded", the pipeline of every run before the field existed)
            default = TrainConfig.from_dict({}).to_dict()

            def same(k):
                theirs = saved[k] if k in saved else default.get(k)
                if k == "density" and isinstance(theirs, dict):  # a density field added since: its default
                    theirs = TrainConfig.from_dict({"density": theirs}).to_dict()["density"]
                return json.dumps(mine.get(k), sort_keys=True) == json.dumps(theirs, sort_keys=True)

            diff = [k for k in sorted(mine) if not same(k)]
            if diff:
                shown = ", ".join(f"{k}: checkpoint {saved.get(k)!r}, config.json {mine.get(k)!r}" for k in diff[:4])
                raise RunError(path, f"belongs to another configuration ({shown}); start a new run with "
                                     "--overwrite or another --out")
        s = self.scene
        want = {"material": s.material.data.shape[1:], "alpha": s.alpha.data.shape[1:]}
        if s.light_params is not None:
            want["light_params"] = s.light_params.data.shape
        if s.vertex_sh is not None:
            want["vertex_sh"] = s.vertex_sh.data.shape[1:]
        for k, shape in want.items():
            if k not in a:
                raise RunError(path, f"belongs to another configuration: no {k!r} (config.json asks for it)")
            got = a[k].shape if k == "light_params" else a[k].shape[1:]
            if tuple(got) != tuple(shape):
                raise RunError(path, f"belongs to another configuration: {k!r} has shape {list(a[k].shape)}, "
                                     f"config.json needs {list(shape)} per row")
        if a["V"].ndim != 2 or a["V"].shape[1] != 3 or a["F"].ndim != 2 or a["F"].shape[1] != 3:
            raise RunError(path, f"damaged: V {list(a['V'].shape)}, F {list(a['F'].shape)} (expected [N, 3], [M, 3])")
        try:
            check_faces("its faces", a["F"], len(a["V"]))
        except ValueError as exc:
            raise RunError(path, f"damaged: {exc}") from None
        for k in ("V", "material", "alpha", "light_params", "vertex_sh"):
            if k in a and a[k].size and not np.isfinite(a[k]).all():
                raise RunError(path, f"holds {int((~np.isfinite(a[k])).sum())} NaN/Inf value(s) in {k!r}: resume "
                                     "from an earlier checkpoint (edit checkpoints/latest) or start again")
        missing = [f"opt.{g}.{j}.{m}" for g in meta["opt_hyper"] if g in self.opt.groups
                   for j in range(len(self.opt.groups[g].params)) for m in "mv" if f"opt.{g}.{j}.{m}" not in a]
        if missing or set(meta["opt_hyper"]) != set(self.opt.groups):
            extra = f"; missing {missing[:3]}" if missing else ""
            raise RunError(path, f"belongs to another configuration: optimizer groups {sorted(meta['opt_hyper'])}, "
                                 f"this run has {sorted(self.opt.groups)}{extra}")


def color_transfer(color: str, color_space: str, sensor_clip: bool = False) -> str | None:
    """The post-compositing transfer of a run's colour pipeline (``TrainConfig.color``) on a dataset whose
    images are ``color_space`` (``"srgb"`` or ``"linear"``); ``sensor_clip`` (``TrainConfig.sensor_clip``): the
    encoded colour saturates at 1, as the photo did."""
    if color == "linear" and color_space == "srgb":
        return "srgb-clip" if sensor_clip else "srgb"
    return None


def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o).__name__)


def _file_logger(path: Path) -> logging.Logger:
    log = logging.getLogger(f"triplet_cl.train.{path}")
    log.setLevel(logging.INFO)
    log.propagate = False
    if not log.handlers:
        try:
            h = logging.FileHandler(path)
        except OSError as exc:
            if exc.errno in (errno.EROFS, errno.EACCES) and path.is_file() and not os.access(path, os.W_OK):
                # a run on read-only storage, loaded to be rendered or relit elsewhere (a battery): nothing to log
                # into; the commands that write the run (train, extract, eval) check its folder is writable first
                quiet = logging.getLogger("triplet_cl.train.readonly")
                quiet.propagate = False
                if not quiet.handlers:
                    quiet.addHandler(logging.NullHandler())
                return quiet
            raise
        h.setFormatter(logging.Formatter("%(asctime)s %(message)s"))
        log.addHandler(h)
    return log
