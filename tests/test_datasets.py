"""Datasets: NeRF-synthetic, instant-ngp and COLMAP (text + binary) into one model; cameras, images,
alpha, downscale, hold-out, backgrounds, and one clear error per malformed input."""

from __future__ import annotations

import json
import pickle
import shutil
import warnings

import numpy as np
import pytest

from tests import data_factory as fac
from triplet_cl.datasets import (
    DatasetWarning,
    View,
    composite_background,
    detect_format,
    downscale_image,
    holdout_split,
    load_dataset,
    read_image,
    read_model,
    resolve_background,
)
from triplet_cl.errors import DatasetError, TripletError

POINT = np.array([0.1, -0.2, 0.3])
Q8 = 0.5 / 255 + 1e-6  # 8-bit quantisation


# ---- NeRF-synthetic -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("with_ext", [False, True])
def test_nerf_loads_cameras_and_images(tmp_path, with_ext):
    written = fac.make_nerf(tmp_path, {"train": 3, "val": 1, "test": 2}, angle_x=0.8, with_ext=with_ext)
    ds = load_dataset(tmp_path)
    assert ds.format == "nerf" and ds.color_space == "srgb"
    assert [len(ds.train), len(ds.val), len(ds.test)] == [3, 1, 2]
    f = 0.5 * fac.W / np.tan(0.4)
    for split, recs in written.items():
        for view, (name, c2w, px) in zip(ds[split], recs, strict=True):
            assert view.name == name
            assert (view.width, view.height) == (fac.W, fac.H)
            assert view.rgb.dtype == np.float32 and view.rgb.shape == (fac.H, fac.W, 3)
            np.testing.assert_allclose(view.rgb[px[..., 3] > 0], px[..., :3][px[..., 3] > 0], atol=Q8)
            np.testing.assert_allclose(view.alpha, px[..., 3], atol=Q8)
            u, v, z = view.camera.project_points(POINT[None])[0]
            assert z > 0
            np.testing.assert_allclose([u, v], fac.expected_nerf_pixel(c2w, f, f, fac.W / 2, fac.H / 2, POINT),
                                       atol=1e-9)
            # the camera looks down its −Z axis: a point straight ahead lands on the image centre
            ahead = c2w[:3, 3] - 2.0 * c2w[:3, 2]
            np.testing.assert_allclose(view.camera.project_points(ahead[None])[0], [fac.W / 2, fac.H / 2, 2.0],
                                       atol=1e-9)


def test_nerf_without_test_split_uses_holdout(tmp_path):
    fac.make_nerf(tmp_path, {"train": 10})
    ds = load_dataset(tmp_path, split_holdout=8)
    assert [v.name for v in ds.test] == ["train/r_0", "train/r_8"]
    assert len(ds.train) == 8
    assert len(load_dataset(tmp_path, split_holdout=0).train) == 10


# ---- instant-ngp --------------------------------------------------------------------------------------------
def test_ngp_intrinsics_and_holdout(tmp_path):
    written = fac.make_ngp(tmp_path, n=9, per_frame={4: {"fl_x": 9.0, "cx": 3.5}})
    ds = load_dataset(tmp_path)
    assert ds.format == "ngp"
    assert [v.name for v in ds.test] == ["images/0000", "images/0008"]
    assert len(ds.train) == 7 and all(v.alpha is None for v in ds.train)
    views = {v.name: v for v in ds.train + ds.test}
    for name, c2w, px, intr in written["frames"]:
        cam = views[name].camera
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (intr["fl_x"], intr["fl_y"], intr["cx"], intr["cy"])
        np.testing.assert_allclose(
            cam.project_points(POINT[None])[0, :2],
            fac.expected_nerf_pixel(c2w, intr["fl_x"], intr["fl_y"], intr["cx"], intr["cy"], POINT), atol=1e-9)
        np.testing.assert_allclose(views[name].rgb, px[..., :3], atol=Q8)


def test_ngp_missing_images_one_warning_counting_them(tmp_path):
    fac.make_ngp(tmp_path, n=6, missing=(1, 3, 4))
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        ds = load_dataset(tmp_path, split_holdout=0)
    ours = [w for w in rec if issubclass(w.category, DatasetWarning)]
    assert len(ours) == 1
    assert "skipped 3 of 6 frames" in str(ours[0].message)
    assert len(ds.train) == 3


def test_windows_separators_in_file_paths_are_named(tmp_path):
    """file_path written with backslashes (a Windows tool's): the missing images' warning says why."""
    fac.make_nerf(tmp_path, {"train": 3, "test": 1})
    doc = json.loads((tmp_path / "transforms_train.json").read_text())
    doc["frames"][1]["file_path"] = doc["frames"][1]["file_path"].replace("/", "\\")
    (tmp_path / "transforms_train.json").write_text(json.dumps(doc))
    with pytest.warns(DatasetWarning, match="skipped 1 of 3 .*backslashes \\(Windows separators\\): write them with /"):
        load_dataset(tmp_path)


def test_ngp_all_images_missing_is_an_error(tmp_path):
    fac.make_ngp(tmp_path, n=3, missing=(0, 1, 2))
    with pytest.warns(DatasetWarning), pytest.raises(DatasetError, match="transforms.json.*no frames left"):
        load_dataset(tmp_path)


def test_ngp_distortion_refused_unless_zero(tmp_path):
    intr = {"fl_x": 7.0, "fl_y": 7.0, "cx": 4.0, "cy": 3.0, "w": fac.W, "h": fac.H,
            "k1": 0.1, "k2": 0.0, "p1": 0.0, "p2": -0.002}
    fac.make_ngp(tmp_path, n=3, intr=intr)
    with pytest.raises(DatasetError) as ei:
        load_dataset(tmp_path)
    msg = str(ei.value)
    assert "transforms.json" in msg and "k1=0.1" in msg and "p2=-0.002" in msg and "k2" not in msg
    intr.update(k1=0.0, p2=0.0)
    fac.make_ngp(tmp_path, n=3, intr=intr)
    assert len(load_dataset(tmp_path, split_holdout=0).train) == 3


def test_ngp_fisheye_refused(tmp_path):
    fac.make_ngp(tmp_path, n=2, intr={"fl_x": 7.0, "camera_model": "OPENCV_FISHEYE"})
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE"):
        load_dataset(tmp_path)


# ---- COLMAP -------------------------------------------------------------------------------------------------
def _same_camera(a, b):
    # (Camera's dataclass == compares the w2c arrays with `==` and raises; compare field by field)
    assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (b.fx, b.fy, b.cx, b.cy, b.width, b.height)
    np.testing.assert_array_equal(a.w2c, b.w2c)


def _same_datasets(a, b):
    assert a.points is not None and b.points is not None
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.colors, b.colors)
    for s in ("train", "val", "test"):
        assert [v.name for v in a[s]] == [v.name for v in b[s]]
        for va, vb in zip(a[s], b[s], strict=True):
            _same_camera(va.camera, vb.camera)
            np.testing.assert_array_equal(va.rgb, vb.rgb)


def test_colmap_text_and_binary(tmp_path):
    written = fac.make_colmap(tmp_path / "txt", n=9, binary=False)
    fac.make_colmap(tmp_path / "bin", n=9, binary=True)
    a, b = load_dataset(tmp_path / "txt"), load_dataset(tmp_path / "bin")
    assert a.format == b.format == "colmap"
    _same_datasets(a, b)
    assert [v.name for v in a.test] == ["img_000", "img_008"] and len(a.train) == 7
    fx, fy, cx, cy = written["params"]
    views = {v.name: v for v in a.train + a.test}
    for name, q, t, px in written["images"]:
        v = views[name.removesuffix(".png")]
        assert (v.camera.fx, v.camera.fy, v.camera.cx, v.camera.cy) == (fx, fy, cx, cy)
        np.testing.assert_allclose(v.camera.project_points(POINT[None])[0, :2],
                                   fac.expected_colmap_pixel(q, t, fx, fy, cx, cy, POINT), atol=1e-9)
        np.testing.assert_allclose(v.rgb, px, atol=Q8)
    pts = np.array([p[1] for p in written["points"]], np.float32)
    np.testing.assert_allclose(a.points, pts, rtol=1e-6)
    np.testing.assert_allclose(a.colors, np.array([p[2] for p in written["points"]]) / 255.0, rtol=1e-6)


@pytest.mark.parametrize("layout", ["sparse/0", "sparse", ""])
def test_colmap_layouts(tmp_path, layout):
    fac.make_colmap(tmp_path, n=3, binary=True, layout=layout)
    assert detect_format(tmp_path) == "colmap"
    assert len(load_dataset(tmp_path, split_holdout=0).train) == 3


def test_colmap_model_folder_given_directly_and_simple_pinhole(tmp_path):
    written = fac.make_colmap(tmp_path, n=3, model="SIMPLE_PINHOLE")
    ds = load_dataset(written["model_dir"], format="colmap", split_holdout=0)
    cam = ds.train[0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (7.0, 7.0, 4.0, 3.0)


def test_colmap_missing_image_warns(tmp_path):
    fac.make_colmap(tmp_path, n=4, missing=(2,))
    with pytest.warns(DatasetWarning, match="skipped 1 of 4"):
        assert len(load_dataset(tmp_path, split_holdout=0).train) == 3


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("model, params", [("SIMPLE_RADIAL", [7.0, 4.0, 3.0, 0.05]),
                                           ("RADIAL", [7.0, 4.0, 3.0, 0.05, 0.01]),
                                           ("OPENCV", [7.0, 7.0, 4.0, 3.0, 0.1, 0.0, 0.0, 0.0]),
                                           ("OPENCV_FISHEYE", [7.0, 7.0, 4.0, 3.0, 0.05, 0.0, 0.0, 0.0])])
def test_colmap_distorting_models_undistorted(tmp_path, binary, model, params, monkeypatch):
    """Distorting cameras (refused before issue 23) are undistorted by pycolmap into a cache and loaded as
    PINHOLE; the photos' exact undistortion is checked in tests/test_sfm.py."""
    pytest.importorskip("pycolmap")
    monkeypatch.delenv("TRIPLET_CACHE", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))  # the default: the user's cache
    root = tmp_path / "scene"
    fac.make_colmap(root, n=2, binary=binary, model=model, params=params)
    before = sorted(root.rglob("*"))
    ds = load_dataset(root, split_holdout=0)
    assert len(ds.train) == 2 and ds.points is not None and len(ds.points) == 5
    assert sorted(root.rglob("*")) == before  # nothing written into the dataset
    cached = list((tmp_path / "xdg" / "triplet_cl").iterdir())
    assert len(cached) == 1
    cams, *_ = read_model(cached[0] / "sparse" / "0")
    assert {c.model for c in cams.values()} == {"PINHOLE"}


def test_colmap_zero_fisheye_is_refused_clearly(tmp_path, monkeypatch):
    """A fisheye with zero coefficients is still a fisheye; pycolmap leaves it as it is: a clear error."""
    pytest.importorskip("pycolmap")
    monkeypatch.setenv("TRIPLET_CACHE", str(tmp_path / "cache"))  # beside the dataset, not inside it
    fac.make_colmap(tmp_path / "data", n=2, model="OPENCV_FISHEYE", params=[7.0, 7.0, 4.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE.*not a pinhole camera"):
        load_dataset(tmp_path / "data")


def test_colmap_zero_distortion_is_pinhole(tmp_path):
    fac.make_colmap(tmp_path, n=2, model="OPENCV", params=[7.0, 6.0, 4.0, 3.0, 0, 0, 0, 0])
    cam = load_dataset(tmp_path, split_holdout=0).train[0].camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (7.0, 6.0, 4.0, 3.0)


# ---- detection ----------------------------------------------------------------------------------------------
def test_detect_format(tmp_path):
    fac.make_nerf(tmp_path / "n")
    fac.make_ngp(tmp_path / "g", n=2)
    fac.make_colmap(tmp_path / "c", n=2)
    assert detect_format(tmp_path / "n") == "nerf"
    assert detect_format(tmp_path / "g") == "ngp"
    assert detect_format(tmp_path / "g" / "transforms.json") == "ngp"
    assert detect_format(tmp_path / "c") == "colmap"
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="cannot tell the dataset format"):
        detect_format(tmp_path / "empty")
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(tmp_path / "nope")
    with pytest.raises(DatasetError, match="transforms_train.json"):
        load_dataset(tmp_path / "c", format="nerf")
    with pytest.raises(ValueError, match="format"):
        load_dataset(tmp_path / "c", format="blender")


# ---- images: alpha, bit depths, downscale --------------------------------------------------------------------
def test_unassociated_alpha_read_as_stored(tmp_path):
    px = np.ones((fac.H, fac.W, 4), np.float32)
    px[..., 3] = 0.5
    fac.write_image(tmp_path / "a.png", px)
    img = read_image(tmp_path / "a.png")
    np.testing.assert_allclose(img.rgb, 1.0)  # not premultiplied to 0.5
    np.testing.assert_allclose(img.alpha, 0.5, atol=Q8)


def test_16bit_png_jpeg_and_exr(tmp_path):
    px = fac.image_pixels(3, alpha=False) * 0.7
    np.testing.assert_allclose(read_image(fac.write_image(tmp_path / "a.png", px, "uint16")).rgb, px, atol=1e-4)
    exr = read_image(fac.write_image(tmp_path / "a.exr", px * 5.0, "half"))
    assert exr.color_space == "linear"
    np.testing.assert_allclose(exr.rgb, px * 5.0, rtol=2e-3)
    jpg = read_image(fac.write_image(tmp_path / "a.jpg", px))
    assert jpg.color_space == "srgb" and jpg.rgb.shape == (fac.H, fac.W, 3) and jpg.alpha is None
    grey = read_image(fac.write_image(tmp_path / "g.png", px[..., :1]))
    np.testing.assert_allclose(grey.rgb, np.repeat(px[..., :1], 3, axis=2), atol=Q8)


def test_downscale_images_and_intrinsics(tmp_path):
    fac.make_nerf(tmp_path, {"train": 2, "test": 1})
    full = load_dataset(tmp_path)
    half = load_dataset(tmp_path, downscale=2)
    for a, b in zip(full.train + full.test, half.train + half.test, strict=True):
        assert (b.width, b.height) == (fac.W // 2, fac.H // 2)
        ca, cb = a.camera, b.camera
        assert (cb.fx, cb.fy, cb.cx, cb.cy) == (ca.fx / 2, ca.fy / 2, ca.cx / 2, ca.cy / 2)
        assert (cb.width, cb.height) == (ca.width // 2, ca.height // 2)
        np.testing.assert_allclose(b.alpha, a.alpha.reshape(3, 2, 4, 2).mean(axis=(1, 3)), atol=1e-6)
        # premultiplied averaging: compositing commutes with the downscale
        for bg in ("white", "black", (0.2, 0.5, 0.9)):
            np.testing.assert_allclose(b.target(bg), a.target(bg).reshape(3, 2, 4, 2, 3).mean(axis=(1, 3)),
                                       atol=1e-5)
        # the same 3D point lands on half the pixel coordinates
        np.testing.assert_allclose(cb.project_points(POINT[None])[0, :2], ca.project_points(POINT[None])[0, :2] / 2)


def test_downscale_auto_keeps_the_longer_side_within_1600_px(tmp_path):
    """``load_dataset(downscale="auto")``: the smallest integer factor bringing the first training image's longer side
    to at most ``AUTO_MAX_SIDE`` (1600 px, 3D Gaussian Splatting's rule), read from its header; every split then loads
    exactly as with that factor given; the chosen factor and the size it came from are on the dataset."""
    from triplet_cl.datasets import AUTO_MAX_SIDE, auto_factor

    def same(a, b):
        for s in ("train", "val", "test"):
            assert [v.name for v in a[s]] == [v.name for v in b[s]]
            for va, vb in zip(a[s], b[s], strict=True):
                _same_camera(va.camera, vb.camera)
                np.testing.assert_array_equal(va.rgb, vb.rgb)
                np.testing.assert_array_equal(va.alpha, vb.alpha)

    assert AUTO_MAX_SIDE == 1600
    assert [auto_factor(w, h) for w, h in ((800, 800), (1600, 1200), (1200, 1601), (4000, 3000), (6000, 4000))] \
        == [1, 1, 2, 3, 4]
    small = tmp_path / "small"
    fac.make_nerf(small, {"train": 2, "test": 1})
    a, b = load_dataset(small, downscale="auto"), load_dataset(small)
    assert a.downscale == 1 and a.auto_downscale == (fac.W, fac.H) and b.auto_downscale is None
    same(a, b)
    wide = tmp_path / "wide"
    fac.make_nerf(wide, {"train": 2, "test": 1}, w=3300, h=12)
    a, b = load_dataset(wide, downscale="auto"), load_dataset(wide, downscale=3)
    assert a.downscale == b.downscale == 3 and a.auto_downscale == (3300, 12)
    assert all((v.width, v.height) == (1100, 4) for v in a.train + a.test)
    same(a, b)
    for bad in ("big", 0, 2.0, True):
        with pytest.raises(ValueError, match="downscale must be a positive integer or 'auto'"):
            load_dataset(small, downscale=bad)



def test_downscale_auto_warns_of_a_larger_later_split_and_names_itself_when_too_small(tmp_path, monkeypatch):
    """The factor "auto" picks comes from the first split's first image; a later split whose images would have
    chosen a larger one loads at that factor with a warning naming both sizes. An auto factor that leaves images
    below the SSIM window is refused saying auto chose it (not "lower --downscale", an option never given)."""
    from triplet_cl.datasets import images
    from triplet_cl.errors import UsageError
    from triplet_cl.validate import check_image_sizes

    monkeypatch.setattr(images, "AUTO_MAX_SIDE", max(fac.W, fac.H))
    fac.make_nerf(tmp_path / "a", {"train": 2, "test": 1})
    big = fac.write_image(next((tmp_path / "a" / "test").iterdir()), fac.image_pixels(0, w=3 * fac.W, h=3 * fac.H))
    with pytest.warns(DatasetWarning, match=f"test images are {3 * fac.W}x{3 * fac.H}.*downscale 1 \\(auto\\)"):
        ds = load_dataset(tmp_path / "a", downscale="auto")
    assert ds.downscale == 1 and (ds.test[0].width, ds.test[0].height) == (3 * fac.W, 3 * fac.H) and big.is_file()
    monkeypatch.setattr(images, "AUTO_MAX_SIDE", 1600)
    fac.make_nerf(tmp_path / "wide", {"train": 2, "test": 1}, w=3300, h=24)
    ds = load_dataset(tmp_path / "wide", downscale="auto")
    assert ds.downscale == 3
    with pytest.raises(UsageError, match="auto chose 3 for 3300x24-pixel photos.*give --downscale 1"):
        check_image_sizes(ds, ds.downscale)


def test_downscale_crops_the_remainder():
    rgb = np.arange(7 * 5 * 3, dtype=np.float32).reshape(7, 5, 3)
    out, alpha = downscale_image(rgb, None, 2)
    assert out.shape == (3, 2, 3) and alpha is None
    np.testing.assert_allclose(out[0, 0], rgb[:2, :2].mean(axis=(0, 1)))
    a = np.zeros((7, 5), np.float32)
    out, alpha = downscale_image(rgb, a, 2)
    assert (out == 0).all() and (alpha == 0).all()


# ---- backgrounds, bounds, splits ---------------------------------------------------------------------------
def test_backgrounds():
    rgb = np.full((2, 3, 3), 0.8, np.float32)
    alpha = np.array([[0, 0.5, 1]] * 2, np.float32)
    np.testing.assert_allclose(composite_background(rgb, alpha, "white")[0, :, 0], [1.0, 0.9, 0.8])
    np.testing.assert_allclose(composite_background(rgb, alpha, "black")[0, :, 0], [0.0, 0.4, 0.8])
    np.testing.assert_allclose(composite_background(rgb, alpha, [0.2, 0.2, 0.2])[0, :, 0], [0.2, 0.5, 0.8])
    assert composite_background(rgb, None, "white") is rgb or np.array_equal(composite_background(rgb, None, "white"),
                                                                              rgb)
    c1 = resolve_background("random", np.random.default_rng(3))
    c2 = resolve_background("random", np.random.default_rng(3))
    assert c1.shape == (3,) and np.array_equal(c1, c2) and ((c1 >= 0) & (c1 < 1)).all()
    np.testing.assert_allclose(composite_background(rgb, alpha, c1)[0, 0], c1)
    with pytest.raises(ValueError, match="resolve_background"):
        composite_background(rgb, alpha, "random")
    with pytest.raises(ValueError, match="background"):
        resolve_background("purple")


def test_scene_extent_and_dataset_background(tmp_path):
    fac.make_nerf(tmp_path, {"train": 4, "test": 1})
    ds = load_dataset(tmp_path, background="random")
    c = ds.camera_centers()
    np.testing.assert_allclose(ds.scene_center(), c.mean(axis=0))
    assert ds.scene_extent() == pytest.approx(1.1 * np.linalg.norm(c - c.mean(axis=0), axis=1).max())
    t = ds.targets("train", rng=np.random.default_rng(0))
    assert t.shape == (4, fac.H, fac.W, 3) and t.dtype == np.float32


def test_holdout_split_by_name():
    views = [View(f"v{k:02d}", None, np.zeros((1, 1, 3), np.float32)) for k in reversed(range(17))]
    s = holdout_split(views, 8)
    assert [v.name for v in s["test"]] == ["v00", "v08", "v16"] and len(s["train"]) == 14
    with pytest.raises(ValueError):
        load_dataset(".", split_holdout=1)


# ---- malformed inputs: one DatasetError naming the file and the problem -------------------------------------
def _edit_json(path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _nerf_case(tmp_path, fn):
    fac.make_nerf(tmp_path, {"train": 3, "test": 1})
    _edit_json(tmp_path / "transforms_train.json", fn)
    return "transforms_train.json"


def _set_frame(key, value, i=1):
    def fn(d):
        d["frames"][i][key] = value
    return fn


NERF_CASES = {
    "no frames key": (lambda d: d.pop("frames"), "missing key 'frames'"),
    "empty frames": (lambda d: d.update(frames=[]), "no frames"),
    "no angle": (lambda d: d.pop("camera_angle_x"), "camera_angle_x"),
    "nan angle": (lambda d: d.update(camera_angle_x=float("nan")), "must be finite"),
    "no matrix": (lambda d: d["frames"][1].pop("transform_matrix"), "frames\\[1\\]: missing key 'transform_matrix'"),
    "no file_path": (lambda d: d["frames"][2].pop("file_path"), "frames\\[2\\]: missing key 'file_path'"),
    "3x3 matrix": (_set_frame("transform_matrix", np.eye(3).tolist()), "4x4.*\\[3, 3\\]"),
    "ragged matrix": (_set_frame("transform_matrix", [[1, 0], [0, 1, 0]]), "4x4"),
    "nan matrix": (_set_frame("transform_matrix", (np.eye(4) * np.nan).tolist()), "NaN or Inf"),
    "scaled rotation": (_set_frame("transform_matrix", (np.eye(4) * 2).tolist()), "frames\\[1\\].*orthonormal"),
    "string angle": (lambda d: d.update(camera_angle_x="wide"), "must be a number"),
}


@pytest.mark.parametrize("case", sorted(NERF_CASES))
def test_malformed_nerf_json(tmp_path, case):
    fn, problem = NERF_CASES[case]
    fname = _nerf_case(tmp_path, fn)
    with pytest.raises(DatasetError, match=problem) as ei:
        load_dataset(tmp_path)
    assert fname in str(ei.value) and isinstance(ei.value, TripletError)


def test_bad_json_reports_line_and_column(tmp_path):
    fac.make_nerf(tmp_path, {"train": 2, "test": 1})
    (tmp_path / "transforms_test.json").write_text('{\n  "camera_angle_x": 0.8,\n  "frames": [,]\n}\n')
    with pytest.raises(DatasetError, match=r"transforms_test.json: invalid JSON at line 3, column 14"):
        load_dataset(tmp_path)


def test_images_of_different_sizes_in_a_split(tmp_path):
    fac.make_nerf(tmp_path, {"train": 3, "test": 1})
    fac.write_image(tmp_path / "train" / "r_2.png", fac.image_pixels(0, 10, 6))
    with pytest.raises(DatasetError, match="r_2.png: image is 10x6 but r_0.png in the same train split is 8x6"):
        load_dataset(tmp_path)


def _write_oriented_jpeg(path, pixels, orientation):
    import OpenImageIO as oiio

    px = np.ascontiguousarray(pixels[..., :3], np.float32)
    spec = oiio.ImageSpec(px.shape[1], px.shape[0], 3, "uint8")
    spec.attribute("Orientation", orientation)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(px), out.geterror()
    out.close()


def test_exif_orientation_named_by_colmap_and_for_colmap_poses(tmp_path):
    """``triplet colmap`` names the photos an EXIF orientation turns (battery 10: solved without a word), and a
    COLMAP dataset's warning says its cameras fit the stored pixels (COLMAP solved on them) instead of asking to
    rotate the files."""
    from triplet_cl.camera import Camera
    from triplet_cl.datasets.images import load_views
    from triplet_cl.datasets.sfm import photo_headers, warn_exif_orientation

    paths = []
    for i, o in enumerate((6, 1, 8)):
        paths.append(tmp_path / f"IMG_{i}.jpg")
        _write_oriented_jpeg(paths[-1], fac.image_pixels(i), o)
    with pytest.warns(DatasetWarning, match=r"2 of the 3 photos carry an EXIF orientation \(IMG_0.jpg: 6, shown "
                                            r"rotated 90° clockwise.*structure from motion solves on the pixels as "
                                            r"stored.*exiftran -ai"):
        assert warn_exif_orientation(photo_headers(paths)) == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        assert warn_exif_orientation(photo_headers([paths[1]])) == 0

    def cam(w, h):
        return Camera.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, w, h)

    records = [(p.stem, p, cam) for p in paths]
    with pytest.warns(DatasetWarning, match=r"COLMAP's cameras were solved on those pixels and fit them"):
        load_views(records, 1, "train", stored_pixel_poses=True)
    with pytest.warns(DatasetWarning, match=r"if the poses were made for the photos as viewers show them"):
        load_views(records, 1, "train")


def test_exif_orientation_is_named(tmp_path):
    """Photos whose EXIF orientation has viewers show them turned are read as stored (as COLMAP and instant-ngp
    read them), with one warning naming the tag; one stored sideways among the others: the size error says why."""
    fac.make_nerf(tmp_path, {"train": 3, "test": 1})
    for i in range(3):
        (tmp_path / "train" / f"r_{i}.png").unlink()
        _write_oriented_jpeg(tmp_path / "train" / f"r_{i}.jpg", fac.image_pixels(i), 6)
    with pytest.warns(DatasetWarning, match=r"3 of 3 train images carry an EXIF orientation \(r_0.jpg: 6, shown "
                                            "rotated 90° clockwise"):
        ds = load_dataset(tmp_path)
    assert ds.train[0].rgb.shape[:2] == (fac.H, fac.W)  # the pixels as stored
    _write_oriented_jpeg(tmp_path / "train" / "r_2.jpg", fac.image_pixels(2, fac.H, fac.W), 6)  # stored sideways
    with pytest.raises(
            DatasetError, match=f"r_2.jpg: image is {fac.H}x{fac.W} but r_0.jpg .*its EXIF orientation 6 has "
                                f"viewers show it rotated 90° clockwise, at {fac.W}x{fac.H}"):
        load_dataset(tmp_path)
    for i in (1, 2):  # the sideways one first: the others' error names it
        _write_oriented_jpeg(tmp_path / "train" / f"r_{i}.jpg", fac.image_pixels(i), 1)
    _write_oriented_jpeg(tmp_path / "train" / "r_0.jpg", fac.image_pixels(0, fac.H, fac.W), 6)
    with pytest.raises(DatasetError, match=f"r_1.jpg: image is {fac.W}x{fac.H} but r_0.jpg .*r_0.jpg's EXIF "
                                           f"orientation 6 has viewers show it rotated 90° clockwise, at "
                                           f"{fac.W}x{fac.H}"):
        load_dataset(tmp_path)


def test_unreadable_image(tmp_path):
    fac.make_nerf(tmp_path, {"train": 3, "test": 1})
    (tmp_path / "train" / "r_1.png").write_bytes(b"this is not a png")
    with pytest.raises(DatasetError, match="r_1.png: cannot read the image"):
        load_dataset(tmp_path)


@pytest.mark.parametrize("ext", ["png", "jpg"])
def test_truncated_image(tmp_path, ext):
    p = fac.write_image(tmp_path / f"t.{ext}", fac.image_pixels(0, 64, 64)[..., :3])
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    with pytest.raises(DatasetError, match=f"t.{ext}: cannot read the image"):
        read_image(p)


def test_missing_folder_and_files(tmp_path):
    with pytest.raises(DatasetError, match="nothing_here: dataset folder not found"):
        load_dataset(tmp_path / "nothing_here", format="nerf")
    (tmp_path / "x").mkdir()
    with pytest.raises(DatasetError, match="transforms.json: file not found"):
        load_dataset(tmp_path / "x", format="ngp")
    with pytest.raises(DatasetError, match="no COLMAP model found"):
        load_dataset(tmp_path / "x", format="colmap")
    fac.make_colmap(tmp_path / "c", n=2)
    shutil.rmtree(tmp_path / "c" / "images")
    with pytest.raises(DatasetError, match="images folder not found"):
        load_dataset(tmp_path / "c")


def _colmap_text_case(tmp_path, fname, edit):
    written = fac.make_colmap(tmp_path, n=3, binary=False)
    p = written["model_dir"] / fname
    p.write_text(edit(p.read_text()))


COLMAP_TEXT_CASES = {
    "unknown model": ("cameras.txt", lambda s: s.replace("PINHOLE", "WEIRD"), "unknown camera model 'WEIRD'"),
    "param count": ("cameras.txt", lambda s: s.replace(" 2.75", ""), "PINHOLE takes 4 parameters, found 3"),
    "bad number": ("cameras.txt", lambda s: s.replace("7.0", "seven"), "camera parameters must be numbers"),
    "short image line": ("images.txt", lambda s: s.replace(" 1 img_001.png", ""), "line 6: expected 'IMAGE_ID"),
    "nan pose": ("images.txt", lambda s: s.replace("\n2 ", "\n2 nan ", 1).replace("nan 0.", "nan ", 1), "NaN"),
    "unknown camera": ("images.txt", lambda s: s.replace(" 1 img_002.png", " 5 img_002.png"),
                       "refers to camera 5"),
    "bad point": ("points3D.txt", lambda s: s.replace("\n3 ", "\n3 x "), "line 4: X Y Z R G B must be numbers"),
}


@pytest.mark.parametrize("case", sorted(COLMAP_TEXT_CASES))
def test_malformed_colmap_text(tmp_path, case):
    fname, edit, problem = COLMAP_TEXT_CASES[case]
    _colmap_text_case(tmp_path, fname, edit)
    with pytest.raises(DatasetError, match=problem) as ei:
        load_dataset(tmp_path)
    assert fname in str(ei.value)


@pytest.mark.parametrize("fname", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_colmap_binary(tmp_path, fname):
    written = fac.make_colmap(tmp_path, n=3, binary=True)
    p = written["model_dir"] / fname
    p.write_bytes(p.read_bytes()[:-5])
    with pytest.raises(DatasetError, match=f"{fname}: truncated binary file"):
        load_dataset(tmp_path)


def test_colmap_image_size_must_match_camera(tmp_path):
    fac.make_colmap(tmp_path, n=2, w=8, h=6)
    fac.write_image(tmp_path / "images" / "img_000.png", fac.image_pixels(0, 8, 6, alpha=False))
    fac.make_colmap(tmp_path / "other", n=2, w=10, h=6)
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text(
        (tmp_path / "other" / "sparse" / "0" / "cameras.txt").read_text())
    with pytest.raises(DatasetError, match="img_000.png: image is 8x6 but camera 1 of cameras.txt is 10x6"):
        load_dataset(tmp_path)


def test_dataset_error_pickles():
    e = pickle.loads(pickle.dumps(DatasetError("a/b.json", "missing key 'frames'")))
    assert str(e) == "a/b.json: missing key 'frames'" and e.path == "a/b.json"


# ---- the shared test scenes -------------------------------------------------------------------------------
def test_spot_small_loads(shared_data):
    root = shared_data / "scenes" / "spot_small"
    if not root.is_dir():
        pytest.skip(f"{root} not found")
    ds = load_dataset(root)
    assert ds.format == "nerf" and ds.color_space == "srgb" and len(ds.train) > 0 and len(ds.test) > 0
    for v in ds.train + ds.test:
        cam = v.camera
        assert np.linalg.norm(cam.center) == pytest.approx(3.2, abs=1e-3)
        u, w, z = cam.project_points(np.zeros((1, 3)))[0]  # the origin is straight ahead
        assert z == pytest.approx(3.2, abs=1e-3)
        assert abs(u - cam.cx) < 1e-6 and abs(w - cam.cy) < 1e-6
        assert v.alpha is not None and v.alpha.max() == 1.0 and v.alpha.min() == 0.0
    assert ds.scene_extent() > 3.2


@pytest.mark.parametrize("intr, want", [({"is_fisheye": "false"}, "is_fisheye: expected true or false"),
                                        ({"camera_model": ["OPENCV"]}, "camera_model: expected a name")])
def test_camera_fields_of_the_wrong_type_are_named(tmp_path, intr, want):
    """is_fisheye given as the string "false" was read as true (refused as a fisheye); camera_model as a list was
    accepted (a battery)."""
    fac.make_ngp(tmp_path, n=2, intr={"fl_x": 7.0, **intr})
    with pytest.raises(DatasetError, match=want):
        load_dataset(tmp_path)
    fac.make_ngp(tmp_path / "ok", n=2, intr={"fl_x": 7.0, "is_fisheye": False})
    assert len(load_dataset(tmp_path / "ok", split_holdout=0).train) == 2


# ---- battery 9 (session 56) ---------------------------------------------------------------------------------
def _write_exr_channels(path, px, names):
    """An EXR with the given channel names (a Blender multi-layer file's ``ViewLayer.Combined.R``, ...)."""
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(px.shape[1], px.shape[0], px.shape[2], "float")
    spec.channelnames = tuple(names)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(np.ascontiguousarray(px, np.float32)), out.geterror()
    out.close()
    return path


def test_exr_alpha_is_premultiplied_and_read_straight(tmp_path):
    """OpenEXR stores colour premultiplied by alpha: it was read as straight, an edge pixel's colour times alpha twice
    (0.51 of the true colour over r_0's edge). The loader divides it back (0 where alpha is 0), as it reads PNG; an
    environment map's colour stays as stored (its radiance)."""
    import OpenImageIO as oiio

    from triplet_cl.mesh.envmap import project_envmap, read_envmap_sh

    straight = fac.image_pixels(2) * np.array([2.0, 1.5, 1.0, 1.0], np.float32)  # alpha 0 .. 1 across the image
    a = straight[..., 3]
    stored = np.concatenate([straight[..., :3] * a[..., None], a[..., None]], axis=-1)
    img = read_image(fac.write_image(tmp_path / "p.exr", stored, "float"))
    assert img.color_space == "linear" and img.alpha is not None
    np.testing.assert_allclose(img.alpha, a, atol=1e-7)
    np.testing.assert_allclose(img.rgb[a > 0], straight[..., :3][a > 0], rtol=1e-5)
    assert (img.rgb[a == 0] == 0).all() and (a == 0).any()
    kept = read_image(tmp_path / "p.exr", unpremultiply=False)
    np.testing.assert_allclose(kept.rgb, stored[..., :3], rtol=1e-6)
    # downscaling averages premultiplied: the stored values' block means, divided by the mean alpha
    two = read_image(tmp_path / "p.exr", downscale=2)
    np.testing.assert_allclose(two.rgb * two.alpha[..., None], stored[:6, :8, :3].reshape(3, 2, 4, 2, 3).mean((1, 3)),
                               rtol=1e-5, atol=1e-7)
    env = fac.write_image(tmp_path / "env.exr", np.concatenate(
        [np.full((8, 16, 3), 0.25, np.float32), np.full((8, 16, 1), 0.5, np.float32)], -1), "float")
    np.testing.assert_allclose(read_envmap_sh(env, 1), project_envmap(np.full((8, 16, 3), 0.25, np.float32), 1))
    # a TIFF: premultiplied unless OIIO reports its alpha unassociated; a PNG is straight
    px = np.concatenate([np.full((4, 4, 3), 0.4, np.float32), np.full((4, 4, 1), 0.5, np.float32)], -1)
    np.testing.assert_allclose(read_image(fac.write_image(tmp_path / "s.png", px)).rgb, 0.4, atol=Q8)
    np.testing.assert_allclose(read_image(fac.write_image(tmp_path / "s.tif", px)).rgb, 0.4, atol=Q8)
    spec = oiio.ImageSpec(4, 4, 4, "uint8")  # no UnassociatedAlpha: OIIO writes the TIFF as associated
    out = oiio.ImageOutput.create(str(tmp_path / "a.tif"))
    assert out.open(str(tmp_path / "a.tif"), spec) and out.write_image(px)
    out.close()
    np.testing.assert_allclose(read_image(tmp_path / "a.tif").rgb, 0.8, atol=2 * Q8)


def test_multilayer_exr_reads_its_colour_layer_by_name(tmp_path):
    """Blender's multi-layer EXR: ViewLayer.AO.* sorts before ViewLayer.Combined.*, and the first three channels (the
    AO pass) were the photo. Plain R, G, B; else the one layer with R, G, B; else the "Combined" one; else refused."""
    h, w = 4, 6
    ao = np.full((h, w, 3), 0.8, np.float32)
    cow = fac.image_pixels(1, w, h)
    cow[..., :3] *= cow[..., 3:]  # premultiplied, as EXR stores it
    px = np.concatenate([ao, cow], -1)
    names = ["ViewLayer.AO.R", "ViewLayer.AO.G", "ViewLayer.AO.B", "ViewLayer.Combined.R", "ViewLayer.Combined.G",
             "ViewLayer.Combined.B", "ViewLayer.Combined.A"]
    img = read_image(_write_exr_channels(tmp_path / "ml.exr", px, names))
    np.testing.assert_allclose(img.alpha, cow[..., 3])
    np.testing.assert_allclose(img.rgb * img.alpha[..., None], cow[..., :3], rtol=1e-5, atol=1e-7)
    # one colour layer (no Combined): that one; a plain R, G, B beside layers: the plain one
    one = ["ViewLayer.AO.X", "ViewLayer.AO.Y", "ViewLayer.AO.Z"] + [n.replace("Combined", "Image") for n in names[3:]]
    img = read_image(_write_exr_channels(tmp_path / "one.exr", px, one))
    np.testing.assert_allclose(img.alpha, cow[..., 3])
    plain = ["R", "G", "B"] + [n.replace("Combined", "Other") for n in names[3:]]
    img = read_image(_write_exr_channels(tmp_path / "plain.exr", px[..., :6], plain[:6]))
    np.testing.assert_allclose(img.rgb, ao)
    assert img.alpha is None
    # two colour layers, neither Combined: refused, naming the file and the layers
    two = [n.replace("Combined", "Diffuse") for n in names]
    with pytest.raises(DatasetError, match="two.exr: a multi-layer EXR.*ViewLayer.AO, ViewLayer.Diffuse"):
        read_image(_write_exr_channels(tmp_path / "two.exr", px, two))


@pytest.mark.parametrize("key", ["camera_angle_y", "fl_y"])
def test_a_vertical_focal_length_alone_means_square_pixels(tmp_path, key):
    """camera_angle_y alone (instant-ngp reads it) was refused: "missing key 'camera_angle_x' (or 'fl_x')". The
    focal length comes from it and the image height, fx = fy."""
    fac.make_nerf(tmp_path, {"train": 2, "test": 1})
    fy = 0.5 * fac.H / np.tan(0.35)
    for split in ("train", "test"):
        p = tmp_path / f"transforms_{split}.json"
        d = json.loads(p.read_text())
        del d["camera_angle_x"]
        d[key] = 0.7 if key == "camera_angle_y" else fy
        p.write_text(json.dumps(d))
    cam = load_dataset(tmp_path).train[0].camera
    assert cam.fx == pytest.approx(fy) and cam.fy == pytest.approx(fy) and fac.W != fac.H
    d.pop(key)
    p.write_text(json.dumps(d))
    with pytest.raises(DatasetError, match="transforms_test.json: missing key 'camera_angle_x'.*'camera_angle_y'"):
        load_dataset(tmp_path)


def test_a_principal_point_far_from_the_image_centre_warns(tmp_path):
    """fl_x / fl_y / cx / cy written for images half the size (no w / h to refuse the mismatch): the principal point at
    a quarter of the image was accepted without a word (battery 9). One warning names the values, the image size and
    the likely cause; a principal point near the centre says nothing."""
    fac.make_ngp(tmp_path / "a", n=3, intr={"fl_x": 3.5, "fl_y": 3.5, "cx": 2.0, "cy": 1.5})
    with pytest.warns(DatasetWarning, match=r"3 of 3 frames put the principal point far from the image centre "
                                            r"\(frames\[0\]: cx = 2, cy = 1.5 on a 8x6 image, whose centre is 4, 3\): "
                                            r"the intrinsics were likely written for images of another size.*give w "
                                            r"and h") as rec:
        load_dataset(tmp_path / "a", split_holdout=0)
    assert len([r for r in rec if issubclass(r.category, DatasetWarning)]) == 1
    fac.make_ngp(tmp_path / "b", n=3, intr={"fl_x": 7.0, "cx": 4.0, "cy": 5.0, "w": fac.W, "h": fac.H})
    with pytest.warns(DatasetWarning, match=r"cy = 5 on a 8x6 image.*check cx / cy"):
        load_dataset(tmp_path / "b", split_holdout=0)
    fac.make_ngp(tmp_path / "c", n=3)  # cx 4.25, cy 2.75 on 8x6
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        load_dataset(tmp_path / "c", split_holdout=0)


def test_nerfstudio_masks_are_named_as_unused(tmp_path):
    """Frames with nerfstudio's mask_path were loaded without a word about their masks (battery 9): one warning names
    the key and how many frames have it. The masks are not applied (they mark pixels to leave out of the loss)."""
    fac.make_ngp(tmp_path, n=4, per_frame={k: {"mask_path": f"masks/{k:04d}.png"} for k in (0, 2, 3)})
    with pytest.warns(DatasetWarning, match=r"transforms.json: 3 of 4 frames have a 'mask_path' \(nerfstudio "
                                            r"masks\): the masks are not used") as rec:
        ds = load_dataset(tmp_path, split_holdout=0)
    assert len([r for r in rec if issubclass(r.category, DatasetWarning)]) == 1
    assert all(v.alpha is None for v in ds.train)


def test_a_test_frame_that_is_a_training_image_warns(tmp_path):
    """A test frame naming a training image (the same file) was scored as a novel view without a word (battery 9):
    one warning per split counts them and names one."""
    fac.make_nerf(tmp_path, {"train": 3, "val": 1, "test": 2})
    p = tmp_path / "transforms_test.json"
    d = json.loads(p.read_text())
    d["frames"][1]["file_path"] = "./train/r_2.png"
    p.write_text(json.dumps(d))
    with pytest.warns(DatasetWarning, match=r"1 of the 2 test frames is a training image too, the same file \(e\.g\. "
                                            r"train/r_2\): scored as novel views") as rec:
        ds = load_dataset(tmp_path)
    assert len([r for r in rec if issubclass(r.category, DatasetWarning)]) == 1 and len(ds.test) == 2


def test_a_scene_far_from_the_origin_warns_before_training(tmp_path):
    """Cameras 1e6 from the origin (georeferenced poses) trained 14 dB against 23 at the origin in float32, without a
    word (battery 9). train warns past FAR_FROM_ORIGIN scene extents, naming the distance and to recentre."""
    from triplet_cl.train import FAR_FROM_ORIGIN, scene_extent, warn_if_far_from_origin

    for shift, far in ((1e6, True), (1e2, False)):
        root = tmp_path / f"s{shift:g}"
        fac.make_nerf(root, {"train": 4})
        p = root / "transforms_train.json"
        d = json.loads(p.read_text())
        for f in d["frames"]:
            f["transform_matrix"][0][3] += shift
        p.write_text(json.dumps(d))
        ds = load_dataset(root, split_holdout=0)
        ext = scene_extent(ds)
        assert (np.linalg.norm(ds.scene_center()) > FAR_FROM_ORIGIN * ext) == far
        with warnings.catch_warnings(record=True) as rec:
            warnings.simplefilter("always")
            warn_if_far_from_origin(ds, ext, "DATA")
        said = [str(r.message) for r in rec if issubclass(r.category, DatasetWarning)]
        assert len(said) == int(far), said
        if far:
            assert said[0].startswith("DATA: the scene lies 1e+06 from the origin") and "recentre the poses" in said[0]


def test_instant_ngp_per_frame_sizes_must_agree_within_a_split(tmp_path):
    """Per-frame w / h are read (README), but one split holds one image size: two sizes in instant-ngp's one split
    are refused, naming both (battery 9 found the README silent about it)."""
    fac.make_ngp(tmp_path, n=3, intr={"fl_x": 7.0}, per_frame={2: {"w": 10, "h": 6}})
    fac.write_image(tmp_path / "images" / "0002.png", fac.image_pixels(2, 10, 6, alpha=False))
    with pytest.raises(DatasetError, match="0002.png: image is 10x6 but 0000.png in the same train split is 8x6: every "
                                           "image of a split must have one size"):
        load_dataset(tmp_path)


def _opaque_alpha_copy(tmp_path, transparent_pixel: bool):
    """A NeRF folder whose images are RGBA with alpha 255 everywhere (an RGBA export of ordinary photos); with
    ``transparent_pixel`` one pixel of one test image is transparent."""
    written = fac.make_nerf(tmp_path, {"train": 3, "test": 2})
    for split, recs in written.items():
        for k, (_, _, px) in enumerate(recs):
            px = px.copy()
            px[..., 3] = 1.0
            if transparent_pixel and split == "test" and k == 1:
                px[2, 3, 3] = 0.0
            fac.write_image(tmp_path / split / f"r_{k}.png", px)
    return written


def test_fully_opaque_alpha_is_dropped_with_a_warning(tmp_path):
    written = _opaque_alpha_copy(tmp_path, transparent_pixel=False)
    with pytest.warns(DatasetWarning, match="fully opaque, so it masks nothing"):
        ds = load_dataset(tmp_path)
    assert not ds.has_alpha
    assert all(v.alpha is None for split in ("train", "test") for v in ds[split])
    for view, (_, _, px) in zip(ds.train, written["train"], strict=True):  # the colour is kept as stored
        np.testing.assert_allclose(view.rgb, px[..., :3], atol=Q8)


def test_alpha_kept_when_any_image_is_transparent_anywhere(tmp_path):
    _opaque_alpha_copy(tmp_path, transparent_pixel=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DatasetWarning)
        ds = load_dataset(tmp_path)
    assert ds.has_alpha and all(v.alpha is not None for v in ds.train)
    assert float(ds.test[1].alpha.min()) == 0.0


def test_blank_images_are_named(tmp_path):
    """A fully transparent training image and an opaque black test image were trained on and scored without a word
    (battery 11): one warning each, naming them."""
    written = fac.make_nerf(tmp_path, {"train": 3, "test": 2})
    px = written["train"][1][2].copy()
    px[..., 3] = 0.0
    fac.write_image(tmp_path / "train" / "r_1.png", px)
    px = written["test"][0][2].copy()
    px[..., :3], px[..., 3] = 0.0, 1.0
    fac.write_image(tmp_path / "test" / "r_0.png", px)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ds = load_dataset(tmp_path)
    msgs = [str(w.message) for w in caught if issubclass(w.category, DatasetWarning)]
    assert any("1 of 3 train images are fully transparent" in m and "r_1.png" in m and "trained" in m for m in msgs)
    assert any("1 of 2 test images are black and opaque" in m and "r_0.png" in m and "scored" in m for m in msgs)
    assert len(ds.train) == 3 and len(ds.test) == 2  # used as they are
