"""The mixture as a predictive distribution: what a trained MixNeRF believes about each pixel.

MixNeRF scores a ray's colour with a mixture of per-sample Laplace densities whose
coefficients are the normalised blending weights (paper eqs. 4-6; a model trained with a
background component adds it as one more component, weighted by the transmittance, and keeps
the weights unnormalised, as its NLL did). Here that mixture is the object: its mean,
per-channel quantiles and central intervals, standard deviation, the mode of its joint RGB
density, and the entropy of its coefficients; and beside it the distribution of
where the ray terminates (the normalised weights, uniform within each interval), with its
mean, quantiles, intervals and spread. `docs/predictive.md` says what each quantity means and
which level's heads it uses.

The per-ray math is pure functions of arrays; `ColourMixture` and `TerminationDistribution`
hold a batch of rays' parameters and lift those functions over it with `vmap`. Colour
quantiles are root finds (`optx.Bisection`, bracketed by the components' own quantiles); the
termination distance's are exact (its distribution function is piecewise linear); the mode
is a coordinate ascent over the components' locations,
channel by channel, to a fixed point (`optx.fixed_point`), started from the best component.
"""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .._custom_types import RGB, Edges, PerSample, PerSampleRGB, ScalarLike
from .._nn.compositing import expected_depth, log_transmittance, termination_cdf, termination_quantile
from .._nn.mixture import LaplaceMixture
from .._nn.mixture.laplace import laplace_log_density
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from .._nn.renderer import LevelOutputs

# A bisection halves its bracket each step: after 24 halvings the answer lies within 6e-8 of
# the bracket's width, float32's resolution for answers at least as large as the bracket
# (colours bracket themselves within about one unit). The tolerance on the residual is rarely
# met exactly in float32, so in practice the solves run to this count (in a batch they run
# until the slowest is done anyway). A safeguarded Newton iteration was tried instead: its
# mean was 4 steps, but under `vmap` every solve runs to the slowest (10 to 13 steps, each
# a value and a slope) and it was no faster.
_BISECTION_STEPS = 24
_TOLERANCE = 1e-7
# Each sweep of the mode search strictly raises the density or ends it; few are ever needed.
_MODE_SWEEPS = 16
# The relative gain in log density below which the mode search stops moving.
_MODE_GAIN = 1e-6

# Normalised weights with no epsilon: the predictive coefficients sum to one, and a ray whose
# weights all vanish gets uniform coefficients (see `LaplaceMixture.log_mixing_coefficients`).
_COEFFICIENTS = LaplaceMixture(weight_eps=0.0)


def mixing_coefficients(weights: PerSample) -> PerSample:
    """`pi_j = w_j / sum_m w_m` (eq. 6), summing to one; uniform for a ray without weight."""
    return jnp.exp(_COEFFICIENTS.log_mixing_coefficients(weights))


# Quantile levels: a sequence of numbers, or a 1-d array of them.
Levels = Sequence[ScalarLike] | Float[Array, " _"] | Float[np.ndarray, " _"]


def _inverse_scale(scale: Float[Array, "*#batch"]) -> Float[Array, "*#batch"]:
    # exp(-log b) rather than 1 / b, so that a scale that underflowed to 0 gives the largest
    # finite inverse instead of inf (and 0 * inf = NaN for a sample sitting on the location).
    return jnp.exp(-jnp.log(jnp.maximum(scale, jnp.finfo(scale.dtype).tiny)))


def laplace_cdf(
    x: Float[Array, "*#batch"], location: Float[Array, "*#batch"], scale: Float[Array, "*#batch"]
) -> Float[Array, "*#batch"]:
    """The Laplace distribution function, `1/2 exp(z)` below the location, `1 - 1/2 exp(-z)`
    above it, with `z = (x - location) / scale`; elementwise with broadcasting."""
    tail = 0.5 * jnp.exp(-jnp.abs(x - location) * _inverse_scale(scale))
    return jnp.where(x < location, tail, 1.0 - tail)


def laplace_quantile(
    level: ScalarLike, location: Float[Array, "*#batch"], scale: Float[Array, "*#batch"]
) -> Float[Array, "*#batch"]:
    """The inverse of `laplace_cdf` at `level` in (0, 1)."""
    offset = jnp.where(level < 0.5, jnp.log(2.0 * level), -jnp.log(2.0 - 2.0 * level))
    return location + scale * offset


def channel_cdf(
    x: Float[Array, ""], coefficients: PerSample, location: PerSample, scale: PerSample
) -> Float[Array, ""]:
    """One colour channel's mixture distribution function `sum_j pi_j F_j(x)`."""
    return _channel_cdf(x, coefficients, location, _inverse_scale(scale))


def _channel_cdf(
    x: Float[Array, ""], coefficients: PerSample, location: PerSample, inverse_scale: PerSample
) -> Float[Array, ""]:
    # With the inverse scales formed once, outside a solve's loop: one exponential per
    # component and step.
    tail = 0.5 * jnp.exp(-jnp.abs(x - location) * inverse_scale)
    return jnp.sum(coefficients * jnp.where(x < location, tail, 1.0 - tail))


def channel_quantile(
    level: ScalarLike, coefficients: PerSample, location: PerSample, scale: PerSample
) -> Float[Array, ""]:
    """One colour channel's mixture quantile at `level` in (0, 1), by bisection.

    The mixture's distribution function is a convex combination of its components', so its
    `level` quantile lies between the smallest and the largest of the components' `level`
    quantiles (components with `pi_j > 0` only): that is the bracket. The root is
    differentiated implicitly with respect to the mixture's parameters.
    """
    level = jnp.asarray(level, location.dtype)
    present = coefficients > 0
    component = jax.lax.stop_gradient(laplace_quantile(level, location, scale))
    lower = jnp.min(jnp.where(present, component, jnp.inf))
    upper = jnp.max(jnp.where(present, component, -jnp.inf))

    def residual(x, args):
        level, coefficients, location, inverse_scale = args
        return _channel_cdf(x, coefficients, location, inverse_scale) - level

    solution = optx.root_find(
        residual,
        optx.Bisection(rtol=_TOLERANCE, atol=_TOLERANCE, flip=False),
        lower + 0.5 * (upper - lower),
        args=(level, coefficients, location, _inverse_scale(scale)),
        options=dict(lower=lower, upper=upper),
        max_steps=_BISECTION_STEPS,
        throw=False,
    )
    return jnp.clip(solution.value, lower, upper)


def joint_log_density(
    rgb: RGB, coefficients: PerSample, location: PerSampleRGB, scale: PerSampleRGB
) -> Float[Array, ""]:
    """`log sum_j pi_j prod_c Laplace(rgb_c; mu_jc, beta_jc)`, the density the colour NLL
    scores (eqs. 4-6); `-inf` nowhere a component has mass and the scales are finite."""
    component = jnp.sum(laplace_log_density(rgb, location, scale), axis=-1)
    present = coefficients > 0
    terms = jnp.where(present, jnp.log(jnp.where(present, coefficients, 1.0)) + component, -jnp.inf)
    return jax.scipy.special.logsumexp(terms)


def channel_log_density(
    x: Float[Array, ""], coefficients: PerSample, location: PerSample, scale: PerSample
) -> Float[Array, ""]:
    """One colour channel's marginal log density `log sum_j pi_j Laplace(x; mu_j, beta_j)`."""
    present = coefficients > 0
    component = laplace_log_density(x, location, scale)
    terms = jnp.where(present, jnp.log(jnp.where(present, coefficients, 1.0)) + component, -jnp.inf)
    return jax.scipy.special.logsumexp(terms)


class _ModeSearch(eqx.Module):
    # What every step of one ray's mode search reuses: log(pi_j / (8 prod_c beta_jc)), the
    # inverse scales, and each channel's scaled distances between component locations.
    log_weight: PerSample
    location: PerSampleRGB
    inverse_scale: PerSampleRGB
    distances: Float[Array, "channels num_samples num_samples"]

    def sweep(self, rgb: RGB, args: None) -> RGB:
        """One sweep of exact coordinate ascent: each channel in turn moves to the component
        location, in that channel, where the density (the other channels held) is highest."""
        del args
        for channel in range(rgb.shape[0]):
            # -|x_c - mu_jc| / beta_jc per component and channel, the moving channel left out.
            exponent = jnp.maximum(-jnp.abs(rgb - self.location) * self.inverse_scale, -1e30)
            held = self.log_weight + jnp.sum(exponent, axis=-1) - exponent[:, channel]
            # Row k: the density with channel `channel` at component k's location.
            candidates = jax.scipy.special.logsumexp(held[None, :] - self.distances[channel], axis=-1)
            here = jax.scipy.special.logsumexp(held + exponent[:, channel])
            best = jnp.argmax(candidates)
            # Move only for a gain above float32's rounding of the log density, so that a
            # fixed point is reached rather than a cycle between two equally dense points.
            gain = candidates[best] - here > _MODE_GAIN * (1.0 + jnp.abs(here))
            rgb = jnp.where(gain, rgb.at[channel].set(self.location[best, channel]), rgb)
        return rgb


def joint_mode(coefficients: PerSample, location: PerSampleRGB, scale: PerSampleRGB) -> RGB:
    """The mode of the joint RGB density, by coordinate ascent from the best component.

    Within each cell of the grid that the components' locations draw in RGB space (the
    planes `x_c = mu_jc`), the density is a positive sum of exponentials of linear functions
    of `x`, hence convex: its maximum over the cell lies at a vertex, and along each channel
    the maximum of the density lies at some component's location in that channel. The search
    therefore starts at the component location where the density is highest and sweeps the
    channels, moving each to its best candidate, until a sweep changes nothing (a fixed
    point, found by `optx.fixed_point`): a maximum along every channel, at least as dense as
    every component location. Not differentiated: the mode sits on a kink.
    """
    coefficients, location, scale = jax.lax.stop_gradient((coefficients, location, scale))
    log_scale = jnp.log(jnp.maximum(scale, jnp.finfo(scale.dtype).tiny))
    present = coefficients > 0
    log_coefficients = jnp.where(present, jnp.log(jnp.where(present, coefficients, 1.0)), -jnp.inf)
    inverse_scale = jnp.exp(-log_scale)
    search = _ModeSearch(
        log_weight=log_coefficients - jnp.sum(log_scale + jnp.log(2.0), axis=-1),
        location=location,
        inverse_scale=inverse_scale,
        # distances[c, k, j] = |mu_kc - mu_jc| / beta_jc
        distances=jnp.minimum(
            jnp.abs(location.T[:, :, None] - location.T[:, None, :]) * inverse_scale.T[:, None, :], 1e30
        ),
    )
    at_components = jax.scipy.special.logsumexp(
        search.log_weight[None, :] - jnp.sum(search.distances, axis=0), axis=-1
    )
    start = location[jnp.argmax(at_components)]
    solution = optx.fixed_point(
        search.sweep,
        optx.FixedPointIteration(rtol=0.0, atol=1e-12),
        start,
        max_steps=_MODE_SWEEPS,
        throw=False,
    )
    return solution.value


def _per_ray(batch_shape: tuple[int, ...], fn, *arrays: Array):
    """`fn` of one ray, vmapped over the rays of `arrays` (each with `batch_shape` in front,
    flattened for the vmap), with `batch_shape` restored in front of every output."""
    count = math.prod(batch_shape)
    flat = [x.reshape(count, *x.shape[len(batch_shape) :]) for x in arrays]
    out = jax.vmap(fn)(*flat)
    return jax.tree_util.tree_map(lambda x: x.reshape(*batch_shape, *x.shape[1:]), out)


def _standard_deviation(masses: PerSample, centres: PerSample, component_std: PerSample) -> Float[Array, ""]:
    """`sqrt(sum_j m_j (s_j^2 + (c_j - mean)^2))`, the standard deviation of a mixture with
    masses `m_j`, component means `c_j` and component standard deviations `s_j`."""
    mean = jnp.sum(masses * centres)
    # Formed in units of the largest spread of a component with mass, so that scales near
    # float32's limit do not overflow when squared.
    present = masses > 0
    deviation = jnp.abs(centres - mean)
    unit = jnp.max(jnp.where(present, jnp.maximum(deviation, component_std), 0.0))
    unit = jax.lax.stop_gradient(jnp.where(unit > 0, unit, 1.0))
    spread = jnp.sum(
        jnp.where(present, masses * ((component_std / unit) ** 2 + (deviation / unit) ** 2), 0.0)
    )
    return unit * jnp.sqrt(spread)


class ColourMixture(eqx.Module):
    """The colour mixture of a batch of rays: component `j` of a ray has coefficient `pi_j`
    and, in each channel, a Laplace density with location `mu_jc` and scale `beta_jc`.

    Each method works ray by ray (and channel by channel where it says so) and returns the
    rays' batch shape in front.
    """

    coefficients: Float[Array, "*batch num_samples"]
    location: Float[Array, "*batch num_samples channels"]
    scale: Float[Array, "*batch num_samples channels"]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.coefficients.shape[:-1]

    def _per_ray(self, fn, *extra):
        return _per_ray(self.batch_shape, fn, self.coefficients, self.location, self.scale, *extra)

    def _colours(self, rgb, name: str) -> Array:
        """`rgb`, checked to hold one colour per ray of the mixture: `(*batch_shape, channels)`."""
        channels = self.location.shape[-1]
        wanted = (*self.batch_shape, channels)
        if tuple(jnp.shape(rgb)) != wanted:
            raise ValueError(
                f"{name} takes one colour per ray, shape {wanted} (the mixture's batch shape "
                f"{self.batch_shape} and {channels} channels); got shape {tuple(jnp.shape(rgb))}"
            )
        return rgb

    def mean(self) -> Float[Array, "*batch channels"]:
        """`sum_j pi_j mu_jc`."""
        return jnp.sum(self.coefficients[..., None] * self.location, axis=-2)

    def std(self) -> Float[Array, "*batch channels"]:
        """Per-channel standard deviation: `sqrt(sum_j pi_j (2 beta_jc^2 + (mu_jc - mean_c)^2))`."""

        def one_ray(coefficients, location, scale):
            return jax.vmap(_standard_deviation, in_axes=(None, 1, 1))(
                coefficients, location, jnp.sqrt(2.0) * scale
            )

        return self._per_ray(one_ray)

    def cdf(self, rgb: Float[Array, "*batch channels"]) -> Float[Array, "*batch channels"]:
        """Per-channel distribution function at `rgb`."""

        def one_ray(coefficients, location, scale, x):
            return jax.vmap(channel_cdf, in_axes=(0, None, 1, 1))(x, coefficients, location, scale)

        return self._per_ray(one_ray, self._colours(rgb, "cdf"))

    def quantiles(self, levels: Levels) -> Float[Array, "_ *batch channels"]:
        """Per-channel quantiles at each of `levels` in (0, 1), stacked in front: one batched
        bisection for every level, channel and ray."""
        levels_array = _check_levels(levels, self.location.dtype)

        def one_ray(coefficients, location, scale):
            per_channel = jax.vmap(channel_quantile, in_axes=(None, None, 1, 1))
            return jax.vmap(per_channel, in_axes=(0, None, None, None))(
                levels_array, coefficients, location, scale
            )

        return jnp.moveaxis(self._per_ray(one_ray), len(self.batch_shape), 0)

    def channel_quantiles(self, levels: Float[Array, "_ channels"]) -> Float[Array, "_ *batch channels"]:
        """Per-channel quantiles where each channel has levels of its own: row `i` of `levels`
        gives channel `c` the level `levels[i, c]` in (0, 1) (recalibrated intervals differ by
        channel, `Recalibration`); one batched bisection as in `quantiles`."""
        levels_array = _check_channel_levels(levels, self.location.shape[-1], self.location.dtype)

        def one_ray(coefficients, location, scale):
            per_channel = jax.vmap(channel_quantile, in_axes=(0, None, 1, 1))
            return jax.vmap(per_channel, in_axes=(0, None, None, None))(
                levels_array, coefficients, location, scale
            )

        return jnp.moveaxis(self._per_ray(one_ray), len(self.batch_shape), 0)

    def quantile(self, level: ScalarLike) -> Float[Array, "*batch channels"]:
        """Per-channel quantile at `level` in (0, 1) (`0.5`: the median)."""
        level = _check_level(level, dtype=self.location.dtype)

        def one_ray(coefficients, location, scale):
            return jax.vmap(channel_quantile, in_axes=(None, None, 1, 1))(
                level, coefficients, location, scale
            )

        return self._per_ray(one_ray)

    def median(self) -> Float[Array, "*batch channels"]:
        return self.quantile(0.5)

    def interval(
        self, mass: ScalarLike
    ) -> tuple[Float[Array, "*batch channels"], Float[Array, "*batch channels"]]:
        """The central interval of each channel that holds `mass` in (0, 1): from the
        `(1 - mass) / 2` quantile to the `(1 + mass) / 2` quantile."""
        mass = _check_level(mass, dtype=self.location.dtype)
        lower, upper = self.quantiles((0.5 * (1.0 - mass), 0.5 * (1.0 + mass)))
        return lower, upper

    def log_prob(self, rgb: Float[Array, "*batch channels"]) -> Float[Array, "*batch"]:
        """The joint log density at `rgb` (no floor: the exact `-NLL`)."""

        def one_ray(coefficients, location, scale, x):
            return joint_log_density(x, coefficients, location, scale)

        return self._per_ray(one_ray, self._colours(rgb, "log_prob"))

    def channel_log_prob(self, rgb: Float[Array, "*batch channels"]) -> Float[Array, "*batch channels"]:
        """Each channel's marginal log density at `rgb` (`channel_log_density`): the density
        that per-channel calibration measures score (FlipNeRF's NLL averages it)."""

        def one_ray(coefficients, location, scale, x):
            return jax.vmap(channel_log_density, in_axes=(0, None, 1, 1))(x, coefficients, location, scale)

        return self._per_ray(one_ray, self._colours(rgb, "channel_log_prob"))

    def mode(self) -> Float[Array, "*batch channels"]:
        """The mode of the joint RGB density (see `joint_mode`)."""
        return self._per_ray(joint_mode)

    def coefficient_entropy(self) -> Float[Array, "*batch"]:
        """`-sum_j pi_j log pi_j` in nats: 0 when one component holds the ray, `log N` when all
        `N` share it evenly."""
        present = self.coefficients > 0
        logs = jnp.log(jnp.where(present, self.coefficients, 1.0))
        return -jnp.sum(jnp.where(present, self.coefficients * logs, 0.0), axis=-1)

    def with_temperature(self, temperature: ScalarLike) -> "ColourMixture":
        """The same mixture with every scale multiplied by `temperature` (> 0)."""
        return ColourMixture(self.coefficients, self.location, _scaled(self.scale, temperature))


class TerminationDistribution(eqx.Module):
    """Where each ray of a batch terminates, given that it does so between its first and last
    edge: interval `i` holds mass `w_i / sum_m w_m`, spread uniformly over it.

    A ray whose weights all vanish (nothing in front of the far bound) puts all its mass at
    the far bound, as `expected_depth` and `depth_quantile` report it.
    """

    weights: Float[Array, "*batch num_samples"]
    t_edges: Float[Array, "*batch num_samples+1"]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.weights.shape[:-1]

    def _per_ray(self, fn):
        return _per_ray(self.batch_shape, fn, self.weights, self.t_edges)

    def mean(self) -> Float[Array, "*batch"]:
        """The expected termination distance (`expected_depth`, what the renderer reports)."""
        return self._per_ray(expected_depth)

    def std(self) -> Float[Array, "*batch"]:
        """The standard deviation of the termination distance (0 for an empty ray)."""

        def one_ray(weights: PerSample, t_edges: Edges) -> Float[Array, ""]:
            total = jnp.sum(weights)
            masses = jnp.where(total > 0, weights / jnp.where(total > 0, total, 1.0), 0.0)
            centres = 0.5 * (t_edges[1:] + t_edges[:-1])
            # A uniform density on an interval of width h has standard deviation h / sqrt(12).
            widths = (t_edges[1:] - t_edges[:-1]) / jnp.sqrt(12.0)
            return _standard_deviation(masses, centres, widths)

        return self._per_ray(one_ray)

    def cdf(self, t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
        """The probability that each ray terminates before `t` (`termination_cdf`); 1 for a
        `t` beyond the last edge, `inf` included. A ray without weight terminates at its far
        bound (as its quantiles say): 0 before it, 1 from it on."""
        if tuple(jnp.shape(t)) != self.batch_shape:
            raise ValueError(f"cdf takes one distance per ray, shape {self.batch_shape}; got shape {tuple(jnp.shape(t))}")

        def one_ray(t, weights, t_edges):
            at_far = (t >= t_edges[-1]).astype(t_edges.dtype)
            return jnp.where(jnp.sum(weights) > 0, termination_cdf(t, weights, t_edges), at_far)

        return _per_ray(self.batch_shape, one_ray, t, self.weights, self.t_edges)

    def quantiles(self, levels: Levels) -> Float[Array, "_ *batch"]:
        """The termination distance's quantiles at each of `levels` in (0, 1), stacked in
        front: exact, from one cumulative sum per ray (`termination_quantile`)."""
        levels_array = _check_levels(levels, self.weights.dtype)

        def one_ray(weights: PerSample, t_edges: Edges) -> Float[Array, " _"]:
            return jax.vmap(termination_quantile, in_axes=(0, None, None))(levels_array, weights, t_edges)

        return jnp.moveaxis(self._per_ray(one_ray), len(self.batch_shape), 0)

    def quantile(self, level: ScalarLike) -> Float[Array, "*batch"]:
        """The `level` quantile of the termination distance (`termination_quantile`: exact, its
        distribution function being piecewise linear)."""
        level = _check_level(level, dtype=self.weights.dtype)
        return self._per_ray(lambda weights, t_edges: termination_quantile(level, weights, t_edges))

    def median(self) -> Float[Array, "*batch"]:
        return self.quantile(0.5)

    def interval(self, mass: ScalarLike) -> tuple[Float[Array, "*batch"], Float[Array, "*batch"]]:
        """The central interval that holds `mass` of the termination distance."""
        mass = _check_level(mass, dtype=self.weights.dtype)
        lower, upper = self.quantiles((0.5 * (1.0 - mass), 0.5 * (1.0 + mass)))
        return lower, upper


def _is_traced(value) -> bool:
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(value))


def _scalar(value, name: str):
    """`value` as given if it is one real number of any accepted type, else a ValueError."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.number | np.ndarray | jax.Array):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    if np.ndim(value) != 0:
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(value)}")
    return value


def _checked(value, ok, message: str):
    """`value` if `ok(xp, value)` holds everywhere (`xp`: numpy for a concrete value, jax.numpy
    for a traced one): else a `ValueError` at once, or, where traced, an error when computed."""
    if _is_traced(value):
        return eqx.error_if(value, ~jnp.all(ok(jnp, value)), message)
    values = np.asarray(value, np.float64)
    bad = values[~ok(np, values)]  # NaN fails every check
    if bad.size:
        raise ValueError(f"{message}, got {bad.tolist()[0] if values.ndim == 0 else bad.tolist()}")
    return value


def _in_unit_interval(dtype):
    """The check that a level lies in (0, 1), and still does once cast to `dtype` (1e-50 is 0
    in float32, and 1 - 1e-9 is 1). A level below `dtype`'s smallest normal number is refused
    too: XLA flushes subnormal numbers to zero on the CPU (1e-44 is 0 there)."""
    smallest = np.finfo(dtype).tiny

    def ok(xp, x):
        inside = (x > 0) & (x < 1)
        cast = xp.asarray(xp.where(inside, x, 0.5), dtype)
        return inside & (cast >= smallest) & (cast < 1)

    return ok


def _finite_positive(dtype):
    """The check that a number is finite and positive, and still is once cast to `dtype`, at
    least `dtype`'s smallest normal number (XLA flushes subnormal numbers to zero on the CPU)."""

    def ok(xp, x):
        good = xp.isfinite(x) & (x > 0)
        cast = xp.asarray(xp.where(good & (xp.abs(x) < xp.finfo(dtype).max), x, 1.0), dtype)
        return good & (xp.abs(x) < xp.finfo(dtype).max) & (cast >= xp.finfo(dtype).tiny)

    return ok


def _level_message(name: str, dtype) -> str:
    smallest = np.finfo(dtype).tiny
    return f"{name} must lie in (0, 1), also as a {jnp.dtype(dtype).name} (and be at least {smallest:.3g})"


def _check_level(level: ScalarLike, name: str = "a quantile level or interval mass", dtype=None):
    """`level`, checked to lie in (0, 1) in float64 and in `dtype` (default: JAX's float, the
    one the distributions compute in) (see `_checked`)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    return _checked(_scalar(level, name), _in_unit_interval(dtype), _level_message(name, dtype))


def _check_levels(levels: Levels, dtype) -> Float[Array, " _"]:
    """`levels` (a sequence or a 1-d array) as an array, each checked as `_check_level` does."""
    if isinstance(levels, Sequence) and not isinstance(levels, str):
        if not levels:
            raise ValueError("quantile levels must not be empty")
        return jnp.stack([jnp.asarray(_check_level(level, dtype=dtype), dtype) for level in levels])
    if not isinstance(levels, np.ndarray | jax.Array) or np.ndim(levels) != 1 or np.shape(levels)[0] == 0:
        raise ValueError(f"quantile levels must be a non-empty sequence or 1-d array, got {levels!r}")
    message = _level_message("a quantile level or interval mass", dtype)
    return jnp.asarray(_checked(levels, _in_unit_interval(dtype), message), dtype)


def _check_channel_levels(levels, channels: int, dtype) -> Float[Array, "_ channels"]:
    """`levels` (an array of shape `(count, channels)`), each checked as `_check_level` does."""
    if not isinstance(levels, np.ndarray | jax.Array) or np.ndim(levels) != 2 or np.shape(levels)[1] != channels:
        raise ValueError(f"per-channel levels must be an array of shape (count, {channels}), got {levels!r}")
    if np.shape(levels)[0] == 0:
        raise ValueError("quantile levels must not be empty")
    message = _level_message("a quantile level or interval mass", dtype)
    return jnp.asarray(_checked(levels, _in_unit_interval(dtype), message), dtype)


_TEMPERATURE_MESSAGE = "temperature must be a finite positive number, a normal float32 (at least 1.18e-38)"


def _check_temperature(temperature: ScalarLike, dtype=None):
    """`temperature`, checked to be finite and positive, also in `dtype` (default: JAX's
    float) (see `_checked`)."""
    dtype = jnp.result_type(float) if dtype is None else dtype
    temperature = _scalar(temperature, "temperature")
    return _checked(temperature, _finite_positive(dtype), _TEMPERATURE_MESSAGE)


def _scaled(
    scale: Float[Array, "*batch num_samples channels"], temperature: ScalarLike
) -> Float[Array, "*batch num_samples channels"]:
    """`scale * temperature`, checked to stay finite and positive where `scale` is (a huge or
    tiny temperature may overflow or underflow the product)."""
    scaled = scale * _check_temperature(temperature, scale.dtype)
    message = f"{_TEMPERATURE_MESSAGE} whose product with every scale is too"

    def ok(xp, pair):
        before, after = pair
        return ~((before > 0) & xp.isfinite(before)) | (xp.isfinite(after) & (after > 0))

    if _is_traced((scale, scaled)):
        return eqx.error_if(scaled, ~jnp.all(ok(jnp, (scale, scaled))), message)
    if not np.all(ok(np, (np.asarray(scale), np.asarray(scaled)))):
        raise ValueError(f"{message}, got {float(np.asarray(temperature))}")
    return scaled


class Predictive(eqx.Module):
    """A batch of rays' predictive distributions, with the render they come from.

    **Fields:**

    - `colour`: the colour mixture (the coarse level's by default: where the NLL trains).
    - `depth`: the termination distance (the fine level's by default: the distribution whose
      mean is the rendered depth).
    - `rgb`, `render_depth`, `acc`: the fine level's render, background included.
    """

    colour: ColourMixture
    depth: TerminationDistribution
    rgb: Float[Array, "*batch channels"]
    render_depth: Float[Array, "*batch"]
    acc: Float[Array, "*batch"]


def _check_bounds(rays: RayBundle) -> RayBundle:
    """`rays`, checked to have finite origins and directions (a NaN or inf one rendered to
    plausible-looking numbers: the far bound as the depth median) and finite bounds with
    `near <= far` (the sampling interval would otherwise be reversed or unbounded)."""
    message = "rays must have finite origins, directions and bounds with near <= far"

    def bad(xp, origins, directions, near, far):
        geometry = xp.all(xp.isfinite(origins), axis=-1) & xp.all(xp.isfinite(directions), axis=-1)
        return ~(geometry[..., None] & xp.isfinite(near) & xp.isfinite(far) & (near <= far))

    parts = (rays.origins, rays.directions, rays.near, rays.far)
    if _is_traced(parts):
        flagged = eqx.error_if(rays.near, jnp.any(bad(jnp, *parts)), message)
        return eqx.tree_at(lambda r: r.near, rays, flagged)
    count = int(np.sum(bad(np, *(np.asarray(p) for p in parts))))
    if count:
        raise ValueError(f"{message}: {count} of {math.prod(rays.batch_shape)} rays do not")
    return rays


class Background(eqx.Module):
    """The background component of a colour mixture (`LaplaceMixture.background`): the light
    that passes a ray's last sample lands on `colour`, a Laplace density of scale `scale` in
    each channel, with coefficient the ray's transmittance `exp(log_transmittance)`."""

    colour: tuple[float, float, float] = eqx.field(static=True)
    scale: float = eqx.field(static=True)
    log_transmittance: Float[Array, "*batch"]


def colour_mixture(
    level: LevelOutputs, temperature: ScalarLike = 1.0, background: Background | None = None
) -> ColourMixture:
    """The colour mixture of one level's render (a model with mixture heads), its scales
    multiplied by `temperature`.

    Without `background`, the coefficients are the weights normalised over the samples (eq. 6).
    With it, as the colour NLL of a mixture with a background component scores a pixel: the
    samples' unnormalised weights and the transmittance, with the background as one more
    component after the samples (its scale multiplied by `temperature` too).
    """
    beta = level.field.beta
    if beta is None:
        raise ValueError(
            "this model has no mixture heads (the mip-NeRF baseline): it predicts no distribution"
        )
    if background is None:
        count = level.weights.shape[-1]
        flat = level.weights.reshape(-1, count)
        coefficients = jax.vmap(mixing_coefficients)(flat).reshape(level.weights.shape)
        return ColourMixture(coefficients, level.field.rgb, _scaled(beta, temperature))
    light = jnp.exp(background.log_transmittance)[..., None]
    # w_j and T sum to one up to rounding; dividing by their sum makes it exact.
    masses = jnp.concatenate([level.weights, light], axis=-1)
    coefficients = masses / jnp.sum(masses, axis=-1, keepdims=True)

    def appended(per_sample, value):  # one more component after the samples
        shape = (*per_sample.shape[:-2], 1, per_sample.shape[-1])
        last = jnp.broadcast_to(jnp.asarray(value, per_sample.dtype), shape)
        return jnp.concatenate([per_sample, last], axis=-2)

    location = appended(level.field.rgb, background.colour)
    return ColourMixture(coefficients, location, _scaled(appended(beta, background.scale), temperature))


def _background(model: MixNeRF, level: LevelOutputs, rays: RayBundle) -> Background | None:
    """The background component of `model`'s colour mixture for `level`, as its colour NLL
    weights it (the log transmittance over the level's densities); `None` without one."""
    colour = getattr(model.mixture, "background", None)
    if colour is None:
        return None
    norm = jnp.linalg.norm(rays.directions, axis=-1)
    flat_density = level.field.density.reshape(-1, level.field.density.shape[-1])
    flat_edges = level.t_edges.reshape(-1, level.t_edges.shape[-1])
    log_t = jax.vmap(log_transmittance)(flat_density, flat_edges, norm.reshape(-1))
    return Background(tuple(colour), model.mixture.background_scale, log_t.reshape(level.weights.shape[:-1]))


def predictive(
    model: MixNeRF,
    rays: RayBundle,
    *,
    colour_level: str = "coarse",  # "coarse" or "fine": checked below, with a one-line error
    depth_level: str = "fine",
    temperature: ScalarLike = 1.0,
) -> Predictive:
    """What `model` predicts for `rays` (any batch shape), as distributions.

    One deterministic render (the evaluation render, no density noise) gives both levels;
    nothing is solved until a quantile or mode is asked for.

    **Arguments:**

    - `model`: a MixNeRF with mixture heads.
    - `rays`: the rays.
    - `colour_level`: the level whose per-sample Laplace components form the colour mixture:
      `"coarse"`, where the colour NLL is trained (the default), or `"fine"` (the same heads
      read at the fine samples; never trained as a distribution there).
    - `depth_level`: the level whose weights give the termination distance.
    - `temperature`: multiplies every scale `beta` (a post-hoc calibration; 1: the model's).

    **Returns:**

    A `Predictive` with `rays.batch_shape` in front.
    """
    for name, value in (("colour_level", colour_level), ("depth_level", depth_level)):
        if value not in ("coarse", "fine"):
            raise ValueError(f"{name} must be 'coarse' or 'fine', got {value!r}")
    if model.mixture is None or not model.field.has_mixture_heads:
        raise ValueError(
            "this model has no mixture heads (the mip-NeRF baseline): it predicts no distribution"
        )
    outputs = model(_check_bounds(rays))
    colour_from = outputs.coarse if colour_level == "coarse" else outputs.fine
    depth_from = outputs.coarse if depth_level == "coarse" else outputs.fine
    return Predictive(
        colour=colour_mixture(colour_from, temperature, _background(model, colour_from, rays)),
        depth=TerminationDistribution(depth_from.weights, depth_from.t_edges),
        rgb=outputs.fine.rgb,
        render_depth=outputs.fine.depth,
        acc=outputs.fine.acc,
    )


class PredictiveSummary(eqx.Module):
    """The numbers a predictive distribution is read as, for a batch of rays.

    **Fields:**

    - `masses` (static): the masses of the central intervals, in the order of the leading
      axis of `colour_lower`, `colour_upper`, `depth_lower` and `depth_upper`.
    - `colour_mean`, `colour_median`, `colour_std`: per channel, of the colour mixture.
    - `colour_mode`: the mode of the joint RGB density (`None` unless asked for).
    - `colour_lower`, `colour_upper`: per channel, the central intervals.
    - `coefficient_entropy`: of the mixing coefficients, in nats.
    - `depth_mean`, `depth_median`, `depth_std`, `depth_lower`, `depth_upper`: of the
      termination distance.
    - `rgb`, `render_depth`, `acc`: the fine level's render.
    - `log_prob`: the joint colour log density of the given targets (`None` without them).
    - `colour_cdf`, `colour_channel_log_prob`: per channel, the colour mixture's distribution
      function and marginal log density at the targets (`None` without them): what
      recalibration is fitted on and per-channel calibration measures score.
    - `depth_cdf`: the termination distance's distribution function at the given true depths
      (`None` without them).
    """

    masses: tuple[float, ...] = eqx.field(static=True)
    colour_mean: Float[Array, "*batch channels"]
    colour_median: Float[Array, "*batch channels"]
    colour_std: Float[Array, "*batch channels"]
    colour_mode: Float[Array, "*batch channels"] | None
    colour_lower: Float[Array, "_ *batch channels"]
    colour_upper: Float[Array, "_ *batch channels"]
    coefficient_entropy: Float[Array, "*batch"]
    depth_mean: Float[Array, "*batch"]
    depth_median: Float[Array, "*batch"]
    depth_std: Float[Array, "*batch"]
    depth_lower: Float[Array, "_ *batch"]
    depth_upper: Float[Array, "_ *batch"]
    rgb: Float[Array, "*batch channels"]
    render_depth: Float[Array, "*batch"]
    acc: Float[Array, "*batch"]
    log_prob: Float[Array, "*batch"] | None
    colour_cdf: Float[Array, "*batch channels"] | None = None
    colour_channel_log_prob: Float[Array, "*batch channels"] | None = None
    depth_cdf: Float[Array, "*batch"] | None = None


DEFAULT_MASSES = (0.5, 0.8, 0.9, 0.95)


class IntervalLevels(eqx.Module):
    """The quantile levels that bound each interval, per interval mass: the raw central
    interval's `(1 - mass) / 2` and `(1 + mass) / 2`, or levels a recalibration moved
    (`mixnerf_eqx.uncertainty.Recalibration.interval_levels`). Arrays, so a new calibration recompiles
    nothing. A level of exactly 0 or 1 is an end without bound (a recalibration that had to
    cover truths outside the distribution's support): the interval reaches the colour range's
    end (0 or 1, or beyond where the mixture's own extreme quantile lies) or the ray's first
    or last edge.

    **Fields:**

    - `masses` (static): the nominal masses the levels belong to, in order.
    - `colour_lower`, `colour_upper`: per mass and colour channel.
    - `depth_lower`, `depth_upper`: per mass, for the termination distance.
    """

    masses: tuple[float, ...] = eqx.field(static=True)
    colour_lower: Float[Array, "masses channels"]
    colour_upper: Float[Array, "masses channels"]
    depth_lower: Float[Array, " masses"]
    depth_upper: Float[Array, " masses"]

    @staticmethod
    def raw(masses: Sequence[ScalarLike], channels: int = 3) -> "IntervalLevels":
        """The model's own central intervals: `(1 -+ mass) / 2` for every channel and depth."""
        masses = np.asarray([float(_check_level(mass, "an interval mass")) for mass in masses], np.float64)
        lower, upper = 0.5 * (1.0 - masses), 0.5 * (1.0 + masses)
        return IntervalLevels(
            masses=tuple(float(mass) for mass in masses),
            colour_lower=jnp.asarray(np.repeat(lower[:, None], channels, axis=1), jnp.float32),
            colour_upper=jnp.asarray(np.repeat(upper[:, None], channels, axis=1), jnp.float32),
            depth_lower=jnp.asarray(lower, jnp.float32),
            depth_upper=jnp.asarray(upper, jnp.float32),
        )


# The most extreme level a quantile is solved at (an end without bound is widened after).
_EXTREME_LEVEL = 1e-6


def _unbounded_ends(colour_quantiles, depth_quantiles, colour_levels, depth_levels, t_edges):
    """The quantiles with every end of level 0 or 1 (see `IntervalLevels`) widened: a colour
    end to the colour range's end, 0 or 1 (or the mixture's extreme quantile beyond it), a
    depth end to the ray's first or last edge."""
    batch = colour_quantiles.ndim - 2  # the levels' axis in front, the channels' behind
    shape = (colour_levels.shape[0], *([1] * batch), colour_levels.shape[1])
    colour_low, colour_high = (colour_levels <= 0).reshape(shape), (colour_levels >= 1).reshape(shape)
    colour_quantiles = jnp.where(colour_low, jnp.minimum(colour_quantiles, 0.0), colour_quantiles)
    colour_quantiles = jnp.where(colour_high, jnp.maximum(colour_quantiles, 1.0), colour_quantiles)
    depth_shape = (depth_levels.shape[0], *([1] * batch))
    depth_low, depth_high = (depth_levels <= 0).reshape(depth_shape), (depth_levels >= 1).reshape(depth_shape)
    depth_quantiles = jnp.where(depth_low, t_edges[..., 0][None], depth_quantiles)
    depth_quantiles = jnp.where(depth_high, t_edges[..., -1][None], depth_quantiles)
    return colour_quantiles, depth_quantiles


def summarise(
    prediction: Predictive,
    masses: Sequence[ScalarLike] = DEFAULT_MASSES,
    targets: Float[Array, "*batch channels"] | None = None,
    *,
    with_mode: bool = False,
    levels: IntervalLevels | None = None,
    depth_targets: Float[Array, "*batch"] | None = None,
) -> PredictiveSummary:
    """Every summary of `prediction` (one batched quantile solve for all channels and
    levels), with the log density and distribution function of `targets` (and of
    `depth_targets`) if given and, with `with_mode`, the mode of each ray's joint colour
    density (a search per ray, which costs about as much as the quantiles). `levels` moves
    the intervals' ends (recalibrated intervals); by default they are the central intervals
    of each mass."""
    if isinstance(masses, str) or not isinstance(masses, Sequence) or not masses:
        raise ValueError(f"masses must be a non-empty sequence of interval masses, got {masses!r}")
    dtype = prediction.colour.location.dtype
    masses = tuple(float(_check_level(mass, "an interval mass", dtype=dtype)) for mass in masses)
    colour, depth = prediction.colour, prediction.depth
    count = len(masses)
    channels = colour.location.shape[-1]
    if levels is None:
        levels = IntervalLevels.raw(masses, channels)
    same_masses = len(levels.masses) == count and np.allclose(levels.masses, masses, rtol=0, atol=1e-9)
    if not same_masses:
        raise ValueError(f"levels belong to the interval masses {levels.masses}, not to {masses}")
    if levels.colour_lower.shape != (count, channels) or levels.depth_lower.shape != (count,):
        raise ValueError(
            f"levels must hold {count} interval masses ({channels} colour channels); got colour levels of "
            f"shape {levels.colour_lower.shape} and depth levels of shape {levels.depth_lower.shape}"
        )
    # One batched solve for every level: the median, then each interval's two ends (an end
    # without bound solved at the extreme level, then widened below).
    half = jnp.full((1, channels), 0.5, dtype)
    colour_levels = jnp.concatenate([half, levels.colour_lower, levels.colour_upper]).astype(dtype)
    depth_levels = jnp.concatenate([half[0, :1], levels.depth_lower, levels.depth_upper]).astype(dtype)
    colour_quantiles = colour.channel_quantiles(jnp.clip(colour_levels, _EXTREME_LEVEL, 1.0 - _EXTREME_LEVEL))
    depth_quantiles = depth.quantiles(jnp.clip(depth_levels, _EXTREME_LEVEL, 1.0 - _EXTREME_LEVEL))
    colour_quantiles, depth_quantiles = _unbounded_ends(
        colour_quantiles, depth_quantiles, colour_levels, depth_levels, depth.t_edges
    )
    return PredictiveSummary(
        masses=masses,
        colour_mean=colour.mean(),
        colour_median=colour_quantiles[0],
        colour_std=colour.std(),
        colour_mode=colour.mode() if with_mode else None,
        colour_lower=colour_quantiles[1 : 1 + count],
        colour_upper=colour_quantiles[1 + count :],
        coefficient_entropy=colour.coefficient_entropy(),
        depth_mean=depth.mean(),
        depth_median=depth_quantiles[0],
        depth_std=depth.std(),
        depth_lower=depth_quantiles[1 : 1 + count],
        depth_upper=depth_quantiles[1 + count :],
        rgb=prediction.rgb,
        render_depth=prediction.render_depth,
        acc=prediction.acc,
        log_prob=None if targets is None else colour.log_prob(targets),
        colour_cdf=None if targets is None else colour.cdf(targets),
        colour_channel_log_prob=None if targets is None else colour.channel_log_prob(targets),
        depth_cdf=None if depth_targets is None else depth.cdf(depth_targets),
    )
