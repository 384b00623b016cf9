"""Hardening (issue 21): every bad input is one clear error (option or file named, exit status 2, no
traceback) raised before any work or output; nothing the user made is lost; training stops on NaN."""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from triplet_cl.cli.main import build_parser, demo_data_path
from triplet_cl.cli.main import main as cli_main

from tests import data_factory as fac
from triplet_cl.datasets import load_dataset
from triplet_cl.datasets.colmap import read_images_text
from triplet_cl.errors import DatasetError, NonFiniteError, RunError
from triplet_cl.train import TrainConfig, Trainer

DEMO = demo_data_path()
TINY_RUN = ["--iterations", "4", "--init-points", "300", "--checkpoint-every", "2", "--faces-per-pixel", "8"]


def _tree(path: Path) -> dict:
    """Every file under ``path`` with its bytes (to prove nothing changed)."""
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def _run_cli(argv, capsys):
    rc = cli_main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, cap.err, cap.out


@pytest.fixture(scope="module")
def demo_copy(tmp_path_factory):
    """The demo dataset copied (renders into it must be refused, never done to the package's copy)."""
    d = tmp_path_factory.mktemp("data") / "spot_small"
    shutil.copytree(DEMO, d)
    return d


@pytest.fixture(scope="module")
def trained(tmp_path_factory, demo_copy):
    """A tiny finished run (4 iterations, checkpoints at 2 and 4)."""
    out = tmp_path_factory.mktemp("runs") / "run"
    assert cli_main(["train", str(demo_copy), "--out", str(out), *TINY_RUN]) == 0
    return out


@pytest.fixture
def run(tmp_path, trained):
    dst = tmp_path / "run"
    shutil.copytree(trained, dst)
    return dst


# ---- bad options: exit 2, the option named, nothing written -------------------------------------------
BAD_TRAIN = {
    "K 0": (["--faces-per-pixel", "0"], "--faces-per-pixel"),
    "K -3": (["--faces-per-pixel", "-3"], "--faces-per-pixel"),
    "K 100000": (["--faces-per-pixel", "100000"], "--faces-per-pixel"),
    "downscale 96": (["--downscale", "96"], "--downscale"),
    "downscale 0": (["--downscale", "0"], "--downscale"),
    "sigma nan": (["--sigma", "nan"], "--sigma"),
    "sigma inf": (["--sigma", "inf"], "--sigma"),
    "sigma -1": (["--sigma", "-1"], "--sigma"),
    "error resplit ratio 0": (["--error-resplit-ratio", "0"], "--error-resplit-ratio"),
    "error resplit ratio nan": (["--error-resplit-ratio", "nan"], "--error-resplit-ratio"),
    "error resplit ratio word": (["--error-resplit-ratio", "often"], "--error-resplit-ratio"),
    "init 0": (["--init-points", "0"], "--init-points"),
    "init -5": (["--init-points", "-5"], "--init-points"),
    "init 5M": (["--init-points", "5000000"], "--init-points"),
    "init 50M memory": (["--init-points", "50000000", "--max-faces", "60000000"], "--init-points"),
    "max-faces 0": (["--max-faces", "0"], "--max-faces"),
    "max-faces memory": (["--max-faces", "2000000000"], "--max-faces"),
    "seed -1": (["--seed", "-1"], "--seed"),
    "iterations 0": (["--iterations", "0"], "--iterations"),
    "sh-degree 9": (["--sh-degree", "9"], "--sh-degree"),
    "checkpoint-every -1": (["--checkpoint-every", "-1"], "--checkpoint-every"),
    "keep-checkpoints -1": (["--keep-checkpoints", "-1"], "--keep-checkpoints"),
    "shadow-every 0": (["--shadow-every", "0"], "--shadow-every"),
    "light-phase -1": (["--light-phase", "-1"], "--light-phase"),
    "device empty": (["--device", ""], "--device"),
    "device blank": (["--device", "  "], "--device"),
    "light-distance 0": (["--light-distance", "0"], "--light-distance"),
    "light-distance nan": (["--light-distance", "nan"], "--light-distance"),
    "light-min-distance -1": (["--light-min-distance", "-1"], "--light-min-distance"),
    "light-min-distance inf": (["--light-min-distance", "inf"], "--light-min-distance"),
    "mesh-light-phase -2": (["--mesh-stage", "--mesh-light-phase", "-2"], "--mesh-light-phase"),
    "mesh-metallic-trial -1": (["--mesh-stage", "--mesh-metallic-trial", "-1"], "--mesh-metallic-trial"),
    "mesh-env-occlusion 5": (["--mesh-stage", "--mesh-env-occlusion", "5"], "--mesh-env-occlusion"),
    "shadow-every without shadows": (["--shadows", "off", "--shadow-every", "5"], "--shadow-every"),
    "light-phase-lobes without a light phase": (["--light-phase", "0", "--light-phase-lobes", "tied"],
                                                "--light-phase-lobes"),
    "blinn-phong-ka with cook-torrance": (["--blinn-phong-ka", "free"], "--blinn-phong-ka"),
    "formats with an empty item": (["--mesh-stage", "--formats", "glb,,obj"], "formats"),
    "mesh-env-occlusion without --mesh-stage": (["--mesh-env-occlusion", "1"], "--mesh-env-occlusion"),
    "lights": (["--lights", "laser"], "--lights"),
    "lights directional twice": (["--lights", "directional,ambient,directional"], "--lights"),
    "lights ambient twice": (["--lights", "point,ambient,ambient"], "--lights"),
    "texture-size -4": (["--mesh-stage", "--texture-size", "-4"], "--texture-size"),
    "mesh-faces 0": (["--mesh-stage", "--mesh-faces", "0"], "--mesh-faces"),
    "formats": (["--mesh-stage", "--formats", "fbx"], "--formats"),
    "mesh option without --mesh-stage": (["--mesh-faces", "5000"], "--mesh-faces"),
    "resume and overwrite": (["--resume", "--overwrite"], "--overwrite"),
    "missing data": ([], "DATA"),
    "DATA and --demo": (["--demo"], "--demo"),
    "background-shell -1": (["--background-shell", "-1"], "--background-shell"),
    "background-shell over the face budget": (["--background-shell", "300000"], "--background-shell"),
    "bbox without --mesh-stage": (["--bbox", "0,0,0,1,1,1"], "--bbox"),
    "mesh-bounce without --mesh-stage": (["--mesh-bounce", "traced"], "--mesh-bounce"),
    "bbox nan": (["--mesh-stage", "--bbox", "0,0,0,1,1,nan"], "--bbox"),
    "bbox inf": (["--mesh-stage", "--bbox", "0,0,0,inf,1,1"], "--bbox"),
    "bbox inverted": (["--mesh-stage", "--bbox", "1,1,1,0,0,0"], "--bbox"),
    "bbox flat": (["--mesh-stage", "--bbox", "0,0,0,0,1,1"], "--bbox"),
    "bbox 3 numbers": (["--mesh-stage", "--bbox", "1,2,3"], "--bbox"),
    "bbox words": (["--mesh-stage", "--bbox", "a,b,c,d,e,f"], "--bbox"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRAIN))
def test_bad_train_options_are_refused_up_front(tmp_path, capsys, case, monkeypatch):
    import triplet_cl.validate as val

    # the memory cases against a 24 GiB machine's memory: on a 128 GiB one 50M initial points fit and the 60M
    # budget beside them was the option refused
    monkeypatch.setattr(val, "available_memory", lambda: 24 * 2**30)
    extra, named = BAD_TRAIN[case]
    out = tmp_path / "out"
    data = tmp_path / "nothing" if case == "missing data" else DEMO
    rc, err, _ = _run_cli(["train", data, "--out", out, *extra], capsys)
    assert rc == 2, err
    assert named in err and err.count("\n") == 1, err
    assert not out.exists(), "nothing written"


def test_downscale_too_large_for_the_images(tmp_path, capsys):
    fac.make_nerf(tmp_path / "ds", w=8, h=6)  # 8x6 / 4 = 2x1 pixels
    rc, err, _ = _run_cli(["train", tmp_path / "ds", "--out", tmp_path / "out", "--downscale", "4"], capsys)
    assert rc == 2 and "--downscale" in err and "2x1" in err
    assert not (tmp_path / "out").exists()


BAD_MESH = {
    "mesh-faces 0": (["--mesh-faces", "0"], "--mesh-faces"),
    "texture-size -4": (["--texture-size", "-4"], "--texture-size"),
    "resolution 3": (["--mesh-resolution", "3"], "--mesh-resolution"),
    "resolution 2048": (["--mesh-resolution", "2048"], "--mesh-resolution"),
    "supersample 9": (["--mesh-supersample", "9"], "--mesh-supersample"),
    "pixel filter word": (["--mesh-pixel-filter", "gauss"], "--mesh-pixel-filter"),
    "pixel filter 0": (["--mesh-pixel-filter", "0"], "--mesh-pixel-filter"),
    "pixel filter nan": (["--mesh-pixel-filter", "nan"], "--mesh-pixel-filter"),
    "formats": (["--formats", "obj,fbx"], "--formats"),
    "bbox nan": (["--bbox", "0,0,0,1,1,nan"], "--bbox"),
    "bbox inverted": (["--bbox", "1,1,1,0,0,0"], "--bbox"),
    "bbox 7 numbers": (["--bbox=-1,-1,-1,1,1,1,1"], "--bbox"),
    "bbox with --mesh-crop none": (["--bbox", "-1,-1,-1,1,1,1", "--mesh-crop", "none"], "--mesh-crop"),
}


@pytest.mark.parametrize("case", sorted(BAD_MESH))
def test_bad_extract_options_write_nothing(run, capsys, case, monkeypatch):
    import triplet_cl.validate as val

    monkeypatch.setattr(val, "available_memory", lambda: 24 * 2**30)  # the memory cases against a 24 GiB machine
    extra, named = BAD_MESH[case]
    before = _tree(run)
    rc, err, _ = _run_cli(["extract", run, *extra], capsys)
    assert rc == 2 and named in err, err
    assert _tree(run) == before


def test_abbreviations_are_not_accepted(run, capsys):
    """`extract RUN --format obj` used to mean `--formats obj` and rerun the whole mesh stage."""
    before = _tree(run)
    with pytest.raises(SystemExit) as ei:
        cli_main(["extract", str(run), "--format", "obj"])
    assert ei.value.code == 2
    with pytest.raises(SystemExit):
        cli_main(["train", str(DEMO), "--out", str(run.parent / "x"), "--iter", "3"])
    assert _tree(run) == before and not (run.parent / "x").exists()


def test_help_and_names():
    p = build_parser()
    train = p._subparsers._group_actions[0].choices["train"]
    helps = {a.dest: a.help for a in train._actions}
    assert "default 2" in helps["sigma"]
    export = p._subparsers._group_actions[0].choices["export"]
    opts = {s for a in export._actions for s in a.option_strings}
    assert {"--formats", "--device"} <= opts
    assert "--data-format" in {s for a in train._actions for s in a.option_strings}


def test_deprecated_format_aliases_warn(capsys):
    args = build_parser().parse_args(["train", "x", "--format", "nerf"])
    assert args.data_format == "nerf" and "--data-format" in capsys.readouterr().err
    args = build_parser().parse_args(["export", "r", "--format", "obj"])
    assert args.formats == "obj" and "--formats" in capsys.readouterr().err


@pytest.mark.parametrize("argv, option", [
    (["export", "RUN", "--formats", "obj", "--format", "ply"], "--format"),
    (["export", "RUN", "--format", "ply", "--formats", "obj"], "--format"),
    (["export", "RUN", "--formats", "glb,"], "--formats"),
    (["extract", "RUN", "--formats", "glb,"], "--formats"),
    (["train", "DEMO", "--out", "OUT", "--data-format", "nerf", "--format", "colmap"], "--format"),
])
def test_format_conflicts_and_empty_items_are_refused_up_front(run, tmp_path, capsys, argv, option):
    """`export --formats obj --format ply` wrote the PLY only (the deprecated alias won, with a deprecation line);
    `--formats glb,` was taken by export and refused by extract only after the device had started, without naming
    the option (battery 8)."""
    before = _tree(run)
    argv = [{"RUN": run, "DEMO": DEMO, "OUT": tmp_path / "out"}.get(a, a) for a in argv]
    rc, err, _ = _run_cli(argv, capsys)
    assert rc == 2 and option in err and "Traceback" not in err and "_" not in err.split("spelling of")[-1][:20], err
    assert _tree(run) == before and not (tmp_path / "out").exists()


# ---- existing runs, resume ----------------------------------------------------------------------------
def test_existing_run_is_refused_without_resume_or_overwrite(run, capsys):
    before = _tree(run)
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, *TINY_RUN], capsys)
    assert rc == 2 and "existing run" in err and "--resume" in err and "--overwrite" in err
    assert _tree(run) == before


def test_overwrite_replaces_the_run(run, tmp_path, capsys):
    (run / "checkpoints" / "ckpt_0009999.npz").write_bytes(b"old")
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, "--overwrite", "--iterations", "2", "--init-points", "200",
                           "--checkpoint-every", "0"], capsys)
    assert rc == 0, err
    assert not (run / "checkpoints" / "ckpt_0009999.npz").exists()
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 2
    assert not list(tmp_path.glob(".run.overwritten*"))


def test_overwrite_keeps_the_old_run_when_the_new_one_cannot_start(run, tmp_path, capsys):
    fac.make_nerf(tmp_path / "bad")
    (tmp_path / "bad" / "transforms_train.json").write_text("{")
    before = _tree(run)
    rc, err, _ = _run_cli(["train", tmp_path / "bad", "--out", run, "--overwrite"], capsys)
    assert rc == 2 and "transforms_train.json" in err
    assert _tree(run) == before


def test_a_folder_that_is_not_a_run_is_never_overwritten(tmp_path, capsys):
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    for extra in ([], ["--overwrite"]):
        rc, err, _ = _run_cli(["train", DEMO, "--out", mine, *extra], capsys)
        assert rc == 2 and "not a triplet run" in err
    assert (mine / "notes.txt").read_text() == "precious" and len(list(mine.iterdir())) == 1


def test_out_is_a_file_or_inside_a_dataset(tmp_path, demo_copy, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    for out in (f, f / "sub"):
        rc, err, _ = _run_cli(["train", DEMO, "--out", out], capsys)
        assert rc == 2 and "--out" in err and "file" in err
    before = _tree(demo_copy)
    rc, err, _ = _run_cli(["train", demo_copy, "--out", demo_copy / "run"], capsys)
    assert rc == 2 and "dataset" in err
    assert _tree(demo_copy) == before


def test_resume_refuses_fixed_options_and_applies_the_others(run, capsys):
    before = _tree(run)
    for extra, named in ((["--seed", "5"], "--seed"), (["--lights", "point,directional"], "--lights"),
                         (["--sigma", "0"], "--sigma"), (["--faces-per-pixel", "9"], "--faces-per-pixel"),
                         (["--iterations", "2"], "--iterations"), (["--data-format", "colmap"], "--data-format"),
                         (["--error-resplit-ratio", "off"], "--error-resplit-ratio"),
                         (["--error-resplit-ratio", "0.5"], "--error-resplit-ratio"),
                         (["--light-min-distance", "2"], "--light-min-distance")):
        rc, err, _ = _run_cli(["train", "--resume", "--out", run, *extra], capsys)
        assert rc == 2 and named in err, (extra, err)
    assert _tree(run) == before
    # the same value as the run's is fine; --iterations / --checkpoint-every / --keep-checkpoints apply and are named
    rc, err, out = _run_cli(["train", "--resume", "--out", run, "--faces-per-pixel", "8", "--iterations", "6",
                             "--checkpoint-every", "1", "--keep-checkpoints", "2"], capsys)
    assert rc == 0, err
    assert "--iterations 6 (was 4)" in out and "--checkpoint-every 1 (was 2)" in out
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 6
    ckpts = sorted(p.name for p in (run / "checkpoints").glob("ckpt_*.npz"))
    assert ckpts == ["ckpt_0000005.npz", "ckpt_0000006.npz"], ckpts


def test_resume_of_a_run_before_the_linear_pipeline(tmp_path, demo_copy, capsys):
    """A config.json without "color" (trained before issue 17) resumes encoded; --color linear is refused, not
    silently dropped; --background-shell likewise cannot change."""
    run = tmp_path / "old"
    assert cli_main(["train", str(demo_copy), "--out", str(run), *TINY_RUN, "--color", "encoded"]) == 0
    cfg = json.loads((run / "config.json").read_text())
    cfg["train"].pop("color")
    (run / "config.json").write_text(json.dumps(cfg))
    before = _tree(run)
    for extra, named in ((["--color", "linear"], "--color"), (["--background-shell", "100"], "--background-shell")):
        rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "6", *extra], capsys)
        assert rc == 2 and named in err and "cannot change on --resume" in err, (extra, err)
    assert _tree(run) == before
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "6", "--color", "encoded"], capsys)
    assert rc == 0, err
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 6
    assert json.loads((run / "config.json").read_text())["train"].get("color", "encoded") == "encoded"


def test_checkpoint_of_another_configuration_is_refused(run, capsys):
    cfg = json.loads((run / "config.json").read_text())
    cfg["train"]["lights"] = ["directional", "ambient"]
    (run / "config.json").write_text(json.dumps(cfg))
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "6"], capsys)
    assert rc == 2 and "ckpt_0000004.npz" in err and "another configuration" in err and "lights" in err


@pytest.mark.parametrize("kind", ["truncated", "empty", "foreign", "nan"])
def test_damaged_checkpoint_is_named(run, capsys, kind):
    ck = run / "checkpoints" / "ckpt_0000004.npz"
    if kind == "truncated":
        ck.write_bytes(ck.read_bytes()[:1000])
    elif kind == "empty":
        ck.write_bytes(b"")
    elif kind == "foreign":
        np.savez(ck, x=np.zeros(3))
    else:
        with np.load(ck) as z:
            a = {k: z[k] for k in z.files}
        a["V"][5] = np.nan
        np.savez(ck, **a)
    for argv in (["train", "--resume", "--out", run, "--iterations", "6"], ["eval", run], ["render", run]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "ckpt_0000004.npz" in err, (argv, err)
        assert err.count("\n") == 1


CONFIG_CASES = {
    "not an object": "[1, 2]",
    "truncated": '{"data": "x", "tra',
    "empty": "",
    "missing train": '{"data": "x"}',
    "missing data": '{"train": {}}',
    "train not an object": '{"data": "x", "train": 3}',
    "wrong field type": None,  # iterations as a string
    "unknown field": None,
    "downscale 0": None,  # was "downscale must be a positive integer, got 0", the file not named
    "unknown format": None,  # was "format must be 'auto' or one of ...", the file not named
    "nested too deeply": '{"data": ' + "[" * 100000 + "]" * 100000 + "}",  # was a RecursionError traceback
}


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_bad_config_json_is_named(run, capsys, case):
    text = CONFIG_CASES[case]
    cfg = json.loads((run / "config.json").read_text())
    if case == "wrong field type":
        cfg["train"]["iterations"] = "many"
        text = json.dumps(cfg)
    elif case == "unknown field":
        cfg["train"]["colour"] = 1
        text = json.dumps(cfg)
    elif case == "downscale 0":
        cfg["train"]["downscale"] = 0
        text = json.dumps(cfg)
    elif case == "unknown format":
        cfg["format"] = "blender"
        text = json.dumps(cfg)
    (run / "config.json").write_text(text)
    for argv in (["eval", run], ["render", run], ["extract", run], ["train", "--resume", "--out", run]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and ("config.json" in err or "not a run directory" in err), (argv, err)


# ---- outputs: never into a dataset, never over files triplet did not make -----------------------------
def test_render_refuses_dataset_and_foreign_files(run, demo_copy, tmp_path, capsys):
    before = _tree(demo_copy)
    rc, err, _ = _run_cli(["render", run, "--out", demo_copy / "test"], capsys)
    assert rc == 2 and "dataset" in err
    assert _tree(demo_copy) == before
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "r_0.png").write_bytes(b"my picture")
    rc, err, _ = _run_cli(["render", run, "--out", mine], capsys)
    assert rc == 2 and "r_0.png" in err and "not written by triplet" in err
    assert (mine / "r_0.png").read_bytes() == b"my picture"
    fresh = tmp_path / "fresh"
    for _ in range(2):  # a folder triplet rendered into may be rendered into again
        rc, err, _ = _run_cli(["render", run, "--out", fresh], capsys)
        assert rc == 0, err
    assert len(list(fresh.glob("*.png"))) == 8
    # the manifest covers only what triplet wrote: a file of the user's added later is still refused
    (fresh / "r_0.png").unlink()
    (fresh / "r_10.png").write_bytes(b"mine")  # a train view's name, not rendered there yet
    rc, err, _ = _run_cli(["render", run, "--split", "train", "--out", fresh], capsys)
    assert rc == 2 and "r_10.png" in err and (fresh / "r_10.png").read_bytes() == b"mine"
    # a folder inside a run holds triplet's renders (here the test renders, replaced by train views of the same names)
    rc, err, _ = _run_cli(["render", run, "--split", "train", "--out", run / "renders" / "test"], capsys)
    assert rc == 0, err


def test_render_val_without_val_split_is_refused(run, tmp_path, capsys):
    rc, err, _ = _run_cli(["render", run, "--split", "val", "--out", tmp_path / "v"], capsys)
    assert rc == 2 and "'val'" in err and "--split" in err
    assert not (tmp_path / "v").exists()


def test_out_errors_of_render_export_eval(run, tmp_path, capsys, monkeypatch):
    f = tmp_path / "file"
    f.write_text("x")
    for argv in (["render", run, "--out", f], ["export", run, "--out", f], ["export", run, "--formats", "fbx"]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and ("--out" in err or "--formats" in err), (argv, err)
    # a read-only run (simulated: the suite runs as root, for whom chmod does not bite)
    import triplet_cl.validate as val

    monkeypatch.setattr(val.os, "access", lambda p, mode: False)
    before = _tree(run)
    rc, err, _ = _run_cli(["eval", run], capsys)
    assert rc == 2 and "not writable" in err
    assert _tree(run) == before


@pytest.mark.parametrize("kind", ["missing", "truncated", "foreign"])
def test_damaged_mesh_stage_is_named(run, capsys, kind):
    p = run / "mesh_stage.npz"
    if kind == "truncated":
        buf = run / "x.npz"
        np.savez(buf, V=np.zeros((9, 3)), F=np.zeros((3, 3), np.int32))
        p.write_bytes(buf.read_bytes()[:200])
        buf.unlink()
    elif kind == "foreign":
        np.savez(p, y=np.ones(2))
    rc, err, _ = _run_cli(["export", run, "--formats", "ply", "--out", run.parent / "exp"], capsys)
    assert rc == 2 and "mesh_stage.npz" in err
    assert not (run.parent / "exp" / "mesh.ply").exists()
    if kind == "missing":  # relight / eval --relight then use the soup
        return
    # relight and eval --relight read it too (they raised a BadZipFile / KeyError traceback)
    (run / "l.json").write_text(json.dumps({"lights": [{"type": "point", "position": [0, 0, 3],
                                                        "intensity": [1, 1, 1]}]}))
    rd = run.parent / "rel"
    rd.mkdir()
    (rd / "relight.json").write_text(json.dumps({"sets": {"a": {"lights": [{"type": "point", "position": [0, 0, 3],
                                                                           "intensity": [1, 1, 1]}]}}}))
    before = _tree(run)
    for argv in (["relight", run, "--lights", run / "l.json", "--out", run.parent / "rl"],
                 ["eval", run, "--relight", rd, "--out", run.parent / "ev"]):
        rc, err, out = _run_cli(argv, capsys)
        assert rc == 2 and "mesh_stage.npz" in err and err.count("\n") == 1, (argv, err)
        assert "PSNR" not in out
    assert _tree(run) == before and not (run.parent / "rl").exists() and not (run.parent / "ev").exists()


def test_os_errors_are_one_line(run, capsys, monkeypatch):
    import triplet_cl.train as train_mod

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", str(run / "checkpoints" / "x"))

    monkeypatch.setattr(train_mod, "atomic_write_bytes", full)
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    last = err.strip().splitlines()[-1]
    assert rc == 2 and last.startswith("triplet train: error:") and "no space left" in last


# ---- the finiteness guard -----------------------------------------------------------------------------
def _small_cfg(**kw) -> TrainConfig:
    from dataclasses import replace

    from triplet_cl.density import DensityConfig

    base = TrainConfig(iterations=12, init_points=400, warmup_until=4, half_res_until=8, checkpoint_every=3,
                       max_test_views=1, faces_per_pixel=8, warmup_faces_per_pixel=16,
                       density=DensityConfig(interval=100, densify_from=200, densify_until=300, grad_threshold=2e-4,
                                             alpha_reset_interval=3000, max_faces=4000, min_faces=10))
    return replace(base, **kw)


@pytest.mark.parametrize("what", ["parameter", "gradient"])
def test_nan_mid_training_stops_with_iteration_group_and_cause(tmp_path, what):
    tr = Trainer(DEMO, tmp_path / "r", _small_cfg(), quiet=True)
    orig = tr.step

    def step():
        if tr.it == 7:
            if what == "parameter":
                tr.scene.V.data[10] = np.nan
            else:
                tr.scene.material.data[3] = np.inf  # inf raw material → NaN gradients
        return orig()

    tr.step = step
    with pytest.raises(NonFiniteError) as ei:
        tr.train()
    e = ei.value
    assert e.iteration == 8 and "iteration 8" in str(e) and "ckpt_0000006.npz" in str(e)
    assert (e.group == "V") if what == "parameter" else e.group in ("material", "render")
    latest = (tmp_path / "r" / "checkpoints" / "latest").read_text()
    assert latest == "ckpt_0000006.npz"
    with np.load(tmp_path / "r" / "checkpoints" / latest) as z:
        assert np.isfinite(z["V"]).all() and np.isfinite(z["material"]).all()
    assert not (tmp_path / "r" / "triplets.ply").exists()
    assert "stopped: non-finite" in (tmp_path / "r" / "train.log").read_text()
    c = Trainer(None, tmp_path / "r", quiet=True, resume=True)  # the last good checkpoint resumes
    assert c.it == 6


def test_nan_gradient_updates_nothing(tmp_path):
    from triplet_cl.optim import Adam, NonFiniteStep

    class P:
        def __init__(self, data, grad):
            self.data, self.grad, self.name = data, grad, "p"

    a, b = P(np.ones(3), np.ones(3)), P(np.ones(2), np.array([1.0, np.nan]))
    opt = Adam()
    opt.add_group("a", [a])
    opt.add_group("b", [b])
    with pytest.raises(NonFiniteStep) as ei:
        opt.step()
    assert ei.value.group == "b" and ei.value.what == "gradient"
    assert opt.t == 0 and (a.data == 1).all() and (b.data == 1).all()


def test_killed_writes_leave_no_temp_files(run, capsys):
    import os
    import time

    junk = [run / "checkpoints" / ".ckpt_0000006.npz.k2j4h5x1.tmp", run / ".metrics.json.abcd1234.tmp",
            run / "renders" / "test" / ".r_3.x8f_2kqa.png"]
    old = time.time() - 3600
    for j in junk:
        j.write_bytes(b"partial")
        os.utime(j, (old, old))
    in_flight = run / "checkpoints" / ".ckpt_0000009.npz.zzzzzzzz.tmp"  # seconds old: another process's write
    in_flight.write_bytes(b"writing")
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    assert rc == 0, err
    assert not any(j.exists() for j in junk) and in_flight.exists()


# ---- datasets ----------------------------------------------------------------------------------------
def test_colmap_images_txt_one_line_per_image(tmp_path):
    cams = [(1, "PINHOLE", fac.W, fac.H, [7.0, 7.0, 4.0, 3.0])]
    images = []
    for k, eye in enumerate(fac.orbit_eyes(6)):
        q, t = fac.colmap_pose(eye)
        images.append((k + 1, q, t, 1, f"im_{k}.png"))
    fac.write_colmap_text(tmp_path, cams, images, [])
    lines = [ln for ln in (tmp_path / "images.txt").read_text().splitlines()
             if ln.startswith("#") or ln.split()[:1] and ln.split()[0].isdigit() and len(ln.split()) >= 10]
    (tmp_path / "images.txt").write_text("\n".join(lines) + "\n")
    got = read_images_text(tmp_path / "images.txt")
    assert sorted(got) == [1, 2, 3, 4, 5, 6]
    assert [got[i].name for i in sorted(got)] == [f"im_{k}.png" for k in range(6)]
    fac.write_colmap_text(tmp_path / "two", cams, images, [])  # the two-line form still reads the same
    assert sorted(read_images_text(tmp_path / "two" / "images.txt")) == [1, 2, 3, 4, 5, 6]


@pytest.mark.parametrize("case", ["degrees", "bottom row", "shear"])
def test_nerf_pose_and_angle_sanity(tmp_path, case):
    fac.make_nerf(tmp_path)
    p = tmp_path / "transforms_train.json"
    d = json.loads(p.read_text())
    if case == "degrees":
        d["camera_angle_x"] = 40
        want = "camera_angle_x.*radians.*0.698"
    elif case == "bottom row":
        d["frames"][1]["transform_matrix"][3] = [0.0, 0.0, 0.5, 1.0]
        want = "frames\\[1\\].*bottom row"
    else:
        m = np.array(d["frames"][2]["transform_matrix"])
        m[:3, :3] = m[:3, :3] @ np.array([[1, 0.3, 0], [0, 1, 0], [0, 0, 1]])
        d["frames"][2]["transform_matrix"] = m.tolist()
        want = "frames\\[2\\].*not orthonormal"
    p.write_text(json.dumps(d))
    with pytest.raises(DatasetError, match=want) as ei:
        load_dataset(tmp_path)
    assert "transforms_train.json" in str(ei.value)


_DEEP = "[" * 100000 + "]" * 100000  # JSON nested past Python's recursion limit
BAD_TRANSFORMS = {  # case -> (edit of transforms_train.json as text or as a dict, what the error says)
    "integer past any float in a matrix": (lambda d: d["frames"][0]["transform_matrix"][0].__setitem__(3, 10**400),
                                           "frames\\[0\\].*too large"),
    "integer past any float as the angle": (lambda d: d.__setitem__("camera_angle_x", 10**400), "camera_angle_x"),
    "5000-digit integer": (lambda t: t.replace('"camera_angle_x": 0.8', '"camera_angle_x": 1' + "0" * 5000),
                           "unreadable JSON.*4300"),
    "nested too deeply": (lambda t: t.replace('"camera_angle_x": 0.8', '"camera_angle_x": ' + _DEEP),
                          "nested too deeply"),
    "matrix of strings": (lambda d: d["frames"][1].__setitem__("transform_matrix", [[str(x) for x in r] for r in
                                                                                    d["frames"][1]["transform_matrix"]]),
                          "frames\\[1\\].*no strings"),
    "matrix of booleans": (lambda d: d["frames"][1]["transform_matrix"][0].__setitem__(0, True),
                           "frames\\[1\\].*no strings or booleans"),
    "field of view 1e-12": (lambda d: d.__setitem__("camera_angle_x", 1e-12), "camera_angle_x.*field of view"),
    "focal length 1e13 px": (lambda d: (d.pop("camera_angle_x"), d.__setitem__("fl_x", 1e13)), "fl_x.*focal length"),
    "principal point far outside": (lambda d: d.__setitem__("cx", -1e6), "cx.*principal point"),
    "the same image twice": (lambda d: d["frames"][2].__setitem__("file_path", d["frames"][0]["file_path"]),
                             "frames\\[2\\].*same image as frames\\[0\\]"),
}


@pytest.mark.parametrize("case", sorted(BAD_TRANSFORMS))
def test_bad_transforms_are_named(tmp_path, case):
    """Found by a battery of bad inputs (session 35): each was a traceback or trained on without a word."""
    fac.make_nerf(tmp_path, splits={"train": 3, "test": 2})
    p = tmp_path / "transforms_train.json"
    edit, want = BAD_TRANSFORMS[case]
    if case in ("5000-digit integer", "nested too deeply"):
        p.write_text(edit(p.read_text().replace('"camera_angle_x": 0.8,', '"camera_angle_x": 0.8,')))
        assert p.read_text().count(_DEEP[:10]) or "0" * 5000 in p.read_text()
    else:
        d = json.loads(p.read_text())
        edit(d)
        p.write_text(json.dumps(d))
    with pytest.raises(DatasetError, match=want) as ei:
        load_dataset(tmp_path)
    assert "transforms_train.json" in str(ei.value)


@pytest.mark.parametrize("case", ["one view", "one view held out", "cameras at one place", "every photo transparent",
                                  "every photo black"])
def test_views_that_cannot_make_a_reconstruction_are_refused(tmp_path, capsys, case):
    from PIL import Image

    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    if case == "one view":
        d["frames"] = d["frames"][:1]
        want = "1 training view: a reconstruction needs"  # its own test split: no word of a hold-out
    elif case == "one view held out":  # without transforms_test.json the hold-out took it: said, not "no views"
        (data / "transforms_test.json").unlink()
        d["frames"] = d["frames"][:1]
        want = "0 training views; 1 more is in the test split held out from them (every 8th photo by name"
    elif case == "cameras at one place":
        for f in d["frames"]:
            for r, v in enumerate((0.0, 0.0, 4.0)):
                f["transform_matrix"][r][3] = v
        want = "same position"
    elif case == "every photo transparent":
        for img in (data / "train").glob("*.png"):
            a = np.array(Image.open(img))
            a[..., 3] = 0
            Image.fromarray(a).save(img)
        want = "fully transparent"
    else:  # opaque where the object is, and black: no light reached the camera
        for img in (data / "train").glob("*.png"):
            a = np.array(Image.open(img))
            a[..., :3] = 0
            Image.fromarray(a).save(img)
        want = "black where it shows anything"
    p.write_text(json.dumps(d))
    out = tmp_path / "out"
    rc, err, _ = _run_cli(["train", data, "--out", out, *TINY_RUN], capsys)
    assert rc == 2 and want in err and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["folder", "named pipe"])
def test_a_frame_whose_image_is_not_a_file_says_what_is_there(tmp_path, capsys, kind):
    """A folder named r_3.png, or a named pipe, was reported as a "missing" image (a warning, and the frame
    dropped)."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    img = data / "train" / "r_3.png"
    img.unlink()
    if kind == "folder":
        img.mkdir()
    else:
        import os

        os.mkfifo(img)
    want = {"folder": "a folder", "named pipe": "not a regular file"}[kind]
    out = tmp_path / "out"
    rc, err, _ = _run_cli(["train", data, "--out", out, *TINY_RUN], capsys)
    assert rc == 2 and want in err and "r_3.png" in err and "frames[3]" in err and err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("kind", ["dangling link", "link loop"])
def test_a_frame_whose_image_is_a_broken_link_is_missing(tmp_path, kind):
    """An unfetched file of a git-annex / DVC checkout is a link to nothing: a missing frame (a warning, the frame
    skipped), as the COLMAP loader does, not a refusal."""
    from triplet_cl.datasets import DatasetWarning

    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    img = data / "train" / "r_3.png"
    img.unlink()
    img.symlink_to(data / "annex" / "r_3.png" if kind == "dangling link" else img.name)
    with pytest.warns(DatasetWarning, match="missing"):
        ds = load_dataset(data)
    assert len(ds.train) == 39

@pytest.mark.parametrize("argv, option", [
    (["--iterations", "20", "--light-phase", "21"], "--light-phase"),
    (["--light-phase", "3001"], "--light-phase"),
    (["--mesh-stage", "--mesh-iterations", "50", "--mesh-light-phase", "51"], "--mesh-light-phase"),
])
def test_a_light_phase_longer_than_its_run_is_refused(tmp_path, capsys, demo_copy, argv, option):
    """--light-phase 500 with --iterations 20 trained with one material for the whole object, without a word."""
    out = tmp_path / "out"
    rc, err, _ = _run_cli(["train", demo_copy, "--out", out, *argv], capsys)
    assert rc == 2 and option in err and "longer than" in err and err.count("\n") == 1, err
    assert not out.exists()


def test_a_light_phase_as_long_as_its_run_is_accepted():
    """Equal: one material for the whole object on purpose (and the mesh stage's the same)."""
    from triplet_cl.validate import _check_phases

    for argv in (["--iterations", "20", "--light-phase", "20"], ["--light-phase", "3000"],
                 ["--mesh-stage", "--mesh-iterations", "50", "--mesh-light-phase", "50"]):
        _check_phases(build_parser().parse_args(["train", str(DEMO), "--out", "/nonexistent/x", *argv]))


@pytest.mark.parametrize("mode", ["RGBA", "RGB"])
def test_a_gif_is_read_or_named(tmp_path, mode):
    """A GIF: OpenImageIO names channel 4 of 4 its alpha (IndexError, a traceback). Read with its alpha where it
    has one."""
    from PIL import Image

    from triplet_cl.datasets.images import read_image

    png = read_image(DEMO / "train" / "r_0.png")
    Image.open(DEMO / "train" / "r_0.png").convert(mode).save(tmp_path / "r_0.gif")
    img = read_image(tmp_path / "r_0.gif")
    assert img.rgb.shape == png.rgb.shape
    if mode == "RGBA":
        # a GIF's transparency is one palette entry: the PNG's partly covered outline pixels come out opaque
        assert img.alpha is not None and np.mean((img.alpha > 0.5) == (png.alpha > 0.5)) > 0.95
        inside = png.alpha > 0.99
        assert np.abs(img.rgb - png.rgb)[inside].mean() < 0.05  # a 256-colour palette
    else:
        assert img.alpha is None or (img.alpha == 1).all()


def test_an_exr_whose_pixels_do_not_cover_its_frame_is_refused(tmp_path):
    """An 86x86 data window at (10, 10) in a 96x96 display window trained as an 86x86 image centred at 43: the
    cameras were wrong, silently."""
    import OpenImageIO as oiio

    from triplet_cl.datasets.images import read_image

    spec = oiio.ImageSpec(86, 86, 4, "float")
    spec.x, spec.y, spec.full_x, spec.full_y, spec.full_width, spec.full_height = 10, 10, 0, 0, 96, 96
    out = oiio.ImageOutput.create(str(tmp_path / "dw.exr"))
    out.open(str(tmp_path / "dw.exr"), spec)
    out.write_image(np.ones((86, 86, 4), np.float32))
    out.close()
    with pytest.raises(DatasetError, match="data window") as ei:
        read_image(tmp_path / "dw.exr")
    assert "dw.exr" in str(ei.value) and "96x96" in str(ei.value)


def test_a_png_with_an_offset_and_a_frame_s_own_focal_length_are_read(tmp_path):
    """The review of the battery-2 fixes: a PNG's oFFs offset (a crop without +repage) read as an EXR data window and
    was refused; a frame's own fl_x beside the file's camera_angle_x (instant-ngp: the frame's overrides) was refused
    as a disagreement."""
    import struct
    import zlib

    from triplet_cl.datasets.images import read_image

    png = (DEMO / "train" / "r_0.png").read_bytes()
    body = struct.pack(">iiB", 10, 20, 0)
    chunk = struct.pack(">I", len(body)) + b"oFFs" + body + struct.pack(">I", zlib.crc32(b"oFFs" + body))
    (tmp_path / "offs.png").write_bytes(png[:33] + chunk + png[33:])  # after the signature and IHDR
    assert read_image(tmp_path / "offs.png").rgb.shape == read_image(DEMO / "train" / "r_0.png").rgb.shape
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    d["frames"][0]["fl_x"] = 30.0
    p.write_text(json.dumps(d))
    assert load_dataset(data).train[0].camera.fx == 30.0


def test_two_images_of_a_split_with_one_file_name_get_two_renders(tmp_path):
    """test/a/r_0 and test/b/r_0: one test render replaced the other (renders are named by the file name). A rig's
    cam0/0001 and cam1/0001 is a normal dataset: where file names repeat, renders are named by the path."""
    from triplet_cl.datasets.base import render_files

    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    for sub, src in (("a", "r_0"), ("b", "r_1")):
        (data / "test" / sub).mkdir()
        shutil.copy(data / "test" / f"{src}.png", data / "test" / sub / "r_0.png")
    p = data / "transforms_test.json"
    d = json.loads(p.read_text())
    d["frames"][0]["file_path"], d["frames"][1]["file_path"] = "./test/a/r_0", "./test/b/r_0"
    p.write_text(json.dumps(d))
    out = tmp_path / "out"
    assert cli_main(["train", str(data), "--out", str(out), *TINY_RUN]) == 0
    got = sorted(x.name for x in (out / "renders" / "test").glob("*.png"))
    assert "test__a__r_0.png" in got and "test__b__r_0.png" in got and len(got) == 8, got
    assert render_files(["test/r_2", "test/r_3"]) == ["r_2.png", "r_3.png"]  # unique names: as before


def test_resuming_after_frames_were_removed_names_the_checkpoint(tmp_path, capsys):
    """--resume after the dataset lost frames: an IndexError traceback in the view order. Evaluating the run still
    works (only training needs the views it was made with)."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    out = tmp_path / "run"
    assert cli_main(["train", str(data), "--out", str(out), *TINY_RUN]) == 0
    capsys.readouterr()
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    d["frames"] = d["frames"][:10]
    p.write_text(json.dumps(d))
    before = _tree(out)
    rc, err, out_text = _run_cli(["train", "--out", out, "--resume", "--iterations", "6"], capsys)
    assert rc == 2 and "ckpt_0000004.npz" in err and "40 training views" in err and "now has 10" in err, err
    assert err.count("\n") == 1 and "resuming" not in out_text and _tree(out) == before
    assert cli_main(["eval", str(out)]) == 0


@pytest.mark.parametrize("split", ["train", "test"])
def test_a_split_file_that_is_a_folder_is_named(tmp_path, split):
    """transforms_test.json as a folder was passed over (the hold-out replaced the test split, silently);
    transforms_train.json as a folder gave "cannot tell the dataset format"."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    (data / f"transforms_{split}.json").unlink()
    (data / f"transforms_{split}.json").mkdir()
    with pytest.raises(DatasetError, match="is a folder") as ei:
        load_dataset(data)
    assert f"transforms_{split}.json" in str(ei.value)


def test_a_bbox_no_camera_sees_is_refused_before_training(tmp_path, capsys, demo_copy, run):
    """--bbox 100,100,100,101,101,101: the whole training ran, then "the mesh extraction found no surface", naming
    nothing. Refused before any work, no run folder left; `extract` refuses it too; a box round the object passes."""
    from triplet_cl.mesh.roi import ROI, cameras_seeing

    out = tmp_path / "out"
    far = "--bbox=100,100,100,101,101,101"
    rc, err, _ = _run_cli(["train", demo_copy, "--out", out, *TINY_RUN, "--mesh-stage", far], capsys)
    assert rc == 2 and "--bbox" in err and "none of the 40 training cameras" in err and err.count("\n") == 1, err
    assert not out.exists()
    before = _tree(run)
    rc, err, _ = _run_cli(["extract", run, far], capsys)
    assert rc == 2 and "--bbox" in err and _tree(run) == before, err
    cams = [v.camera for v in load_dataset(demo_copy).train]
    assert cameras_seeing(ROI.from_bbox((-1, -1, -1, 1, 1, 1)), cams) == len(cams)
    assert cameras_seeing(ROI.from_bbox((100, 100, 100, 101, 101, 101)), cams) == 0
    c = cams[0].center  # a box round one camera: seen by it whatever the grid's points
    assert cameras_seeing(ROI.from_bbox((*(c - 0.01), *(c + 0.01))), cams[:1]) == 1
    for out in (tmp_path / "empty", tmp_path / "a" / "b" / "c"):  # an empty folder stays empty; new parents go
        if out.name == "empty":
            out.mkdir()
        rc, err, _ = _run_cli(["train", demo_copy, "--out", out, *TINY_RUN, "--mesh-stage", far], capsys)
        assert rc == 2 and "--bbox" in err, err
    assert not any((tmp_path / "empty").iterdir()) and not (tmp_path / "a").exists()


def test_warnings_are_one_line_naming_the_command(tmp_path, capsys):
    """A dataset warning printed the module's path and line and the source line that warned (two lines of
    internals); pyopencl's "Non-empty compiler output" notice is not the user's business."""
    import warnings

    import pyopencl
    from triplet_cl.cli.main import _one_line_warnings

    from triplet_cl.datasets import DatasetWarning

    with _one_line_warnings("train"):
        warnings.warn("skipped 1 of 40 frames", DatasetWarning, stacklevel=1)
        warnings.warn("Non-empty compiler output encountered", pyopencl.CompilerWarning, stacklevel=1)
    err = capsys.readouterr().err
    assert err == "triplet train: warning: skipped 1 of 40 frames\n", err


def test_out_through_a_missing_folder_and_dot_dot_says_so(tmp_path, capsys, demo_copy, monkeypatch):
    """--out new/../run gave "new/..: File exists" (the OS cannot step out of a folder that is not there)."""
    monkeypatch.chdir(tmp_path)
    rc, err, _ = _run_cli(["train", demo_copy, "--out", "new/../run", *TINY_RUN], capsys)
    assert rc == 2 and "'..' after new, a folder that does not exist" in err and err.count("\n") == 1, err
    assert not (tmp_path / "run").exists() and not (tmp_path / "new").exists()
    (tmp_path / "new").mkdir()  # through a folder that exists, '..' is an ordinary path
    assert cli_main(["train", str(demo_copy), "--out", "new/../run", *TINY_RUN]) == 0
    assert (tmp_path / "run" / "metrics.json").is_file()


def test_render_over_a_folder_named_like_a_render_is_refused_first(run, capsys):
    """RUN/renders/test/r_0.png a folder (holding a user file): refused after rendering, naming the temporary file
    (.r_0.q2ld2bfr.png)."""
    target = run / "renders" / "test" / "r_0.png"
    target.unlink()
    target.mkdir()
    (target / "user.txt").write_text("mine")
    before = _tree(run)
    rc, err, out = _run_cli(["render", run], capsys)
    assert rc == 2 and "renders/test/r_0.png is a folder" in err and err.count("\n") == 1, err
    assert _tree(run) == before and "render" not in out


@pytest.mark.parametrize("cmd", ["render", "relight"])
def test_images_are_not_written_among_the_run_s_own_files(run, tmp_path, capsys, cmd):
    """relight RUN --out RUN wrote its PNGs into the run's root folder, beside config.json and the checkpoints."""
    lf = tmp_path / "l.json"
    lf.write_text(json.dumps({"lights": [_POINT]}))
    before = _tree(run)
    extra = ["--lights", lf] if cmd == "relight" else []
    rc, err, _ = _run_cli([cmd, run, *extra, "--out", str(run) + "/"], capsys)
    assert rc == 2 and "is the run folder itself" in err and err.count("\n") == 1, err
    assert _tree(run) == before


def test_out_as_a_dangling_link_says_so(tmp_path, capsys, demo_copy):
    """A dangling symbolic link as --out: "File exists"."""
    (tmp_path / "out").symlink_to(tmp_path / "nowhere")
    rc, err, _ = _run_cli(["train", demo_copy, "--out", tmp_path / "out", *TINY_RUN], capsys)
    assert rc == 2 and "symbolic link that leads nowhere" in err and err.count("\n") == 1, err
    assert not (tmp_path / "nowhere").exists()


def test_a_key_given_twice_in_a_json_object_is_refused(tmp_path, run, capsys):
    """json keeps the last of two equal keys silently: two camera_angle_x trained on the second."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    p.write_text(p.read_text().replace('"camera_angle_x":', '"camera_angle_x": 0.5, "camera_angle_x":', 1))
    with pytest.raises(DatasetError, match="'camera_angle_x' appears twice") as ei:
        load_dataset(data)
    assert "transforms_train.json" in str(ei.value)
    lf = tmp_path / "l.json"
    lf.write_text('{"lights": [{"type": "point", "position": [0, 0, 3], "position": [0, 0, 4], "intensity": 1}]}')
    rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and "'position' appears twice" in err and err.count("\n") == 1, err


def test_an_empty_light_kind_and_a_non_panorama_envmap_are_refused(tmp_path, run, capsys, demo_copy):
    """--lights point,,ambient dropped the empty item silently; 1x1 and 8x64 "environment maps" were projected."""
    rc, err, _ = _run_cli(["train", demo_copy, "--out", tmp_path / "o", "--lights", "point,,ambient", *TINY_RUN],
                          capsys)
    assert rc == 2 and "--lights: an empty item" in err and not (tmp_path / "o").exists(), err
    for w, h in ((1, 1), (8, 64)):
        env = fac.write_image(tmp_path / f"e{w}x{h}.exr", np.ones((h, w, 4), np.float32), "float")
        lf = tmp_path / "l.json"
        lf.write_text(json.dumps({"lights": [{"type": "envmap", "filename": env.name}]}))
        rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
        assert rc == 2 and f"is {w}x{h}: an equirectangular environment map is twice as wide" in err, err
    assert not (tmp_path / "out").exists()


def test_relight_with_many_lights_prints_a_short_summary(run, tmp_path, capsys):
    """5000 lights printed every light's class name: a 60 kB line (battery 8). Each kind once, with its count."""
    lf = tmp_path / "many.json"
    lf.write_text(json.dumps({"lights": [_POINT] * 300 + [{"type": "constant", "radiance": 0.1}]}))
    rc, err, out = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out", "--split", "test"], capsys)
    assert rc == 0, err
    assert "300 x PointLight, SHEnvironmentLight" in out and len(out.splitlines()[-1]) < 300, out


def _relight_refs(folder: Path) -> Path:
    """A relight references' folder with one set "a" (its images folder "a", absent) and no albedo images."""
    folder.mkdir()
    (folder / "relight.json").write_text(json.dumps({"sets": {"a": {"lights": [_POINT], "images": "a"}},
                                                     "albedo": "albedo"}))
    return folder


def test_eval_out_inside_the_relight_references_is_refused(run, tmp_path, capsys):
    """eval --relight REFS --out REFS/x wrote relit images among the user's reference images."""
    refs = _relight_refs(tmp_path / "refs")
    before = _tree(refs)
    for out in (refs, refs / "x"):
        rc, err, _ = _run_cli(["eval", run, "--relight", refs, "--out", out], capsys)
        assert rc == 2 and "inside the relight references' folder" in err and err.count("\n") == 1, err
    assert _tree(refs) == before and not (refs / "x").exists()


def test_focal_length_given_twice_must_agree(tmp_path):
    """fl_x = 40 beside camera_angle_x = 0.698 (a focal length of 131.9 pixels at 96²): fl_x was used silently."""
    import math

    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    d["fl_x"] = 40
    p.write_text(json.dumps(d))
    with pytest.raises(DatasetError, match="disagree") as ei:
        load_dataset(data)
    assert "fl_x = 40" in str(ei.value) and "131.9" in str(ei.value)
    d["fl_x"] = 0.5 * 96 / math.tan(0.5 * d["camera_angle_x"]) * 1.005  # the same camera, rounded: accepted
    p.write_text(json.dumps(d))
    assert load_dataset(data).train[0].camera.fx == pytest.approx(d["fl_x"])


def _damage(a, meta, case):
    if case == "faces past the vertices":
        a["F"] = a["F"] + len(a["V"])
    elif case == "iteration as text":
        meta["it"] = "four"
    elif case == "rng state":
        meta["rng"] = {"x": 1}
    elif case == "alpha rows":
        a["alpha"] = a["alpha"][:10]
    elif case == "view order":
        meta["order"] = [999, 1000, -5]


@pytest.mark.parametrize("case", ["faces past the vertices", "iteration as text", "rng state", "alpha rows",
                                  "view order"])
def test_a_damaged_checkpoint_is_named(run, capsys, case):
    """Hand-edited or damaged checkpoints were refused with raw internal text ("invalid literal for int()", "state
    must be for a PCG64 RNG") or an IndexError traceback (the view order), naming no file."""
    import io

    ck = run / "checkpoints" / (run / "checkpoints" / "latest").read_text()
    a = dict(np.load(ck))
    meta = json.loads(bytes(a["meta"]).decode())
    _damage(a, meta, case)
    a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **a)
    ck.write_bytes(buf.getvalue())
    before = _tree(run)
    rc, err, _ = _run_cli(["train", "--out", run, "--resume", "--iterations", "6"], capsys)
    assert rc == 2 and ck.name in err and "damaged" in err and err.count("\n") == 1, err
    assert _tree(run) == before


def test_negative_linear_images_are_refused_and_ringing_clipped(tmp_path):
    """A linear (EXR) photo with radiance below 0: a filter's ringing of a few thousandths is clipped to 0, more is
    an error naming the file."""
    from triplet_cl.datasets.images import read_image

    px = np.full((12, 12, 4), 0.5, np.float32)
    px[0, 0, :3] = -0.004  # ringing
    assert read_image(fac.write_image(tmp_path / "ok.exr", px, "float")).rgb.min() == 0.0
    px[..., :3] = -5.0
    with pytest.raises(DatasetError, match="negative radiance") as ei:
        read_image(fac.write_image(tmp_path / "bad.exr", px, "float"))
    assert "bad.exr" in str(ei.value)


def test_runerror_is_a_triplet_error():
    from triplet_cl.errors import TripletError

    assert issubclass(RunError, TripletError) and issubclass(NonFiniteError, TripletError)


# ---- mesh export details ------------------------------------------------------------------------------
def _png_chunks(data: bytes) -> list[bytes]:
    import struct

    out, i = [], 8
    while i < len(data):
        n = struct.unpack(">I", data[i:i + 4])[0]
        out.append(data[i + 4:i + 8])
        i += 12 + n
    return out


def _small_asset(lights):
    import trimesh

    from triplet_cl.mesh.asset import MeshAsset

    m = trimesh.creation.icosphere(subdivisions=1)
    n = len(m.vertices)
    attrs = {"albedo": np.full((n, 3), 0.5), "roughness": np.full(n, 0.4), "metallic": np.full(n, 0.2),
             "ao": np.ones(n), "alpha": np.ones(n)}
    return MeshAsset(m.vertices, m.faces, attrs, "cook_torrance", lights)


def test_mesh_files_headers_colour_tags_and_lights(tmp_path):
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from tests.tools.gltf_check import check_glb
    from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight
    from triplet_cl.mesh.export import export_asset

    d = np.array([0.3, 0.8, -0.5])
    lights = [PointLight([0.0, 3.0, 1.0], [4.0, 2.0, 1.0]), DirectionalLight(d, [0.5, 0.5, 0.25]),
              AmbientLight([0.1, 0.1, 0.1])]
    paths = export_asset(_small_asset(lights), tmp_path, texture_size=64)
    header = paths["ply"].read_bytes().split(b"end_header")[0]
    assert b"connected triangle mesh" in header and b"soup" not in header
    # data maps carry no colour-space tag; the base colour stays sRGB
    for name in ("mesh_roughness.png", "mesh_metallic.png"):
        chunks = _png_chunks((tmp_path / name).read_bytes())
        assert not {b"sRGB", b"gAMA", b"cHRM", b"iCCP"} & set(chunks), (name, chunks)
        assert np.asarray(Image.open(tmp_path / name)).ndim == 2  # still a valid PNG
    assert b"sRGB" in _png_chunks((tmp_path / "mesh_basecolor.png").read_bytes())
    doc, _ = check_glb(paths["glb"])
    defs = doc["extensions"]["KHR_lights_punctual"]["lights"]
    assert [x["type"] for x in defs] == ["point", "directional"] and "KHR_lights_punctual" in doc["extensionsUsed"]
    assert defs[0]["intensity"] == 4.0 and np.allclose(defs[0]["color"], [1, 0.5, 0.25])
    nodes = {n["extensions"]["KHR_lights_punctual"]["light"]: n for n in doc["nodes"] if "extensions" in n}
    assert np.allclose(nodes[0]["translation"], [0, 3, 1])
    shines = Rotation.from_quat(nodes[1]["rotation"]).apply([0, 0, -1])  # a glTF directional light shines along -Z
    assert np.allclose(shines, -d / np.linalg.norm(d))
    assert set(doc["scenes"][0]["nodes"]) == {0, 1, 2}


def test_resume_with_another_dataset_is_refused(run, tmp_path, capsys):
    other = tmp_path / "other"
    fac.make_nerf(other)
    before = _tree(run)
    rc, err, _ = _run_cli(["train", other, "--resume", "--out", run, "--iterations", "5"], capsys)
    assert rc == 2 and "DATA" in err and "not the run's dataset" in err
    assert _tree(run) == before


def test_resume_finds_the_newest_checkpoint_when_latest_is_lost(run, capsys):
    (run / "checkpoints" / "latest").unlink()
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    assert rc == 0, err
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 5


def test_diverging_learning_rate_is_stopped(tmp_path):
    tr = Trainer(DEMO, tmp_path / "r", _small_cfg(lr_position=1e30, lr_position_final=1e30), quiet=True)
    with pytest.raises(NonFiniteError) as ei:
        tr.train()
    assert ei.value.group == "V" and "learning rate" in str(ei.value) and ei.value.iteration <= 3
    assert not (tmp_path / "r" / "triplets.ply").exists()


def test_device_allocation_failure_is_one_line(run, capsys, monkeypatch):
    import pyopencl as cl

    from triplet_cl.device import get_device
    from triplet_cl.validate import device_memory_message

    dev = get_device()
    ctx = getattr(dev, "context", None) or dev.ctx
    with pytest.raises(cl.Error) as ei:
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, size=2**50)
        # a driver that allocates on first use (NVIDIA's) accepts the buffer and fails here
        cl.enqueue_fill_buffer(dev.queue, buf, np.uint8(0), 0, 2**50).wait()
    assert "--faces-per-pixel" in device_memory_message(ei.value)
    assert device_memory_message(ValueError("x")) is None
    import triplet_cl.train as train_mod

    def boom(*a, **k):
        raise ei.value

    monkeypatch.setattr(train_mod, "render", boom)
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    last = err.strip().splitlines()[-1]
    assert rc == 2 and "cannot allocate" in last


def test_export_device_spec_is_checked(run, capsys):
    rc, err, _ = _run_cli(["export", run, "--device", "no-such-device-xyz"], capsys)
    assert rc == 2 and "no-such-device-xyz" in err


def test_mesh_resolution_memory_is_checked(run, capsys, monkeypatch):
    import triplet_cl.validate as val

    monkeypatch.setattr(val, "available_memory", lambda: 2**30)
    rc, err, _ = _run_cli(["extract", run, "--mesh-resolution", "512"], capsys)
    assert rc == 2 and "--mesh-resolution" in err and "GiB" in err


@pytest.mark.parametrize("command", ["extract", "export", "train"])
def test_texture_size_memory_is_checked(run, tmp_path, capsys, monkeypatch, command):
    """--texture-size 16384 is in range but needs ~32 GiB while baking: a MemoryError after the whole mesh stage."""
    import triplet_cl.validate as val

    monkeypatch.setattr(val, "available_memory", lambda: 8 * 2**30)
    argv = {"extract": ["extract", run], "export": ["export", run, "--out", tmp_path / "x"],
            "train": ["train", DEMO, "--out", tmp_path / "x", "--mesh-stage"]}[command]
    before = _tree(run)
    rc, err, _ = _run_cli([*argv, "--texture-size", "16384"], capsys)
    assert rc == 2 and "--texture-size" in err and "GiB" in err and err.count("\n") == 1, err
    assert _tree(run) == before and not (tmp_path / "x").exists()


def test_init_points_memory_is_checked(tmp_path, capsys, monkeypatch):
    import triplet_cl.validate as val

    monkeypatch.setattr(val, "available_memory", lambda: 300 * 2**20)
    rc, err, _ = _run_cli(["train", DEMO, "--out", tmp_path / "o", "--init-points", "150000"], capsys)
    assert rc == 2 and "--init-points" in err and "GiB" in err and not (tmp_path / "o").exists()


def test_bad_color_is_refused_by_argparse(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli_main(["train", str(DEMO), "--out", str(tmp_path / "o"), "--color", "srgb"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--color" in err and "'linear', 'encoded'" in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    assert err.count("\n") == 1 and "usage:" not in err, err  # one line, not argparse's usage block as well


@pytest.mark.parametrize("extra", [["--white-light", "blue"], ["--light-phase", "1.5"], ["--sensor-clip", "maybe"]])
def test_bad_light_rules_are_refused_by_argparse(tmp_path, capsys, extra):
    with pytest.raises(SystemExit) as exc:
        cli_main(["train", str(DEMO), "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and extra[0] in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    assert err.count("\n") == 1 and "usage:" not in err, err


def test_background_shell_memory_is_checked(tmp_path, capsys, monkeypatch):
    import triplet_cl.validate as val

    monkeypatch.setattr(val, "available_memory", lambda: 300 * 2**20)  # 20000 initial points fit, 150000 more do not
    rc, err, _ = _run_cli(["train", DEMO, "--out", tmp_path / "o", "--background-shell", "150000"], capsys)
    assert rc == 2 and "--background-shell" in err and "GiB" in err and not (tmp_path / "o").exists()


def test_atlas_padding_grows_with_the_texture(monkeypatch):
    import triplet_cl.mesh.export as ex
    from triplet_cl.lights import PointLight

    seen = []
    orig = ex.uv_atlas

    def spy(V, F, size, padding):
        seen.append((size, padding))
        return orig(V, F, size, padding)

    monkeypatch.setattr(ex, "uv_atlas", spy)
    asset = _small_asset([PointLight([0, 3, 0], [1, 1, 1])])
    for size in (64, 1024):
        ex.bake_asset(asset, size)
    ex.bake_asset(asset, 64, padding=3)
    assert seen == [(64, 2), (1024, 4), (64, 3)]


def test_checkpoint_from_before_a_new_config_field_still_resumes(run, capsys):
    """A field added to TrainConfig later (absent from an old checkpoint's record) matches at its default."""
    ck = run / "checkpoints" / "ckpt_0000004.npz"
    with np.load(ck) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(bytes(a["meta"]).decode())
    del meta["config"]["ssim_lambda"]
    del meta["config"]["density"]["error_resplit_ratio"]  # a density field added later: off (None) before it
    meta["config"]["a_field_since_removed"] = 1
    a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(ck, **a)
    cfg = json.loads((run / "config.json").read_text())  # a run from before it has no such field in config.json
    del cfg["train"]["density"]["error_resplit_ratio"]  # either (today's runs: 0.9)
    (run / "config.json").write_text(json.dumps(cfg))
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    assert rc == 0, err
    from triplet_cl.runs import config_from_saved, read_run_config

    assert config_from_saved(run, read_run_config(run)).density.error_resplit_ratio is None  # it resumed as it was


# ---- review of issue 17 / 23 surfaces: relight, eval --relight, colmap -----------------------------------
_POINT = {"type": "point", "position": [0, 0, 3], "intensity": [1, 1, 1]}
BAD_RELIGHT = {  # case -> (light file content or None (a folder), extra argv, what the one-line error names)
    "folder": (None, [], "is a folder"),
    "empty set name": ({"sets": {"a": {"lights": [_POINT]}}}, ["#"], "names no set"),
    "unknown set": ({"sets": {"a": {"lights": [_POINT]}}}, ["#b"], "no set named 'b'"),
    "env degree": ({"lights": [_POINT]}, ["--env-degree", "9"], "--env-degree"),
    "negative env degree": ({"lights": [_POINT]}, ["--env-degree", "-1"], "--env-degree"),
    "split": ({"lights": [_POINT]}, ["--split", "val"], "--split val"),
    "not an image": ({"lights": [{"type": "envmap", "filename": "sky.exr"}]}, [], "sky.exr"),
    "bool intensity": ({"lights": [{**_POINT, "intensity": True}]}, [], "lights[0].intensity"),
    "bool in a vector": ({"lights": [{**_POINT, "position": [0, False, 3]}]}, [], "lights[0].position"),
    "our form without its parameters": ({"lights": [{"type": "PointLight"}]}, [], "lights[0].position: missing"),
    "our form, NaN": ({"lights": [{"type": "AmbientLight", "color": [0, float("nan"), 0]}]}, [], "lights[0].color"),
    "our form, text": ({"lights": [{"type": "AmbientLight", "color": "grey"}]}, [], "lights[0].color"),
    "vertex SH light on a run without one": ({"lights": [{"type": "VertexSHLight"}]}, [], "VertexSHLight"),
    "integer past any float": ({"lights": [{**_POINT, "intensity": [10**400, 1, 1]}]}, [], "lights[0].intensity"),
    "nested too deeply": ('{"lights": ' + "[" * 100000 + "]" * 100000 + "}", [], "nested too deeply"),
    # battery 2 (session 36): a set's name is the folder its renders go to
    "set name with a path": ({"sets": {"../victim": {"lights": [_POINT]}}}, [], "not a plain folder name"),
    "absolute set name": ({"sets": {"/tmp/victim": {"lights": [_POINT]}}}, [], "not a plain folder name"),
    "blank set name": ({"sets": {"": {"lights": [_POINT]}}}, [], "not a plain folder name"),
    "our form, negative intensity": ({"lights": [{"type": "PointLight", "position": [1, 2, 3],
                                                  "intensity": [-5, -5, -5]}]}, [], "must be >= 0"),
    "overflowing intensity": ({"lights": [{**_POINT, "intensity": 1e308}]}, [], "at most 1e+30"),
    "our form, overflowing": ({"lights": [{"type": "AmbientLight", "color": [1e300, 1, 1]}]}, [], "at most 1e+30"),
    "falloff as text": ({"lights": [{"type": "PointLight", "position": [1, 2, 3], "intensity": [5, 5, 5],
                                     "falloff": "no"}]}, [], "lights[0].falloff"),
}


@pytest.mark.parametrize("case", sorted(BAD_RELIGHT))
def test_bad_relight_inputs_are_one_line_and_write_nothing(run, tmp_path, capsys, case):
    doc, extra, needle = BAD_RELIGHT[case]
    lf = tmp_path / "lights"
    lf.mkdir()
    (lf / "sky.exr").write_text("not an image")
    spec = str(lf)
    if doc is not None:
        (lf / "l.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
        spec = str(lf / "l.json") + (extra[0] if extra and extra[0].startswith("#") else "")
    argv = ["relight", run, "--lights", spec, "--out", tmp_path / "out", *[a for a in extra if not a.startswith("#")]]
    before = _tree(run)
    rc, err, _ = _run_cli(argv, capsys)
    assert rc == 2 and needle in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists() and _tree(run) == before


def test_a_set_named_like_a_path_writes_nothing_outside_out(run, tmp_path, capsys):
    """A set named "../victim" wrote its renders over the user's victim/r_0.png, beside --out."""
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "r_0.png").write_text("USER DATA")
    lf = tmp_path / "l.json"
    lf.write_text(json.dumps({"sets": {"../victim": {"lights": [_POINT]}, "ok": {"lights": [_POINT]}}}))
    for spec in (str(lf), str(lf) + "#../victim"):
        rc, err, _ = _run_cli(["relight", run, "--lights", spec, "--out", tmp_path / "out"], capsys)
        assert rc == 2 and "not a plain folder name" in err, err
    assert _tree(victim) == {"r_0.png": b"USER DATA"} and not (tmp_path / "out").exists()


def test_eval_relight_missing_references_fail_before_any_work(run, tmp_path, capsys):
    rd = _relight_refs(tmp_path / "rel")
    before = _tree(run)
    rc, err, out = _run_cli(["eval", run, "--relight", rd], capsys)
    assert rc == 2 and "sets.a.images" in err and "folder not found" in err, err
    assert "PSNR" not in out and _tree(run) == before  # the novel views were not even evaluated
    (rd / "a").mkdir()
    rc, err, _ = _run_cli(["eval", run, "--relight", rd], capsys)
    assert rc == 2 and "sets.a.images" in err and "no image for the test view" in err, err
    assert _tree(run) == before
    (rd / "a" / "r_0.png").mkdir()  # a folder where the image should be: named as such (battery 11)
    rc, err, _ = _run_cli(["eval", run, "--relight", rd], capsys)
    assert rc == 2 and "r_0.png: a folder, not the image of the test view" in err, err


def test_colmap_paths_are_checked_before_any_work(tmp_path, demo_copy, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    f = tmp_path / "file"
    f.write_text("x")
    for argv, needle in ((["colmap", f, "--out", tmp_path / "o"], "IMAGES"),
                         (["colmap", photos, "--out", f], "--out"),
                         (["colmap", photos, "--out", photos / "sub"], "inside the photos folder"),
                         (["colmap", photos, "--out", photos], "inside the photos folder"),
                         (["colmap", photos, "--out", demo_copy / "sfm"], "inside the dataset folder")):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and needle in err, (argv, err)
    assert list(photos.iterdir()) == [] and not (demo_copy / "sfm").exists()
    assert not [p for p in demo_copy.iterdir() if p.name.startswith(".")]


def test_compare_runs_tool_tells_identical_from_different(run, tmp_path, capsys):
    """tests/tools/compare_runs.py (the refactorings' bitwise check) had no test of its own."""
    from tests.tools.compare_runs import main as compare_main

    twin = tmp_path / "twin"
    shutil.copytree(run, twin)
    assert compare_main([str(run), str(twin)]) == 0
    assert compare_main([str(run)]) == 2
    lights = json.loads((twin / "lights.json").read_text())
    (twin / "lights.json").write_text(json.dumps(lights) + " ")
    assert compare_main([str(run), str(twin)]) == 1
    assert "lights.json DIFFERS" in capsys.readouterr().out


@pytest.mark.parametrize("content", ['{"psnr": ', "[1, 2]", ""])
def test_extract_names_a_damaged_metrics_json_before_any_work(run, capsys, content):
    """The mesh stage merges its "mesh" section into metrics.json: a damaged one failed at the end, after
    minutes of work (a JSON error), or with a TypeError traceback (a list)."""
    (run / "metrics.json").write_text(content)
    before = _tree(run)
    rc, err, out = _run_cli(["extract", run], capsys)
    assert rc == 2 and "metrics.json: damaged" in err and "extract" in err and err.count("\n") == 1, err
    assert "mesh" not in out and _tree(run) == before


@pytest.mark.parametrize("content", ['{"psnr": ', "[1, 2]", ""])
def test_eval_names_a_damaged_metrics_json_before_any_work(run, capsys, content):
    (run / "metrics.json").write_text(content)
    before = _tree(run)
    rc, err, out = _run_cli(["eval", run], capsys)
    assert rc == 2 and "metrics.json: damaged" in err and err.count("\n") == 1, err
    assert "PSNR" not in out and _tree(run) == before


# ---- the verification pass of 2026-11-24 (issue 21, second round) --------------------------------------
ARGPARSE_ERRORS = {  # argv -> what the one-line error names
    "bad choice": (["train", "DEMO", "--out", "OUT", "--color", "srgb"], "--color"),
    "abbreviation": (["train", "DEMO", "--out", "OUT", "--iter", "3"], "--iter"),
    "not a number": (["train", "DEMO", "--out", "OUT", "--iterations", "ten"], "--iterations"),
    "missing RUN": (["extract"], "run"),
    "unknown command": (["frobnicate"], "frobnicate"),
    "bad split": (["render", "OUT", "--split", "holdout"], "--split"),
    "option without its value": (["train", "DEMO", "--out"], "--out"),
}


@pytest.mark.parametrize("case", sorted(ARGPARSE_ERRORS))
def test_argparse_errors_are_one_line(tmp_path, capsys, case):
    argv, named = ARGPARSE_ERRORS[case]
    argv = [str(DEMO) if a == "DEMO" else str(tmp_path / "o") if a == "OUT" else a for a in argv]
    with pytest.raises(SystemExit) as ei:
        cli_main(argv)
    err = capsys.readouterr().err
    assert ei.value.code == 2 and named in err and err.count("\n") == 1 and "usage:" not in err, err
    assert err.startswith("triplet") and "--help" in err
    assert not (tmp_path / "o").exists()


def _relight_dir(tmp_path) -> Path:
    rd = tmp_path / "rel"
    rd.mkdir(exist_ok=True)
    (rd / "relight.json").write_text(json.dumps({"sets": {"a": {"lights": [_POINT]}}}))
    return rd


INTO_CHECKPOINTS = {  # a command writing into RUN/checkpoints (the run's own state) is refused before any work
    "render": lambda run, tmp: ["render", run, "--out", run / "checkpoints"],
    "render below": lambda run, tmp: ["render", run, "--out", run / "checkpoints" / "png"],
    "eval --relight --out": lambda run, tmp: ["eval", run, "--relight", _relight_dir(tmp), "--out",
                                              run / "checkpoints"],
    "relight": lambda run, tmp: ["relight", run, "--lights", run / "lights.json", "--out", run / "checkpoints"],
    "export": lambda run, tmp: ["export", run, "--out", run / "checkpoints"],
    "train a new run there": lambda run, tmp: ["train", DEMO, "--out", run / "checkpoints" / "new", *TINY_RUN],
}


@pytest.mark.parametrize("case", sorted(INTO_CHECKPOINTS))
def test_outputs_into_a_runs_checkpoints_are_refused(run, tmp_path, capsys, case):
    argv = INTO_CHECKPOINTS[case](run, tmp_path)
    before = _tree(run)
    rc, err, out = _run_cli(argv, capsys)
    assert rc == 2 and "--out" in err and "checkpoints folder of the run" in err and err.count("\n") == 1, err
    assert "PSNR" not in out and _tree(run) == before


def test_a_nerf_split_file_given_as_data_is_named(tmp_path, demo_copy, capsys):
    """`train X/transforms_train.json` was read as an instant-ngp transforms.json."""
    for extra in ([], ["--data-format", "nerf"]):
        rc, err, _ = _run_cli(["train", demo_copy / "transforms_train.json", "--out", tmp_path / "o", *extra], capsys)
        assert rc == 2 and "transforms_train.json" in err and str(demo_copy) in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()
    from triplet_cl.datasets import detect_format

    ngp = tmp_path / "my_capture.json"  # any other JSON file given directly is still an instant-ngp file
    ngp.write_text("{}")
    assert detect_format(ngp) == "ngp"


def test_undistortion_cache_is_outside_the_dataset(tmp_path, monkeypatch):
    """The README says triplet never writes into a dataset: the undistorted copy goes to the user's cache;
    one that an older version left in DATA/.triplet_cache is still used (read, nothing written)."""
    pytest.importorskip("pycolmap")
    from triplet_cl.datasets.sfm import LEGACY_CACHE, cache_root

    monkeypatch.delenv("TRIPLET_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root(tmp_path) == tmp_path / "xdg" / "triplet_cl"
    root = tmp_path / "scene"
    fac.make_colmap(root, n=3, model="SIMPLE_RADIAL", params=[7.0, 4.0, 3.0, 0.05])
    before = _tree(root)
    a = load_dataset(root, split_holdout=0)
    assert _tree(root) == before
    made = list((tmp_path / "xdg" / "triplet_cl").iterdir())
    assert len(made) == 1
    # an older version's copy inside the dataset (its key without the alpha's salt) is read, nothing new written
    from triplet_cl.datasets.sfm import _model_key

    old_key = _model_key(root / "sparse" / "0", root / "images", [p.name for p in (root / "images").iterdir()], b"")
    shutil.move(str(made[0]), str(root / LEGACY_CACHE / f"undistorted-{old_key}"))
    before = _tree(root)
    b = load_dataset(root, split_holdout=0)
    assert _tree(root) == before and list((tmp_path / "xdg" / "triplet_cl").iterdir()) == []
    assert np.array_equal(a.train[0].rgb, b.train[0].rgb)


def _photos(folder: Path, n: int = 3) -> Path:
    folder.mkdir(parents=True)
    for k in range(n):
        fac.write_image(folder / f"p{k}.png", np.full((fac.H, fac.W, 3), 0.1 * k, np.float32))
    return folder


def test_sigterm_during_colmap_removes_its_work_folder(tmp_path, capsys, monkeypatch):
    """A SIGTERM (`kill PID`) in the middle of `triplet colmap` left its temporary folder beside --out."""
    pytest.importorskip("pycolmap")
    import os
    import signal
    import time

    import triplet_cl.datasets.sfm as sfm

    def solve(pycolmap, photos, images_dir, work, *a):
        (work / "database.db").write_bytes(b"half a database")
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the signal arrives here
        raise AssertionError("not interrupted")

    monkeypatch.setattr(sfm, "_solve", solve)
    photos = _photos(tmp_path / "photos")
    old = signal.getsignal(signal.SIGTERM)
    rc, err, _ = _run_cli(["colmap", photos, "--out", tmp_path / "data"], capsys)
    assert rc == 143 and "interrupted" in err  # 128 + SIGTERM (Ctrl-C: 130)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["photos"]  # no .data.tmp-* left, no data/
    assert signal.getsignal(signal.SIGTERM) == old  # the CLI restored the handler


def test_failed_colmap_removes_the_parents_it_made_and_names_duplicate_photos(tmp_path, capsys, monkeypatch):
    """`colmap PHOTOS --out a/b/c` made a/b for its work folder and left them when structure from motion failed; and
    byte-for-byte copies among the photos registered at their originals' poses without a word (battery 8)."""
    pytest.importorskip("pycolmap")
    import shutil as _shutil

    import triplet_cl.datasets.sfm as sfm
    from triplet_cl.errors import DatasetError

    def solve(pycolmap, photos, images_dir, work, *a):
        raise DatasetError(images_dir, "structure from motion failed (a test)")

    monkeypatch.setattr(sfm, "_solve", solve)
    photos = _photos(tmp_path / "photos")
    first = sorted(photos.iterdir())[0]
    _shutil.copy(first, photos / ("copy_of_" + first.name))
    (tmp_path / "kept").mkdir()
    rc, err, _ = _run_cli(["colmap", photos, "--out", tmp_path / "kept" / "a" / "b" / "c"], capsys)
    assert rc == 2 and "a test" in err, err
    assert "1 of the 4 photos is a byte-for-byte copy" in err and f"{first.name} = copy_of_{first.name}" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept", "photos"] and not any((tmp_path / "kept").iterdir())


def test_work_folders_of_killed_colmap_runs_are_removed(tmp_path):
    """SIGKILL cannot be caught: the next `triplet colmap` with the same --out removes the dead process's
    folder, never one of a process still running."""
    import os
    import subprocess
    import sys

    from triplet_cl.datasets.sfm import WORK_PID, remove_dead_work_dirs

    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    dead, alive, other = (tmp_path / ".data.tmp-dead", tmp_path / ".data.tmp-alive", tmp_path / ".data.tmp-nopid")
    for d, pid in ((dead, p.pid), (alive, os.getpid()), (other, None)):
        d.mkdir()
        if pid is not None:
            (d / WORK_PID).write_text(str(pid))
    assert remove_dead_work_dirs(tmp_path / "data") == [dead]
    assert not dead.exists() and alive.exists() and other.exists()


def _ply_header_and_vertices(path: Path):
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    n = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
    props = [(ln.split()[2], "<f4" if ln.split()[1] == "float" else "u1") for ln in lines
             if ln.startswith("property ") and not ln.startswith("property list")]
    return lines, np.frombuffer(body[: n * np.dtype(props).itemsize], np.dtype(props))


@pytest.mark.parametrize("brdf, color", [("blinn-phong", "linear"), ("cook-torrance", "encoded")])
def test_triplets_ply_columns_and_byte_colours(tmp_path, demo_copy, capsys, brdf, color):
    """triplets.ply of Blinn-Phong had no shininess column, and its byte colours were the linear albedo
    (viewers take them as sRGB: too dark)."""
    from triplet_cl.ops.color import srgb_encode

    out = tmp_path / "r"
    rc, err, _ = _run_cli(["train", demo_copy, "--out", out, *TINY_RUN, "--brdf", brdf, "--color", color], capsys)
    assert rc == 0, err
    lines, v = _ply_header_and_vertices(out / "triplets.ply")
    names = set(v.dtype.names)
    if brdf == "blinn-phong":
        assert {"shininess", "ks_0", "ka_2", "albedo_0"} <= names
        assert (v["shininess"] > 0).all() and np.isfinite(v["shininess"]).all()
        assert abs(float(np.median(v["shininess"])) - 64) < 8  # softplus-activated (initial 64), not sigmoid
    else:
        assert {"roughness", "metallic", "ao", "albedo_0"} <= names
    alb = np.stack([v[f"albedo_{i}"] for i in range(3)], 1).astype(np.float64)
    want = srgb_encode(np.clip(alb, 0, 1)) if color == "linear" else np.clip(alb, 0, 1)
    got = np.stack([v["red"], v["green"], v["blue"]], 1).astype(np.float64) / 255
    assert np.abs(got - want).max() <= 0.5 / 255 + 1e-6
    assert any("red/green/blue" in ln and ("sRGB-encoded" in ln) for ln in lines)


def test_mesh_ply_byte_colours_are_srgb_for_a_linear_run(tmp_path):
    from triplet_cl.lights import PointLight
    from triplet_cl.mesh.export import export_asset
    from triplet_cl.ops.color import srgb_encode

    asset = _small_asset([PointLight([0, 3, 0], [1, 1, 1])])
    asset.attributes["albedo"][:] = 0.2
    for space, want in (("linear", srgb_encode(0.2)), ("srgb", 0.2)):
        paths = export_asset(asset, tmp_path / space, formats=("ply",), albedo_space=space)
        _, v = _ply_header_and_vertices(paths["ply"])
        assert (v["red"] == int(want * 255 + 0.5)).all() and np.allclose(v["albedo_0"], 0.2)


@pytest.mark.parametrize("extra, named", [(["--out", "OUT"], "--out"), (["--renderer", "hybrid"], "--renderer"),
                                          (["--env-degree", "3"], "--env-degree")])
def test_eval_options_of_the_relit_evaluation_need_relight(run, tmp_path, capsys, extra, named):
    """`eval RUN --out DIR` (no --relight) was accepted and wrote nothing there: silently ignored."""
    extra = [str(tmp_path / "e") if a == "OUT" else a for a in extra]
    before = _tree(run)
    rc, err, out = _run_cli(["eval", run, *extra], capsys)
    assert rc == 2 and named in err and "--relight" in err and err.count("\n") == 1, err
    assert "PSNR" not in out and _tree(run) == before and not (tmp_path / "e").exists()


INTO_ANOTHER_RUN = {  # RUN's outputs into another run's folder replaced that run's own files (its lights.json)
    "export": lambda run, other: ["export", run, "--formats", "ply", "--out", other],
    "render": lambda run, other: ["render", run, "--out", other / "renders" / "test"],
    "relight": lambda run, other: ["relight", run, "--lights", run / "lights.json", "--out", other / "relit"],
}


@pytest.mark.parametrize("case", sorted(INTO_ANOTHER_RUN))
def test_outputs_into_another_run_are_refused(run, tmp_path, capsys, case):
    other = tmp_path / "other"
    shutil.copytree(run, other)
    (other / "lights.json").write_text('{"lights": "the other run\'s"}')
    before = _tree(other)
    rc, err, _ = _run_cli(INTO_ANOTHER_RUN[case](run, other), capsys)
    assert rc == 2 and "--out" in err and "inside another run" in err and err.count("\n") == 1, err
    assert _tree(other) == before
    # the run's own folders stay allowed
    rc, err, _ = _run_cli(["render", run, "--out", run / "renders" / "again"], capsys)
    assert rc == 0, err


@pytest.mark.parametrize("command", ["train", "render", "export", "colmap"])
def test_out_that_cannot_be_created_names_the_option(run, tmp_path, capsys, command):
    """/proc (and /sys in a container) pass os.access for root but refuse mkdir: the error came from deep inside
    the command (`/proc/x: no such file or folder`, no option named); now --out is tried up front."""
    if not Path("/proc/self").exists():
        pytest.skip("no /proc here")
    out = Path("/proc/triplet_harden_test/sub")
    argv = {"train": ["train", DEMO, "--out", out], "render": ["render", run, "--out", out],
            "export": ["export", run, "--out", out], "colmap": ["colmap", _photos(tmp_path / "p"), "--out", out]}
    before = _tree(run)
    rc, err, _ = _run_cli(argv[command], capsys)
    assert rc == 2 and err.startswith(f"triplet {command}: error: --out:") and "cannot be created" in err, err
    assert err.count("\n") == 1 and _tree(run) == before


def test_out_probe_leaves_nothing_behind(tmp_path):
    from triplet_cl.validate import check_writable_dir

    check_writable_dir(tmp_path / "a" / "b" / "c", "--out")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_interrupted_training_saves_a_checkpoint_and_resumes(tmp_path, sig):
    """Ctrl-C, and now SIGTERM (`kill PID`, a scheduler's stop) too, end training cleanly: a checkpoint of
    the iteration reached, the handlers restored, and --resume continues from it."""
    import os
    import signal

    signum = getattr(signal, sig)
    old = signal.getsignal(signum)
    tr = Trainer(DEMO, tmp_path / "r", _small_cfg(checkpoint_every=0), quiet=True)
    orig = tr.step

    def step():
        if tr.it == 4:
            os.kill(os.getpid(), signum)
        return orig()

    tr.step = step
    with pytest.raises(KeyboardInterrupt):
        tr.train()
    assert signal.getsignal(signum) == old
    assert (tmp_path / "r" / "checkpoints" / "latest").read_text() == "ckpt_0000005.npz"
    assert Trainer(None, tmp_path / "r", quiet=True, resume=True).it == 5


def test_sigterm_during_training_exits_143(tmp_path, capsys, demo_copy, monkeypatch):
    """`kill PID` on `triplet train` exited 130 (Ctrl-C's status): the trainer's own SIGTERM handler (the clean
    stop with a checkpoint) replaced the CLI's, which records the signal (battery 8). It now hands the signal on."""
    import os
    import signal

    from triplet_cl import train as train_mod

    orig = train_mod.Trainer.step

    def step(self):
        if self.it == 2:
            os.kill(os.getpid(), signal.SIGTERM)
        return orig(self)

    monkeypatch.setattr(train_mod.Trainer, "step", step)
    old = signal.getsignal(signal.SIGTERM)
    rc, err, _ = _run_cli(["train", demo_copy, "--out", tmp_path / "r", "--iterations", "20", "--init-points",
                           "300"], capsys)
    assert rc == 143 and "interrupted" in err, err
    assert signal.getsignal(signal.SIGTERM) == old
    assert (tmp_path / "r" / "checkpoints" / "latest").read_text() == "ckpt_0000003.npz"


def test_cameras_looking_away_from_the_object_warn(tmp_path, demo_copy):
    """Every camera turned 180° about its own y axis (looking away from the object): the soup was trained unseen
    without a word, its face count never moving (battery 8). The demo's own cameras do not warn."""
    import warnings

    from triplet_cl.datasets import DatasetWarning

    d = tmp_path / "away"
    shutil.copytree(demo_copy, d)
    for split in ("train", "test"):
        p = d / f"transforms_{split}.json"
        doc = json.loads(p.read_text())
        for fr in doc["frames"]:
            m = np.array(fr["transform_matrix"], float)
            m[:3, 0] *= -1
            m[:3, 2] *= -1
            fr["transform_matrix"] = m.tolist()
        p.write_text(json.dumps(doc))
    with pytest.warns(DatasetWarning, match=r"only 0 of the 40 training cameras see the initial soup.*-z axis"):
        Trainer(d, tmp_path / "r", _small_cfg(), quiet=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        Trainer(demo_copy, tmp_path / "r2", _small_cfg(), quiet=True)


def test_a_split_mixing_images_with_and_without_alpha_warns(tmp_path):
    """One RGB image among RGBA ones trained its white background as part of the object, silently."""
    from triplet_cl.datasets import DatasetWarning

    fac.make_nerf(tmp_path / "ds")
    p = sorted((tmp_path / "ds").rglob("*.png"))[0]
    from triplet_cl.datasets.images import read_image

    img = read_image(p)
    fac.write_image(p, img.rgb)  # the same picture without its alpha channel
    with pytest.warns(DatasetWarning, match=rf"no alpha channel \({p.name}\)"):
        load_dataset(tmp_path / "ds")


def test_extract_of_an_untrained_soup_says_why(run, capsys):
    """The 4-iteration soup is still transparent: the message named tsdf_fusion and alpha_threshold only."""
    before = _tree(run)
    rc, err, _ = _run_cli(["extract", run, "--mesh-iterations", "0", "--mesh-resolution", "16"], capsys)
    assert rc == 2 and "no surface" in err and "untrained" in err and "tsdf_fusion" not in err, err
    assert err.count("\n") == 1 and _tree(run) == before


# ---- held-out battery (bad datasets, damaged or moved runs) ------------------------------------------
@pytest.mark.parametrize("sizes", [{"train": (8, 6), "test": (8, 6)}, {"train": (16, 12), "test": (10, 12)}])
def test_images_smaller_than_the_ssim_window_are_refused_before_any_work(tmp_path, capsys, sizes):
    """8x6 photos trained to the end, then failed in the test views' SSIM ("pred must have shape [H>=11, ...]")
    after the run folder was written."""
    fac.make_nerf(tmp_path / "ds", splits={"train": 3}, w=sizes["train"][0], h=sizes["train"][1])
    fac.make_nerf(tmp_path / "t", splits={"test": 2}, w=sizes["test"][0], h=sizes["test"][1])
    shutil.copytree(tmp_path / "t" / "test", tmp_path / "ds" / "test")
    shutil.copy(tmp_path / "t" / "transforms_test.json", tmp_path / "ds")
    before = _tree(tmp_path / "ds")
    rc, err, _ = _run_cli(["train", tmp_path / "ds", "--out", tmp_path / "out", *TINY_RUN], capsys)
    small = "train" if sizes["train"] == (8, 6) else "test"
    w, h = sizes[small]
    assert rc == 2 and f"{w}x{h} pixels" in err and "11x11" in err and f"{small}/r_0.png" in err, err
    assert err.count("\n") == 1
    assert not (tmp_path / "out").exists() and _tree(tmp_path / "ds") == before


def test_an_unreadable_image_is_one_line(tmp_path, capfd):
    """A truncated PNG: OpenImageIO's error is three lines (the read error, libpng's, "PNG library error"); and
    libpng wrote its own "libpng error: ..." line to the process's stderr before it (battery 7)."""
    fac.make_nerf(tmp_path / "ds", w=64, h=48)
    p = tmp_path / "ds" / "train" / "r_1.png"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    capfd.readouterr()
    with pytest.raises(DatasetError) as ei:
        load_dataset(tmp_path / "ds")
    msg = str(ei.value)
    assert "r_1.png: cannot read the image" in msg and "\n" not in msg, msg
    assert "libpng" not in capfd.readouterr().err


def test_library_lines_are_held_while_images_are_read(capfd):
    """What a C library writes to stderr during a read passes on when the read succeeds, in order, and is dropped
    when it fails (the error carries it); nested (and threaded) reads go through the outer redirection."""
    import os

    from triplet_cl.datasets.images import _library_stderr

    capfd.readouterr()
    with _library_stderr():
        os.write(2, b"warning: kept\n")
        with _library_stderr():
            os.write(2, b"nested\n")
    assert capfd.readouterr().err == "warning: kept\nnested\n"
    with pytest.raises(DatasetError), _library_stderr():
        os.write(2, b"libpng error: dropped\n")
        raise DatasetError("x.png", "cannot read the image")
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "after\n"


@pytest.mark.parametrize("content", [b"\xff\xfe\x00garbage", b"ckpt\x00.npz"])
def test_a_damaged_latest_pointer_counts_as_lost(run, content):
    """A `latest` of binary garbage was "'utf-8' codec can't decode byte 0xff ...", no file named."""
    (run / "checkpoints" / "latest").write_bytes(content)
    assert Trainer(None, run, quiet=True, resume=True).it == 4  # the newest checkpoint, as with `latest` lost


def test_a_moved_dataset_is_named_with_the_runs_config(run, tmp_path, capsys):
    """The dataset of config.json no longer there: "X: dataset folder not found" said neither which run nor
    what to do."""
    cfg = json.loads((run / "config.json").read_text())
    cfg["data"] = str(tmp_path / "moved_away")
    (run / "config.json").write_text(json.dumps(cfg))
    before = _tree(run)
    relight = ["--lights", run / "lights.json"]
    for argv in (["render", run], ["eval", run], ["extract", run], ["relight", run, *relight]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "config.json" in err and "moved_away does not exist" in err and "move it back" in err, err
    rc, err, _ = _run_cli(["train", "--resume", "--out", run], capsys)
    assert rc == 2 and "moved_away does not exist" in err and "DATA" in err, err
    assert _tree(run) == before


def test_resume_of_a_moved_dataset_checks_its_views_and_records_its_place(run, tmp_path, capsys, monkeypatch):
    """The run's dataset moved: `train NEWPLACE --resume` takes it when its training views are the run's (names, image
    size, cameras: checkpoints hold their digest) and config.json then names the new place (and the new
    --iterations), so that render, eval and the next resume find it; another dataset with as many training views
    (renamed frames, other poses) was accepted before, and is refused, naming what differs, with nothing written."""
    cfg = json.loads((run / "config.json").read_text())
    moved = tmp_path / "moved"
    shutil.copytree(cfg["data"], moved)
    cfg["data"] = str(tmp_path / "gone")
    (run / "config.json").write_text(json.dumps(cfg))
    renamed, posed = tmp_path / "renamed", tmp_path / "posed"
    for d in (renamed, posed):
        shutil.copytree(moved, d)
    doc = json.loads((renamed / "transforms_train.json").read_text())
    for f in doc["frames"]:
        old = renamed / (f["file_path"] + ("" if f["file_path"].endswith(".png") else ".png"))
        f["file_path"] = f["file_path"].replace("r_", "view_")
        old.rename(renamed / (f["file_path"] + ("" if f["file_path"].endswith(".png") else ".png")))
    (renamed / "transforms_train.json").write_text(json.dumps(doc))
    doc = json.loads((posed / "transforms_train.json").read_text())
    for f in doc["frames"]:
        f["transform_matrix"][1][3] += 0.05  # every camera 5 cm higher
    (posed / "transforms_train.json").write_text(json.dumps(doc))
    before = _tree(run)
    for data, named in ((renamed, "its training frames were train/r_0"), (posed, "cameras")):
        rc, err, _ = _run_cli(["train", data, "--resume", "--out", run, "--iterations", "6"], capsys)
        assert rc == 2 and "other training views" in err and named in err, err
        assert _tree(run) == before
    monkeypatch.chdir(tmp_path)  # DATA given relative: config.json records it absolute, as a new run's
    rc, err, _ = _run_cli(["train", "moved", "--resume", "--out", run, "--iterations", "6"], capsys)
    assert rc == 0, err
    saved = json.loads((run / "config.json").read_text())
    assert saved["data"] == str(moved) and saved["train"]["iterations"] == 6
    monkeypatch.chdir(run.parent.parent)
    rc, err, _ = _run_cli(["eval", run], capsys)
    assert rc == 0, err


def test_checkpoint_without_the_training_views_record_resumes(run, capsys):
    """A checkpoint written before the training views' record (session 54: no digest, no cameras) resumes, the
    number of views checked as before."""
    ck = run / "checkpoints" / "ckpt_0000004.npz"
    with np.load(ck) as z:
        a = {k: z[k] for k in z.files}
    meta = json.loads(bytes(a["meta"]).decode())
    del meta["train_views_id"], a["views.cameras"]
    a["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(ck, **a)
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5"], capsys)
    assert rc == 0, err


def test_same_cameras_tolerates_what_a_new_undistortion_moves():
    """The cameras compared on resume: the same within rounding and a 0.5 % focal length (COLMAP's undistortion
    run again), not a camera moved by a thousandth of the rig's spread or turned by 0.1 degree."""
    from triplet_cl.train import same_cameras

    rng = np.random.default_rng(3)
    c = np.concatenate([np.tile([100.0, 100.0, 48.0, 48.0], (6, 1)), rng.normal(0, 3, (6, 3)),
                        rng.normal(0, 1, (6, 3))], 1)
    c[:, 7:] /= np.linalg.norm(c[:, 7:], axis=1, keepdims=True)
    spread = np.linalg.norm(c[:, 4:7] - c[:, 4:7].mean(0), axis=1).max()
    d = c.copy()
    d[:, :2] *= 1.005
    assert same_cameras(c, c + 1e-12) and same_cameras(c, d)
    d = c.copy()
    d[2, 5] += 1e-3 * spread
    assert not same_cameras(c, d)
    d = c.copy()
    t = np.radians(0.1)
    x, z = d[0, 7], d[0, 9]
    d[0, 7], d[0, 9] = np.cos(t) * x - np.sin(t) * z, np.sin(t) * x + np.cos(t) * z
    assert not same_cameras(c, d) and not same_cameras(c, c[:5])


def test_config_json_records_the_dataset_as_an_absolute_path(tmp_path, demo_copy, monkeypatch):
    """A run trained with a relative DATA could not be rendered from any other folder."""
    monkeypatch.chdir(demo_copy.parent)
    Trainer(Path(demo_copy.name), tmp_path / "r", _small_cfg(), quiet=True)
    saved = json.loads((tmp_path / "r" / "config.json").read_text())["data"]
    assert Path(saved).is_absolute() and Path(saved) == demo_copy.absolute()



# ---- battery 3 (session 37) ---------------------------------------------------------------------------------------


def test_a_user_folder_inside_a_run_is_the_user_s(run, capsys):
    """``render RUN --out RUN/my_stuff`` replaced the user's ``r_0.png`` there: only the run itself and its own output
    folders (renders/, relight/) are exempt from the foreign-file check."""
    mine = run / "my_stuff"
    mine.mkdir()
    (mine / "r_0.png").write_bytes(b"user image")
    rc, err, _ = _run_cli(["render", run, "--out", mine], capsys)
    assert rc == 2 and "not written by triplet" in err and (mine / "r_0.png").read_bytes() == b"user image", err
    rc, _, _ = _run_cli(["render", run], capsys)  # the run's own renders/test: rendered again
    assert rc == 0 and (run / "renders" / "test" / "r_0.png").is_file()


def _mesh_state(run, far: float | None = None):
    from triplet_cl.lights import PointLight
    from triplet_cl.mesh.refine import MeshConfig, save_mesh_state
    from triplet_cl.scene import Scene

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float64) * 0.5
    V = np.concatenate([V + 0.01 * k for k in range(40)])  # 160 vertices, 40 small tetrahedra
    F = np.concatenate([np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]) + 4 * k for k in range(40)])
    if far is not None:
        V[7] = far
    scene = Scene.from_arrays(V, F, lights=[PointLight([0, 0, 3], [1, 1, 1])])
    save_mesh_state(run / "mesh_stage.npz", scene, MeshConfig())


def test_a_mesh_state_with_a_vertex_far_out_is_damaged(run, capsys):
    """A vertex at 1e12 made xatlas's chart packing run for ever (deaf to SIGTERM and Ctrl-C)."""
    _mesh_state(run, far=1e12)
    rc, err, _ = _run_cli(["export", run, "--formats", "obj", "--texture-size", "16", "--out", run.parent / "x"],
                          capsys)
    assert rc == 2 and "mesh_stage.npz" in err and "vertex 7" in err and not (run.parent / "x").exists(), err
    _mesh_state(run)
    rc, err, _ = _run_cli(["export", run, "--formats", "ply", "--out", run.parent / "y"], capsys)
    assert rc == 0 and (run.parent / "y" / "mesh.ply").is_file(), err


@pytest.mark.parametrize("item, where, says", [
    ({"type": ["point"], "position": [1, 2, 3], "intensity": [1, 1, 1]}, "lights[0].type", "expected one of"),
    ({"type": {"point": 1}, "position": [1, 2, 3], "intensity": [1, 1, 1]}, "lights[0].type", "expected one of"),
    ({"position": [1, 2, 3], "intensity": [1, 1, 1]}, "lights[0].type", "missing: every light needs a \"type\""),
    ({"type": "DirectionalLight", "direction": [0, 0, 0], "intensity": [1, 1, 1]}, "lights[0].direction",
     "zero vector"),
    ({"type": "PointLight", "position": [0, 0, 3], "intensity": [1, 1, 1], "radius": 2}, "lights[0]",
     "unknown field(s) ['radius']"),
    ({"type": "envmap", "filename": "e.exr", "scale": 1e308}, "lights[0].scale", "at most 1e+30"),
])
def test_bad_light_items_are_named(run, tmp_path, capsys, item, where, says):
    """A list or an object as a light's type (a TypeError traceback), a zero direction in lights.json's form and an
    environment map scaled past float32 (black renders, exit 0), an unknown field (a Python signature error)."""
    fac.write_image(tmp_path / "e.exr", np.full((8, 16, 4), 0.5, np.float32), "float")
    lf = tmp_path / "l.json"
    lf.write_text(json.dumps({"lights": [item]}))
    rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and where in err and says in err and not (tmp_path / "out").exists(), err


def test_an_environment_map_past_float32_is_refused(run, tmp_path, capsys):
    px = np.full((8, 16, 4), 0.5, np.float32)
    px[3, 5, 0] = 3e38
    fac.write_image(tmp_path / "e.exr", px, "float")
    lf = tmp_path / "l.json"
    lf.write_text(json.dumps({"lights": [{"type": "envmap", "filename": "e.exr"}]}))
    rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and "e.exr holds a value of 3e+38" in err, err


@pytest.mark.parametrize("name", ["mesh.glb", "renders/mesh/r_0.png"])
def test_extract_refuses_a_folder_where_its_files_go_before_any_work(run, capsys, name):
    """A ``mesh.glb`` folder failed only after the whole mesh stage, naming a temporary file, metrics.json rewritten."""
    (run / name).mkdir(parents=True)
    (run / name / "user.txt").write_text("mine")
    before = _tree(run)
    rc, err, out = _run_cli(["extract", run, "--mesh-iterations", "2"], capsys)
    assert rc == 2 and f"{name} is a folder" in err and "mesh stage:" not in out, err
    assert _tree(run) == before


def test_extract_against_another_dataset_is_refused(run, tmp_path, demo_copy, capsys):
    """A run whose config.json names another dataset was refined against that one's photos (exit 0)."""
    other = tmp_path / "other"
    shutil.copytree(demo_copy, other)
    doc = json.loads((other / "transforms_train.json").read_text())
    doc["frames"] = doc["frames"][:10]
    (other / "transforms_train.json").write_text(json.dumps(doc))
    cfg = json.loads((run / "config.json").read_text())
    cfg["data"] = str(other)
    (run / "config.json").write_text(json.dumps(cfg))
    rc, err, out = _run_cli(["extract", run, "--mesh-iterations", "2"], capsys)
    assert rc == 2 and "training views" in err and "now has 10" in err and "mesh stage:" not in out, err
    assert not (run / "mesh_stage.npz").exists()


def test_a_device_from_the_environment_is_named_as_such(run, capsys, monkeypatch):
    monkeypatch.setenv("TRIPLET_DEVICE", "garbage")
    rc, err, _ = _run_cli(["render", run], capsys)
    assert rc == 2 and "'garbage' ($TRIPLET_DEVICE" in err, err


def test_a_mesh_state_without_faces_is_named_and_makes_no_folder(run, capsys):
    from triplet_cl.lights import PointLight
    from triplet_cl.mesh.refine import MeshConfig, save_mesh_state
    from triplet_cl.scene import Scene

    scene = Scene.from_arrays(np.zeros((3, 3)), np.zeros((0, 3), np.int32), lights=[PointLight([0, 0, 3], [1, 1, 1])])
    save_mesh_state(run / "mesh_stage.npz", scene, MeshConfig())
    rc, err, _ = _run_cli(["export", run, "--formats", "ply", "--out", run.parent / "x"], capsys)
    assert rc == 2 and "mesh_stage.npz" in err and "no faces" in err and not (run.parent / "x").exists(), err


def test_an_environment_map_one_pixel_high_says_so(run, tmp_path, capsys):
    fac.write_image(tmp_path / "e.exr", np.full((1, 2, 4), 0.5, np.float32), "float")
    lf = tmp_path / "l.json"
    lf.write_text(json.dumps({"lights": [{"type": "envmap", "filename": "e.exr"}]}))
    rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and "is 2x1: an equirectangular environment map is at least 2 pixels high" in err, err


# ---- battery 4 (session 40) -------------------------------------------------------------------------------


def test_overwrite_refuses_a_run_holding_the_user_s_files_and_keeps_a_folder_beside_it(run, tmp_path, capsys):
    """--overwrite deleted the user's notes and a dataset copy inside the run with it, and a user folder named
    ``.RUN.overwritten`` beside it (it was the fixed name of the aside copy)."""
    (run / "my_notes.txt").write_text("notes")
    before = _tree(run)
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, "--overwrite", *TINY_RUN], capsys)
    assert rc == 2 and "my_notes.txt" in err and "not written by triplet" in err and err.count("\n") == 1, err
    assert _tree(run) == before
    (run / "my_notes.txt").unlink()
    mine = tmp_path / ".run.overwritten"
    mine.mkdir()
    (mine / "thesis.tex").write_text("x")
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, "--overwrite", *TINY_RUN], capsys)
    assert rc == 0, err
    assert (mine / "thesis.tex").read_text() == "x" and [p.name for p in tmp_path.iterdir() if p.name != "run"] == \
        [mine.name]


def test_overwrite_of_the_current_folder(run, tmp_path, capsys, monkeypatch):
    """``cd RUN && triplet train DATA --out . --overwrite`` said "PosixPath('.') has an empty name"; the dataset
    given relative to the run was then looked for inside the folder moved aside."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    monkeypatch.chdir(run)
    rc, err, out = _run_cli(["train", "../data", "--out", ".", "--overwrite", *TINY_RUN], capsys)
    assert rc == 0, err
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 4
    # the user's shell is left in the deleted old folder (battery 10): the command says how to get back
    assert "your shell's working folder was inside the old run" in out and f"cd {run.resolve()}" in out


@pytest.mark.parametrize("value, want", [(1e300, "expected coordinates within"), (1e6, "farther from the cameras")])
def test_a_camera_far_from_the_others_is_refused(tmp_path, capsys, value, want):
    """A translation of 1e300 overflowed the initial soup's range (a traceback); a mistyped 1e12 trained nothing."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    d["frames"][0]["transform_matrix"][0][3] = value
    p.write_text(json.dumps(d))
    rc, err, _ = _run_cli(["train", data, "--out", tmp_path / "out", *TINY_RUN], capsys)
    assert rc == 2 and want in err and d["frames"][0]["file_path"].lstrip("./") in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["transforms_test.json", "transforms_train.json"])
def test_a_split_file_that_is_a_dangling_link_is_named(tmp_path, name):
    """A dangling transforms_test.json (an unfetched annex file) was passed over: a hold-out became the test split."""
    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    (data / name).unlink()
    (data / name).symlink_to(".git/annex/objects/x")
    with pytest.raises(DatasetError, match="link to nothing"):
        load_dataset(data)


def test_outputs_that_are_folders_or_files_are_refused_before_the_work(run, capsys):
    """A metrics.json folder was met after a whole resumed training (the error naming a temporary file) or eval; a
    renders/mesh file after the whole mesh stage ("File exists")."""
    (run / "metrics.json").unlink()
    (run / "metrics.json").mkdir()
    before = _tree(run)
    for argv in (["train", "--resume", "--out", run, "--iterations", "6"], ["eval", run]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "metrics.json is a folder" in err and err.count("\n") == 1, err
        assert _tree(run) == before
    (run / "metrics.json").rmdir()
    shutil.rmtree(run / "renders")
    (run / "renders").write_text("mine")
    for argv in (["train", "--resume", "--out", run, "--iterations", "6"],
                 ["extract", run, "--mesh-iterations", "1", "--mesh-resolution", "24"]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "renders is a file" in err, err
    assert not (run / "mesh_stage.npz").exists() and (run / "renders").read_text() == "mine"


def test_resume_accepts_the_background_it_was_started_with(run, capsys):
    """``--resume --background auto`` on a run started with the default (auto) was refused: the run had 'white'."""
    rc, err, _ = _run_cli(["train", "--resume", "--out", run, "--iterations", "5", "--background", "auto"], capsys)
    assert rc == 0, err


def test_a_vanishing_sigma_is_refused(tmp_path, capsys):
    """--sigma 1e-30 left the soup invisible to its gradients: nothing learned, exit 0."""
    for v in ("1e-30", "5e-324", "0.001"):
        rc, err, _ = _run_cli(["train", DEMO, "--out", tmp_path / "o", "--sigma", v, *TINY_RUN], capsys)
        assert rc == 2 and "--sigma" in err and "[0.01, 1000]" in err, err


@pytest.mark.parametrize("dup", ["id", "name"])
def test_colmap_images_given_twice_are_refused(tmp_path, dup):
    """A duplicate IMAGE_ID dropped one photo; a duplicate NAME trained one photo under two poses."""
    p = tmp_path / "images.txt"
    lines = ["1 1 0 0 0 0 0 4 1 a.png", "", "2 1 0 0 0 1 0 4 1 b.png", ""]
    if dup == "id":
        lines[2] = lines[2].replace("2 1 0 0 0 1", "1 1 0 0 0 1", 1)
    else:
        lines[2] = lines[2].replace("b.png", "a.png")
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match="appears twice"):
        read_images_text(p)


def test_references_that_cannot_be_scored_as_meant_warn_and_wrong_kinds_are_named(run, tmp_path, capsys):
    """References without alpha (1.04 dB) and fully transparent ones (24.80 dB) were scored without a word; a set's
    images given as a file, "cameras" naming a folder and an envmap named as a folder were all "not found" (battery
    8)."""
    from PIL import Image

    refs = _relight_refs(tmp_path / "refs")
    names = [Path(f["file_path"]).name for f in json.loads((DEMO / "transforms_test.json").read_text())["frames"]]
    (refs / "a").mkdir()
    (refs / "albedo").mkdir()
    for n in names:
        Image.fromarray(np.full((96, 96, 3), 200, np.uint8)).save(refs / "a" / f"{n}.png")  # RGB: no alpha
        Image.fromarray(np.full((96, 96, 4), 200, np.uint8)).save(refs / "albedo" / f"{n}.png")
    Image.fromarray(np.zeros((96, 96, 4), np.uint8)).save(refs / "albedo" / f"{names[0]}.png")  # transparent
    rc, err, _ = _run_cli(["eval", run, "--relight", refs, "--out", tmp_path / "ev"], capsys)
    assert rc == 0, err
    assert f"{len(names)} of the {len(names)} references" in err and "no alpha channel" in err, err
    assert f"1 of the {len(names)} references" in err and "fully transparent" in err, err
    doc = json.loads((refs / "relight.json").read_text())
    for change, needle in (({"sets": {"a": {**doc["sets"]["a"], "images": "relight.json"}}}, "a file, not a folder"),
                           ({"cameras": "a"}, "a folder, not a transforms JSON file")):
        (refs / "relight.json").write_text(json.dumps({**doc, **change}))
        rc, err, _ = _run_cli(["eval", run, "--relight", refs], capsys)
        assert rc == 2 and needle in err, err
    (tmp_path / "sky.exr").mkdir()
    lf = tmp_path / "env.json"
    lf.write_text(json.dumps({"lights": [{"type": "envmap", "filename": "sky.exr"}]}))
    rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and "is a folder, not an image" in err, err


def test_relight_references_are_read_before_the_evaluation(run, tmp_path, capsys):
    """A set named 'albedo' beside an albedo folder had its relit images replaced by the albedo renders; a reference of
    another size, an unreadable one or a fully transparent albedo were met after the whole evaluation."""
    from PIL import Image

    refs = _relight_refs(tmp_path / "refs")
    names = [Path(f["file_path"]).name for f in json.loads((DEMO / "transforms_test.json").read_text())["frames"]]
    for folder in ("a", "albedo"):
        (refs / folder).mkdir()
        for n in names:
            Image.fromarray(np.full((96, 96, 4), 200, np.uint8)).save(refs / folder / f"{n}.png")
    before = _tree(run)
    doc = json.loads((refs / "relight.json").read_text())
    (refs / "relight.json").write_text(json.dumps({**doc, "sets": {"albedo": doc["sets"]["a"]}}))
    rc, err, _ = _run_cli(["eval", run, "--relight", refs, "--out", tmp_path / "ev"], capsys)  # with --out only
    assert rc == 2 and "may not be named 'albedo'" in err and not (tmp_path / "ev").exists(), err
    (refs / "relight.json").write_text(json.dumps(doc))
    Image.fromarray(np.full((48, 96, 4), 200, np.uint8)).save(refs / "a" / f"{names[0]}.png")
    rc, err, _ = _run_cli(["eval", run, "--relight", refs], capsys)
    assert rc == 2 and "is 96x48, its view 96x96" in err, err
    (refs / "a" / f"{names[0]}.png").write_bytes(b"not a png")
    rc, err, _ = _run_cli(["eval", run, "--relight", refs], capsys)
    assert rc == 2 and f"{names[0]}.png" in err, err
    Image.fromarray(np.full((96, 96, 4), 200, np.uint8)).save(refs / "a" / f"{names[0]}.png")
    for n in names:
        Image.fromarray(np.zeros((96, 96, 4), np.uint8)).save(refs / "albedo" / f"{n}.png")
    rc, err, _ = _run_cli(["eval", run, "--relight", refs], capsys)
    assert rc == 2 and "every image is transparent" in err, err
    assert _tree(run) == before


def test_a_run_on_read_only_storage_renders_elsewhere(run, tmp_path, capsys, monkeypatch):
    """A run on read-only storage could not be rendered to a writable --out: loading it opened train.log to append
    ("read-only file system: choose a writable --out")."""
    import logging

    real = logging.FileHandler

    def handler(path, *a, **k):
        if str(path).startswith(str(run)):
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(logging, "FileHandler", handler)
    import os

    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: (False if mode & os.W_OK and
                                                                str(p).startswith(str(run))
                                                                else real_access(p, mode, *a, **k)))
    for name in list(logging.Logger.manager.loggerDict):
        if name.startswith("triplet_cl.train.") and str(run) in name:
            logging.getLogger(name).handlers.clear()
    before = _tree(run)
    rc, err, out = _run_cli(["render", run, "--out", tmp_path / "elsewhere"], capsys)
    assert rc == 0, err
    assert len(list((tmp_path / "elsewhere").glob("*.png"))) > 0 and _tree(run) == before


def test_a_run_inside_another_run_is_refused(run, capsys):
    """``train --out RUN/sub`` was accepted, though render, export and relight refuse outputs inside another run."""
    before = _tree(run)
    rc, err, _ = _run_cli(["train", DEMO, "--out", run / "sub", *TINY_RUN], capsys)
    assert rc == 2 and "is inside the run" in err and err.count("\n") == 1, err
    assert _tree(run) == before and not (run / "sub").exists()


def test_a_bbox_holding_no_surface_is_refused_by_extract(run, capsys):
    """A box the cameras see but where the soup has nothing (inside the object, or beside it) gave a box-shaped mesh
    over the run's mesh files, or "found no surface" after the extraction."""
    from types import SimpleNamespace

    from triplet_cl.cli.main import _check_bbox_holds_soup

    from triplet_cl.errors import UsageError
    from triplet_cl.mesh.refine import MeshConfig
    from triplet_cl.scene import Scene, logit

    before = _tree(run)
    rc, err, _ = _run_cli(["extract", run, "--bbox", "0,0.1,0.2,0.01,0.11,0.21"], capsys)
    assert rc == 2 and "opaque triplet" in err and _tree(run) == before, err
    V = np.random.default_rng(0).uniform(-0.5, 0.5, (300, 3))
    tr = SimpleNamespace(scene=Scene.from_arrays(V, np.arange(300).reshape(100, 3), alpha=np.full((300, 1),
                                                                                                logit(0.9))))
    _check_bbox_holds_soup(MeshConfig(bbox=(-1, -1, -1, 1, 1, 1)), tr)  # every face opaque and inside: passes
    with pytest.raises(UsageError, match="0 opaque"):
        _check_bbox_holds_soup(MeshConfig(bbox=(2, 2, 2, 3, 3, 3)), tr)
    tr.scene.alpha.data[:] = logit(0.1)
    with pytest.raises(UsageError, match="0 opaque"):
        _check_bbox_holds_soup(MeshConfig(bbox=(-1, -1, -1, 1, 1, 1)), tr)


def test_clustered_cameras_are_not_outliers(tmp_path):
    """The outlier rule is robust: a capture that rests in one place for
    half its frames (a still start of a video) and a far overview camera at 30x are accepted; a run already trained
    is never refused on loading (``new_run=False``)."""
    from triplet_cl.validate import check_training_views

    data = tmp_path / "data"
    shutil.copytree(DEMO, data)
    p = data / "transforms_train.json"
    d = json.loads(p.read_text())
    rng = np.random.default_rng(0)
    rest = np.array([f["transform_matrix"][r][3] for r in range(3) for f in d["frames"][:1]])
    for f in d["frames"][: len(d["frames"]) // 2 + 2]:  # more than half the cameras within 2 mm of one place
        for r in range(3):
            f["transform_matrix"][r][3] = float(rest[r] + rng.normal(0, 0.002))
    M = np.array(d["frames"][-1]["transform_matrix"])
    M[:3, 3] *= 30.0  # an overview camera 30x farther along its own axis
    d["frames"][-1]["transform_matrix"] = M.tolist()
    p.write_text(json.dumps(d))
    check_training_views(load_dataset(data))
    M[:3, 3] *= 10.0  # 300x: a mistyped pose
    d["frames"][-1]["transform_matrix"] = M.tolist()
    p.write_text(json.dumps(d))
    with pytest.raises(DatasetError, match="farther from the cameras"):
        check_training_views(load_dataset(data))
    check_training_views(load_dataset(data), new_run=False)


def test_eval_after_the_test_split_vanished_warns(tmp_path, demo_copy, capsys):
    """With transforms_test.json gone, eval and render silently used a hold-out of the training views as the test
    split (metrics.json rewritten from views the run trained on): they still run, with one warning line."""
    data = tmp_path / "data"
    shutil.copytree(demo_copy, data)
    run = tmp_path / "run"
    assert cli_main(["train", str(data), "--out", str(run), *TINY_RUN]) == 0
    capsys.readouterr()
    (data / "transforms_test.json").unlink()
    for argv in (["eval", run], ["render", run, "--out", tmp_path / "r"]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 0 and "may hold views the run trained on" in err and err.count("\n") == 1, err


def test_another_capture_at_the_run_s_dataset_path_is_refused(tmp_path, demo_copy, capsys):
    """Another capture with as many training views put where the run's dataset was: eval scored the run against it
    (9.8 dB into metrics.json), render and relight rendered it, without a word (battery 11). Refused before anything
    is written, as train --resume and extract refuse it."""
    data = tmp_path / "data"
    shutil.copytree(demo_copy, data)
    run = tmp_path / "run"
    assert cli_main(["train", str(data), "--out", str(run), *TINY_RUN]) == 0
    capsys.readouterr()
    before = (run / "metrics.json").read_bytes()
    p = data / "transforms_train.json"  # the same frames under other names (another capture's files)
    d = json.loads(p.read_text())
    for k, f in enumerate(d["frames"]):
        src = data / (f["file_path"].lstrip("./") + ".png")
        src.rename(data / "train" / f"other_{k}.png")
        f["file_path"] = f"./train/other_{k}"
    p.write_text(json.dumps(d))
    for argv in (["eval", run], ["render", run, "--out", tmp_path / "r"],
                 ["relight", run, "--lights", run / "lights.json", "--out", tmp_path / "l"]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "was trained on other training views" in err and "another capture" in err, (argv, err)
    assert (run / "metrics.json").read_bytes() == before
    assert not (tmp_path / "r").exists() and not (tmp_path / "l").exists()


def test_resume_keeps_a_mesh_stage_s_metrics_and_lights_and_says_it_is_stale(tmp_path, capsys):
    """`train --resume` on a run with a mesh stage dropped the mesh's metrics and put the soup's lights in lights.json
    beside the mesh's files, without a word (battery 11). The mesh's section is kept (marked stale when the soup
    trained on), lights.json stays the mesh's, and the command says how to remake the mesh."""
    run = tmp_path / "run"
    assert cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN]) == 0
    (run / "mesh_stage.npz").write_bytes(b"a mesh stage's state")  # (only its presence is read here)
    m = json.loads((run / "metrics.json").read_text())
    m["mesh"] = {"psnr": 33.3, "chamfer_to_gt": 0.005}
    (run / "metrics.json").write_text(json.dumps(m))
    mesh_lights = '{"lights": [{"type": "AmbientLight", "color": [0.1, 0.1, 0.1]}]}'
    (run / "lights.json").write_text(mesh_lights)
    capsys.readouterr()
    rc, err, out = _run_cli(["train", "--resume", "--out", run, "--iterations", "4"], capsys)  # nothing to train
    assert rc == 0 and "stale" not in err, err
    m = json.loads((run / "metrics.json").read_text())
    assert m["mesh"] == {"psnr": 33.3, "chamfer_to_gt": 0.005} and (run / "lights.json").read_text() == mesh_lights
    rc, err, out = _run_cli(["train", "--resume", "--out", run, "--iterations", "6"], capsys)
    assert rc == 0 and "made from the soup at iteration 4, not from this one (6)" in err, err
    assert f"triplet extract {run}" in err
    m = json.loads((run / "metrics.json").read_text())
    assert m["iterations"] == 6 and m["mesh"]["psnr"] == 33.3
    assert m["mesh"]["stale"] == {"made_from_iterations": 4, "soup_iterations": 6}
    assert (run / "lights.json").read_text() == mesh_lights


def test_commands_on_an_unfinished_soup_say_so(tmp_path, capsys):
    """A run stopped at 61 of 150 iterations: extract, eval and render used its soup without a word (battery 11)."""
    run = tmp_path / "run"
    assert cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN]) == 0
    (run / "checkpoints" / "ckpt_0000004.npz").unlink()  # as if stopped after the checkpoint at 2
    (run / "checkpoints" / "latest").write_text("ckpt_0000002.npz")
    capsys.readouterr()
    rc, err, _ = _run_cli(["eval", run], capsys)
    assert rc == 0 and "training stopped at iteration 2 of 4" in err and f"train --resume --out {run}" in err, err
    rc, err, _ = _run_cli(["train", "--resume", "--out", run], capsys)
    assert rc == 0
    rc, err, _ = _run_cli(["eval", run], capsys)
    assert rc == 0 and "stopped" not in err, err


def test_a_finished_run_without_its_checkpoints_is_named_as_such(tmp_path, capsys):
    """Checkpoints deleted from a finished run (to save space): the advice was "a run stopped before its first
    checkpoint starts again with --overwrite", which would delete the run and its mesh (battery 11)."""
    run = tmp_path / "run"
    assert cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN]) == 0
    shutil.rmtree(run / "checkpoints")
    (run / "mesh_stage.npz").write_bytes(b"a mesh stage's state")
    capsys.readouterr()
    rc, err, _ = _run_cli(["eval", run], capsys)
    assert rc == 2 and "the run finished (metrics.json) but its checkpoints were removed" in err, err
    assert "not --overwrite: it would delete this run, mesh included" in err and "triplet export" in err, err


def test_a_run_left_aside_by_a_killed_overwrite_is_named(tmp_path, capsys):
    """SIGKILL early in `train --overwrite` leaves RUN empty and the old run in .RUN.overwritten.XXXX/RUN, where no
    message pointed (battery 11: "is not a run directory", as if lost): the commands on RUN name it and the way back."""
    run = tmp_path / "run"
    assert cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN]) == 0
    holder = tmp_path / ".run.overwritten.abc123"
    holder.mkdir()
    run.rename(holder / "run")
    run.mkdir()  # what the killed process had claimed
    capsys.readouterr()
    for argv in (["eval", run], ["export", run], ["train", "--resume", "--out", run]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "an interrupted --overwrite left the previous run in" in err, (argv, err)
        assert str(holder / "run") in err and "mv " in err, err


def test_an_interrupted_mesh_stage_s_hint_repeats_its_options(tmp_path, capsys, monkeypatch):
    """"run it again with: triplet extract RUN (with the same mesh options, if any)": config.json keeps no mesh
    options, so the bare command ran 600 steps instead of the 30 asked (battery 11). The hint now carries them."""
    from triplet_cl.mesh.refine import MeshStage

    run = tmp_path / "run"
    assert cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN]) == 0

    def stop(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(MeshStage, "run", stop)
    capsys.readouterr()
    rc = cli_main(["extract", str(run), "--mesh-iterations", "30", "--mesh-light-phase", "0", "--formats", "glb,obj",
                   "--mesh-faces", "2000"])
    err = capsys.readouterr().err
    assert rc == 130 and f"triplet extract {run} --mesh-faces 2000 --mesh-iterations 30 --mesh-light-phase 0" in err
    assert "--formats glb,obj" in err and "if any" not in err, err

    def stop_after_save(self):  # the new mesh saved, its files not yet written (battery 11: a mixed mesh, no word)
        self.state_saved = True
        raise KeyboardInterrupt

    monkeypatch.setattr(MeshStage, "run", stop_after_save)
    assert cli_main(["extract", str(run), "--mesh-iterations", "30"]) == 130
    err = capsys.readouterr().err
    assert "the new mesh is saved (mesh_stage.npz replaced)" in err and f"triplet export {run}" in err, err


def test_interruptions_after_the_training_and_in_export_say_what_is_left(tmp_path, capsys, monkeypatch):
    """A bare "interrupted" after the last checkpoint (the training renders 3 of 40) or in an export (mesh.glb new,
    mesh.obj old) said nothing of what was left (battery 11)."""
    from triplet_cl.train import Trainer

    run = tmp_path / "run"

    def stop(self, split="test", write_renders=False, out_dir=None):
        if split == "train":
            raise KeyboardInterrupt
        return real(self, split, write_renders, out_dir)

    real = Trainer.evaluate
    monkeypatch.setattr(Trainer, "evaluate", stop)
    rc = cli_main(["train", str(DEMO), "--out", str(run), *TINY_RUN, "--save-train-renders"])
    err = capsys.readouterr().err
    assert rc == 130 and "interrupted after training: the run is complete" in err, err
    assert f"triplet render {run} --split train" in err, err
    from triplet_cl.cli import main as cm

    assert "command again" in cm._interrupted_message(cm.build_parser().parse_args(["export", str(run)]))


def test_a_new_out_created_meanwhile_is_refused(tmp_path, capsys, monkeypatch):
    """Two trains started together into one new --out both ran into it (config.json of one, checkpoints of the other):
    the folder is claimed with an exclusive mkdir; the second is refused."""
    import triplet_cl.cli.main as cm

    out = tmp_path / "new"
    real = cm._first_missing

    def racing(path):  # the other train creates the folder between this one's checks and its claim
        r = real(path)
        out.mkdir(exist_ok=True)
        return r

    monkeypatch.setattr(cm, "_first_missing", racing)
    rc, err, _ = _run_cli(["train", DEMO, "--out", out, *TINY_RUN], capsys)
    assert rc == 2 and "created meanwhile" in err, err


def test_latest_naming_another_run_s_checkpoint_is_not_followed(run, tmp_path, trained):
    """checkpoints/latest naming ../../other/checkpoints/ckpt_*.npz resumed from another run, silently: only a name in
    the run's own checkpoints folder is followed (else the newest of its own)."""
    other = tmp_path / "other"
    shutil.copytree(trained, other)
    theirs = sorted((other / "checkpoints").glob("ckpt_*.npz"))[0]
    (run / "checkpoints" / "latest").write_text(f"../../other/checkpoints/{theirs.name}")
    tr = Trainer(None, run, resume=True, quiet=True)
    assert tr.latest_checkpoint().parent == run / "checkpoints"


def test_a_checkpoints_file_is_named_as_such(run, tmp_path, capsys):
    """`checkpoints` a file said "no checkpoint in RUN/checkpoints"."""
    shutil.rmtree(run / "checkpoints")
    (run / "checkpoints").write_text("x")
    rc, err, _ = _run_cli(["render", run, "--out", tmp_path / "r"], capsys)
    assert rc == 2 and "checkpoints is a file" in err and err.count("\n") == 1, err


# ---- battery 5 (session 44) -------------------------------------------------------------------------------


def test_overwrite_refuses_the_user_s_files_inside_the_run_s_own_folders(run, capsys):
    """--overwrite looked only at the run's top level: the user's notes in renders/test/, a photo in a folder of their
    own under renders/, a backup in checkpoints/, a file in relight/ and a mesh.obj of their own went with the run."""
    (run / "renders" / "test" / "notes.txt").write_text("notes")
    (run / "renders" / "mine").mkdir()
    (run / "renders" / "mine" / "photo.jpg").write_bytes(b"x")
    (run / "checkpoints" / "my_backup.txt").write_text("keep")
    (run / "relight").mkdir()
    (run / "relight" / "a.txt").write_text("mine")
    (run / "mesh.obj").write_text("v 0 0 0\n")
    before = _tree(run)
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, "--overwrite", *TINY_RUN], capsys)
    assert rc == 2 and "not written by triplet" in err and err.count("\n") == 1, err
    for name in ("checkpoints/my_backup.txt", "mesh.obj", "relight/a.txt", "renders/mine/photo.jpg"):
        assert name in err, (name, err)
    assert "and 1 more" in err  # renders/test/notes.txt, the fifth
    assert _tree(run) == before
    # what triplet writes there does not stop it: its renders, manifests, checkpoints and signed mesh files
    for p in ("renders/test/notes.txt", "renders/mine/photo.jpg", "checkpoints/my_backup.txt", "relight/a.txt"):
        (run / p).unlink()
    (run / "relight" / "point").mkdir()
    (run / "relight" / "point" / "r_0.png").write_bytes(b"png")
    (run / "relight" / "point" / ".triplet-output").write_text('{"files": ["r_0.png"]}')
    (run / "mesh.obj").write_text("# triplet_cl mesh: 1 vertices, 0 faces\n")
    rc, err, _ = _run_cli(["train", DEMO, "--out", run, "--overwrite", *TINY_RUN], capsys)
    assert rc == 0, err
    assert not (run / "mesh.obj").exists()


@pytest.mark.parametrize("name", ["mesh.obj", "mesh.ply", "mesh.glb", "mesh_basecolor.png"])
def test_extract_and_export_refuse_the_user_s_mesh_files_in_the_run(run, capsys, name):
    """`extract RUN` and `export RUN` (into the run) replaced a mesh.obj / mesh.ply the user had put there; and a
    text file named like a texture (battery 8: a PNG or EXR that is not one is not triplet's)."""
    from triplet_cl.mesh.refine import MeshConfig, save_mesh_state
    from triplet_cl.scene import Scene

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    from triplet_cl.lights import PointLight

    save_mesh_state(run / "mesh_stage.npz", Scene.from_arrays(V, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
                                                              lights=[PointLight([0, 0, 3], [1, 1, 1])]),
                    MeshConfig())
    (run / name).write_bytes(b"USER MESH\n")
    before = _tree(run)
    fmt = "obj" if name.endswith(".png") else name.split(".")[1]  # (the OBJ's textures)
    for argv in (["extract", run, "--formats", fmt], ["export", run, "--formats", fmt]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and name in err and "not written by triplet" in err and err.count("\n") == 1, (argv, err)
        assert _tree(run) == before
    # triplet's own file of that name is replaced as before
    (run / name).unlink()
    rc, err, _ = _run_cli(["export", run, "--formats", fmt], capsys)
    assert rc == 0, err
    rc, err, _ = _run_cli(["export", run, "--formats", fmt], capsys)
    assert rc == 0, err


def test_eval_relight_checks_the_references_cameras(run, tmp_path, capsys):
    """relight.json's "cameras" (the transforms its references were rendered from) was never read: a missing file or
    other cameras than the run's test views went unnoticed. Checked before any work; the run's own cameras pass."""
    rd = _relight_refs(tmp_path / "rel")
    doc = json.loads((rd / "relight.json").read_text())
    before = _tree(run)
    data = Path(json.loads((run / "config.json").read_text())["data"])
    for cams, needle in (("../nope.json", "file not found"), (7, "expected the name of a transforms JSON"),
                         (str(data / "transforms_train.json"), "is not the run's test camera")):
        (rd / "relight.json").write_text(json.dumps({**doc, "cameras": cams}))
        rc, err, out = _run_cli(["eval", run, "--relight", rd], capsys)
        assert rc == 2 and "cameras" in err and needle in err and err.count("\n") == 1, (cams, err)
        assert "PSNR" not in out and _tree(run) == before
    wide = json.loads((data / "transforms_test.json").read_text())  # the same poses through a wider lens (battery 8)
    wide["camera_angle_x"] *= 1.2
    (tmp_path / "wide.json").write_text(json.dumps(wide))
    for cams, needle in ((str(tmp_path / "wide.json"), "field of view"),):
        (rd / "relight.json").write_text(json.dumps({**doc, "cameras": cams}))
        rc, err, out = _run_cli(["eval", run, "--relight", rd], capsys)
        assert rc == 2 and "cameras" in err and needle in err and "another lens" in err and err.count("\n") == 1, err
    (rd / "relight.json").write_text(json.dumps({**doc, "cameras": str(data / "transforms_test.json")}))
    rc, err, _ = _run_cli(["eval", run, "--relight", rd], capsys)
    assert rc == 2 and "cameras" not in err and "sets.a.images" in err, err  # past the cameras: the next check


def test_a_file_given_as_the_dataset_folder_is_named_as_such(tmp_path):
    """`train FILE` said "dataset folder not found" for a file that exists."""
    from triplet_cl.datasets import load_dataset
    from triplet_cl.errors import DatasetError

    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(DatasetError, match="is a file, not a dataset folder"):
        load_dataset(f)
    with pytest.raises(DatasetError, match="dataset folder not found"):
        load_dataset(tmp_path / "nothing")


def test_json_files_with_a_byte_order_mark_are_read(demo_copy, tmp_path):
    """A transforms file or relight.json saved with a UTF-8 BOM (Windows editors) was refused with "Unexpected UTF-8
    BOM (decode using utf-8-sig)"."""
    from triplet_cl.datasets import load_dataset
    from triplet_cl.relight import load_light_sets

    d = tmp_path / "bom"
    shutil.copytree(demo_copy, d)
    for name in ("transforms_train.json", "transforms_test.json"):
        p = d / name
        p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes())
    assert len(load_dataset(d).train) == len(load_dataset(demo_copy).train)
    lf = tmp_path / "l.json"
    lf.write_bytes(b"\xef\xbb\xbf" + json.dumps({"sets": {"a": {"lights": [_POINT]}}}).encode())
    assert [s.name for s in load_light_sets(lf, 2)] == ["a"]


def test_a_non_finite_number_in_config_json_is_named(run, capsys):
    """config.json with "sigma": NaN was reported as "checkpoint belongs to another configuration (sigma: checkpoint
    2.0, config.json nan)"."""
    cfg = json.loads((run / "config.json").read_text())
    cfg["train"]["sigma"] = float("nan")
    (run / "config.json").write_text(json.dumps(cfg))
    before = _tree(run)
    for argv in (["eval", run], ["train", DEMO, "--out", run, "--resume", "--iterations", "6"]):
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and "sigma must be a finite number, got nan" in err and err.count("\n") == 1, (argv, err)
    assert _tree(run) == before


def test_a_run_killed_while_it_was_created_can_be_started_again(tmp_path, capsys):
    """SIGKILL while `train` created its run left train.log and config.json's temporary file: every command refused the
    folder ("not a triplet run", also with --overwrite). Those leftovers are triplet's: the new run clears them; a
    folder holding anything else is still refused, untouched."""
    out = tmp_path / "pk"
    out.mkdir()
    (out / "train.log").write_text("2026-11-27 11:59:58,123 INFO dataset ...\n")
    (out / ".config.json.x1y2z3ab.tmp").write_text("{")
    (out / "checkpoints").mkdir()
    rc, err, _ = _run_cli(["train", DEMO, "--out", out, *TINY_RUN], capsys)
    assert rc == 0, err
    assert (out / "config.json").is_file() and not list(out.glob(".config.json.*.tmp"))
    for extra in ({"notes.txt": "mine"}, {}):  # a file of the user's beside it; a train.log of the user's alone
        other = tmp_path / f"other{len(extra)}"
        other.mkdir()
        (other / "train.log").write_text("my own training notes\n")
        for k, v in extra.items():
            (other / k).write_text(v)
        before = _tree(other)
        rc, err, _ = _run_cli(["train", DEMO, "--out", other, *TINY_RUN], capsys)
        assert rc == 2 and "is not a triplet run" in err, err
        assert _tree(other) == before


def test_a_run_being_written_by_another_process_is_refused(run, capsys):
    """`train --resume` / `--overwrite` and `extract` were accepted on a run that another process was training: both
    wrote the folder. The run folder's lock (flock, dropped when its holder ends) refuses them; afterwards they run."""
    import subprocess
    import sys as _sys

    holder = subprocess.Popen([_sys.executable, "-c", "import fcntl, os, sys, time; fd = os.open(sys.argv[1], "
                               "os.O_RDONLY); fcntl.flock(fd, fcntl.LOCK_EX); print('held', flush=True); "
                               "time.sleep(60)", str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        before = _tree(run)
        for argv in (["train", DEMO, "--out", run, "--resume", "--iterations", "6"],
                     ["train", DEMO, "--out", run, "--overwrite", *TINY_RUN], ["extract", run], ["export", run],
                     ["eval", run], ["render", run], ["relight", run, "--lights", _light_file(run.parent)]):
            rc, err, _ = _run_cli(argv, capsys)
            assert rc == 2 and "being written by another triplet process" in err and err.count("\n") == 1, (argv, err)
            assert _tree(run) == before
        rc, err, _ = _run_cli(["render", run, "--out", run.parent / "elsewhere"], capsys)  # not into the run
        assert rc == 0, err
    finally:
        holder.kill()
        holder.wait()
    rc, err, _ = _run_cli(["train", "--out", run, "--resume", "--iterations", "6"], capsys)
    assert rc == 0, err


def _light_file(folder):
    f = folder / "lights_for_relight.json"
    f.write_text(json.dumps({"lights": [_POINT]}))
    return f


def test_reference_frames_are_keyed_as_the_views_are_named():
    """The cameras check matched frames by ``Path.stem``: ``test/frame.0001`` and ``test/frame.0002`` were one key
    (every view but the last refused as "not the run's test camera"); a repeated name is refused, not overwritten."""
    from triplet_cl.relight import LightFileError, _frame_key, check_reference_cameras

    assert [_frame_key(p) for p in ("./test/r_0", "test/r_0.png", "test/frame.0001", "x/frame.0002.PNG")] == \
        ["r_0", "r_0", "frame.0001", "frame.0002"]
    spec = Path("/nonexistent/relight.json")
    with pytest.raises(LightFileError, match="file not found"):
        check_reference_cameras(spec, {"cameras": "t.json"}, [], [])


def test_a_sigterm_swallowed_while_starting_still_stops_training(tmp_path, capsys, monkeypatch):
    """A SIGTERM during the imports raised its KeyboardInterrupt inside an import lock's callback, which Python ignores:
    the killed `train` trained to the end. The flag the handler sets stops it before the training."""
    import triplet_cl.cli.main as cm

    real = cm._raise_if_terminated

    def swallowed():  # the signal arrived and its exception was lost on the way
        cm._TERMINATED[0] = True
        real()

    monkeypatch.setattr(cm, "_raise_if_terminated", swallowed)
    rc, err, _ = _run_cli(["train", DEMO, "--out", tmp_path / "run", *TINY_RUN], capsys)
    assert rc == 143 and "interrupted" in err, err
    assert not (tmp_path / "run" / "metrics.json").exists()


# ---- battery 9 ---------------------------------------------------------------------------------------------------
def test_render_through_a_linked_renders_folder_keeps_the_user_s_files(run, tmp_path, capsys):
    """`render RUN` wrote through RUN/renders/test when it was a link to the user's folder, replacing their r_0.png
    (battery 9), the same link that --overwrite calls the user's. The linked folder is judged as any other."""
    mine = tmp_path / "photos"
    mine.mkdir()
    (mine / "r_0.png").write_bytes(b"my photo")
    shutil.rmtree(run / "renders" / "test")
    (run / "renders" / "test").symlink_to(mine, target_is_directory=True)
    rc, err, _ = _run_cli(["render", run], capsys)
    assert rc == 2 and "no record that triplet wrote them" in err and "through a link" in err, err
    assert err.count("\n") == 1, err
    assert (mine / "r_0.png").read_bytes() == b"my photo" and sorted(p.name for p in mine.iterdir()) == ["r_0.png"]
    rc, err, _ = _run_cli(["train", "--out", run, "--resume", "--iterations", "6"], capsys)  # its final renders too
    assert rc == 2 and "no record that triplet wrote them" in err and "through a link" in err, err
    assert (mine / "r_0.png").read_bytes() == b"my photo"
    (mine / "r_0.png").unlink()  # an empty linked folder is written, and its files are triplet's from then on
    rc, err, _ = _run_cli(["render", run], capsys)
    assert rc == 0 and (mine / "r_0.png").is_file(), err
    rc, err, _ = _run_cli(["render", run], capsys)
    assert rc == 0, err


def test_light_files_with_a_hash_in_their_name_and_with_both_sets_and_lights(run, tmp_path, capsys):
    """`--lights 'studio#1.json'` was split at '#' ("lights/studio: does not exist"); a file holding both "sets" and a
    top-level "lights" list relit the sets and ignored the list (battery 9)."""
    lf = tmp_path / "studio#1.json"
    lf.write_text(json.dumps({"lights": [_POINT]}))
    rc, err, out = _run_cli(["relight", run, "--lights", lf, "--out", tmp_path / "out"], capsys)
    assert rc == 0 and (tmp_path / "out" / "r_0.png").is_file(), err
    both = tmp_path / "both.json"
    both.write_text(json.dumps({"lights": [_POINT], "sets": {"a": {"lights": [_POINT]}}}))
    rc, err, _ = _run_cli(["relight", run, "--lights", both, "--out", tmp_path / "out2"], capsys)
    assert rc == 2 and "both \"sets\" and a top-level \"lights\"" in err and err.count("\n") == 1, err
    assert not (tmp_path / "out2").exists()


def test_relight_of_each_split_goes_to_its_own_folder(run, tmp_path, capsys):
    """`relight --split train` then `--split test` wrote both into RUN/relight/SET/, the test views' r_0 ... replacing
    the training views' (battery 9). The test split keeps RUN/relight/SET/, another split RUN/relight/SPLIT/SET/."""
    lf = _light_file(tmp_path)
    for split in ("train", "test"):
        rc, err, _ = _run_cli(["relight", run, "--lights", lf, "--split", split], capsys)
        assert rc == 0, err
    n_train = len(json.loads((Path(json.loads((run / "config.json").read_text())["data"])
                              / "transforms_train.json").read_text())["frames"])
    name = lf.stem
    assert len(list((run / "relight" / "train" / name).glob("*.png"))) == n_train
    assert len(list((run / "relight" / name).glob("*.png"))) == 8


def test_eval_relight_reads_full_size_references_for_a_downscaled_run(tmp_path, demo_copy, capsys):
    """A run trained with --downscale 2 was refused against the scene's full-size references ("r_0.png is 96x96, its
    view 48x48", battery 9): a reference n times the view's size is downscaled as the photos were."""
    from triplet_cl.datasets.images import downscale_image, read_image
    from triplet_cl.relight import read_reference

    run = tmp_path / "run"
    rc, err, _ = _run_cli(["train", demo_copy, "--out", run, "--downscale", "2", *TINY_RUN], capsys)
    assert rc == 0, err
    refs = tmp_path / "refs"
    refs.mkdir()
    shutil.copytree(demo_copy / "test", refs / "a")
    (refs / "relight.json").write_text(json.dumps({"sets": {"a": {"lights": [_POINT], "images": "a"}},
                                                   "albedo": "a", "cameras": str(demo_copy / "transforms_test.json")}))
    rc, err, out = _run_cli(["eval", run, "--relight", refs], capsys)
    assert rc == 0 and "relight (soup" in out, err
    full = read_image(refs / "a" / "r_0.png")
    small = read_reference(refs / "a" / "r_0.png", full.width // 2, full.height // 2)
    want = downscale_image(full.rgb, full.alpha, 2)
    assert np.array_equal(small.rgb, want[0]) and np.array_equal(small.alpha, want[1])
    assert read_reference(refs / "a" / "r_0.png", 50, 50).rgb.shape[:2] == full.rgb.shape[:2]  # not a multiple


def test_a_closed_pipe_ends_quietly(capsys, monkeypatch):
    """`triplet devices | head -1` printed "error: Broken pipe" and exited 2 (battery 9): quiet, status 141."""
    import triplet_cl.cli.main as cm

    def closed(args):
        raise BrokenPipeError(32, "Broken pipe")

    parser_default = cm.build_parser
    monkeypatch.setattr(cm, "build_parser", lambda: _with_func(parser_default(), "devices", closed))
    rc, err, _ = _run_cli(["devices"], capsys)
    assert rc == 141 and err == "", err


def _with_func(parser, command, func):
    parser._subparsers._group_actions[0].choices[command].set_defaults(func=func)
    return parser


def test_os_error_advice_follows_the_command():
    """A full disk advised "--keep-checkpoints and resume" to every command, and to a run with no checkpoint to resume
    (battery 9): train's advice names --resume and --overwrite, the others' says to run it again."""
    import errno

    from triplet_cl.validate import os_error_message

    exc = OSError(errno.ENOSPC, "No space left on device")
    assert "--resume" in os_error_message(exc, "train") and "--overwrite" in os_error_message(exc, "train")
    other = os_error_message(exc, "eval")
    assert "checkpoint" not in other and "run the command again" in other


def test_a_read_only_folder_of_the_run_is_refused_before_the_work(run, capsys, monkeypatch):
    """A read-only checkpoints/ inside a writable run was met at the first checkpoint, after the training, naming a
    temporary file (battery 9). Each command's own folders are checked up front (os.access is what the check asks; as
    root every folder is writable, so it is answered here for the folder in question)."""
    import triplet_cl.validate as val

    real = os.access
    before = _tree(run)
    for folder, argv in (("checkpoints", ["train", "--out", run, "--resume", "--iterations", "6"]),
                         ("renders/test", ["render", run])):
        ro = str(run / folder)
        monkeypatch.setattr(val.os, "access", lambda p, mode, ro=ro, **kw: False if str(p) == ro else
                            real(p, mode, **kw))
        rc, err, _ = _run_cli(argv, capsys)
        assert rc == 2 and folder in err and "not writable" in err and err.count("\n") == 1, (argv, err)
        assert _tree(run) == before
    rc, err, _ = _run_cli(["eval", run], capsys)  # eval writes metrics.json only: its renders/ is not its business
    assert rc == 0, err


def test_relighting_an_encoded_run_warns(tmp_path, demo_copy, capsys):
    """A --color encoded run (its lights and albedo not physical) was relit and scored without a word (battery 9)."""
    run = tmp_path / "run"
    rc, err, _ = _run_cli(["train", demo_copy, "--out", run, "--color", "encoded", *TINY_RUN], capsys)
    assert rc == 0, err
    rc, err, _ = _run_cli(["relight", run, "--lights", _light_file(tmp_path), "--out", tmp_path / "out"], capsys)
    assert rc == 0 and "--color encoded" in err and "warning" in err, err


def test_view_progress_is_silent_off_a_terminal(capsys):
    """render / eval / relight show a bar per view on a terminal (battery 9: silent for minutes); off a terminal (a
    log, a pipe, these tests) and with quiet, nothing is printed and every item comes through."""
    from triplet_cl.runs import view_progress

    assert list(view_progress(range(5), "render test")) == list(range(5))
    assert list(view_progress(iter("ab"), "x", quiet=True)) == ["a", "b"]
    assert capsys.readouterr().err == ""


def test_the_next_command_after_colmap_can_be_pasted():
    """`triplet colmap` ended with "next: triplet train ds/cöl map --out RUN", which breaks on the space (battery 9)."""
    import shlex

    from triplet_cl.cli.main import train_hint

    hint = train_hint(Path("ds/cöl map"))
    assert shlex.split(hint) == ["triplet", "train", "ds/cöl map", "--out", "RUN"]


@pytest.mark.parametrize("kind,power", [("directional", "irradiance"), ("DirectionalLight", "intensity")])
def test_a_tiny_direction_is_a_direction(tmp_path, kind, power):
    """`[1e-200, 0, 0]` was refused as "the zero vector" (its squared norm underflows; battery 9); zero still is."""
    from triplet_cl.relight import LightFileError, load_light_sets

    f = tmp_path / "l.json"
    f.write_text(json.dumps({"lights": [{"type": kind, "direction": [0, -1e-300, 1e-320], power: [1, 1, 1]}]}))
    d = np.asarray(load_light_sets(f)[0].lights[0].direction)
    assert np.allclose(np.abs(d), [0, 1, 0])
    f.write_text(json.dumps({"lights": [{"type": kind, "direction": [0, 0, 0], power: [1, 1, 1]}]}))
    with pytest.raises(LightFileError, match="zero vector"):
        load_light_sets(f)


# ---- battery 10 --------------------------------------------------------------------------------------------------
def test_strided_device_arrays_are_refused_by_the_ops(run):
    """A strided device view (`a[::2]`) was read as if it were contiguous: projections 33.7 px off, no fragments,
    wrong gradients, without a word (battery 10). The ops and backward_device refuse it, naming the argument."""
    import pyopencl.array as cla

    from triplet_cl import get_device
    from triplet_cl.camera import Camera
    from triplet_cl.ops.project import project

    dev = get_device()
    V = np.random.default_rng(0).normal(size=(64, 3)).astype(np.float32)
    cam = Camera.look_at((0, 0, 4), (0, 0, 0), (0, 1, 0), 40.0, 32, 32)
    wide = cla.to_device(dev.queue, np.repeat(V, 2, axis=0))
    with pytest.raises(ValueError, match="V must be a C-contiguous device array"):
        project(dev, wide[::2], cam)
    assert np.allclose(project(dev, cla.to_device(dev.queue, V), cam).get(), project(dev, V, cam).get())


def test_paths_that_are_not_utf8_and_an_unexpanded_tilde_are_refused_up_front(tmp_path, capsys, monkeypatch):
    """A Latin-1 folder name trained to the end and then failed with OpenImageIO's traceback; `--out '~/x'` made a
    folder named "~" in the current folder (battery 10)."""
    monkeypatch.chdir(tmp_path)
    latin = os.fsdecode(b"r\xf6n")
    rc, err, _ = _run_cli(["train", DEMO, "--out", latin, *TINY_RUN], capsys)
    assert rc == 2 and "--out" in err and "not UTF-8" in err and err.count("\n") == 1, err
    rc, err, _ = _run_cli(["train", os.fsdecode(b"sp\xf6t"), "--out", "run", *TINY_RUN], capsys)
    assert rc == 2 and "DATA" in err and "not UTF-8" in err, err
    rc, err, _ = _run_cli(["train", DEMO, "--out", "~/x", *TINY_RUN], capsys)
    assert rc == 2 and "did not expand" in err, err
    assert list(tmp_path.iterdir()) == []


def test_a_bare_number_or_letter_is_not_a_device(capsys):
    """`--device 1` chose the device whose name holds a "1" ("OpenCL C 1.2"), "a" any device (battery 10)."""
    from triplet_cl.device import DeviceSelectionError, get_device

    for spec in ("1", "0", "a"):
        with pytest.raises(DeviceSelectionError, match="is not a device: give 'P:D'"):
            get_device(spec)
    d = get_device("0:0")
    assert (d.info.platform_index, d.info.device_index) == (0, 0)


def test_hard_edges_are_still_a_sigma():
    """sigma None (hard edges, `--sigma 0`) must pass the new checks (a review found it refused, and every hard-edge
    run with it)."""
    TrainConfig(sigma=None).validate()


@pytest.mark.parametrize("field,value", [("faces_per_pixel", 0), ("sigma", -1.0), ("seed", -1), ("init_points", 0),
                                         ("iterations", 2.5), ("faces_per_pixel", 2000), ("sigma", float("nan"))])
def test_train_config_refuses_what_the_command_line_refuses(field, value):
    """The library's TrainConfig passed faces_per_pixel=0 (trained to the end, then failed at the renders) and
    iterations=2.5 (saved, then refused by eval and --resume) (battery 10)."""
    with pytest.raises(ValueError, match=field):
        TrainConfig(**{field: value}).validate()


def test_the_library_trainer_keeps_the_user_s_files(tmp_path):
    """Trainer(DATA, FOLDER) replaced the user's config.json, metrics.json, lights.json and triplets.ply (battery 10);
    the CLI refused such a folder."""
    from triplet_cl.errors import RunError

    mine = tmp_path / "mine"
    mine.mkdir()
    for n in ("config.json", "lights.json", "notes.txt"):
        (mine / n).write_text("{}")
    before = _tree(mine)
    with pytest.raises(RunError, match="not a triplet run and holds config.json, lights.json"):
        Trainer(DEMO, mine, _small_cfg())
    assert _tree(mine) == before


def test_a_closed_stderr_does_not_stop_the_command(tmp_path):
    """`triplet train ... 2>&-` (a daemon, cron) exited 1 with nothing written and nothing said: sys.stderr was None
    (battery 10). The closed stream is opened on /dev/null and the command runs."""
    import subprocess
    import sys as _sys

    out = tmp_path / "run"
    code = "import sys; from triplet_cl.cli.main import main; sys.exit(main(sys.argv[1:]))"
    p = subprocess.run(f"{_sys.executable} -c '{code}' train '{DEMO}' --out '{out}' {' '.join(TINY_RUN)} 2>&-",
                       shell=True, capture_output=False, stdout=subprocess.PIPE, text=True, timeout=600)
    assert p.returncode == 0 and (out / "metrics.json").is_file(), p.stdout[-500:]


def test_integer_options_take_no_underscores_and_huge_textures_warn(run, capsys):
    """`--iterations 3_0` was read as 30 (Python's int); --texture-size 8193 was written without a word (battery 10)."""
    with pytest.raises(SystemExit) as exc:  # argparse's own refusal
        cli_main(["train", str(DEMO), "--out", str(run.parent / "new"), "--iterations", "3_0"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "invalid integer '3_0'" in err, err
    import warnings

    from triplet_cl.cli.main import build_parser

    from triplet_cl.validate import MAX_VIEWER_TEXTURE, _check_options

    for size, warned in ((MAX_VIEWER_TEXTURE, False), (MAX_VIEWER_TEXTURE + 1, True)):
        args = build_parser().parse_args(["export", str(run), "--texture-size", str(size)])
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            _check_options(args)
        assert any("many viewers" in str(w.message) for w in got) == warned, size


# ---- library calls named instead of failing deep inside (battery 10's "low" leftovers, session 61) ----------------
@pytest.mark.parametrize("call, match", [
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 0, 64, 64), r"fov_x_deg .*\(0, 180\)"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 180, 64, 64), r"fov_x_deg .*\(0, 180\)"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), float("nan"), 64, 64), r"fov_x_deg"),
    (lambda C: C.look_at((1, 2, 3), (1, 2, 3), (0, 1, 0), 40, 64, 64), r"eye and target are the same point"),
    (lambda C: C.look_at((0, 0, 3), (0, 0), (0, 1, 0), 40, 64, 64), r"target must be 3 finite numbers"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 64.5, 64), r"width must be a whole number"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 0, 64), r"at least 1x1"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 64, 64).scaled(0), r"factor must be a finite number > 0"),
    (lambda C: C.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 64, 64).scaled(-1), r"factor must be a finite number"),
])
def test_camera_refusals_name_the_argument(call, match):
    from triplet_cl.camera import Camera

    with pytest.raises(ValueError, match=match):
        call(Camera)


def test_render_settings_and_render_arguments_are_named():
    from triplet_cl.camera import Camera
    from triplet_cl.lights import PointLight
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.scene import Scene

    assert RenderSettings(background="white").background == (1.0, 1.0, 1.0)  # the names the options use
    assert RenderSettings(background="black").background == (0.0, 0.0, 0.0)
    assert RenderSettings(background=0.5).background == (0.5, 0.5, 0.5)
    assert RenderSettings(background=np.float32([0.25, 0.5, 1.0])).background == (0.25, 0.5, 1.0)
    assert RenderSettings(K=np.int64(8)).K == 8
    for bad in ("random", "grey", (1, 1), (0, np.nan, 0), "1,1,1"):
        with pytest.raises(ValueError, match="background must be"):
            RenderSettings(background=bad)
    for bad in (2.5, "30", True, 0, 1025):
        with pytest.raises(ValueError, match=r"K must be in \[1, 1024\]"):
            RenderSettings(K=bad)
    V = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], np.float32)
    F = np.array([[0, 1, 2]])
    scene = Scene.from_arrays(V, F, lights=PointLight((0, 0, 3), (10, 10, 10)))  # one light alone is a list of one
    assert len(scene.lights) == 1
    cam = Camera.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 16, 16)
    with pytest.raises(TypeError, match="settings must be a RenderSettings"):
        render(scene, cam, settings={"K": 4})
    with pytest.raises(TypeError, match="device must be a Device"):
        render(scene, cam, device="0:0")
    with pytest.raises(TypeError, match="render takes a Scene and a Camera"):
        render(cam, scene)
    img = render(scene, cam, RenderSettings(K=4, background="black")).image
    assert img.shape == (16, 16, 3) and np.isfinite(img).all()


def test_load_dataset_takes_a_numpy_integer_downscale():
    ds = load_dataset(DEMO, downscale=np.int64(2))
    assert ds.downscale == 2 and ds.train[0].width == 48
