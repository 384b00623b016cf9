"""Light-model candidates across captures lit in different ways (issue 18, item 1): which default fits
captures it was not told about.

Each candidate (a ``--lights`` mix plus options) is trained on each capture (soup stage) with
``triplet train``; ``triplet eval --relight`` then scores novel views, the three relight sets and the
albedo. The captures are a dev scene and its re-renders under other training lights
(``bench/make_scene.py``: two point lights, sun + sky, an environment), so every relight reference
is the same and the rows differ only by how training decomposed the capture.

    python bench/make_scene.py /work/shared/data/scenes/spot_small --lights two_points --out /tmp/sc/spot_two_points
    python bench/light_models.py --captures spot_small=/work/shared/data/scenes/spot_small \\
        spot_two_points=/tmp/sc/spot_two_points --candidates pa=point,ambient pp_env=point,point,sh-env \\
        --out /tmp/lm --iterations 1500 --jobs 2

A candidate is ``NAME=LIGHTS[;OPTION VALUE;...]`` (e.g. ``pp_env=point,point,sh-env;--sh-degree 1``); an item
``@{JSON}`` overrides configuration defaults through ``bench/cfg_triplet.py`` (``@{"prior_metallic": 0.01}``).
Runs that already have a relight section in ``metrics.json`` are not trained again (``--force`` re-runs).
``--stage mesh`` also runs ``triplet extract`` (the mesh stage) and scores the mesh, the asset a user exports.
Prints one markdown table (rows: capture × candidate) and the mean over captures per candidate.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

SETS = ("point_left", "sun_and_sky", "env_rotated")
TRIPLET = str(Path(sys.executable).parent / "triplet")


def _parse_candidate(s: str):
    name, _, rest = s.partition("=")
    parts = rest.split(";")
    args = ["--lights", parts[0]]
    over: dict = {}
    for p in parts[1:]:
        if p.startswith("@"):  # @{"field": value, "mesh.field": value}: config defaults (bench/cfg_triplet.py)
            over.update(json.loads(p[1:]))
        else:
            args += shlex.split(p)
    return name, (args, over)


def _done(m_file: Path, stage: str) -> bool:
    return m_file.is_file() and stage in json.loads(m_file.read_text()).get("relight", {})


def _run_one(capture: str, data: Path, cand: str, cspec: tuple, out: Path, iterations: int, seed: int,
             force: bool, stage: str = "soup") -> tuple[str, str, dict | None, float]:
    cargs, over = cspec
    cmd = [TRIPLET]
    env = None
    if over:
        cmd = [sys.executable, str(Path(__file__).with_name("cfg_triplet.py"))]
        env = {**os.environ, "TRIPLET_BENCH_CFG": json.dumps(over)}
    run = out / capture / cand
    m_file = run / "metrics.json"
    if not force and _done(m_file, stage):
        return capture, cand, json.loads(m_file.read_text()), 0.0
    t0 = time.time()
    log = out / capture / f"{cand}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a" if _done(m_file, "soup") and not force else "w") as fh:
        rc = 0
        if force or not _done(m_file, "soup"):
            rc = subprocess.call([*cmd, "train", str(data), "--out", str(run), "--iterations", str(iterations),
                                  "--seed", str(seed), "--overwrite", *cargs], stdout=fh, stderr=subprocess.STDOUT,
                                 env=env)
            if rc == 0:
                rc = subprocess.call([*cmd, "eval", str(run), "--relight", str(data / "relight")], stdout=fh,
                                     stderr=subprocess.STDOUT, env=env)
        if rc == 0 and stage == "mesh":  # the product's asset: the mesh stage, then its relight
            rc = subprocess.call([*cmd, "extract", str(run)], stdout=fh, stderr=subprocess.STDOUT, env=env)
            if rc == 0:
                rc = subprocess.call([*cmd, "eval", str(run), "--relight", str(data / "relight")], stdout=fh,
                                     stderr=subprocess.STDOUT, env=env)
    if rc != 0:
        return capture, cand, None, time.time() - t0
    return capture, cand, json.loads(m_file.read_text()), time.time() - t0


def _row(capture, cand, m, dt, stage="soup"):
    if m is None:
        return f"| {capture} | {cand} | failed (see log) |  |  |  |  |  |", None
    r = m["relight"][stage]
    sets = [r["sets"][s]["psnr"] for s in SETS]
    alb = r["albedo"]["psnr_scaled"]
    nvs = m["psnr"] if stage == "soup" else m["mesh"]["psnr"]
    vals = [nvs, *sets, alb]
    wall = m.get("wall_time_s", dt) + (m["mesh"].get("wall_time_s", 0.0) if stage == "mesh" else 0.0)
    return (f"| {capture} | {cand} | {nvs:.2f} | " + " | ".join(f"{v:.2f}" for v in sets)
            + f" | {alb:.2f} | {wall:.0f} s |"), vals


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--captures", nargs="+", required=True, help="NAME=FOLDER (a dataset with relight/)")
    ap.add_argument("--candidates", nargs="+", required=True, help="NAME=LIGHTS[;OPTION VALUE...]")
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--force", action="store_true")
    ap.add_argument("--stage", choices=("soup", "mesh"), default="soup",
                    help="score the soup, or also run `triplet extract` and score the mesh (the exported asset)")
    args = ap.parse_args(argv)
    caps = [(c.partition("=")[0], Path(c.partition("=")[2])) for c in args.captures]
    cands = [_parse_candidate(c) for c in args.candidates]
    jobs = [(cn, d, kn, ka) for cn, d in caps for kn, ka in cands]
    with ThreadPoolExecutor(args.jobs) as ex:
        res = list(ex.map(lambda j: _run_one(j[0], j[1], j[2], j[3], args.out, args.iterations, args.seed,
                                             args.force, args.stage), jobs))
    print(f"# {args.iterations} iterations, seed {args.seed}, {args.stage} stage; relight PSNR per set, albedo PSNR "
          "scaled")
    print("| capture | candidate | NVS | " + " | ".join(SETS) + " | albedo | time |")
    print("|---|---|---|---|---|---|---|---|")
    per = {}
    for capture, cand, m, dt in res:
        line, vals = _row(capture, cand, m, dt, args.stage)
        print(line)
        if vals:
            per.setdefault(cand, []).append(vals)
    print("\n| candidate (mean over captures) | NVS | relight mean | worst relight set | albedo |")
    print("|---|---|---|---|---|")
    for cand, rows in per.items():
        n = len(rows)
        nvs = sum(r[0] for r in rows) / n
        rel = sum(sum(r[1:4]) / 3 for r in rows) / n
        worst = min(min(r[1:4]) for r in rows)
        alb = sum(r[4] for r in rows) / n
        print(f"| {cand} ({n} captures) | {nvs:.2f} | {rel:.2f} | {worst:.2f} | {alb:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
