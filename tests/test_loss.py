"""The objective (paper eq. 11) against a float64 transcription of the released `train.py`.

The reference below follows the released arithmetic step by step in numpy: the colour MSE is
the squared error summed over rays and channels divided by the number of rays; the NLLs are
`-log(sum_j pi_j prod_c Laplace_jc + 1e-12)` with `pi = w / sum w`, averaged over rays and
applied to the coarse level; the regenerated weights composite the same densities with the
per-sample ray depth in place of `||d||`. It shares no code with the package.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import as_f32, as_f64

import mixnerf_eqx as mx
from mixnerf_eqx._config import LossConfig
from mixnerf_eqx._nn.compositing import distortion
from mixnerf_eqx._nn.field import FieldOutputs
from mixnerf_eqx._nn.model import RenderOutputs
from mixnerf_eqx._nn.renderer import LevelOutputs
from mixnerf_eqx._train.loss import LossWeights, loss_terms, opacity_entropy


def _ref_weights(density, t_edges, step_scale):
    """`w = alpha * T` over a batch of rays (`step_scale`: `||d||` per ray, or per sample)."""
    delta = np.diff(t_edges, axis=-1) * step_scale
    density_delta = density * delta
    alpha = 1.0 - np.exp(-density_delta)
    optical_depth = np.concatenate(
        [np.zeros_like(density_delta[:, :1]), np.cumsum(density_delta[:, :-1], axis=-1)], axis=-1
    )
    return alpha * np.exp(-optical_depth)


def _ref_nll(mu, pi, gamma, gt):
    """The released `compute_nll` with the Laplace density, in float64: one value per ray."""
    eps = 1e-12
    gamma = gamma + eps
    pdf = np.exp(-np.abs(gt - mu) / gamma) / (2 * gamma)
    likelihood = np.sum(pi * np.prod(pdf, axis=2), axis=1)
    return -np.log(likelihood + eps)


def _ref_level_nlls(level, target, dirs_norm):
    weights = level["weights"]
    pi = weights / np.sum(weights, axis=-1, keepdims=True)
    colour = _ref_nll(level["rgb_samples"], pi, level["beta"], target[:, None, :])
    depth = _ref_nll(level["ray_depth"][..., None], pi, level["beta"], dirs_norm[:, None, None])
    regen_weights = _ref_weights(level["density"], level["t_edges"], level["ray_depth"])
    pi_regen = regen_weights / np.sum(regen_weights, axis=-1, keepdims=True)
    regen = _ref_nll(level["rgb_samples"], pi_regen, level["beta"], target[:, None, :])
    return np.mean(colour), np.mean(depth), np.mean(regen)


def _ref_objective(levels, target, directions, lambdas, *, nll_levels="coarse", coarse_mult=0.1):
    """The released total loss (and its terms) for `levels = {"coarse": ..., "fine": ...}`."""
    num_rays = target.shape[0]
    sse = {name: np.sum((level["rgb"] - target) ** 2) / num_rays for name, level in levels.items()}
    dirs_norm = np.linalg.norm(directions, axis=-1)
    nll = np.zeros(3)
    for name in ["coarse"] if nll_levels == "coarse" else ["coarse", "fine"]:
        nll += np.asarray(_ref_level_nlls(levels[name], target, dirs_norm))
    lambda_colour, lambda_depth, lambda_regen = lambdas
    total = sse["fine"] + coarse_mult * sse["coarse"] + lambda_colour * nll[0]
    total += lambda_depth * nll[1] + lambda_regen * nll[2]
    return total, sse, nll


def _random_level(rng, num_rays, num_samples, dirs_norm, background):
    t_edges = np.sort(rng.uniform(2.0, 6.0, (num_rays, num_samples + 1)), axis=-1)
    density = rng.uniform(0.0, 2.0, (num_rays, num_samples))
    rgb_samples = rng.uniform(0.0, 1.0, (num_rays, num_samples, 3))
    beta = rng.uniform(0.05, 0.6, (num_rays, num_samples, 3))
    ray_depth = rng.uniform(0.5, 1.5, (num_rays, num_samples))
    t_edges, density, rgb_samples, beta, ray_depth = as_f64(
        *as_f32(t_edges, density, rgb_samples, beta, ray_depth)
    )
    return _level(t_edges, density, rgb_samples, beta, ray_depth, dirs_norm, background)


def _level(t_edges, density, rgb_samples, beta, ray_depth, dirs_norm, background):
    weights = as_f64(as_f32(_ref_weights(density, t_edges, dirs_norm[:, None])))
    rgb = np.sum(weights[..., None] * rgb_samples, axis=1) + (1 - weights.sum(-1))[:, None] * background
    return {
        "t_edges": t_edges,
        "density": density,
        "rgb_samples": rgb_samples,
        "beta": beta,
        "ray_depth": ray_depth,
        "weights": weights,
        "rgb": as_f64(as_f32(rgb)),
    }


def _as_outputs(levels):
    def level_outputs(level):
        f32 = {k: jnp.asarray(as_f32(v)) for k, v in level.items()}
        return LevelOutputs(
            weights=f32["weights"],
            t_edges=f32["t_edges"],
            field=FieldOutputs(
                density=f32["density"], rgb=f32["rgb_samples"], beta=f32["beta"], ray_depth=f32["ray_depth"]
            ),
            rgb=f32["rgb"],
            depth=jnp.zeros(level["rgb"].shape[0]),
            acc=jnp.sum(f32["weights"], axis=-1),
        )

    return RenderOutputs(coarse=level_outputs(levels["coarse"]), fine=level_outputs(levels["fine"]))


def _rays(directions):
    count = directions.shape[0]
    directions = jnp.asarray(as_f32(directions))
    return mx.nn.RayBundle(
        origins=jnp.zeros((count, 3)),
        directions=directions,
        viewdirs=directions / jnp.linalg.norm(directions, axis=-1, keepdims=True),
        radii=jnp.full((count, 1), 1e-3),
        near=jnp.full((count, 1), 2.0),
        far=jnp.full((count, 1), 6.0),
    )


@pytest.fixture(scope="module")
def mixnerf_model():
    config = mx.load_config("builtin", ["mlp.width=16", "mlp.depth=2", "mlp.skip_layer=1"])
    return mx.build_model(config, key=jax.random.key(0))


def _package_terms(model, levels, target, directions, lambdas, nll_levels="coarse"):
    loss = LossConfig(lambda_depth=lambdas[1], lambda_regen=lambdas[2], nll_levels=nll_levels)
    weights = LossWeights.from_config(loss, "mixnerf")
    return loss_terms(
        _as_outputs(levels),
        model,
        _rays(directions),
        jnp.asarray(as_f32(target)),
        jnp.asarray(lambdas[0], jnp.float32),
        weights,
    )


def test_a_known_input_gives_the_written_out_loss(mixnerf_model):
    """Two rays, two samples each, white background: every number chosen by hand.

    The total below was computed once with the float64 transcription and is written out, so
    that both the package and the transcription are held to it.
    """
    background = np.ones(3)
    directions = np.array([[0.0, 0.0, -1.0], [0.6, 0.0, -0.8]]) * np.array([[1.0], [1.25]])
    dirs_norm = np.linalg.norm(directions, axis=-1)
    target = np.array([[0.25, 0.5, 0.75], [1.0, 0.5, 0.0]])
    t_edges = np.array([[2.0, 3.0, 5.0], [2.0, 2.5, 6.0]])
    density = np.array([[0.5, 2.0], [1.0, 0.25]])
    rgb_samples = np.array([[[0.2, 0.4, 0.8], [0.5, 0.5, 0.5]], [[0.9, 0.6, 0.1], [0.0, 1.0, 0.0]]])
    beta = np.array([[[0.1, 0.2, 0.3], [0.25, 0.25, 0.25]], [[0.5, 0.125, 0.1], [0.2, 0.4, 0.2]]])
    ray_depth = np.array([[1.0, 0.75], [1.5, 1.25]])
    level = _level(t_edges, density, rgb_samples, beta, ray_depth, dirs_norm, background)
    # The fine level of this example is the coarse level with other sample colours.
    fine = _level(t_edges, density, rgb_samples[:, ::-1], beta, ray_depth, dirs_norm, background)
    levels = {"coarse": level, "fine": fine}
    lambdas = (4.0, 1e-3, 1e-4)
    total, sse, nll = _ref_objective(levels, target, directions, lambdas)
    written_out = -2.975172005
    assert total == pytest.approx(written_out, abs=5e-6)
    terms = _package_terms(mixnerf_model, levels, target, directions, lambdas)
    assert float(terms.total) == pytest.approx(written_out, rel=2e-6)
    # The MSE terms the package logs are per-element means: a third of the summed error.
    assert float(terms["mse_fine"]) == pytest.approx(sse["fine"] / 3, rel=1e-6)
    assert float(terms["mse_coarse"]) == pytest.approx(sse["coarse"] / 3, rel=1e-6)
    np.testing.assert_allclose([terms["nll_colour"], terms["nll_depth"], terms["nll_regen"]], nll, rtol=2e-6)


@pytest.mark.parametrize("nll_levels", ["coarse", "both"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_objective_matches_the_released_arithmetic(mixnerf_model, seed, nll_levels):
    rng = np.random.default_rng(seed)
    num_rays, num_samples = 16, 12
    directions = as_f64(as_f32(rng.normal(size=(num_rays, 3)) * np.array([0.3, 0.3, 1.0]) - [0, 0, 1]))
    dirs_norm = np.linalg.norm(directions, axis=-1)
    background = np.ones(3) if seed % 2 else np.zeros(3)
    levels = {
        name: _random_level(rng, num_rays, num_samples, dirs_norm, background) for name in ("coarse", "fine")
    }
    target = as_f64(as_f32(rng.uniform(0, 1, (num_rays, 3))))
    lambdas = (float(rng.uniform(0.001, 4.0)), 1e-3, 1e-4)
    total, sse, nll = _ref_objective(levels, target, directions, lambdas, nll_levels=nll_levels)
    terms = _package_terms(mixnerf_model, levels, target, directions, lambdas, nll_levels)
    assert float(terms.total) == pytest.approx(total, rel=1e-5)
    assert 3 * float(terms["mse_fine"]) == pytest.approx(sse["fine"], rel=1e-5)
    np.testing.assert_allclose(
        [terms["nll_colour"], terms["nll_depth"], terms["nll_regen"]], nll, rtol=1e-5, atol=1e-5
    )


def test_the_baseline_objective_is_the_summed_squared_error(mixnerf_model):
    """With no mixture term the loss is `sum_c` squared error of the fine level plus 0.1 times
    the coarse level's, averaged over rays: three per-element MSEs, not one."""
    rng = np.random.default_rng(3)
    directions = np.tile([[0.0, 0.0, -1.0]], (8, 1))
    levels = {name: _random_level(rng, 8, 6, np.ones(8), np.ones(3)) for name in ("coarse", "fine")}
    target = as_f64(as_f32(rng.uniform(0, 1, (8, 3))))
    terms = loss_terms(
        _as_outputs(levels),
        mixnerf_model,
        _rays(directions),
        jnp.asarray(as_f32(target)),
        jnp.asarray(0.0),
        LossWeights.from_config(LossConfig(), "mipnerf"),
    )
    expected = sum(
        mult * np.sum((levels[name]["rgb"] - target) ** 2) / 8
        for name, mult in (("fine", 1.0), ("coarse", 0.1))
    )
    assert float(terms.total) == pytest.approx(expected, rel=1e-6)
    assert float(terms["nll_colour"]) == float(terms["nll_depth"]) == float(terms["nll_regen"]) == 0.0


def _ref_distortion_double_integral(weights, t_edges, near, far, points_per_interval=400):
    """mip-NeRF 360's distortion as its defining double integral `int int w(s) w(s') |s - s'|`.

    The weights become a step function in `s = (t - near) / (far - near)` (density
    `w_i / width_i` on interval i); the integral is a midpoint-rule sum on a fine grid, in
    float64. It shares nothing with the closed form the package uses.
    """
    s_edges = (t_edges - near) / (far - near)
    points, masses = [], []
    for i, w in enumerate(weights):
        cell = np.linspace(s_edges[i], s_edges[i + 1], points_per_interval + 1)
        points.append(0.5 * (cell[1:] + cell[:-1]))
        masses.append(np.full(points_per_interval, w / points_per_interval))
    points, masses = np.concatenate(points), np.concatenate(masses)
    return float(np.sum(masses[:, None] * masses[None, :] * np.abs(points[:, None] - points[None, :])))


NEAR_FAR = (jnp.float32(2.0), jnp.float32(6.0))


@pytest.mark.parametrize("seed", range(3))
def test_the_distortion_loss_is_its_double_integral(seed):
    rng = np.random.default_rng(40 + seed)
    t_edges = as_f64(as_f32(np.sort(rng.uniform(2.0, 6.0, 9))))
    weights = as_f64(as_f32(rng.dirichlet(np.ones(8)) * rng.uniform(0.3, 1.0)))
    got = float(distortion(jnp.asarray(as_f32(weights)), jnp.asarray(as_f32(t_edges)), *NEAR_FAR))
    # The midpoint rule's error inside an interval is O(1/points^2) of its self term.
    assert got == pytest.approx(_ref_distortion_double_integral(weights, t_edges, 2.0, 6.0), rel=1e-4)


def test_the_distortion_loss_of_one_interval_is_its_closed_form():
    # All the weight w in one interval of normalised width d: w^2 d / 3, however far away.
    t_edges = jnp.asarray([2.0, 3.0, 3.5, 6.0])
    got = distortion(jnp.asarray([0.0, 0.8, 0.0]), t_edges, *NEAR_FAR)
    assert float(got) == pytest.approx(0.8**2 * (0.5 / 4.0) / 3, rel=1e-6)
    # Two point-like masses a and b at distance D: 2abD, plus their self terms.
    t_edges = jnp.asarray([2.0, 2.01, 5.99, 6.0])
    got = distortion(jnp.asarray([0.5, 0.0, 0.5]), t_edges, *NEAR_FAR)
    gap = (5.995 - 2.005) / 4.0
    assert float(got) == pytest.approx(2 * 0.25 * gap + 2 * 0.25 * (0.01 / 4.0) / 3, rel=1e-5)


@pytest.mark.parametrize("method", ["mixnerf", "mipnerf"])
def test_the_priors_on_the_weights_add_their_weighted_terms(mixnerf_model, method):
    """Both methods get the distortion and opacity priors, as written out from the levels."""
    rng = np.random.default_rng(5)
    directions = np.tile([[0.0, 0.0, -1.0]], (8, 1))
    levels = {name: _random_level(rng, 8, 6, np.ones(8), np.ones(3)) for name in ("coarse", "fine")}
    target = jnp.asarray(as_f32(rng.uniform(0, 1, (8, 3))))
    base = mx.load_config("builtin").loss

    def terms_with(**priors):
        weights = LossWeights.from_config(dataclasses.replace(base, **priors), method)
        return loss_terms(
            _as_outputs(levels), mixnerf_model, _rays(directions), target, jnp.asarray(1.0), weights
        )

    plain = terms_with()
    priors = terms_with(distortion_weight=0.3, opacity_weight=0.02, opacity_entropy_weight=0.05)
    expected_distortion = (
        sum(
            _ref_distortion_double_integral(
                levels[name]["weights"][ray], levels[name]["t_edges"][ray], 2.0, 6.0
            )
            for name in ("coarse", "fine")
            for ray in range(8)
        )
        / 8
    )
    expected_opacity = sum(levels[name]["weights"].sum() for name in ("coarse", "fine")) / 8
    opacities = [np.clip(levels[name]["weights"].sum(-1), 1e-4, 1 - 1e-4) for name in ("coarse", "fine")]
    expected_entropy = sum(np.mean(-(a * np.log(a) + (1 - a) * np.log(1 - a))) for a in opacities)
    assert float(priors["distortion"]) == pytest.approx(expected_distortion, rel=1e-4)
    assert float(priors["opacity"]) == pytest.approx(expected_opacity, rel=1e-5)
    assert float(priors["opacity_entropy"]) == pytest.approx(expected_entropy, rel=1e-5)
    assert float(priors.total - plain.total) == pytest.approx(
        0.3 * expected_distortion + 0.02 * expected_opacity + 0.05 * expected_entropy, rel=1e-4
    )
    assert float(plain["distortion"]) == float(plain["opacity"]) == float(plain["opacity_entropy"]) == 0.0


def test_opacity_entropy_is_zero_at_empty_and_opaque_and_log2_at_half():
    """The binary entropy against its closed form, and its gradient bounded by the clipping."""
    acc = jnp.asarray([0.0, 1.0, 0.5, 0.25])
    each = [float(opacity_entropy(acc[i : i + 1])) for i in range(4)]
    assert each[0] == pytest.approx(0.0, abs=2e-3) and each[1] == pytest.approx(0.0, abs=2e-3)
    assert each[2] == pytest.approx(np.log(2.0), rel=1e-6)
    assert each[3] == pytest.approx(-(0.25 * np.log(0.25) + 0.75 * np.log(0.75)), rel=1e-6)
    # d/da of the entropy is log((1 - a) / a): towards 0 below half, towards 1 above it.
    grad = np.asarray(jax.grad(lambda a: opacity_entropy(a) * a.size)(jnp.asarray([0.1, 0.9, 1.0])))
    np.testing.assert_allclose(grad[:2], [np.log(9.0), -np.log(9.0)], rtol=1e-5)
    assert grad[2] == 0.0  # clipped: an opaque ray is left alone


@dataclasses.dataclass(frozen=True)
class _LossWithDummy(LossConfig):
    """`[loss]` with the one line a new term adds: its weight."""

    dummy_weight: float = mx.config.loss_weight(0.0)


@pytest.fixture
def dummy_term():
    """A term registered for one test: the mean squared opacity of the fine level."""
    term = mx.training.LossTerm("dummy", lambda inputs: jnp.mean(inputs.outputs.fine.acc**2), weight="dummy_weight")
    mx.training.register_loss_term(term)
    yield term
    mx.training.unregister_loss_term("dummy")
    assert "dummy" not in mx.training.loss_term_names()


def test_a_registered_term_is_weighted_logged_and_range_checked(mixnerf_model, tiny_config, dummy_term):
    assert mx.training.loss_term_names()[-1] == "dummy"
    loss = _LossWithDummy(**dataclasses.asdict(tiny_config.loss))
    # Range-checked: its weight is one of the `[loss]` weights, each at least 0.
    with pytest.raises(mx.ConfigError, match=r"loss\.dummy_weight must be >= 0, got -0\.5"):
        dataclasses.replace(tiny_config, loss=dataclasses.replace(loss, dummy_weight=-0.5))
    with pytest.raises(ValueError, match="already registered"):
        mx.training.register_loss_term(dummy_term)
    # A term whose weight its [loss] section does not declare is refused when weighed.
    with pytest.raises(ValueError, match=r"weighted by loss.dummy_weight, which the \[loss\] section does not"):
        LossWeights.from_config(tiny_config.loss, "mixnerf")
    # Weighted: it enters the total with its weight, and a zero weight computes nothing.
    rng = np.random.default_rng(7)
    directions = np.tile([[0.0, 0.0, -1.0]], (8, 1))
    levels = {name: _random_level(rng, 8, 6, np.ones(8), np.ones(3)) for name in ("coarse", "fine")}
    target = jnp.asarray(as_f32(rng.uniform(0, 1, (8, 3))))

    def terms_with(weight):
        weights = LossWeights.from_config(dataclasses.replace(loss, dummy_weight=weight), "mixnerf")
        return loss_terms(
            _as_outputs(levels), mixnerf_model, _rays(directions), target, jnp.asarray(1.0), weights
        )

    expected = np.mean(np.sum(levels["fine"]["weights"], axis=-1) ** 2)
    off, on = terms_with(0.0), terms_with(0.25)
    assert float(off["dummy"]) == 0.0
    assert float(on["dummy"]) == pytest.approx(expected, rel=1e-6)
    assert float(on.total - off.total) == pytest.approx(0.25 * expected, rel=1e-4)
    # Logged: the training log's entries carry it.
    config = dataclasses.replace(
        tiny_config,
        loss=dataclasses.replace(loss, dummy_weight=0.25),
        train=dataclasses.replace(tiny_config.train, max_steps=3, checkpoint_every=0),
    )
    result = mx.fit(config, progress=False)
    entries = [json.loads(line) for line in (result.run_dir / "train_log.jsonl").read_text().splitlines()]
    steps = [entry for entry in entries if "loss" in entry]
    assert steps and all(0 < entry["dummy"] <= 1 for entry in steps)


def test_the_colour_nlls_can_leave_the_sample_colours_untrained(mixnerf_model):
    """`loss.nll_trains_colour = false` stops the colour NLLs' gradient at the components'
    locations (the samples' colours): the same loss, no gradient into those colours, the same
    gradient into the scales."""
    rng = np.random.default_rng(3)
    directions = as_f64(as_f32(rng.normal(size=(8, 3)) * np.array([0.3, 0.3, 1.0]) - [0, 0, 1]))
    dirs_norm = np.linalg.norm(directions, axis=-1)
    levels = {n: _random_level(rng, 8, 6, dirs_norm, np.ones(3)) for n in ("coarse", "fine")}
    target = jnp.asarray(as_f32(rng.uniform(0, 1, (8, 3))))
    outputs = _as_outputs(levels)

    def total(field_rgb, beta, trains):
        loss = LossConfig(nll_trains_colour=trains)
        weights = LossWeights.from_config(loss, "mixnerf")
        coarse = outputs.coarse
        field = dataclasses.replace(coarse.field, rgb=field_rgb, beta=beta)
        changed = dataclasses.replace(outputs, coarse=dataclasses.replace(coarse, field=field))
        lam = jnp.asarray(2.0, jnp.float32)
        return loss_terms(changed, mixnerf_model, _rays(directions), target, lam, weights).total

    rgb, beta = outputs.coarse.field.rgb, outputs.coarse.field.beta
    assert float(total(rgb, beta, False)) == float(total(rgb, beta, True))
    grad = jax.grad(total, argnums=(0, 1))
    rgb_trained, beta_trained = grad(rgb, beta, True)
    rgb_fixed, beta_fixed = grad(rgb, beta, False)
    assert float(jnp.abs(rgb_trained).max()) > 1e-3  # the paper's NLLs pull the sample colours
    assert float(jnp.abs(rgb_fixed).max()) == 0.0
    np.testing.assert_array_equal(np.asarray(beta_fixed), np.asarray(beta_trained))
