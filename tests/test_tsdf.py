"""The device votes of TSDF fusion (``kernels_cl/tsdf.cl``, ``triplet_cl.ops.tsdf``) against the numpy reference
(``tests/reference/tsdf.py``): random maps seen from cameras around a grid, views of different sizes, with and
without the photos' background and silhouette distance, one launch and many chunks."""

from __future__ import annotations

import numpy as np
import pytest

from tests.reference.tsdf import fuse_votes
from triplet_cl.camera import Camera
from triplet_cl.ops.tsdf import FusionView, TsdfVotes

TAU = 0.06
THR = 0.5


def _views(rng, n=7):
    views = []
    for i in range(n):
        w, h = (24, 18) if i % 2 else (31, 31)
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        up = [0, 0, 1] if abs(d[2]) < 0.9 else [0, 1, 0]
        cam = Camera.look_at(2.5 * d, rng.normal(scale=0.05, size=3), up, 45, w, h)
        depth = (2.5 + rng.uniform(-0.6, 0.6, (h, w))).astype(np.float32)
        acc = rng.uniform(0, 1, (h, w)).astype(np.float32)
        free = acc < 0.3
        photo_bg = rng.uniform(size=(h, w)) < 0.2 if i % 3 else None
        sd = rng.uniform(-4, 4, (h, w)).astype(np.float32) if i % 3 != 1 else None
        views.append(FusionView(cam, depth, acc, free, photo_bg, sd))
    return views


def _axes(n=(17, 13, 15)):
    return [np.linspace(-0.8, 0.8, k).astype(np.float64) for k in n]


@pytest.mark.parametrize("chunk_bytes", [64 << 20, 1])
def test_votes_match_the_reference(device, rng, chunk_bytes):
    """Every sum equal to the numpy loop's, whether the views go in one launch or one launch each (the
    accumulators carry over between chunks)."""
    views, axes = _views(rng), _axes()
    votes = TsdfVotes(device, axes, THR, TAU, chunk_bytes=chunk_bytes)
    for v in views:
        votes.add(v)
    got = votes.get()
    ref = fuse_votes(axes, views, THR, TAU)
    assert ref["seen"].max() > 3 and ref["hull_exact"].max() > 0 and ref["hidden"].max() > 0  # every rule votes
    # On PoCL every sum is equal bit for bit. A GPU's single-precision division may be up to 2.5 ulp off (OpenCL's
    # default), which can move a voxel that projects within ulps of a pixel edge to the next pixel: such voxels
    # (where any count differs) may be at most 0.1 %, and the float sums must match everywhere else.
    moved = np.zeros(len(ref["seen"]), bool)
    for name in ("seen", "hidden", "hull_out", "hull_exact"):
        moved |= got[name] != ref[name]
    assert moved.mean() <= 1e-3, f"{moved.sum()} voxels of {moved.size} counted differently"
    for name in ("num", "wsum"):
        np.testing.assert_allclose(got[name][~moved], ref[name][~moved], rtol=1e-6, atol=1e-6, err_msg=name)
    # the silhouette distance is interpolated at the projected position, so those few ulps of the division reach it
    # times the distance map's slope: NVIDIA's OpenCL (H100) differed by up to 1.5e-5 (of the truncation) in 2 % of
    # the voxels; PoCL is exact
    np.testing.assert_allclose(got["hull_sdf"][~moved], ref["hull_sdf"][~moved], rtol=0, atol=1e-4, err_msg="hull_sdf")


def test_votes_of_no_view_are_the_initial_sums(device):
    votes = TsdfVotes(device, _axes((3, 4, 5)), THR, TAU)
    got = votes.get()
    assert all(got[k].shape == (60,) for k in TsdfVotes.NAMES)
    assert not got["seen"].any() and not got["wsum"].any() and np.isneginf(got["hull_sdf"]).all()


def test_votes_errors(device, rng):
    with pytest.raises(ValueError, match="axes"):
        TsdfVotes(device, _axes()[:2], THR, TAU)
    with pytest.raises(ValueError, match="alpha_threshold"):
        TsdfVotes(device, _axes(), 1.5, TAU)
    votes = TsdfVotes(device, _axes(), THR, TAU)
    v = _views(rng, 1)[0]
    v.acc = v.acc[:-1]
    with pytest.raises(ValueError, match="view.acc"):
        votes.add(v)
