"""The BRDF descriptors of triplet_cl.materials (channels, activations, initial values, asset
attributes, glTF mapping, kernel defines) and the one home of logit / inverse_softplus."""

from __future__ import annotations

import numpy as np
import pytest

from triplet_cl.activations import inverse_softplus, logit, sigmoid, softplus
from triplet_cl.materials import BRDFS, DEFAULT_BRDF, blinn_phong_roughness, brdf_from_cli, get_brdf


def test_descriptors_channels_and_defines():
    ct, bp = get_brdf("cook_torrance"), get_brdf("blinn_phong")
    assert DEFAULT_BRDF == "cook_torrance" and set(BRDFS) == {"cook_torrance", "blinn_phong"}
    assert ct.channel_names == ("albedo_r", "albedo_g", "albedo_b", "roughness", "metallic", "ao")
    assert bp.channel_names == ("kd_r", "kd_g", "kd_b", "ks_r", "ks_g", "ks_b", "shininess", "ka_r", "ka_g", "ka_b")
    assert ct.softplus_columns == [] and bp.softplus_columns == [6]
    assert ct.kernel_defines() == {"BRDF_COOK_TORRANCE": 0, "BRDF_BLINN_PHONG": 1, "BRDF": 0, "NMAT": 6}
    assert bp.kernel_defines()["BRDF"] == 1 and bp.kernel_defines()["NMAT"] == 10
    assert len({b.kernel_id for b in BRDFS.values()}) == len(BRDFS)
    for b in BRDFS.values():  # the attributes tile the channels
        cols = [c for a in b.attributes for c in range(a.start, a.start + a.width)]
        assert cols == list(range(b.num_channels))
    assert bp.bounded_attributes == ["albedo", "ks", "ka"]
    with pytest.raises(ValueError, match="brdf must be one of"):
        get_brdf("phong")
    assert brdf_from_cli("blinn-phong") == "blinn_phong" and brdf_from_cli("cook_torrance") == "cook_torrance"


def test_initial_values_and_activation():
    for b in BRDFS.values():
        raw = b.initial_raw(4)
        assert raw.shape == (4, b.num_channels)
        np.testing.assert_allclose(b.activate(raw)[0], [c.init for c in b.channels], rtol=1e-12)
    # the method's values (docs/ARCHITECTURE.md §8), as the scene set them before the descriptors, except the
    # roughness: 0.5 since issue 18 (was the method's 0.9; README "Roughness and metallic" for the measurements)
    old_ct = np.log(np.array([0.5, 0.5, 0.5, 0.5, 0.1, 0.99]) / (1 - np.array([0.5, 0.5, 0.5, 0.5, 0.1, 0.99])))
    assert np.array_equal(get_brdf("cook_torrance").initial_raw(1)[0].astype(np.float32), old_ct.astype(np.float32))
    raw = np.random.default_rng(0).normal(0, 2, (5, 10))
    act = get_brdf("blinn_phong").activate(raw)
    assert np.array_equal(act[:, 6], softplus(raw[:, 6])) and np.array_equal(act[:, :6], sigmoid(raw[:, :6]))


def test_pbr_mapping():
    n = 3
    a = {"albedo": np.full((n, 3), 0.5), "ks": np.full((n, 3), 0.2), "shininess": np.array([0.0, 10.0, 100.0]),
         "ka": np.zeros((n, 3))}
    r, m, ao = get_brdf("blinn_phong").pbr(a, n)
    np.testing.assert_allclose(r ** 4, 2 / (a["shininess"] + 3))
    assert np.array_equal(m, np.zeros(n)) and np.array_equal(ao, np.ones(n))
    assert np.array_equal(blinn_phong_roughness(a["shininess"]), r)
    assert get_brdf("blinn_phong").specular == "ks" and get_brdf("cook_torrance").specular is None


def test_logit_and_inverse_softplus_have_one_home():
    p = np.concatenate([np.linspace(0, 1, 1001), [1e-9, 1 - 1e-9]])
    # the scene's former logit: clipped to (1e-6, 1 - 1e-6), then log(p / (1 - p))
    pc = np.clip(p, 1e-6, 1 - 1e-6)
    np.testing.assert_allclose(logit(p), np.log(pc / (1 - pc)), rtol=1e-13, atol=1e-13)
    # the density module's former one, on its pre-clipped input: bitwise
    q = np.clip(p, 1e-300, 1 - 1e-16)
    assert np.array_equal(logit(q, eps=None), np.log(q) - np.log1p(-q))
    y = np.concatenate([np.geomspace(1e-320, 1e3, 2000), [0.0, 20.0, 30.0]])
    with np.errstate(over="ignore"):
        old_scene = np.where(y > 20, y, np.log(np.expm1(np.maximum(y, 1e-12))))
    ym = np.maximum(y, 1e-300)
    old_density = np.where(ym > 30.0, ym, np.log(np.expm1(np.minimum(ym, 30.0))))
    assert np.array_equal(inverse_softplus(y), old_scene)
    assert np.array_equal(inverse_softplus(y, floor=1e-300, linear_above=30.0), old_density)
    np.testing.assert_allclose(softplus(inverse_softplus(np.array([0.5, 3.0, 64.0]))), [0.5, 3.0, 64.0], rtol=1e-12)
