"""Re-render a dev scene's capture under another *training* light set with Mitsuba 3 (bench only).

Why: the dev scenes are lit by one point light (spot, gadget) or one environment (bob_env); the
held-out scenes use other light setups (several point lights, sun and sky, environments). A light
model chosen on two setups is a guess for the others. This renders the same object, material and
cameras as ``SCENE`` under a new training light set, so the scene's ``relight/`` references (test
cameras under three fixed light sets, and the albedo) stay valid for the new capture: the relight
and albedo scores then measure how well training *decomposes* under lights it was not told about.

    python bench/make_scene.py /work/shared/data/scenes/spot_small --lights two_points --out /tmp/spot2p
    python bench/make_scene.py SCENE --lights original --out /tmp/check   # fidelity check vs the shipped images

Light sets (``LIGHT_SETS``; Mitsuba 3 units, see ``relight/relight.json``'s conventions):
``original`` (the scene's own ground_truth.json lights), ``relight:SET`` (a set of the scene's
relight.json: checks the emitter conventions against its references), ``two_points``, ``sun_sky``, ``env``.
``--light-scale S`` multiplies every emitter of the set (the same capture brighter or dimmer).
Writes ``transforms_{train,test}.json``, ``train/``, ``test/`` (RGBA PNG, straight alpha, sRGB),
``ground_truth.json`` (the new lights) and a symlink ``relight -> SCENE/relight``.
Mitsuba is a bench-only peer, never a dependency of the package.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

LIGHT_SETS = {
    # two white-ish point lights, left-front and right-back, unequal, a dim fill
    "two_points": [
        {"type": "point", "position": [2.2, 2.6, 2.0], "intensity": [20.0, 19.0, 18.0]},
        {"type": "point", "position": [-2.6, 1.0, -1.8], "intensity": [11.0, 11.5, 12.5]},
        {"type": "constant", "radiance": [0.05, 0.05, 0.05]},
    ],
    # a sun from above-front-left and a blue-ish sky
    "sun_sky": [
        {"type": "directional", "direction": [-0.35, -0.85, -0.4], "irradiance": [2.4, 2.3, 2.1]},
        {"type": "constant", "radiance": [0.10, 0.12, 0.16]},
    ],
    # the HDR environment of bob_env, rotated
    "env": [{"type": "envmap", "filename": "overcast_soil_puresky_1k.hdr", "rotate_y_deg": 60.0, "scale": 1.0}],
}


def _emitters(mi, lights, envdir: Path):
    out = {}
    for i, lt in enumerate(lights):
        t = lt["type"]
        if t == "point":
            d = {"type": "point", "position": lt["position"],
                 "intensity": {"type": "rgb", "value": _rgb(lt["intensity"])}}
        elif t == "directional":
            d = {"type": "directional", "direction": lt["direction"],
                 "irradiance": {"type": "rgb", "value": _rgb(lt["irradiance"])}}
        elif t == "constant":
            d = {"type": "constant", "radiance": {"type": "rgb", "value": _rgb(lt["radiance"])}}
        elif t == "envmap":
            fn = Path(lt["filename"])
            fn = fn if fn.is_absolute() else envdir / fn.name
            d = {"type": "envmap", "filename": str(fn), "scale": float(lt.get("scale", 1.0)),
                 "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], float(lt.get("rotate_y_deg", 0.0)))}
        else:
            raise ValueError(f"light {i}: unknown type {t!r}")
        out[f"emitter_{i}"] = d
    return out


def scaled_light(lt: dict, s: float) -> dict:
    """A light of the light-set format with its radiometric value (intensity, irradiance, radiance, scale) x ``s``."""
    out = dict(lt)
    for k in ("intensity", "irradiance", "radiance"):
        if k in out:
            out[k] = (np.asarray(out[k], float) * s).tolist()
    if out["type"] == "envmap":
        out["scale"] = float(out.get("scale", 1.0)) * s
    return out


def _rgb(v):
    a = np.broadcast_to(np.asarray(v, float), 3)
    return [float(x) for x in a]


def _gt_lights(gt: dict) -> list:
    """The scene's own lights (ground_truth.json) in the light-set format above."""
    out = []
    for lt in gt["lights"]:
        lt = dict(lt)
        if lt["type"] == "envmap":
            lt["filename"] = Path(lt["filename"]).name
        out.append(lt)
    if gt.get("ambient", 0.0):
        out.append({"type": "constant", "radiance": gt["ambient"]})
    return out


def srgb(x):
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def render_split(mi, scene_dict_base, frames, res, fov_deg, spp, out_dir: Path):
    import OpenImageIO as oiio

    out_dir.mkdir(parents=True, exist_ok=True)
    for k, fr in enumerate(frames):
        c2w = np.asarray(fr["transform_matrix"], float)
        # NeRF / Blender camera (looks down -Z, +Y up) -> Mitsuba's (looks down +Z, +Y up, +X left)
        m = c2w @ np.diag([-1.0, 1.0, -1.0, 1.0])
        d = dict(scene_dict_base)
        d["sensor"] = {
            "type": "perspective", "fov": fov_deg, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(m.tolist()),
            "sampler": {"type": "independent", "sample_count": spp, "seed": k},
            "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba"},
        }
        img = np.asarray(mi.render(mi.load_dict(d)), dtype=np.float64)  # [H, W, 4] premultiplied linear
        a = np.clip(img[..., 3:4], 0.0, 1.0)
        rgb = np.where(a > 1e-6, img[..., :3] / np.maximum(a, 1e-6), 0.0)
        px = np.concatenate([srgb(rgb), a], axis=-1)
        u8 = np.round(px * 255.0).astype(np.uint8)
        name = Path(fr["file_path"]).name + ".png"
        spec = oiio.ImageSpec(res, res, 4, oiio.UINT8)
        spec.attribute("oiio:UnassociatedAlpha", 1)
        tmp = out_dir / (name + ".tmp.png")
        o = oiio.ImageOutput.create(str(tmp))
        o.open(str(tmp), spec)
        o.write_image(u8)
        o.close()
        os.replace(tmp, out_dir / name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--lights", required=True, help=f"original or one of {sorted(LIGHT_SETS)}")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--light-scale", type=float, default=1.0, help="every emitter of the light set x this factor (the "
                    "same capture brighter or dimmer: does the recovered albedo keep its level, or the lights theirs?)")
    ap.add_argument("--roughness", type=float, help="override the scene's roughness")
    ap.add_argument("--metallic", type=float, help="override the scene's metallic (the relight/ references are then "
                    "re-rendered with the new material under each set, the albedo linked)")
    ap.add_argument("--limit", type=int, help="render only the first N views of each split (fidelity checks)")
    ap.add_argument("--face-normals", action="store_true", help="shade with the mesh's face normals (Mitsuba's obj "
                    "default interpolates vertex normals: a coarse CAD mesh such as gadget's then shades flat faces "
                    "as curved ones); the relight/ references are re-rendered the same way")
    args = ap.parse_args(argv)

    for lib in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
        if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib  # Debian's libllvm19 (older LLVMs cannot select fminimum)
    import mitsuba as mi

    mi.set_variant("llvm_ad_rgb")
    scene = args.scene.resolve()
    data = scene.parents[1]
    gt = json.loads((scene / "ground_truth.json").read_text())
    if args.lights == "original":
        lights = _gt_lights(gt)
    elif args.lights.startswith("relight:"):  # a relight set's lights: checks the emitter conventions
        lights = json.loads((scene / "relight" / "relight.json").read_text())["sets"][args.lights[8:]]["lights"]
    else:
        lights = LIGHT_SETS[args.lights]
    if args.light_scale != 1.0:
        lights = [scaled_light(lt, args.light_scale) for lt in lights]
    rough = gt["roughness"] if args.roughness is None else args.roughness
    metal = gt["metallic"] if args.metallic is None else args.metallic
    tex = next((data / "meshes").rglob(gt["texture"]))
    base = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4, "hide_emitters": True},
        "shape": {"type": "obj", "filename": str(scene / "gt_mesh.obj"), "face_normals": bool(args.face_normals),
                  "bsdf": {"type": "principled", "roughness": rough, "metallic": metal,
                           "base_color": {"type": "bitmap", "filename": str(tex)}}},
    }
    base.update(_emitters(mi, lights, data / "envmaps"))
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    for split in ("train", "test"):
        tj = json.loads((scene / f"transforms_{split}.json").read_text())
        frames = tj["frames"][: args.limit] if args.limit else tj["frames"]
        res = int(gt["res"])
        fov = float(np.degrees(tj["camera_angle_x"]))
        render_split(mi, base, frames, res, fov, args.spp, out / split)
        (out / f"transforms_{split}.json").write_text(json.dumps({**tj, "frames": frames}, indent=1))
        print(f"{split}: {len(frames)} views at {res}² in {time.time() - t0:.0f} s", flush=True)
    new_gt = dict(gt, roughness=rough, metallic=metal, ambient=0.0, lights=lights, face_normals=bool(args.face_normals),
                  renderer=f"Mitsuba 3 path tracer (max_depth 4, {args.spp} spp), principled BSDF "
                           "(bench/make_scene.py)")
    (out / "ground_truth.json").write_text(json.dumps(new_gt, indent=1))
    for f in ("gt_mesh.ply", "gt_mesh.obj"):
        if not (out / f).exists():
            (out / f).symlink_to(scene / f)
    if metal == gt["metallic"] and rough == gt["roughness"] and not args.face_normals:
        if not (out / "relight").exists():
            (out / "relight").symlink_to(scene / "relight")
    else:  # another material: the relight references change with it (the albedo does not)
        render_relight(mi, base, scene, data, out, args.spp, args.limit)
        print(f"relight: re-rendered with roughness {rough}, metallic {metal}, face normals {args.face_normals} in "
              f"{time.time() - t0:.0f} s", flush=True)
    return 0


def render_relight(mi, base: dict, scene: Path, data: Path, out: Path, spp: int, limit) -> None:
    """``out/relight/``: the scene's relight sets rendered with ``base``'s object and material (the new one),
    the albedo folder linked, environment file names made absolute."""
    spec = json.loads((scene / "relight" / "relight.json").read_text())
    rdir = out / "relight"
    rdir.mkdir(parents=True, exist_ok=True)
    tj = json.loads((scene / "transforms_test.json").read_text())
    frames = tj["frames"][:limit] if limit else tj["frames"]
    gt = json.loads((scene / "ground_truth.json").read_text())
    fov = float(np.degrees(tj["camera_angle_x"]))
    obj = {k: v for k, v in base.items() if not k.startswith("emitter_")}
    for st in spec["sets"].values():
        for lt in st["lights"]:
            if lt["type"] == "envmap":
                lt["filename"] = str(next((data / "envmaps").rglob(Path(lt["filename"]).name)))
        render_split(mi, {**obj, **_emitters(mi, st["lights"], data / "envmaps")}, frames, int(gt["res"]), fov,
                     spp, rdir / st["images"])
    spec["cameras"] = str((out / "transforms_test.json").resolve())
    (rdir / "relight.json").write_text(json.dumps(spec, indent=1))
    if not (rdir / spec["albedo"]).exists():
        (rdir / spec["albedo"]).symlink_to(scene / "relight" / spec["albedo"])


if __name__ == "__main__":
    sys.exit(main())
