"""The object's region of interest in a capture with a background (mesh/roi.py) and the cropped TSDF extraction."""

from __future__ import annotations

import math

import numpy as np
import pytest
from triplet_cl.cli.main import _bbox

from triplet_cl.camera import Camera
from triplet_cl.mesh.refine import MeshConfig
from triplet_cl.mesh.roi import ROI, auto_roi, ground_plane, look_at_point


def _tilted_frame(seed=0):
    """A random rotation and offset: the SfM frame is arbitrary (not z-up)."""
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=seed).as_matrix(), np.array([0.3, -1.2, 2.0])


def _capture(R, t, n_cams=16, seed=0):
    """Cameras on a ring around an object (a 0.6 × 0.4 × 0.5 box standing on a 6 × 6 ground at z = 0), and the
    sparse points of both, all mapped by ``x → R x + t``."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-3, 3, (600, 2)), rng.normal(0, 0.002, 600)]
    box = rng.uniform([-0.3, -0.2, 0.02], [0.3, 0.2, 0.5], (300, 3))
    up = R @ np.array([0.0, 0.0, 1.0])
    cams = []
    for k in range(n_cams):
        a = 2 * math.pi * k / n_cams
        eye = np.array([2.5 * math.cos(a), 2.5 * math.sin(a), 1.2])
        cams.append(Camera.look_at(R @ eye + t, R @ np.array([0.0, 0.0, 0.2]) + t, up, 50.0, 64, 48))
    return cams, (ground @ R.T + t), (box @ R.T + t)


def test_auto_roi_is_the_object_not_the_ground():
    R, t = _tilted_frame()
    cams, ground, box = _capture(R, t)
    np.testing.assert_allclose(look_at_point(cams), R @ [0, 0, 0.2] + t, atol=1e-6)
    roi = auto_roi(cams, np.concatenate([ground, box]))
    assert roi is not None and roi.source == "auto" and roi.ground is not None
    np.testing.assert_allclose(abs(roi.ground[0] @ (R @ [0, 0, 1.0])), 1.0, atol=1e-3)
    inside_box = roi.contains(box).mean()
    inside_ground = roi.contains(ground).mean()
    assert inside_box > 0.9 and inside_ground == 0.0, (inside_box, inside_ground)
    # the box is about the object's size (15 % padding), not the scene's
    assert np.all(roi.half < 0.5), roi.half


def test_ground_plane_none_without_a_plane():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(200, 3))
    assert ground_plane(pts, np.array([0, 0, 1.0]), np.zeros(3), band=0.01) is None


def test_roi_from_bbox_and_validation():
    roi = ROI.from_bbox([0, 1, 2, 1, 3, 5])
    np.testing.assert_allclose(roi.aabb(), [[0, 1, 2], [1, 3, 5]])
    assert roi.contains(np.array([[0.5, 2, 3], [1.5, 2, 3]])).tolist() == [True, False]
    with pytest.raises(ValueError, match="bbox"):
        ROI.from_bbox([0, 0, 0, 1, 1])
    with pytest.raises(ValueError, match="bbox"):
        MeshConfig(bbox=(0, 0, 0, -1, 1, 1)).validate()
    with pytest.raises(ValueError, match="--bbox"):
        _bbox("0,0,0,1,1")
    with pytest.raises(ValueError, match="--bbox"):
        _bbox("0,0,0,1,x,1")
    assert _bbox("0,0,0,1,1,1") == (0.0, 0.0, 0.0, 1.0, 1.0, 1.0)
    assert MeshConfig.from_dict(MeshConfig(bbox=(0, 0, 0, 1, 1, 1)).to_dict()).bbox == (0, 0, 0, 1, 1, 1)


def test_tsdf_with_roi_keeps_the_object_only(device):
    """A soup of a box on a ground plane: the fused surface without a region holds the ground; cropped to the
    automatic region, it is the box alone (closed at its bottom)."""
    from triplet_cl.mesh.extract import tsdf_fusion

    cams, ground, box = _capture(np.eye(3), np.zeros(3), n_cams=12)
    cams = [Camera.look_at(c.center, [0, 0, 0.2], [0, 0, 1.0], 50.0, 96, 72) for c in cams]
    scene = _box_and_ground_soup()
    roi = auto_roi(cams, np.concatenate([ground[np.abs(ground).max(1) < 1.5], box]))
    V, F = tsdf_fusion(scene, cams, resolution=48, roi=roi, device=device, sigma=None)
    assert len(F) > 100 and roi.contains(V).all()
    lo, hi = V.min(0), V.max(0)
    np.testing.assert_allclose(lo[:2], [-0.3, -0.2], atol=0.06)
    np.testing.assert_allclose(hi, [0.3, 0.2, 0.5], atol=0.06)
    assert lo[2] < 0.05  # down to the ground, not below it
    V0, _ = tsdf_fusion(scene, cams, resolution=48, device=device, sigma=None)
    assert np.abs(V0[:, :2]).max() > 1.0  # without the crop: the ground too


def _box_and_ground_soup():
    from triplet_cl.scene import Scene, logit

    tris = []
    for i in range(12):
        for j in range(12):
            x0, y0 = -1.5 + 0.25 * i, -1.5 + 0.25 * j
            a, b, c, d = [x0, y0, 0], [x0 + 0.25, y0, 0], [x0 + 0.25, y0 + 0.25, 0], [x0, y0 + 0.25, 0]
            tris += [(a, b, c), (a, c, d)]
    lo, hi = np.array([-0.3, -0.2, 0.0]), np.array([0.3, 0.2, 0.5])
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        for side in (lo[axis], hi[axis]):
            p = np.zeros((4, 3))
            p[:, axis] = side
            p[:, u] = [lo[u], hi[u], hi[u], lo[u]]
            p[:, v] = [lo[v], lo[v], hi[v], hi[v]]
            tris += [(p[0], p[1], p[2]), (p[0], p[2], p[3])]
    V = np.asarray(tris, np.float64).reshape(-1, 3)
    F = np.arange(len(V)).reshape(-1, 3)
    return Scene.from_arrays(V, F, alpha=np.full((len(V), 1), logit(0.99)))
