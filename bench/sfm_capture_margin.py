"""How much margin the SfM test's synthetic capture has (`tests/test_sfm.py`): over texture seeds and ring sizes,
how often `triplet colmap`'s pipeline (:func:`triplet_cl.datasets.sfm.run_sfm`) registers every photo.

The test's capture once registered all 16 photos for its own seed and few others, and a CI machine registered 15 of
16; this scan is how its texture was chosen. ``--waves N --fmax F``: N random sinusoids per channel of 8–F rad/unit
(the test's texture at N = 64, F = 80; the one before it N = 16, F = 40).

    python bench/sfm_capture_margin.py --seeds 0-11 --views 16 --waves 64 --fmax 80
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests import data_factory as fac  # noqa: E402
from tests import test_sfm as T  # noqa: E402
from triplet_cl.datasets.sfm import run_sfm  # noqa: E402
from triplet_cl.device import get_device  # noqa: E402
from triplet_cl.errors import DatasetError  # noqa: E402
from triplet_cl.lights import AmbientLight  # noqa: E402
from triplet_cl.materials import colour_display_raw  # noqa: E402
from triplet_cl.render import RenderSettings, render  # noqa: E402
from triplet_cl.scene import Scene, logit  # noqa: E402


def scene(seed: int, waves: int, fmax: float, cells: int = 96) -> Scene:
    """The test's `textured_scene` with its texture's wave count and top frequency as parameters."""
    rng = np.random.default_rng(seed)
    e = np.eye(3)
    parts = [T._grid_quads(np.array([-1.2, -1.2, 0.0]), 2.4 * e[0], 2.4 * e[1], cells, cells)]
    lo, size = np.array([-0.4, -0.3, 0.0]), np.array([0.8, 0.6, 0.6])
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for side in (0.0, 1.0):
            parts.append(T._grid_quads(lo + side * size[axis] * e[axis], size[u] * e[u], size[v] * e[v],
                                       cells // 3, cells // 4))
    V = np.concatenate(parts).reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    k = rng.normal(size=(3, waves, 3))
    k *= rng.uniform(8.0, fmax, (3, waves, 1)) / np.linalg.norm(k, axis=-1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, (3, waves))
    field = np.sin(np.einsum("ckd,nd->nck", k, V) + phase).sum(-1) / np.sqrt(waves / 16)
    albedo = np.clip(0.5 + 0.45 * np.tanh(0.6 * field), 0.02, 0.98)
    return Scene.from_arrays(V, F, material=colour_display_raw(logit(albedo)),
                             alpha=np.full((len(V), 1), logit(0.999)), lights=[AmbientLight(np.ones(3))],
                             brdf="blinn_phong")


def seeds_arg(s: str) -> list[int]:
    if "-" in s:
        a, b = s.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in s.split(",")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=seeds_arg, default=seeds_arg("0-11"))
    ap.add_argument("--views", type=int, default=16)
    ap.add_argument("--waves", type=int, default=64)
    ap.add_argument("--fmax", type=float, default=80.0)
    a = ap.parse_args()
    dev = get_device()
    cams = T.ring_cameras(a.views)
    settings = RenderSettings(K=8, sigma=None, background=(0.7, 0.75, 0.8))
    ok = 0
    print(f"{a.views} views {T.W}x{T.H}, {a.waves} waves of 8-{a.fmax:g} rad/unit")
    print("seed  registered  models  points  seconds")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in a.seeds:
            sc = scene(seed, a.waves, a.fmax)
            folder = Path(tmp) / f"s{seed}" / "photos"
            for k, c in enumerate(cams):
                fac.write_image(folder / f"IMG_{k:04d}.png", np.clip(render(sc, c, settings, dev).image, 0, 1))
            t = time.perf_counter()
            try:
                s = run_sfm(folder, folder.parent / "data", progress=lambda _: None, num_threads=2)
                ok += s["registered"] == a.views
                row = f"{s['registered']:>10}  {s['models']:>6}  {s['points']:>6}"
            except DatasetError as exc:
                row = f"{'failed':>10}  ({str(exc).split(': ', 2)[-1][:60]})"
            print(f"{seed:>4}  {row}  {time.perf_counter() - t:6.1f}", flush=True)
            shutil.rmtree(folder.parent)
    print(f"every photo registered for {ok} of {len(a.seeds)} seeds")


if __name__ == "__main__":
    main()
