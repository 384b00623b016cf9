"""Material and light priors (triplet_cl/priors.py): forward against loop references, random-cotangent
VJPs and float64 central differences, the training hook (gradients added, kNN graph rebuilt), config."""

from __future__ import annotations

import numpy as np
import pytest

from tests.gradients import fd_grad
from tests.reference import priors as ref
from triplet_cl import priors as P
from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight, pack_lights
from triplet_cl.scene import Scene
from triplet_cl.train import TrainConfig

COLS = [0, 1, 2, 3, 4]  # cook-torrance: albedo rgb, roughness, metallic


def _soup(rng, m=12):
    V = rng.normal(size=(3 * m, 3))
    F = np.arange(3 * m).reshape(m, 3)
    raw = rng.normal(size=(3 * m, 6))
    return V, F, raw


def _lights():
    return [AmbientLight(np.array([0.2, 0.3, 0.25])), PointLight(np.array([1.0, 2.0, 1.5]), np.array([5.0, 6.0, 4.0])),
            DirectionalLight(np.array([0.0, 1.0, 0.0]), np.array([1.0, 1.2, 0.8])),
            SHEnvironmentLight.constant(np.array([0.1, 0.2, 0.3]))]


def _check_grad(f, g, x, rng, rtol=1e-6, atol=1e-9):
    """float64 central differences of the whole gradient, and a random-cotangent VJP (v · dE/dx)."""
    num = fd_grad(f, x)
    np.testing.assert_allclose(g, num, rtol=rtol, atol=atol)
    v = rng.normal(size=x.shape)
    h = 1e-6
    dir_num = (f(x + h * v) - f(x - h * v)) / (2 * h)
    assert float(np.sum(g * v)) == pytest.approx(dir_num, rel=1e-6, abs=1e-10)


def test_knn_pairs_match_brute_force(rng):
    pts = rng.normal(size=(25, 3))
    got = [tuple(p) for p in P.knn_pairs(pts, 4)]
    assert got == ref.knn_pairs(pts, 4)
    assert P.knn_pairs(pts[:1], 4).shape == (0, 2)


def test_knn_smoothness_forward_and_gradients(rng):
    V, F, raw = _soup(rng)
    pairs = P.knn_pairs(V[F].mean(axis=1), 3)
    e, g = P.knn_smoothness(raw, F, pairs, COLS, 0.01)
    assert e == pytest.approx(ref.knn_smoothness(raw, F, [tuple(p) for p in pairs], COLS, 0.01), rel=1e-12)
    assert (g[:, 5] == 0).all()  # ao is not smoothed
    _check_grad(lambda x: P.knn_smoothness(x, F, pairs, COLS, 0.01)[0], g, raw, rng)


def test_knn_smoothness_is_zero_for_constant_materials():
    raw = np.tile(np.array([0.3, -0.2, 0.1, 1.0, -2.0, 3.0]), (9, 1))
    F = np.arange(9).reshape(3, 3)
    e, g = P.knn_smoothness(raw, F, np.array([[0, 1], [1, 2]]), COLS)
    assert e == 0.0 and np.abs(g).max() == 0.0


def test_metallic_and_roughness_forward_and_gradients(rng):
    _, _, raw = _soup(rng)
    e, g = P.metallic_l1(raw, 4)
    assert e == pytest.approx(ref.metallic_l1(raw, 4), rel=1e-12)
    _check_grad(lambda x: P.metallic_l1(x, 4)[0], g, raw, rng)
    e, g = P.roughness_target(raw, 3, 0.5)
    assert e == pytest.approx(ref.roughness_target(raw, 3, 0.5), rel=1e-12)
    _check_grad(lambda x: P.roughness_target(x, 3, 0.5)[0], g, raw, rng)
    # the roughness prior pulls towards its target from both sides
    lo, hi = np.full((1, 6), -3.0), np.full((1, 6), 3.0)
    assert P.roughness_target(lo, 3, 0.5)[1][0, 3] < 0 < P.roughness_target(hi, 3, 0.5)[1][0, 3]


def test_ambient_fraction_forward_and_gradients(rng):
    L = _lights()
    lp = pack_lights(L).params.astype(np.float64)
    c = np.array([0.1, 0.0, 0.2])
    e, g = P.ambient_fraction(L, lp, c)
    want = ref.ambient_fraction([L[0].color], [(L[1].position, L[1].intensity)], [L[2].intensity], c)
    assert e == pytest.approx(want, rel=1e-12) and 0 < e < 1
    _check_grad(lambda x: P.ambient_fraction(L, x, c)[0], g, lp, rng)
    # it lowers the ambient light and raises the others
    assert g[0:3].min() > 0 and g[6:9].max() < 0
    # no ambient light: no term; a negative ambient light is penalised like a positive one (pushed up to 0)
    assert P.ambient_fraction(L[1:], pack_lights(L[1:]).params, c)[0] == 0.0
    neg = [AmbientLight(-L[0].color), L[1], L[2]]
    en, gn = P.ambient_fraction(neg, pack_lights(neg).params, c)
    assert en == pytest.approx(e, rel=1e-12) and gn[0:3].max() < 0
    _check_grad(lambda x: P.ambient_fraction(neg, x, c)[0], gn, pack_lights(neg).params.astype(np.float64), rng)


def test_chroma_forward_and_gradients(rng):
    L = _lights()
    lp = pack_lights(L).params.astype(np.float64)
    e, g = P.chroma(L, lp, 1e-6)
    want = ref.chroma([L[0].color, L[1].intensity, L[2].intensity], 1e-6)
    assert e == pytest.approx(want, rel=1e-12)
    _check_grad(lambda x: P.chroma(L, x, 1e-6)[0], g, lp, rng)
    # scale-free; zero for white lights
    assert P.chroma(L, 7.0 * lp, 0.0)[0] == pytest.approx(P.chroma(L, lp, 0.0)[0], rel=1e-9)
    white = [AmbientLight(np.full(3, 0.2)), PointLight(np.zeros(3), np.full(3, 9.0))]
    e, g = P.chroma(white, pack_lights(white).params)
    assert e == pytest.approx(0.0, abs=1e-20) and np.abs(g).max() < 1e-9


def test_hook_adds_weighted_gradients_and_rebuilds_graph(rng):
    V, F, raw = _soup(rng)
    L = _lights()[:2]
    s = Scene.from_arrays(V, F, material=raw, lights=L, dtype=np.float64)
    cfg = TrainConfig(prior_smooth=0.3, prior_k=3, prior_metallic=0.2, prior_roughness=0.1, prior_ambient=0.5,
                      prior_chroma=0.05)
    assert P.Priors(cfg, np.zeros(3)).apply(s, cfg.prior_from - 1) == {}  # not before prior_from
    cfg.prior_from = 0
    pr = P.Priors(cfg, np.zeros(3))
    s.material.grad = np.ones_like(raw)
    terms = pr.apply(s, 0)
    assert set(terms) == {"smooth", "metallic", "roughness", "ambient", "chroma"}
    pairs = P.knn_pairs(V[F].mean(axis=1), 3)
    want = (1.0 + 0.3 * P.knn_smoothness(raw, F, pairs, COLS)[1] + 0.2 * P.metallic_l1(raw, 4)[1]
            + 0.1 * P.roughness_target(raw, 3, 0.5)[1])
    np.testing.assert_allclose(s.material.grad, want, rtol=1e-12)
    lp = s.light_params.data
    np.testing.assert_allclose(s.light_params.grad, 0.5 * P.ambient_fraction(L, lp, np.zeros(3))[1]
                               + 0.05 * P.chroma(L, lp)[1], rtol=1e-12)
    # the graph follows the soup: kept within rebuild_every, rebuilt after invalidate()
    old = pr.pairs
    s.V.data = s.V.data[::-1].copy()
    pr.apply(s, 1)
    assert pr.pairs is old
    pr.invalidate()
    pr.apply(s, 2)
    np.testing.assert_array_equal(pr.pairs, P.knn_pairs(s.V.data[F].mean(axis=1), 3))


def test_priors_off_by_absent_config_and_validated():
    assert not P.Priors(TrainConfig.from_dict({}), np.zeros(3)).active
    with pytest.raises(ValueError, match="prior weights"):
        TrainConfig(prior_metallic=-1.0).validate()
    with pytest.raises(ValueError, match="prior_k"):
        TrainConfig(prior_k=0).validate()


def test_priors_act_in_training_and_cli_switch(tmp_path, capsys):
    """A training step records the priors' energies from prior_from on; `--priors off` zeroes every weight in
    config.json and cannot change on --resume; the default has none, `--priors lights` the light terms only."""
    d = TrainConfig()
    assert all(getattr(d, k) == 0 for k in P.WEIGHT_FIELDS) and not P.Priors(d, np.zeros(3)).active
    import json

    from cli.main import demo_data_path
    from cli.main import main as cli_main
    from triplet_cl.train import Trainer

    tr = Trainer(demo_data_path(), tmp_path / "p", TrainConfig(iterations=2, init_points=300, prior_from=1,
                                                               **P.MATERIAL_WEIGHTS, **P.LIGHT_WEIGHTS),
                 quiet=True)
    first, second = tr.step(), tr.step()
    assert "priors" not in first and set(second["priors"]) == {"smooth", "metallic", "roughness", "ambient", "chroma"}
    assert all(np.isfinite(v) for v in second["priors"].values())
    out = tmp_path / "off"
    assert cli_main(["train", "--demo", "--iterations", "2", "--init-points", "300", "--out", str(out),
                     "--priors", "off"]) == 0
    saved = json.loads((out / "config.json").read_text())["train"]
    assert all(saved[k] == 0.0 for k in P.WEIGHT_FIELDS)
    lit = tmp_path / "lights"
    assert cli_main(["train", "--demo", "--iterations", "2", "--init-points", "300", "--out", str(lit),
                     "--priors", "lights"]) == 0
    saved = json.loads((lit / "config.json").read_text())["train"]
    assert all(saved[k] == v for k, v in P.LIGHT_WEIGHTS.items())
    assert all(saved[k] == 0.0 for k in P.MATERIAL_WEIGHTS)
    capsys.readouterr()
    assert cli_main(["train", "--resume", "--out", str(out), "--iterations", "3", "--priors", "all"]) == 2
    assert "--priors" in capsys.readouterr().err
