"""``triplet`` — the command line. Parses arguments into config dataclasses and calls the library."""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import shlex
import shutil
import sys
import time
from pathlib import Path

from triplet_cl import __version__
from triplet_cl.datasets import FORMATS as DATASET_FORMATS
from triplet_cl.errors import TripletError, UsageError
from triplet_cl.lights import LIGHT_KINDS
from triplet_cl.materials import BRDFS, DEFAULT_BRDF, brdf_from_cli
from triplet_cl.validate import DeprecatedAlias, os_error_message, validate_args


def _gib(n: int) -> str:
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"


def _env_spec() -> str:
    return os.environ.get("TRIPLET_DEVICE", "").strip()


def demo_data_path() -> Path:
    """The small dataset shipped inside the package (Spot, 40 + 8 views at 96²)."""
    import triplet_cl

    return Path(triplet_cl.__file__).resolve().parent / "data" / "spot_small"


# ---------------------------------------------------------------------------------------------- devices


def cmd_devices(args: argparse.Namespace) -> int:
    """List every OpenCL platform/device and mark the one that would be chosen."""
    from triplet_cl.device import list_devices, resolve_spec

    infos = list_devices()
    chosen, _, _ = resolve_spec(args.device)
    header = f"{'':2}{'P:D':5} {'type':5} {'CUs':>4} {'global':>9} {'max alloc':>9} {'fp64':4}  {'OpenCL C':18} device"
    print(header)
    for info in infos:
        mark = "*" if info.index == chosen.index else " "
        print(
            f"{mark:2}{info.index:5} {info.type:5} {info.compute_units:4d} {_gib(info.global_mem_bytes):>9} "
            f"{_gib(info.max_alloc_bytes):>9} {'yes' if info.fp64 else 'no':4}  "
            f"{info.opencl_c_version[:18]:18} {info.platform_name} / {info.device_name}"
        )
    how = "--device" if args.device else ("$TRIPLET_DEVICE" if _env_spec() else "default: first GPU, else first CPU")
    print(f"\n* chosen: {chosen.index} {chosen.platform_name} / {chosen.device_name} ({how})")
    return 0


# ---------------------------------------------------------------------------------------------- train


def _config_from_args(args: argparse.Namespace):
    from dataclasses import replace

    from triplet_cl.train import TrainConfig

    cfg = TrainConfig()
    over = {}
    if args.seed is not None:
        over["seed"] = args.seed
    if args.brdf:
        over["brdf"] = brdf_from_cli(args.brdf)
    if args.lights:
        items = tuple(x.strip() for x in args.lights.split(","))
        if not all(items):
            raise ValueError(f"--lights: an empty item in {args.lights!r}: expected a comma-separated mix of "
                             f"{', '.join(LIGHT_KINDS)}")
        over["lights"] = items
    if args.sh_degree is not None:
        over["sh_degree"] = args.sh_degree
    if args.light_distance is not None:
        over["light_distance"] = args.light_distance
    if args.light_min_distance is not None:
        over["light_min_distance"] = args.light_min_distance
    if args.sensor_clip is not None:
        over["sensor_clip"] = args.sensor_clip == "on"
    if args.faces_per_pixel is not None:
        over["faces_per_pixel"] = args.faces_per_pixel
    if args.init_points is not None:
        over["init_points"] = args.init_points
    if args.background:
        over["background"] = args.background
    if args.downscale is not None:
        over["downscale"] = args.downscale
    if args.sigma is not None:
        over["sigma"] = None if args.sigma <= 0 else args.sigma
    if args.checkpoint_every is not None:
        over["checkpoint_every"] = args.checkpoint_every
    if args.keep_checkpoints is not None:
        over["keep_checkpoints"] = args.keep_checkpoints
    if args.renderer:
        over["renderer"] = args.renderer
    if getattr(args, "shadows", None):
        over["shadows"] = args.shadows
    if getattr(args, "shadow_every", None) is not None:
        over["shadow_every"] = args.shadow_every
    if getattr(args, "background_shell", None) is not None:
        over["background_shell"] = args.background_shell
    if getattr(args, "color", None):
        over["color"] = args.color
    if getattr(args, "priors", None):
        from triplet_cl.priors import LIGHT_WEIGHTS, MATERIAL_WEIGHTS, Priors

        over.update(Priors.off())
        if args.priors in ("lights", "all"):
            over.update(LIGHT_WEIGHTS)
        if args.priors in ("materials", "all"):
            over.update(MATERIAL_WEIGHTS)
    cfg = replace(cfg, **over)
    if args.iterations is not None:  # every schedule follows the run's length (TrainConfig.with_iterations)
        cfg = cfg.with_iterations(args.iterations)
    if args.max_faces is not None:
        cfg.density = replace(cfg.density, max_faces=args.max_faces)
    ratio = getattr(args, "error_resplit_ratio", None)  # a number or "off" (validate_args parsed it)
    if ratio is not None:
        cfg.density = replace(cfg.density, error_resplit_ratio=None if ratio == "off" else ratio)
    if getattr(args, "white_light", None):
        cfg = replace(cfg, white_light=args.white_light)
    if getattr(args, "light_phase_lobes", None):
        cfg = replace(cfg, light_phase_lobes=args.light_phase_lobes)
    if getattr(args, "blinn_phong_ka", None):
        cfg = replace(cfg, blinn_phong_ka=args.blinn_phong_ka)
    if getattr(args, "light_phase", None) is not None:  # after --iterations: the value given, not scaled
        cfg = replace(cfg, material_tie_until=args.light_phase)
    return cfg


def cmd_train(args: argparse.Namespace) -> int:
    from triplet_cl.device import get_device
    from triplet_cl.train import Trainer

    if args.demo:
        data = demo_data_path()
        out = Path(args.out or "runs/demo")
        if args.iterations is None and not args.resume:
            from triplet_cl.train import DEMO_ITERATIONS

            args.iterations = DEMO_ITERATIONS
    else:
        if not args.data and not args.resume:
            print("triplet train: error: give a DATA folder (or --demo)", file=sys.stderr)
            return 2
        data = args.data
        out = Path(args.out) if args.out else None
        if out is None:
            print("triplet train: error: --out RUN is required", file=sys.stderr)
            return 2
    mesh_cfg = _mesh_config_from_args(args) if args.mesh_stage else None  # bad options fail before training
    if mesh_cfg is not None and out.is_dir() and not args.overwrite:  # --overwrite moves the old run aside
        from triplet_cl.validate import check_mesh_outputs

        check_mesh_outputs(out, mesh_cfg.formats)
    if (out / "config.json").is_file():  # an existing run: not while another process writes it
        from triplet_cl.runs import lock_run

        lock_run(out)
    dev = get_device(args.device)
    if args.resume:
        from triplet_cl.runs import config_from_saved, read_run_config
        from triplet_cl.validate import check_resume_iterations, resume_config, resume_data

        saved = read_run_config(out)
        cfg, notes = resume_config(args, config_from_saved(out, saved), _config_from_args(args))
        data, moved = resume_data(data if args.data or args.demo else None, saved["data"], out)
        notes += moved
        tr = Trainer(data, out, cfg, device=dev, resume=True)
        check_resume_iterations("--iterations", tr.cfg.iterations, tr.it)
        tr.check_resumable()
        from triplet_cl.datasets.base import render_files
        from triplet_cl.validate import check_output_slots

        tests = render_files(tr.ds["test"][: tr.cfg.max_test_views or None])
        check_output_slots(out, ["config.json", "train.log", "metrics.json", "lights.json", "triplets.ply",
                                 *[f"renders/test/{n}" for n in tests]], "training")
        _check_bbox_seen(mesh_cfg, tr)
        if notes:  # the dataset's new place and the options changed: config.json says what the run now is
            from triplet_cl.io import write_json

            write_json(out / "config.json", {**saved, "data": tr.data, "train": tr.cfg.to_dict()})  # data: absolute
        print(f"triplet train: resuming at iteration {tr.it}" + (f"; applying {', '.join(notes)}" if notes else ""))
    else:
        from triplet_cl.runs import replacing_run

        cwd_inside = None
        if args.overwrite:  # the paths as they are now: replacing moves the old run (and a cwd inside it) aside
            out = out.resolve()  # a link to a run: the run it names is replaced, the link kept
            data = os.path.abspath(data) if data else data  # ".." folded now: the run it goes through moves
            here = Path.cwd()
            cwd_inside = here.relative_to(out) if here.is_relative_to(out) else None
        with replacing_run(out, args.overwrite):  # the old run is deleted only once the new one has started
            made = _first_missing(out)  # what the trainer creates: the folder (and missing parents), or nothing
            empty = out.is_dir() and not any(out.iterdir())
            if made is not None:  # a new folder, claimed at once (two trains started together into one new --out
                # both ran into it: config.json of one, the checkpoints of the other)
                out.parent.mkdir(parents=True, exist_ok=True)
                try:
                    out.mkdir()
                except FileExistsError:
                    from triplet_cl.errors import UsageError

                    raise UsageError("--out", f"{out} was created meanwhile (another `triplet train` into the same "
                                              "folder?): choose another --out") from None
            from triplet_cl.runs import lock_run

            lock_run(out)  # the new run's own lock (an --overwrite's old one stays held, aside); refused: nothing done
            if made is None and not (empty and not any(out.iterdir())):  # filled meanwhile by another process
                from triplet_cl.errors import UsageError

                raise UsageError("--out", f"{out} was filled meanwhile (another `triplet train` into the same "
                                          "folder?): choose another --out (nothing was touched)")
            tr = None
            try:
                tr = Trainer(data, out, _config_from_args(args), device=dev, data_format=args.data_format)
                _check_bbox_seen(mesh_cfg, tr)  # needs the dataset's cameras, which the trainer has just read
            except BaseException:  # nothing of the run it had started stays: nothing there was the user's
                if tr is not None:
                    tr.close_log()
                if made is not None:  # the folder claimed above (and its new parents)
                    shutil.rmtree(made, ignore_errors=True)
                elif empty:
                    for p in out.iterdir():
                        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink()
                raise
            if cwd_inside is not None and (out / cwd_inside).is_dir():
                os.chdir(out / cwd_inside)  # the old folder is about to go: the process stays in the new run
    print(f"triplet train: {tr.ds.summary()}\n  device: {dev.name}\n  run: {out}  "
          f"({len(tr.scene.F)} initial triplets, {tr.cfg.iterations} iterations)")
    for note in (tr.background_note, tr.shell_note, tr.downscale_note):
        if note:
            print(f"  {note}")
    if not args.resume and args.overwrite and cwd_inside is not None:  # the shell's folder is the deleted old run
        print(f"  note: your shell's working folder was inside the old run, which --overwrite replaces: run `cd "
              f"{out / cwd_inside}` (or `cd .`) afterwards to be in the new one")
    if getattr(args, "init_points", None) is not None and not args.resume:
        from triplet_cl.train import MIN_INIT_POINTS, num_sfm_points

        if num_sfm_points(tr.ds) >= MIN_INIT_POINTS:  # (battery 10: ignored without a word)
            print(f"  --init-points {args.init_points} unused: the soup starts from the dataset's "
                  f"{num_sfm_points(tr.ds)} SfM points (one triangle each)")
    try:
        _raise_if_terminated()
        metrics = tr.train()
    except KeyboardInterrupt:
        print(f"\ninterrupted at iteration {tr.it}: checkpoint saved in {out / 'checkpoints'}; "
              f"continue with: triplet train --resume --out {shlex.quote(str(out))}", file=sys.stderr)
        return _interrupted_status()
    if args.save_train_renders:
        try:
            tr.evaluate("train", write_renders=True)
        except KeyboardInterrupt:  # (battery 11: a bare "interrupted", the renders 3 of 40)
            print(f"\ninterrupted after training: the run is complete (metrics.json, triplets.ply, checkpoints), its "
                  f"training renders may not be: write them with: triplet render {shlex.quote(str(out))} --split "
                  "train", file=sys.stderr)
            return _interrupted_status()
    print(f"done: test PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}, {metrics['faces']} triplets, "
          f"{metrics.get('wall_time_s', 0):.0f} s")
    from triplet_cl.mesh.refine import MESH_STATE

    kept = "" if (out / MESH_STATE).is_file() else "lights.json, "  # a mesh stage's lights.json is kept
    print(f"results in {out}/: triplets.ply, {kept}renders/test/, metrics.json, checkpoints/, train.log")
    mesh = metrics.get("mesh")
    stale = mesh.get("stale") if isinstance(mesh, dict) else None
    if stale and not args.mesh_stage:  # a resumed run with a mesh stage (battery 11: its metrics, lights replaced)
        print(f"warning: the run's mesh (mesh_stage.npz, mesh.*, lights.json) was made from the soup at iteration "
              f"{stale['made_from_iterations']}, not from this one ({stale['soup_iterations']}): it is kept as it "
              f"was (metrics.json's \"mesh\" marked stale); remake it with: triplet extract "
              f"{shlex.quote(str(out))}", file=sys.stderr)
    if args.mesh_stage:
        return _run_mesh_stage(tr, mesh_cfg, args)
    return 0


def _load_run(args):
    from triplet_cl.device import get_device
    from triplet_cl.train import Trainer

    tr = Trainer(None, Path(args.run), device=get_device(args.device), resume=True, quiet=True)
    tr.view_progress = True  # quiet (no training bar, no notes), but a bar per rendered view on a terminal
    if tr.it < tr.cfg.iterations:  # (battery 11: extract, eval and render used a stopped soup without a word)
        print(f"warning: {args.run}: training stopped at iteration {tr.it} of {tr.cfg.iterations} (interrupted?): "
              f"this is the unfinished soup; finish it with: triplet train --resume --out "
              f"{shlex.quote(str(args.run))}", file=sys.stderr)
    return tr


def _lock_if_writing_into(run, writes: bool) -> None:
    """A command that writes into the run (eval's metrics.json, render's and relight's default folders) takes its
    lock first: an `eval` beside a running `extract` wrote its metrics.json over the mesh stage's, whose results
    were lost (battery 8); refused instead, as train, extract and export are."""
    if writes and Path(run).is_dir():
        from triplet_cl.runs import lock_run

        lock_run(run, "RUN")


def cmd_render(args: argparse.Namespace) -> int:
    _lock_if_writing_into(args.run, not args.out)
    tr = _load_run(args)
    tr.warn_if_dataset_changed()
    if args.renderer:
        tr.cfg.renderer = args.renderer
    out = Path(args.out) if args.out else Path(args.run) / "renders" / args.split
    from triplet_cl.validate import check_render_out

    check_render_out(tr, args.split, out, "--out" if args.out else "RUN")
    m = tr.evaluate(args.split, write_renders=True, out_dir=out)
    print(f"rendered {len(m['views'])} {args.split} views to {out} (PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f})")
    return 0


def cmd_eval(args: argparse.Namespace) -> int:

    from triplet_cl.io import write_json

    run = Path(args.run)
    spec = None
    if args.relight:
        spec = Path(args.relight)
        spec = spec / "relight.json" if spec.is_dir() else spec
        if not spec.is_file():
            raise FileNotFoundError(f"--relight {args.relight}: expected a folder holding relight.json (or the file "
                                    f"itself); {spec} does not exist")
        from triplet_cl.relight import load_light_sets

        load_light_sets(spec, args.env_degree)  # a bad light file fails before any rendering
    from triplet_cl.runs import read_metrics

    path = run / "metrics.json"
    if run.is_dir():
        from triplet_cl.validate import check_output_slots

        check_output_slots(run, ["metrics.json"], "eval")
    _lock_if_writing_into(run, True)
    old = read_metrics(run, "eval")  # before any work: a damaged file is named, not met after the evaluation
    tr = _load_run(args)
    tr.warn_if_dataset_changed()
    if spec is not None:
        from triplet_cl.mesh.refine import MESH_STATE, load_mesh_state
        from triplet_cl.relight import check_references, check_vertex_sh

        if (run / MESH_STATE).is_file():
            load_mesh_state(run / MESH_STATE)  # a damaged mesh stage is named before the soup is evaluated

        tv = tr.ds["test"][: tr.cfg.max_test_views or None]
        check_references(spec, [v.name for v in tv], args.env_degree, [(v.camera.width, v.camera.height) for v in tv],
                         writes_out=args.out is not None, cameras=[v.camera for v in tv])
        check_vertex_sh(load_light_sets(spec, args.env_degree), tr.scene.vertex_sh is not None)
    m = tr.evaluate("test")
    m.update({"iterations": tr.it, "faces": len(tr.scene.F)})
    merged = {**old, **m}  # the other sections ("mesh", timings, "relight") stay
    print(f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} over {len(m['views'])} views")
    if spec is not None:
        from triplet_cl.relight import Relighter, evaluate_relight

        stages = ["soup"] + (["mesh"] if (run / "mesh_stage.npz").is_file() else [])
        if args.out:
            from triplet_cl.datasets.base import render_files
            from triplet_cl.relight import load_light_sets as _sets

            names = render_files(tr.ds["test"][: tr.cfg.max_test_views or None])
            _check_image_outs([Path(args.out) / st / ls.name for st in stages for ls in _sets(spec, args.env_degree)]
                              + [Path(args.out) / st / "albedo" for st in stages], names, "--out", tr.ds.root)
        rel = dict(merged.get("relight") or {})
        for stage in stages:
            rl = Relighter(tr, stage, args.renderer, args.shadows)
            out_dir = Path(args.out) / stage if args.out else None
            r = evaluate_relight(rl, spec.parent, args.env_degree, out_dir)
            rel[stage] = r
            sets = ", ".join(f"{k} {v['psnr']:.2f} dB" for k, v in r["sets"].items())
            alb = r.get("albedo")
            alb = f"; albedo {alb['psnr_raw']:.2f} / {alb['psnr_scaled']:.2f} dB (raw / scaled)" if alb else ""
            print(f"relight ({stage}, {rl.renderer}, shadows {rl.shadows_used}): {sets}{alb}")
        merged["relight"] = rel
    write_json(path, merged)
    print(f"-> {path}")
    return 0


def _check_image_outs(outs, names, option: str, dataset) -> None:
    """Image folders triplet writes: not in the dataset, no file of the user replaced; then recorded as triplet's."""
    from triplet_cl.runs import mark_output_dir
    from triplet_cl.validate import check_not_in_dataset, check_output_files

    for out in outs:
        check_not_in_dataset(out, option, dataset)
        check_output_files(out, names, option)
    for out in outs:
        mark_output_dir(out, names)


def cmd_relight(args: argparse.Namespace) -> int:
    from triplet_cl.relight import Relighter, check_vertex_sh, load_light_sets, relight_run

    sets = load_light_sets(args.light_file, args.env_degree)  # a bad light file fails before the run is loaded
    run = Path(args.run)
    if args.out is not None and Path(args.out).is_file():
        raise ValueError(f"--out {args.out} is a file; expected a folder")
    _lock_if_writing_into(run, args.out is None)
    tr = _load_run(args)
    tr.warn_if_dataset_changed()  # another capture at the run's path is refused (battery 11)
    rl = Relighter(tr, args.stage, args.renderer, args.shadows)
    # the default folder of a split other than test is the split's own (battery 9: `--split train` then `--split
    # test` mixed both splits' r_0.png ... in RUN/relight/SET/), as render's renders/SPLIT/
    base = Path(args.out) if args.out else run / "relight" / ("" if args.split == "test" else args.split)
    if not args.out and args.split == "test":
        clash = [ls.name for ls in sets if ls.name in ("train", "val")]
        if clash:  # RUN/relight/train/ is the train split's folder of sets
            raise UsageError("--lights", f"the set {clash[0]!r} would write the test views into RUN/relight/"
                                         f"{clash[0]}/, the {clash[0]} split's folder of relit sets: give --out DIR")
    outs = [base / ls.name if (len(sets) > 1 or not args.out) else base for ls in sets]
    check_vertex_sh(sets, rl.base.vertex_sh is not None)
    from triplet_cl.datasets.base import render_files

    names = render_files(rl.views(args.split))
    _check_image_outs(outs, names, "--out" if args.out else "RUN", tr.ds.root)  # every set's, before any work
    from collections import Counter

    for ls, out in zip(sets, outs, strict=True):
        paths = relight_run(rl, ls, out, args.split)
        # each kind once, with its count (5000 lights printed a 60 kB line, battery 8)
        count = Counter(type(lt).__name__ for lt in ls.lights)
        kinds = ", ".join(k if n == 1 else f"{n} x {k}" for k, n in count.items())
        print(f"relit {len(paths)} {args.split} views of the {rl.stage_name} under {ls.name!r} ({kinds}; "
              f"{rl.renderer}) -> {out}")
    return 0


# ---------------------------------------------------------------------------------------------- mesh phase


def _add_mesh_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh-method", choices=["tsdf", "weld"], help="soup → mesh: TSDF fusion + marching cubes "
                   "(default) or welding of coincident vertices")
    p.add_argument("--mesh-resolution", type=_int, help="TSDF voxels along the longest side (default: a voxel ≈ a "
                   "pixel of the training views)")
    p.add_argument("--mesh-faces", type=_int, help="simplify the extracted mesh to at most this many faces "
                   "(default 50000)")
    p.add_argument("--mesh-rounds", type=_int, help="extraction → refinement rounds (default 1)")
    p.add_argument("--mesh-iterations", type=_int, help="refinement steps per round (default 600; 0 = extract only)")
    p.add_argument("--mesh-light-phase", type=_int, metavar="N", help="the first N refinement steps of a round keep "
                   "roughness, metallic and AO one value for the whole mesh (started at their mean), the lights "
                   "learning; then per vertex (default 300; 0 = none; at most --mesh-iterations)")
    p.add_argument("--mesh-metallic-trial", type=_int, metavar="N", help="before the light phase, fit the mesh "
                   "as a dielectric and as a metal for N steps each and keep the better one's metallic, held "
                   "through the light phase (default 200; 0 = none: the metallic is tied with the others; "
                   "Cook-Torrance only, and only with a light phase: --mesh-light-phase > 0)")
    p.add_argument("--mesh-ao", choices=["auto", "learned", "computed"], help="Cook-Torrance's ambient occlusion on "
                   "the mesh: learned per vertex, or computed: traced from the mesh's geometry and held, or auto "
                   "(default): computed where the AO the soup learned follows the traced occlusion (rank correlation "
                   "at least 0.15), else learned (no effect with blinn-phong)")
    p.add_argument("--mesh-light-fit", choices=["auto", "off"], help="read the lights again from the extracted "
                   "mesh's shading (a metal's: from its highlights) before its light phase (auto, default: when the "
                   "lights are point and ambient ones; kept when clearly better than the soup's, the number of point "
                   "lights, up to 3, is then the data's) or keep the soup's (off)")
    p.add_argument("--mesh-env-degree", type=_int, metavar="D", help="after the light fit, the ambient light becomes "
                   "an SH environment of degree D (the same radiance in band 0, the higher bands learned: a sky "
                   "brighter above than below, a room); default 2, 0 = keep the ambient light (Cook-Torrance only); "
                   "also a metal's unless --mesh-env-degree-metal is given")
    p.add_argument("--mesh-env-degree-metal", type=_int, metavar="D", help="the same for a metal (the metallic trial's "
                   "verdict): its reflections keep the environment's higher bands; default 8 (or --mesh-env-degree's D "
                   "when that is given)")
    p.add_argument("--mesh-env-occlusion", type=_int, metavar="D", help="the SH environment is occluded by the mesh "
                   "itself: its bands 1..D see only the sky each vertex sees (traced from the geometry when its faces "
                   "change); default 0 = off, at most 4")
    p.add_argument("--mesh-metal-f0", type=float, metavar="F", help="a metal's brightness gauge: its lights are "
                   "scaled so that the median F0 (luminance) they imply is F, when fitted and at the end of each "
                   "round (default 0.75, the median of measured metals' F0; 0 = the F0 the soup left; only for an "
                   "object the metallic trial finds metal)")
    p.add_argument("--mesh-bounce", choices=["traced", "off"], help="interreflection on the mesh: traced (one diffuse "
                   "bounce of the lights off the rest of the mesh, per vertex, re-traced with the cast shadows) "
                   "or off (default)")
    p.add_argument("--remesh-every", type=_int, help="steps between gradient-driven subdivision / simplification "
                   "(default 200; 0 = never)")
    p.add_argument("--mesh-supersample", type=_int, help="render the mesh at this × resolution during refinement "
                   "and box-filter down (antialiased outlines; default 3, 2 is ~1.5× faster)")
    p.add_argument("--mesh-eval-supersample", type=_int, help="samples per pixel side of the mesh's test renders "
                   "(default 4)")
    p.add_argument("--mesh-pixel-filter", metavar="auto|box|SIGMA",
                   help="the photos' pixel filter in the mesh renders: auto (default: a Gaussian whose width is read "
                   "from the photos' alpha edges; 0.5 px without alpha), box (each pixel's average), or a Gaussian "
                   "of standard deviation SIGMA pixels in [0.1, 4]")
    p.add_argument("--mesh-laplacian", choices=["uniform", "rest"], help="the refinement's position Laplacian: "
                   "uniform |L x|² (default), or rest |L x - L x0|², the Laplacian of the displacement from the "
                   "extracted shape (does not round its edges and thin parts)")
    p.add_argument("--mesh-creases", choices=["keep", "smooth"], help="the refinement's face-normal smoothing: keep "
                   "(default) lets creases form where the photos show them (a robust term: small bends smoothed, "
                   "bends of ~25-75 degrees pulled weakly, right angles and folds as by the plain term or harder), "
                   "smooth pulls every crease towards a round edge (the plain term: for smooth, organic objects with "
                   "painted detail)")
    p.add_argument("--texture-size", type=_int, help="baked texture size in texels (default 1024)")
    p.add_argument("--formats", help="comma-separated export formats among glb,obj,ply (default all)")
    p.add_argument("--bbox", help="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX: extract only the object inside this box (world "
                   "units of the dataset); default for photos without alpha: a box found from the cameras' look-at "
                   "point, the ground plane and the sparse points")
    p.add_argument("--mesh-crop", choices=["auto", "none"], help="auto (default): crop photos without alpha to the "
                   "automatic region of interest; none: keep everything")


def _mesh_config_from_args(args: argparse.Namespace):
    from dataclasses import replace

    from triplet_cl.mesh.refine import MeshConfig

    over = {}
    for opt, field in (("mesh_method", "method"), ("mesh_resolution", "resolution"), ("mesh_faces", "extract_faces"),
                       ("mesh_rounds", "rounds"),
                       ("mesh_iterations", "iterations"), ("remesh_every", "remesh_every"),
                       ("mesh_light_phase", "material_tie"),
                       ("mesh_metallic_trial", "metallic_trial"),
                       ("mesh_ao", "ao"), ("mesh_bounce", "bounce"), ("mesh_light_fit", "light_fit"),
                       ("mesh_metal_f0", "metal_f0"), ("mesh_env_degree", "env_degree"),
                       ("mesh_env_degree", "env_degree_metal"), ("mesh_env_degree_metal", "env_degree_metal"),
                       ("mesh_env_occlusion", "env_occlusion"),
                       ("mesh_supersample", "supersample"), ("mesh_eval_supersample", "eval_supersample"),
                       ("mesh_laplacian", "laplacian"), ("texture_size", "texture_size")):
        v = getattr(args, opt, None)
        if v is not None:
            over[field] = v
    if getattr(args, "formats", None):
        over["formats"] = _formats(args.formats)
    if getattr(args, "mesh_pixel_filter", None) is not None:
        over["pixel_sigma"] = _pixel_filter(args.mesh_pixel_filter)
    if getattr(args, "mesh_crop", None):
        over["crop"] = args.mesh_crop
    if getattr(args, "mesh_creases", None) == "smooth":
        over["normal_kappa"] = None
    if getattr(args, "bbox", None):
        over["bbox"] = _bbox(args.bbox)
    cfg = replace(MeshConfig(), **over)
    cfg.validate()
    return cfg


def _bbox(text: str) -> tuple:
    from triplet_cl.mesh.roi import parse_bbox

    try:
        return parse_bbox(text)
    except ValueError as exc:
        raise ValueError(f"--bbox: {exc}") from None


def _pixel_filter(text) -> float | None:
    """``--mesh-pixel-filter``: auto → None (read from the photos), box → 0, else a standard deviation in [0.1, 4]."""
    from triplet_cl.ops.downsample import check_pixel_sigma

    t = str(text).strip().lower()
    if t == "auto":
        return None
    if t == "box":
        return 0.0
    return check_pixel_sigma("--mesh-pixel-filter (auto, box or SIGMA)", t, allow_box=False)


def _formats(text: str) -> tuple:
    from triplet_cl.validate import parse_formats

    return parse_formats("--formats", text)


def _mesh_flags(args) -> list[str]:
    """The mesh options given on the command line, as flags (for the hint after an interruption: config.json keeps
    no mesh options, and a bare `triplet extract RUN` runs the defaults; battery 11)."""
    p = argparse.ArgumentParser(add_help=False)
    _add_mesh_options(p)
    out = []
    for a in p._actions:
        v = getattr(args, a.dest, None) if a.option_strings else None
        if v is None or v is False:
            continue
        flag = a.option_strings[-1]
        if v is True:
            out.append(flag)
        elif isinstance(v, tuple | list):
            out += [flag, ",".join(map(str, v)) if a.dest == "formats" else " ".join(map(str, v))]
        else:
            out += [flag, str(v)]
        if len(out) > 1 and out[-1].startswith("-") and out[-2] == flag:  # a negative value: one token
            out[-2:] = [f"{flag}={out[-1]}"]
    return out


def _run_mesh_stage(tr, cfg, args=None) -> int:
    from triplet_cl.mesh.refine import MeshStage

    stage = MeshStage(tr, cfg)
    print(f"mesh stage: {cfg.method} extraction, {cfg.rounds} round(s) of {cfg.iterations} steps")
    try:
        _raise_if_terminated()
        m = stage.run()
    except KeyboardInterrupt:  # the soup is complete and saved; the stage's files are written at its end only
        flags = " ".join(shlex.quote(f) for f in _mesh_flags(args)) if args is not None else ""
        again = (f"triplet extract {shlex.quote(str(tr.run_dir))}" + (f" {flags}" if flags else "")
                 + ("" if args is not None else " (with the same mesh options, if any)"))
        if getattr(stage, "state_saved", False):  # (battery 11: a mixed mesh left without a word)
            print(f"\ninterrupted in the mesh stage's last phase: the new mesh is saved (mesh_stage.npz replaced) but "
                  f"its files (mesh.*, lights.json, textures, metrics.json's \"mesh\") may still be the previous "
                  f"extract's: write them with: triplet export {shlex.quote(str(tr.run_dir))}, or redo the stage: "
                  f"{again}", file=sys.stderr)
        else:
            print(f"\ninterrupted in the mesh stage (the trained soup is complete); run it again with: {again}",
                  file=sys.stderr)
        return _interrupted_status()
    chamfer = f", Chamfer to gt_mesh {m['chamfer_to_gt']:.4f}" if "chamfer_to_gt" in m else ""
    if (m.get("gt_buried_fraction") or 0) > 0:  # a reference of overlapping parts: also against what a camera sees
        chamfer += (f" (its outer surface {m['chamfer_surface_to_gt']:.4f}; {100 * m['gt_buried_fraction']:.0f} % of "
                    "gt_mesh's area lies inside its other parts)")
    if m.get("cropped_to_object"):
        print(f"mesh: {m['faces']} faces, cropped to the object (its test PSNR {m['psnr']:.2f} dB is against photos "
              f"that also show the background it no longer has; soup {m['soup_psnr']:.2f} dB){chamfer}")
    else:
        print(f"mesh: {m['faces']} faces, test PSNR {m['psnr']:.2f} dB (soup {m['soup_psnr']:.2f} dB){chamfer}")
    print(f"wrote {', '.join(m['files'])} in {tr.run_dir}/")
    return 0


def _first_missing(path: Path) -> Path | None:
    """The topmost of ``path`` and its parents that does not exist yet (what ``mkdir(parents=True)`` creates)."""
    p, first = path.absolute(), None
    while not p.exists() and p != p.parent:
        first, p = p, p.parent
    return first


def _check_bbox_seen(cfg, tr) -> None:
    """``--bbox`` must hold something the training cameras see (else the mesh stage finds no surface, after the
    whole training)."""
    if cfg is None or cfg.bbox is None:
        return
    from triplet_cl.errors import UsageError
    from triplet_cl.mesh.roi import ROI, cameras_seeing

    cams = [v.camera for v in tr.ds.train]
    if cameras_seeing(ROI.from_bbox(cfg.bbox), cams) == 0:
        raise UsageError("--bbox", f"{','.join(f'{x:g}' for x in cfg.bbox)}: none of the {len(cams)} training cameras "
                                   "sees any part of this box (world units of the dataset's cameras)")


def _check_bbox_holds_soup(cfg, tr, min_faces: int = 20) -> None:
    """``extract --bbox``: the soup has opaque triplets inside the box (a battery's box inside the object, or beside
    it, gave a box-shaped mesh over the run's mesh files, or "found no surface" after the extraction)."""
    if cfg is None or cfg.bbox is None:
        return
    import numpy as np

    from triplet_cl.density import face_alpha
    from triplet_cl.errors import UsageError

    V = np.asarray(tr.scene.V.data, np.float64)
    F = np.asarray(tr.scene.F)
    if len(F) == 0:
        return
    c = V[F].mean(axis=1)
    lo, hi = np.asarray(cfg.bbox[:3]), np.asarray(cfg.bbox[3:])
    inside = np.all((c >= lo) & (c <= hi), axis=1)
    opaque = face_alpha(tr.scene.alpha.data, F) > 0.5  # (the prune criterion's face alpha)
    n = int(np.count_nonzero(inside & opaque))
    if n < min_faces:
        raise UsageError("--bbox", f"{','.join(f'{x:g}' for x in cfg.bbox)}: the soup has {n} opaque triplet(s) in "
                                   f"this box (at least {min_faces} make a surface): the box holds no part of the "
                                   "object's surface (world units of the dataset's cameras)")


def cmd_extract(args: argparse.Namespace) -> int:
    from triplet_cl.runs import read_metrics

    cfg = _mesh_config_from_args(args)
    read_metrics(args.run, "extract")  # the stage merges its "mesh" section: a damaged file fails now, not at the end
    from triplet_cl.runs import lock_run

    lock_run(args.run, "RUN")
    from triplet_cl.validate import check_mesh_outputs

    tr = _load_run(args)
    tr.check_resumable("extract")  # the stage refines against the training photos: they must be the run's
    check_mesh_outputs(args.run, cfg.formats, tr.ds["test"] or tr.ds.train)
    _check_bbox_seen(cfg, tr)
    _check_bbox_holds_soup(cfg, tr)
    tr.quiet = False
    return _run_mesh_stage(tr, cfg, args)


def cmd_export(args: argparse.Namespace) -> int:
    from triplet_cl.mesh.asset import MeshAsset
    from triplet_cl.mesh.export import check_asset
    from triplet_cl.mesh.refine import (
        MESH_STATE,
        albedo_space,
        export_run_mesh,
        load_mesh_state,
        run_color,
    )
    from triplet_cl.validate import check_export_out, parse_formats

    run = Path(args.run)
    formats = parse_formats("--formats", args.formats)
    if args.device:  # unused (export bakes on the CPU) but a wrong spec is still an error
        from triplet_cl.device import resolve_spec

        resolve_spec(args.device)
    out = Path(args.out) if args.out else run
    if out.resolve() == run.resolve():  # into the run: not while its mesh stage writes the same files
        from triplet_cl.runs import lock_run

        lock_run(run, "RUN")
    scene = load_mesh_state(run / MESH_STATE)
    asset = MeshAsset.from_scene(scene)
    try:  # before --out is made (and before the UV unwrap, which a vertex far out kept busy for ever)
        check_asset(asset, "export")
    except ValueError as exc:
        from triplet_cl.errors import RunError

        raise RunError(run / MESH_STATE, f"cannot be exported ({exc}): run `triplet extract` again") from None
    check_export_out(out, formats, "--out")
    paths = export_run_mesh(out, asset, formats, args.texture_size,
                            albedo_space=albedo_space(run_color(run)))
    print(f"wrote {', '.join(str(p) for p in paths)}")
    return 0


# ---------------------------------------------------------------------------------------------- colmap (photos)


def cmd_colmap(args: argparse.Namespace) -> int:
    """Cameras from a folder of photos: SfM with pycolmap, undistortion, a COLMAP folder for `train`."""
    from triplet_cl.datasets.sfm import run_sfm

    t0 = time.perf_counter()
    s = run_sfm(args.images, args.out, camera_model=args.camera_model, max_features=args.max_features,
                min_registered=args.min_registered, num_threads=args.threads, verbose=args.verbose,
                progress=lambda line: print(line, flush=True))
    cam = s["camera"]
    print(f"registered {s['registered']} of {s['photos']} photos, {s['points']} points, mean reprojection error "
          f"{s['mean_reprojection_error_px']:.2f} px; camera {cam['model']} "
          f"{' '.join(f'{x:.5g}' for x in cam['params'])}")
    print(f"wrote {args.out}/ (images/, sparse/0/, distorted/, sfm.json) in {time.perf_counter() - t0:.0f} s "
          f"(CPU {s['cpu_s']:.0f} s); next: {train_hint(args.out)}")
    return 0


def train_hint(data) -> str:
    """The command that trains on ``data``, as it can be pasted into a shell (a path with a space was not quoted)."""
    return f"triplet train {shlex.quote(str(data))} --out RUN"


def add_colmap_parser(sub) -> None:
    c = sub.add_parser("colmap", help="solve the cameras of a folder of photos (pycolmap structure from motion) and "
                       "write an undistorted COLMAP folder that `triplet train` reads")
    c.add_argument("images", help="folder of photos (JPEG/PNG/TIFF, one camera, one size)")
    c.add_argument("--out", required=True, help="new dataset folder to write (refused if it exists and is not empty)")
    c.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   choices=["SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"],
                   help="COLMAP camera model shared by all photos (default SIMPLE_RADIAL)")
    c.add_argument("--max-features", type=_int, default=1024, help="SIFT features per photo (default 1024; matching "
                   "time grows with its square: raise it for hard captures)")
    c.add_argument("--min-registered", type=float, default=0.5, help="fail when fewer than this fraction of the "
                   "photos register (default 0.5; at least 3 always)")
    c.add_argument("--threads", type=_int, default=-1, help="CPU threads of the SfM steps (default -1: all cores)")
    c.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    c.set_defaults(func=cmd_colmap)


# ---------------------------------------------------------------------------------------------- parser


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors on one line (``triplet train: error: argument --color: invalid choice ...``),
    as every other error of the CLI, instead of the usage block followed by the message; exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="triplet",
        allow_abbrev=False,
        description="Mesh-based inverse rendering (Triplet) with OpenCL kernels and hand-derived adjoints.",
    )
    p.add_argument("--version", action="version", version=f"triplet_cl {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    renderer_help = ("raster (default): K-nearest rasterization; raytrace: BVH primary rays, ray-traced shadows and "
                     "a reflection bounce; hybrid: rasterized primary visibility, ray-traced shadows and reflection")
    dev_help = ("OpenCL device: 'P:D' indices or a substring of the platform/device name "
                "(default: $TRIPLET_DEVICE, else the first GPU, else the first CPU)")

    d = sub.add_parser("devices", help="list OpenCL platforms/devices and the one that would be chosen")
    d.add_argument("--device", default=None, help=dev_help)
    d.set_defaults(func=cmd_devices)

    t = sub.add_parser("train", help="reconstruct a scene from a dataset (or --demo)")
    t.add_argument("data", nargs="?", help="dataset folder (NeRF-synthetic, instant-ngp or COLMAP)")
    t.add_argument("--out", help="run directory (default for --demo: runs/demo)")
    t.add_argument("--demo", action="store_true", help="train on the small Spot dataset shipped with the package")
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint "
                   "(--iterations, --checkpoint-every, --keep-checkpoints may change; other options must match)")
    t.add_argument("--overwrite", action="store_true", help="replace the existing run in --out (deletes it)")
    t.add_argument("--data-format", default="auto", choices=["auto", *DATASET_FORMATS], help="dataset format",
                   action=DeprecatedAlias.given())
    t.add_argument("--format", dest="data_format", choices=["auto", *DATASET_FORMATS],
                   action=DeprecatedAlias.action("--data-format"), help=argparse.SUPPRESS)
    t.add_argument("--iterations", type=_int, help="optimisation steps (default 3000; --demo: 1500)")
    t.add_argument("--seed", type=_int, help="random seed (default 0)")
    t.add_argument("--brdf", choices=[b.cli for b in BRDFS.values()],
                   help=f"BRDF (default {BRDFS[DEFAULT_BRDF].cli})")
    t.add_argument("--lights", help=f"comma-separated mix of {','.join(LIGHT_KINDS)} (default point,ambient)")
    t.add_argument("--sensor-clip", choices=["on", "off"], help="model the photos' saturation: a render above a "
                   "clipped (white) photo value is not pulled down (default on; sRGB photos only)")
    t.add_argument("--light-distance", type=float, metavar="D", help="point lights start D scene extents from the "
                   "centre (default 0.6); their intensity follows so that the irradiance at the centre is the same")
    t.add_argument("--light-min-distance", type=float, metavar="R", help="point lights are kept (and start) at "
                   "least R frame radii (the half-width the cameras see at the centre) from the centre, outside the "
                   "object (default 1; 0: anywhere)")
    t.add_argument("--sh-degree", type=_int, help="max SH degree of vertex-SH / SH-environment lights (default 2)")
    t.add_argument("--faces-per-pixel", type=_int, help="K after the warm-up (default 30)")
    t.add_argument("--init-points", type=_int, help="random initial triangles (default 20000)")
    t.add_argument("--max-faces", type=_int, help="face budget of density control (default 200000)")
    t.add_argument("--error-resplit-ratio", metavar="R|off",
                   help="split a face by the error criterion again only once its error is <= R x its error at its "
                   "last error split (default 0.9; off: no such rule; README 'Density control')")
    t.add_argument("--background", choices=["auto", "white", "black", "random"],
                   help="background the photos' alpha is composited over in training: white, black, random (a new "
                        "colour every iteration) or auto (default: random for photos without alpha with SfM points, "
                        "white without them, unless their borders are a flat white / black backdrop; with alpha "
                        "white, random when 5 %% or more of the photos' object pixels are white themselves)")
    t.add_argument("--background-shell", metavar="N|auto", help="photos with a background: add this many triangles "
                   "on a far sphere for the sky / walls; auto (default): 4000 for photos without alpha trained over "
                   "the random background with SfM points to crop the mesh by, else 0 (README 'Your own photos')")
    t.add_argument("--downscale", help="reduce the dataset's images by this integer factor, or "
                   "auto (default): the smallest factor that brings the photos' longer side to at most 1600 px (1 for "
                   "smaller photos)")
    t.add_argument("--sigma", type=float, help="soft-coverage sharpness in 1/px; 0 = hard edges (default 2)")
    t.add_argument("--checkpoint-every", type=_int, help="iterations between checkpoints (default 1000)")
    t.add_argument("--keep-checkpoints", type=_int, help="keep the newest N checkpoints (default 3; 0 = all)")
    t.add_argument("--renderer", choices=["raster", "raytrace", "hybrid"], help=renderer_help)
    t.add_argument("--shadows", choices=["vertex", "off"], help="cast shadows in training with the raster renderer "
                   "(default vertex: per-vertex visibility towards point / directional lights, ray-traced through the "
                   "soup every --shadow-every steps, from iteration 600; off: none; README 'Cached shadows')")
    t.add_argument("--shadow-every", type=_int, help="steps between visibility refreshes (default 100; also after "
                   "density control, and when a light moved, at most every N/2 steps)")
    t.add_argument("--light-phase", type=_int, metavar="N", help="the first N steps fit the lights with one material "
                   "for the whole object (every vertex the same albedo, roughness, metallic), then per vertex "
                   "(default 40 %% of --iterations: 1200 of 3000; 0 = none; at most --iterations; "
                   "README 'Light phase')")
    t.add_argument("--light-phase-lobes", choices=["held", "tied"], help="roughness and metallic during the light "
                   "phase: held (default) at their initial values while their per-vertex gradients build Adam's "
                   "moments, then per vertex; tied: one learning value, as the albedo (runs before 2026-11-26)")
    t.add_argument("--blinn-phong-ka", choices=["diffuse", "free"], help="with --brdf blinn-phong: diffuse (default) "
                   "keeps the ambient reflectance ka equal to kd (one reflectance under the point and the ambient "
                   "light, as Cook-Torrance's albedo); free: ka its own channel (runs before 2026-11-26); no effect "
                   "with cook-torrance")
    t.add_argument("--white-light", choices=["each", "total", "off"], help="each (default): every light stays white "
                   "(its brightness learned; the photos' colours go to the albedo); total: the lights together white "
                   "at the scene centre, their colours relative to each other free; off: the lights may take any tint")
    t.add_argument("--save-train-renders", action="store_true", help="also render the training views")
    t.add_argument("--color", choices=["linear", "encoded"], help="colour pipeline (default linear: linear radiance "
                   "inside, the photos' sRGB transfer before the loss; encoded: fit the encoded values, as before)")
    t.add_argument("--priors", choices=["lights", "materials", "all", "off"], help="priors (default off; lights: a "
                   "small ambient share, white-ish lights, light colours >= 0; materials: kNN smoothness of the "
                   "materials, metallic towards 0, roughness towards 0.5; all: both; README 'Material and light "
                   "priors')")
    t.add_argument("--mesh-stage", action="store_true", help="after the soup stage, extract a connected mesh, "
                   "refine it and export mesh.glb/.obj/.ply (as `triplet extract`)")
    _add_mesh_options(t)
    t.add_argument("--device", default=None, help=dev_help)
    t.set_defaults(func=cmd_train)

    r = sub.add_parser("render", help="render a trained run (RGBA PNGs named after the dataset's frames)")
    r.add_argument("run", help="run directory")
    r.add_argument("--split", default="test", choices=["test", "train", "val"])
    r.add_argument("--out", help="output folder (default RUN/renders/SPLIT)")
    r.add_argument("--renderer", choices=["raster", "raytrace", "hybrid"], help="renderer (default: the run's)")
    r.add_argument("--device", default=None, help=dev_help)
    r.set_defaults(func=cmd_render)

    e = sub.add_parser("eval", help="recompute RUN/metrics.json (PSNR, SSIM per test view and mean; other "
                       "sections are kept)")
    e.add_argument("run", help="run directory")
    e.add_argument("--relight", help="folder with relight.json (light sets + reference images + albedo/): relit "
                   "PSNR/SSIM per set and albedo PSNR (raw / per-channel scaled) of soup and mesh, under \"relight\"")
    e.add_argument("--renderer", choices=["raster", "raytrace", "hybrid"], help="renderer of the relit views "
                   "(default: as `triplet relight`)")
    e.add_argument("--shadows", choices=["vertex", "off"], help="cast shadows of the relit soup with the raster "
                   "renderer (default: as `triplet relight`)")
    e.add_argument("--env-degree", type=_int, help="SH degree of projected environment maps, 0..8 "
                   "(default 8)")
    e.add_argument("--out", help="also write the relit images (and albedo) to OUT/STAGE/SET/")
    e.add_argument("--device", default=None, help=dev_help)
    e.set_defaults(func=cmd_eval)

    lt = sub.add_parser("relight", help="render a run (its refined mesh, else the soup) under other lights")
    lt.add_argument("run", help="run directory")
    lt.add_argument("--lights", required=True, dest="light_file", help="light file: a relight.json (FILE#set picks "
                    "one of its sets; without #set every set), a bare {\"lights\": [...]} or a run's lights.json")
    lt.add_argument("--split", default="test", choices=["test", "train", "val"], help="views to render (default test)")
    lt.add_argument("--out", help="output folder (default RUN/relight/SET, RUN/relight/SPLIT/SET for --split train or "
                    "val; with several sets OUT/SET)")
    lt.add_argument("--renderer", choices=["raster", "raytrace", "hybrid"], help="renderer (default: the run's for the "
                    "soup, raster for the mesh; hybrid gives cast shadows)")
    lt.add_argument("--shadows", choices=["vertex", "off"], help="cast shadows of the relit lights on the soup with "
                    "the raster renderer (vertex: per-vertex visibility traced once per light set; off: none; default: "
                    "as the run was trained; the mesh stage has none; README 'Cached shadows')")
    lt.add_argument("--stage", default="auto", choices=["auto", "soup", "mesh"], help="what to render (default auto: "
                    "the refined mesh when the run has one, else the soup)")
    lt.add_argument("--env-degree", type=_int, help="SH degree of projected environment maps, 0..8 "
                    "(default 8: see README, Relighting)")
    lt.add_argument("--device", default=None, help=dev_help)
    lt.set_defaults(func=cmd_relight)

    x = sub.add_parser("extract", help="soup → connected mesh: extract, refine as a mesh, export PBR assets")
    x.add_argument("run", help="run directory of a trained soup")
    _add_mesh_options(x)
    x.add_argument("--device", default=None, help=dev_help)
    x.set_defaults(func=cmd_extract)

    o = sub.add_parser("export", help="write the refined mesh of a run (from `triplet extract`) in other formats")
    o.add_argument("run", help="run directory")
    o.add_argument("--formats", default="glb", action=DeprecatedAlias.given(),
                   help="comma-separated among glb,obj,ply (default glb)")
    o.add_argument("--format", dest="formats", action=DeprecatedAlias.action("--formats"), help=argparse.SUPPRESS)
    o.add_argument("--out", help="output folder (default RUN)")
    o.add_argument("--texture-size", type=_int, default=1024, help="baked texture size in texels (default 1024)")
    o.add_argument("--device", default=None, help="accepted for uniformity with the other commands; export bakes "
                   "on the CPU and uses no OpenCL device")
    o.set_defaults(func=cmd_export)
    add_colmap_parser(sub)
    return p


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--bbox -1,-1,0,1,1,2`` as ``--bbox=-1,-1,0,1,1,2`` (argparse takes a value starting with '-' that is not
    one number for an option and says "expected one argument")."""
    out, i = [], 0
    while i < len(argv):
        a = str(argv[i])
        if a == "--bbox" and i + 1 < len(argv) and re.match(r"^-[0-9.]", str(argv[i + 1])):
            out.append(f"--bbox={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def _reopen_closed_streams() -> None:
    """A standard stream the caller closed (`2>&-`, a daemon, cron) is opened on /dev/null: Python sets
    ``sys.stderr`` to None then, and the first warning or progress line raised AttributeError with nothing printed
    anywhere (battery 10); the C libraries' writes to the descriptor would land in whatever file took its number."""
    for fd, name, mode in ((0, "stdin", "r"), (1, "stdout", "w"), (2, "stderr", "w")):
        try:
            os.fstat(fd)
            closed = False
        except OSError:
            closed = True
        if closed:
            null = os.open(os.devnull, os.O_RDWR)
            if null != fd:
                os.dup2(null, fd)
                os.close(null)
        if closed or getattr(sys, name) is None:
            setattr(sys, name, open(fd, mode, closefd=False, encoding="utf-8", errors="replace"))


def _int(text: str) -> int:
    """An integer option: decimal digits with an optional sign (Python's ``int`` also reads ``3_0`` as 30, ten times
    what a typo for 3.0 or 3,0 meant: battery 10)."""
    t = str(text).strip()
    if "_" in t:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r} (no '_' separators)")
    try:
        return int(t)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    _reopen_closed_streams()
    parser = build_parser()
    for sp in parser._subparsers._group_actions[0].choices.values():  # `--format` never silently `--formats`
        sp.allow_abbrev = False
    args = parser.parse_args(_join_negative_values(sys.argv[1:] if argv is None else list(argv)))
    _TERMINATED[0] = False
    from triplet_cl.runs import release_run_locks

    try:
        with _sigterm_as_interrupt(), _one_line_warnings(args.command):
            return _dispatch(args)
    finally:
        release_run_locks()  # (the process ends next; in one process running several commands, the next may lock)


@contextlib.contextmanager
def _one_line_warnings(command: str):
    """Warnings as one line each, ``triplet COMMAND: warning: ...`` (Python's default printed the module's path and
    line and the source line that warned: two lines of internals for "3 of 40 frames have no image"); pyopencl's
    "Non-empty compiler output" notice, which PoCL's build logs raise on every first run, is not shown unless
    ``PYOPENCL_COMPILER_OUTPUT`` asks for the compiler's output."""
    import warnings

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"triplet {command}: warning: {message}", file=sys.stderr if file is None else file)

    with warnings.catch_warnings():
        warnings.showwarning = show
        if not os.environ.get("PYOPENCL_COMPILER_OUTPUT"):
            with contextlib.suppress(ImportError):
                from pyopencl import CompilerWarning

                warnings.simplefilter("ignore", CompilerWarning)
        yield


_TERMINATED = [False]  # set by SIGTERM: the exit status is then 143 (128 + 15), Ctrl-C's 130


def _interrupted_status() -> int:
    return 143 if _TERMINATED[0] else 130


def _raise_if_terminated() -> None:
    """A SIGTERM whose KeyboardInterrupt was swallowed (raised inside an import lock's callback while the modules
    loaded: Python prints "Exception ignored" and goes on; a battery saw a killed `train` then train to the end) stops
    the command here, before its long work."""
    if _TERMINATED[0]:
        raise KeyboardInterrupt


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM (``kill PID``, a scheduler's stop) raises KeyboardInterrupt like Ctrl-C, so that every
    command's clean-up runs (temporary folders removed, a checkpoint saved by ``train``) instead of the
    process vanishing mid-write; the previous handler is restored afterwards."""
    import signal

    def on_term(signum, frame):
        _TERMINATED[0] = True
        raise KeyboardInterrupt

    try:
        old = signal.signal(signal.SIGTERM, on_term)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _dispatch(args) -> int:
    try:
        validate_args(args)  # every option and path, before any work
        return int(args.func(args) or 0)
    except (TripletError, FileNotFoundError, ValueError) as exc:
        msg = os_error_message(exc, args.command) if isinstance(exc, OSError) and exc.errno else exc  # by the OS
        print(f"triplet {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `triplet devices | head -1`: the reader left; quiet, the status of a SIGPIPE death
        with contextlib.suppress(OSError, ValueError):  # (and no second error when Python flushes stdout at exit)
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, sys.stdout.fileno())
            os.close(null)
        return 141
    except OSError as exc:  # not a folder, read-only, permission, no space left: one line
        print(f"triplet {args.command}: error: {os_error_message(exc, args.command)}", file=sys.stderr)
        return 2
    except MemoryError as exc:  # Device.check_alloc says which buffer and the device's limit; a bare one does not
        detail = f"{exc}; " if str(exc) else ""
        print(f"triplet {args.command}: error: out of memory ({detail}reduce --init-points / --max-faces or the image "
              "size with --downscale)", file=sys.stderr)
        return 2
    except Exception as exc:  # an OpenCL allocation failure is one line too; anything else is a bug: traceback
        from triplet_cl.validate import device_memory_message

        msg = device_memory_message(exc)
        if msg is None:
            raise
        print(f"triplet {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(_interrupted_message(args), file=sys.stderr)
        return _interrupted_status()


def _interrupted_message(args) -> str:
    """What an interruption the command did not handle itself left behind (battery 11: a bare "interrupted" after a
    half-written export)."""
    if args.command == "export":
        return ("interrupted: the export's folder may hold some files of this export beside older ones: run the same "
                "command again to write them all")
    if args.command in ("render", "relight"):
        return ("interrupted: the output folder holds the views written so far (the others missing, or an older "
                "command's): run the same command again")
    if args.command == "eval":
        return (f"interrupted: {shlex.quote(str(args.run))}/metrics.json is unchanged (written at the end); relit "
                "images written so far (with --out) stay")
    return "interrupted"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
