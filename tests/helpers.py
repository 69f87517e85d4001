"""Shared fixtures and float64 numpy references for the tests.

Nothing here imports the package's math: every reference is written from the paper's
equations (or from geometry, for the frustums) so that it cannot share a bug with the code.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mixnerf_eqx.nn import RayBundle


@pytest.fixture(name="key")
def key_fixture():
    """A fixed PRNG key; import `key_fixture` into a test module to use it as `key`."""
    return jax.random.key(0)


def as_f32(*arrays):
    """The arrays as float32 numpy arrays (what the package sees)."""
    converted = tuple(np.asarray(a, np.float32) for a in arrays)
    return converted[0] if len(converted) == 1 else converted


def as_f64(*arrays):
    """The arrays as float64 numpy arrays (what the references compute in)."""
    converted = tuple(np.asarray(a, np.float64) for a in arrays)
    return converted[0] if len(converted) == 1 else converted


def make_ray(origin=(0.1, -0.3, 2.0), direction=(0.3, -0.2, -1.0), *, near=2.0, far=6.0, radius=0.002):
    """One float32 ray (empty batch shape)."""
    direction = as_f32(direction)
    return RayBundle(
        origins=jnp.asarray(as_f32(origin)),
        directions=jnp.asarray(direction),
        viewdirs=jnp.asarray(direction / np.linalg.norm(direction)),
        radii=jnp.full((1,), radius, jnp.float32),
        near=jnp.full((1,), near, jnp.float32),
        far=jnp.full((1,), far, jnp.float32),
    )


def random_ray(rng, num_samples, *, near=2.0, far=6.0, max_density=3.0):
    """Sorted edges, densities and colours of one random ray, as float32-representable float64."""
    interior = np.sort(rng.uniform(near, far, num_samples - 1))
    t_edges = np.concatenate([[near], interior, [far]])
    density = rng.uniform(0.0, max_density, num_samples)
    rgb = rng.uniform(0.0, 1.0, (num_samples, 3))
    # Round through float32 so that the package and the reference see the same numbers.
    return as_f64(as_f32(t_edges), as_f32(density), as_f32(rgb))


# --- Volume rendering (paper eq. 2 and eq. 8) -------------------------------------------


def ref_blend_weights(density, t_edges, step_scale):
    """`w_i = T_i alpha_i` with `T_i` the product of `(1 - alpha_j)` over the samples before i.

    `step_scale` is `||d||` (a scalar) or the per-sample ray depth of eq. 8.
    """
    density, t_edges = as_f64(density, t_edges)
    deltas = np.diff(t_edges) * np.asarray(step_scale, np.float64)
    alpha = 1.0 - np.exp(-density * deltas)
    transmittance = np.ones_like(alpha)
    for i in range(1, alpha.shape[0]):
        transmittance[i] = transmittance[i - 1] * (1.0 - alpha[i - 1])
    return transmittance * alpha


def ref_composite_rgb(weights, rgb, background=None):
    weights, rgb = as_f64(weights, rgb)
    colour = (weights[:, None] * rgb).sum(axis=0)
    if background is not None:
        colour = colour + (1.0 - weights.sum()) * as_f64(background)
    return colour


def ref_accumulation(weights):
    return as_f64(weights).sum()


def ref_expected_depth(weights, t_edges):
    """Weighted mean of interval midpoints, clipped to the ray; the far bound when empty."""
    weights, t_edges = as_f64(weights, t_edges)
    total = weights.sum()
    if total <= 0:
        return t_edges[-1]
    mids = 0.5 * (t_edges[:-1] + t_edges[1:])
    return float(np.clip((weights * mids).sum() / total, t_edges[0], t_edges[-1]))


# --- Laplace mixture NLLs (paper eqs. 4-7, 9) --------------------------------------------


def ref_laplace_pdf(x, location, scale):
    return np.exp(-np.abs(x - location) / scale) / (2.0 * scale)


def ref_mixing(weights, weight_eps):
    """`pi_j = w_j / (sum_m w_m + eps)` (eq. 6, with the released code's epsilon slot)."""
    weights = as_f64(weights)
    return weights / (weights.sum() + weight_eps)


def ref_colour_nll(weights, rgb, beta, target, *, weight_eps=0.0, floor=None):
    """`-log(sum_j pi_j prod_c Laplace(c_c; rgb_jc, beta_jc) [+ floor])` in linear float64."""
    weights, rgb, beta, target = as_f64(weights, rgb, beta, target)
    components = np.prod(ref_laplace_pdf(target[None, :], rgb, beta), axis=-1)
    likelihood = (ref_mixing(weights, weight_eps) * components).sum()
    return -np.log(likelihood + (floor or 0.0))


def ref_depth_nll(weights, ray_depth, beta, target, *, scale="colour", weight_eps=0.0, floor=None):
    """Depth mixture NLL (eq. 7) in linear float64.

    `scale="colour"`: each component is the product of three Laplace densities of the same
    residual with the three colour scales (the released code's broadcasting);
    `scale="single"`: one Laplace density with the mean of the three scales.
    """
    weights, ray_depth, beta = as_f64(weights, ray_depth, beta)
    target = float(target)
    if scale == "colour":
        components = np.prod(ref_laplace_pdf(target, ray_depth[:, None], beta), axis=-1)
    else:
        components = ref_laplace_pdf(target, ray_depth, beta.mean(axis=-1))
    likelihood = (ref_mixing(weights, weight_eps) * components).sum()
    return -np.log(likelihood + (floor or 0.0))


def ref_colour_nll_logspace(weights, rgb, beta, target, *, weight_eps=0.0, floor=None):
    """The same NLL as `ref_colour_nll`, for likelihoods below float64's range.

    Uses `log sum_j exp(a_j) = m + log sum_j exp(a_j - m)` with `m = max_j a_j`.
    """
    weights, rgb, beta, target = as_f64(weights, rgb, beta, target)
    log_components = np.sum(-np.log(2.0 * beta) - np.abs(target[None, :] - rgb) / beta, axis=-1)
    with np.errstate(divide="ignore"):
        terms = np.log(ref_mixing(weights, weight_eps)) + log_components
    peak = terms.max()
    log_likelihood = peak + np.log(np.exp(terms - peak).sum())
    if floor is None:
        return -log_likelihood
    return -np.logaddexp(log_likelihood, np.log(floor))


def central_difference(fn, x, step=1e-6):
    """Float64 central finite differences of a scalar function of an array."""
    x = as_f64(x)
    grad = np.zeros_like(x)
    for index in np.ndindex(x.shape):
        plus, minus = x.copy(), x.copy()
        plus[index] += step
        minus[index] -= step
        grad[index] = (fn(plus) - fn(minus)) / (2 * step)
    return grad


# --- Encodings --------------------------------------------------------------------------


def encoding_phases(x, min_deg, max_deg):
    """`2^k x` for every frequency, in the package's layout: frequency-major, then coordinate."""
    x = as_f64(x)
    scales = 2.0 ** np.arange(min_deg, max_deg)
    return (scales[:, None] * x[..., None, :]).reshape(*x.shape[:-1], -1)


def ref_positional_encoding(x, min_deg, max_deg, append_identity=True):
    """`[x, sin(2^k x) for all k, cos(2^k x) for all k]`."""
    phases = encoding_phases(x, min_deg, max_deg)
    parts = [np.sin(phases), np.cos(phases)]
    if append_identity:
        parts.insert(0, as_f64(x))
    return np.concatenate(parts, axis=-1)


def monte_carlo_ipe(rng, mean, var, min_deg, max_deg, num_draws):
    """Monte-Carlo estimate of `E[PE(x)]` for `x ~ N(mean, diag(var))`, with its standard error."""
    mean, var = as_f64(mean, var)
    draws = mean + np.sqrt(var) * rng.standard_normal((num_draws, 3))
    features = ref_positional_encoding(draws, min_deg, max_deg, append_identity=False)
    return features.mean(axis=0), features.std(axis=0, ddof=1) / np.sqrt(num_draws)


# --- Frustum geometry -------------------------------------------------------------------


def quadrature_frustum_moments(t0, t1, radius, shape):
    """Moments of a frustum by Gauss-Legendre quadrature over `t` (exact for polynomials).

    A cone's cross-section at `t` is a disc of radius `radius * t`, so the density of `t`
    within its volume is proportional to `t^2`; a cylinder's is uniform. Each of the two
    axes across the ray of a uniform disc of radius `rho` has variance `rho^2 / 4`, hence
    `r_var = radius^2 E[t^2] / 4` for the cone, `radius^2 / 4` for the cylinder.
    """
    nodes, node_weights = np.polynomial.legendre.leggauss(16)
    t = 0.5 * (t1 - t0) * nodes + 0.5 * (t1 + t0)
    density = t**2 if shape == "cone" else np.ones_like(t)
    mass = node_weights * density
    mass = mass / mass.sum()
    t_mean = (mass * t).sum()
    t_var = (mass * (t - t_mean) ** 2).sum()
    if shape == "cone":
        r_var = radius**2 * (mass * t**2).sum() / 4
    else:
        r_var = radius**2 / 4
    return t_mean, t_var, r_var


def orthonormal_frame(direction):
    """A unit vector along `direction` and two unit vectors orthogonal to it and each other."""
    axis = as_f64(direction) / np.linalg.norm(direction)
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    first = np.cross(axis, helper)
    first /= np.linalg.norm(first)
    second = np.cross(axis, first)
    return axis, first, second


def monte_carlo_frustum_points(rng, origin, direction, t0, t1, radius, shape, num_points):
    """Points uniform in the volume of the frustum between `t0` and `t1`, by rejection.

    The solid is `{origin + t d + p : t0 <= t <= t1, p orthogonal to d, |p| <= R(t)}` with
    `R(t) = radius * t` (cone) or `radius` (cylinder): the cross-section is measured in
    world units, `t` along the unnormalised direction `d`. Candidates are uniform in a box
    in the ray's orthonormal frame (so uniform in world volume) and kept if inside.
    """
    origin, direction = as_f64(origin, direction)
    norm = np.linalg.norm(direction)
    axis, first, second = orthonormal_frame(direction)
    max_radius = radius * t1 if shape == "cone" else radius
    kept = []
    count = 0
    while count < num_points:
        along = rng.uniform(t0 * norm, t1 * norm, num_points)
        across = rng.uniform(-max_radius, max_radius, (num_points, 2))
        t = along / norm
        bound = radius * t if shape == "cone" else np.full_like(t, radius)
        inside = np.hypot(across[:, 0], across[:, 1]) <= bound
        points = (
            origin + along[inside, None] * axis + across[inside, :1] * first + across[inside, 1:] * second
        )
        kept.append(points)
        count += points.shape[0]
    return np.concatenate(kept)[:num_points]


# --- Resampling -------------------------------------------------------------------------


def ref_blur_weights(weights, padding):
    """mip-NeRF's blur: max over each pair of neighbours, then the mean of each pair, plus padding."""
    weights = as_f64(weights)
    n = weights.shape[0]
    blurred = np.empty(n)
    for i in range(n):
        left = max(weights[max(i - 1, 0)], weights[i])
        right = max(weights[i], weights[min(i + 1, n - 1)])
        blurred[i] = 0.5 * (left + right) + padding
    return blurred


def ref_cdf(bins, weights, t):
    """The CDF at `t` of the piecewise-constant pdf proportional to `weights` on `bins`."""
    bins, weights = as_f64(bins, weights)
    cdf = np.concatenate([[0.0], np.cumsum(weights) / weights.sum()])
    return np.interp(t, bins, cdf)


# A model and scene small enough that a training run takes seconds on two CPU cores (the
# `tiny_config` and `tiny_scene` fixtures of conftest.py use it).
TINY_OVERRIDES = [
    "data.resolution=32",
    "data.num_train_views=4",
    "data.num_test_views=3",
    "mlp.width=32",
    "mlp.depth=2",
    "mlp.skip_layer=1",
    "mlp.view_width=16",
    "mlp.max_deg=8",
    "model.num_coarse_samples=16",
    "model.num_fine_samples=16",
    "optim.lr_init=5e-3",
    "optim.lr_final=5e-4",
    "optim.warmup_steps=20",
    "loss.lambda_colour_steps=20",
    "train.batch_size=256",
    "train.anneal_steps=20",
    "train.max_steps=150",
    "train.checkpoint_every=0",
]
# The same for a run of the grid field: the MLP's own keys would not apply to it (an error).
TINY_SHARED_OVERRIDES = [o for o in TINY_OVERRIDES if not o.startswith("mlp.")]
