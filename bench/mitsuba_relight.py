"""Relight an exported asset with an independent path tracer (Mitsuba 3, bench only) and score it against the
scene's relight references: how a user relighting our OBJ/GLB in another renderer would see it.

Why: ``triplet eval --relight`` relights with our own renderer, whose physics (direct light, cached shadows, the
learned AO, optionally one traced bounce) is the one the materials were fitted with. A path tracer has full
interreflection and no AO channel: materials that only our renderer's approximations explain relight worse there.
This renders the run's ``mesh.obj`` (its base-colour, roughness and metallic textures in Mitsuba's principled
BSDF, the same parameterisation as the references' renderer; GGX alpha = roughness², as ours) under every light
set of ``relight/relight.json`` (``bench/make_scene.py``'s emitters), through the test cameras, and prints the PSNR
of each set (images over white, as ``triplet eval --relight``) for each run, side by side.

    python bench/mitsuba_relight.py --scene /work/shared/data/scenes/spot --runs base=/tmp/a bounce=/tmp/b --views 8

Mitsuba is a bench-only peer, never a dependency of the package.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_scene import _emitters, srgb  # noqa: E402


def _mitsuba():
    for lib in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
        if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    return mi


def _read_rgba(path: Path) -> np.ndarray:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path), oiio.ImageSpec())
    img = inp.read_image("float")
    inp.close()
    if img.shape[2] == 3:
        img = np.concatenate([img, np.ones_like(img[..., :1])], 2)
    return img


def render_asset(mi, run: Path, lights: list, frames: list, res: int, fov: float, spp: int, envdir: Path):
    """``[V, H, W, 3]`` sRGB images over white of the run's exported mesh under ``lights``."""
    bsdf = {"type": "principled",
            "base_color": {"type": "bitmap", "filename": str(run / "mesh_basecolor.png")},  # sRGB-encoded
            "roughness": {"type": "bitmap", "filename": str(run / "mesh_roughness.png"), "raw": True},
            "metallic": {"type": "bitmap", "filename": str(run / "mesh_metallic.png"), "raw": True}}
    base = {"type": "scene", "integrator": {"type": "path", "max_depth": 4, "hide_emitters": True},
            "shape": {"type": "obj", "filename": str(run / "mesh.obj"), "bsdf": bsdf}}
    base.update(_emitters(mi, lights, envdir))
    out = []
    for k, fr in enumerate(frames):
        m = np.asarray(fr["transform_matrix"], float) @ np.diag([-1.0, 1.0, -1.0, 1.0])
        d = dict(base)
        d["sensor"] = {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(m.tolist()),
                       "sampler": {"type": "independent", "sample_count": spp, "seed": k},
                       "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba"}}
        img = np.asarray(mi.render(mi.load_dict(d)), np.float64)
        a = np.clip(img[..., 3:4], 0, 1)
        rgb = np.where(a > 1e-6, img[..., :3] / np.maximum(a, 1e-6), 0.0)
        out.append(srgb(rgb) * a + (1 - a))
    return np.stack(out)


def psnr(a, b) -> float:
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return 10 * math.log10(1 / mse) if mse > 0 else float("inf")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", required=True, type=Path, help="the dev scene (its relight/ and transforms_test.json)")
    ap.add_argument("--runs", nargs="+", required=True, help="LABEL=RUN_DIR (each with the exported mesh.obj)")
    ap.add_argument("--views", type=int, default=8, help="the first N test views")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--out", type=Path, help="append the table to this file")
    args = ap.parse_args(argv)
    mi = _mitsuba()
    scene = args.scene.resolve()
    data = scene.parents[1]
    spec = json.loads((scene / "relight" / "relight.json").read_text())
    tj = json.loads((scene / "transforms_test.json").read_text())
    frames = tj["frames"][: args.views]
    res = int(json.loads((scene / "ground_truth.json").read_text())["res"])
    fov = float(np.degrees(tj["camera_angle_x"]))
    sets = list(spec["sets"])
    refs = {}
    for name, st in spec["sets"].items():
        ims = [_read_rgba(scene / "relight" / st["images"] / (Path(f["file_path"]).name + ".png")) for f in frames]
        refs[name] = np.stack([im[..., :3] * im[..., 3:] + (1 - im[..., 3:]) for im in ims])
    lines = [f"# bench/mitsuba_relight.py {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} scene={scene.name} "
             f"views={len(frames)} spp={args.spp} (Mitsuba 3 path tracer, max_depth 4, principled BSDF)",
             "| run | " + " | ".join(sets) + " | mean | seconds |", "|---|" + "---|" * (len(sets) + 2)]
    print("\n".join(lines), flush=True)
    for item in args.runs:
        label, run = item.split("=", 1)
        t = time.perf_counter()
        ps = []
        for name, st in spec["sets"].items():
            lights = [dict(lt) for lt in st["lights"]]
            img = render_asset(mi, Path(run), lights, frames, res, fov, args.spp, data / "envmaps")
            ps.append(float(np.mean([psnr(a, b) for a, b in zip(img, refs[name], strict=True)])))
        row = f"| {label} | " + " | ".join(f"{p:.2f}" for p in ps) + f" | {np.mean(ps):.2f} | " \
              f"{time.perf_counter() - t:.0f} |"
        lines.append(row)
        print(row, flush=True)
    if args.out:
        with open(args.out, "a") as f:
            f.write("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
