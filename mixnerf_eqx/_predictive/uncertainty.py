"""Predictive distributions over whole views, and how well calibrated they are.

`predict_rays` and `predict_views` run the predictive pass (`mixnerf_eqx.predictive` and
`summarise`) in fixed-size chunks of rays, as `render_rays` renders them, and bring the maps
back to the host. The calibration measures compare them with the true pixels: the coverage of
the central intervals, the held-out negative log-likelihood, and sparsification curves with
their area against the oracle (AUSE). `fit_temperature` fits one factor on every `beta` by
minimising the negative log-likelihood of pixels that the model did not train on.
"""

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .._nn.chunks import join_chunks, map_ray_chunks
from .._nn.model import MixNeRF
from .._nn.rays import RayBundle
from .._util.images import save_png
from ..data import Views, rays_for_views
from .distribution import (
    DEFAULT_MASSES,
    ColourMixture,
    IntervalLevels,
    PredictiveSummary,
    _check_level,
    _check_bounds,
    _check_temperature,
    predictive,
    summarise,
)
from .recalibration import Recalibration, calibration_error


def _summarise_rays(
    model: MixNeRF,
    rays: RayBundle,
    temperature: Float[Array, ""],
    targets: Float[Array, "batch channels"] | None,
    masses: tuple[float, ...],
    with_mode: bool,
    levels: IntervalLevels,
    depth_targets: Float[Array, " batch"] | None,
) -> PredictiveSummary:
    return summarise(
        predictive(model, rays, temperature=temperature),
        masses,
        targets,
        with_mode=with_mode,
        levels=levels,
        depth_targets=depth_targets,
    )


_summarise_chunk = eqx.filter_jit(_summarise_rays)


@eqx.filter_jit
def _coarse_mixture(model: MixNeRF, rays: RayBundle) -> ColourMixture:
    return predictive(model, rays).colour


def predict_rays(
    model: MixNeRF,
    rays: RayBundle,
    chunk: int = 4096,
    *,
    masses: Sequence[float] = DEFAULT_MASSES,
    temperature: float = 1.0,
    targets: np.ndarray | None = None,
    with_mode: bool = False,
    levels: IntervalLevels | None = None,
    depth_targets: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The predictive summaries of any number of rays, `chunk` rays at a time, on the host.

    Every call of the compiled pass sees `chunk` rays (the last chunk is padded), so it
    compiles once per chunk size and interval masses; `temperature` is an array argument and
    changing it does not recompile.

    **Arguments:**

    - `model`: a MixNeRF with mixture heads.
    - `rays`: rays of any batch shape.
    - `chunk`: rays at once.
    - `masses`: the masses of the central intervals.
    - `temperature`: multiplies every `beta` (see `fit_temperature`).
    - `targets`: true colours with the rays' batch shape, to score (`log_prob`, and the
      distribution function and marginal densities that recalibration is fitted on).
    - `with_mode`: also the mode of each ray's joint colour density (`colour_mode`).
    - `levels`: the intervals' quantile levels (`Recalibration.interval_levels`; default:
      the central intervals of `masses`).
    - `depth_targets`: true depths with the rays' batch shape (`inf` where a ray hits
      nothing), to give the termination distance's distribution function there (`depth_cdf`).

    **Returns:**

    The fields of `PredictiveSummary` as numpy arrays with `rays.batch_shape` in front (the
    interval masses' axis before it), `log_prob` only with `targets`, `colour_mode` only with
    `with_mode`.
    """
    if chunk < 1:
        raise ValueError(f"chunk must be at least 1, got {chunk}")
    masses = tuple(float(_check_level(mass, "an interval mass")) for mass in masses)
    _check_temperature(temperature)
    _check_bounds(rays)  # on the host: one ValueError, before any chunk is rendered
    if targets is not None and tuple(np.shape(targets)) != (*rays.batch_shape, 3):
        raise ValueError(
            f"targets takes one colour per ray, shape {(*rays.batch_shape, 3)} (the rays' batch shape and "
            f"3 channels); got shape {tuple(np.shape(targets))}"
        )
    if depth_targets is not None and tuple(np.shape(depth_targets)) != rays.batch_shape:
        raise ValueError(
            f"depth_targets takes one depth per ray, shape {rays.batch_shape}; got shape "
            f"{tuple(np.shape(depth_targets))}"
        )
    if levels is None:
        levels = IntervalLevels.raw(masses)
    elif len(levels.masses) != len(masses) or not np.allclose(levels.masses, masses, rtol=0, atol=1e-9):
        raise ValueError(f"levels belong to the interval masses {levels.masses}, not to masses={masses}")
    batch_shape = rays.batch_shape
    if math.prod(batch_shape) == 0:
        return _no_rays(model, rays, masses, targets is not None, with_mode, levels, depth_targets is not None)
    scale = jnp.asarray(temperature, jnp.float32)

    # The true colours and depths travel as one array of columns (the chunked map pads one).
    columns = []
    if targets is not None:
        columns.append(np.asarray(targets, np.float32).reshape(-1, 3))
    if depth_targets is not None:
        columns.append(np.asarray(depth_targets, np.float32).reshape(-1, 1))
    extra = np.concatenate(columns, axis=1) if columns else None

    def summarise_chunk(piece: RayBundle, real: int, target) -> dict[str, Array]:
        del real
        colours = None if targets is None else target[:, :3]
        depths = None if depth_targets is None else target[:, -1]
        summary = _summarise_chunk(model, piece, scale, colours, masses, with_mode, levels, depths)
        return _fields(summary)

    parts, count = map_ray_chunks(summarise_chunk, rays, chunk, extra)
    result = {}
    for name in parts[0]:
        # Interval bounds carry the masses' axis in front of the rays'.
        axis = 1 if name.endswith(("_lower", "_upper")) else 0
        joined = join_chunks([part[name] for part in parts], count, axis)
        lead = joined.shape[:1] if axis else ()
        result[name] = joined.reshape(*lead, *batch_shape, *joined.shape[len(lead) + 1 :])
    result["masses"] = np.asarray(masses)
    return result


def _no_rays(
    model: MixNeRF,
    rays: RayBundle,
    masses: tuple[float, ...],
    with_targets: bool,
    with_mode: bool,
    levels: IntervalLevels,
    with_depth_targets: bool,
) -> dict[str, np.ndarray]:
    """`predict_rays`'s answer for a batch without rays: every field, empty, at its shape."""
    one = jax.tree_util.tree_map(
        lambda x: jnp.ones((1, *jnp.shape(x)[len(rays.batch_shape) :]), jnp.float32), rays
    )
    one = eqx.tree_at(lambda r: r.far, one, 2.0 * one.near)
    target = jnp.zeros((1, 3), jnp.float32) if with_targets else None
    depth = jnp.zeros((1,), jnp.float32) if with_depth_targets else None
    shapes = eqx.filter_eval_shape(
        _summarise_rays, model, one, jnp.float32(1.0), target, masses, with_mode, levels, depth
    )
    fields = {f.name: getattr(shapes, f.name) for f in dataclasses.fields(shapes) if f.name != "masses"}
    result = {}
    for name, shape in fields.items():
        if shape is None:
            continue
        lead = shape.shape[:1] if name.endswith(("_lower", "_upper")) else ()
        rest = shape.shape[len(lead) + 1 :]
        result[name] = np.zeros((*lead, *rays.batch_shape, *rest), np.dtype(shape.dtype))
    result["masses"] = np.asarray(masses)
    return result


def _fields(summary: PredictiveSummary) -> dict[str, Array]:
    """The summary's arrays by name (those it has; the masses apart)."""
    fields = (f.name for f in dataclasses.fields(summary) if f.name != "masses")
    return {name: getattr(summary, name) for name in fields if getattr(summary, name) is not None}


def depths_are_ray_distances(views: Views) -> bool:
    """Whether `views.depths` (camera z-depths) are distances along the rays the model renders:
    true for rays from the camera centre along the unnormalised directions; not in NDC, nor
    for origins moved onto a plane."""
    return views.depths is not None and not views.ndc and views.origin_plane_z is None


def predict_views(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    chunk: int = 4096,
    *,
    masses: Sequence[float] = DEFAULT_MASSES,
    temperature: float = 1.0,
    with_targets: bool = True,
    with_mode: bool = False,
    levels: IntervalLevels | None = None,
) -> dict[str, np.ndarray]:
    """`predict_rays` over every view of `views`, one view's rays at a time, stacked over
    the views; scored against the views' images (and true depths, where the views have
    them) unless `with_targets` is false (`with_mode` and `levels` as in `predict_rays`)."""
    per_view = []
    for index in range(views.num_views):
        one = views.select([index])
        targets = one.images if with_targets else None
        depths = one.depths if with_targets and depths_are_ray_distances(one) else None
        per_view.append(
            predict_rays(
                model,
                rays_for_views(one, near, far),
                chunk,
                masses=masses,
                temperature=temperature,
                targets=targets,
                with_mode=with_mode,
                levels=levels,
                depth_targets=depths,
            )
        )
    stacked = {}
    for name in per_view[0]:
        if name == "masses":
            stacked[name] = per_view[0][name]
        elif name.endswith(("_lower", "_upper")):
            stacked[name] = np.concatenate([view[name] for view in per_view], axis=1)
        else:
            stacked[name] = np.concatenate([view[name] for view in per_view], axis=0)
    return stacked


# ----------------------------------------------------------------------------- calibration


def interval_coverage(
    lower: Float[np.ndarray, "*batch channels"],
    upper: Float[np.ndarray, "*batch channels"],
    truth: Float[np.ndarray, "*batch channels"],
) -> Float[np.ndarray, "channels"]:
    """The fraction of pixels whose true value lies in `[lower, upper]`, per channel."""
    inside = (truth >= lower) & (truth <= upper)
    return inside.reshape(-1, inside.shape[-1]).mean(axis=0)


@dataclasses.dataclass(frozen=True)
class Sparsification:
    """Sparsification curves of one error against one predicted spread.

    **Fields:**

    - `fractions`: the fraction of pixels removed, from 0 up.
    - `by_spread`: the mean error of the pixels left after removing those of largest
      predicted spread, divided by the mean error of all pixels.
    - `oracle`: the same, removing the pixels of largest true error (the best any spread can do).
    - `ause`: the area between the two curves over `fractions` (0: the spread orders the
      pixels as their errors do; a spread unrelated to the error gives about the area under
      the oracle's curve below 1).
    - `random_area`: the area between a constant curve at 1 (an uninformative order) and the
      oracle: the AUSE of a spread that knows nothing.
    """

    fractions: np.ndarray
    by_spread: np.ndarray
    oracle: np.ndarray
    ause: float
    random_area: float


def _removal_curve(order: np.ndarray, error: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    # The mean error of what is left after removing the first `f * n` pixels of `order`.
    sorted_error = error[order]
    # suffix_sum[k]: the sum of sorted_error[k:].
    suffix_sum = np.concatenate([np.cumsum(sorted_error[::-1])[::-1], [0.0]])
    count = error.size
    removed = np.minimum(np.floor(fractions * count).astype(int), count - 1)
    return suffix_sum[removed] / (count - removed)


def sparsification(spread: np.ndarray, error: np.ndarray, num_fractions: int = 50) -> Sparsification:
    """Sparsification curves and AUSE of `error` (per pixel, any shape) ordered by `spread`
    (the same shape), with the curves normalised by the mean error of all pixels.

    Pixels are removed largest first; ties in `spread` are broken by position (a stable
    sort), never by the error.
    """
    spread = np.asarray(spread, np.float64).ravel()
    error = np.asarray(error, np.float64).ravel()
    if spread.shape != error.shape:
        raise ValueError(f"spread and error differ in size: {spread.size} and {error.size}")
    fractions = np.linspace(0.0, 1.0, num_fractions, endpoint=False)
    total = error.mean()
    norm = total if total > 0 else 1.0
    by_spread = _removal_curve(np.argsort(-spread, kind="stable"), error, fractions) / norm
    oracle = _removal_curve(np.argsort(-error, kind="stable"), error, fractions) / norm
    width = 1.0 / num_fractions
    return Sparsification(
        fractions=fractions,
        by_spread=by_spread,
        oracle=oracle,
        ause=float(np.sum(by_spread - oracle) * width),
        random_area=float(np.sum(1.0 - oracle) * width),
    )


def collect_mixtures(model: MixNeRF, rays: RayBundle, chunk: int = 4096) -> ColourMixture:
    """The coarse colour mixtures of a flat batch of rays, rendered `chunk` rays at a time."""
    parts, count = map_ray_chunks(lambda piece, real, _: _coarse_mixture(model, piece), rays, chunk)
    return jax.tree_util.tree_map(lambda *xs: jnp.asarray(join_chunks(xs, count)), *parts)


def fit_temperature(mixtures: ColourMixture, targets: Float[Array, "batch channels"]) -> float:
    """The factor `T` on every `beta` that minimises the mean negative log-likelihood of
    `targets` (pixels the model did not train on) under `mixtures` (one per pixel).

    The mean NLL is a smooth function of `log T`; it is minimised by `optx.BFGS` from
    `log T = 0`.
    """

    def mean_nll(log_temperature, args):
        mixtures, targets = args
        scaled = mixtures.with_temperature(jnp.exp(log_temperature))
        return -jnp.mean(scaled.log_prob(targets))

    solution = optx.minimise(
        mean_nll,
        optx.BFGS(rtol=1e-6, atol=1e-6),
        jnp.zeros((), targets.dtype),
        args=(mixtures, targets),
        max_steps=100,
    )
    return float(jnp.exp(solution.value))


@eqx.filter_jit
def _pit_chunk(
    model: MixNeRF, rays: RayBundle, temperature: Float[Array, ""], targets: Float[Array, "batch _"]
) -> dict[str, Array]:
    prediction = predictive(model, rays, temperature=temperature)
    colours, depths = targets[:, :3], targets[:, 3]
    return {
        "colour_cdf": prediction.colour.cdf(colours),
        "colour_log_density": prediction.colour.channel_log_prob(colours),
        "depth_cdf": prediction.depth.cdf(depths),
    }


def calibration_pit(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    chunk: int = 4096,
    *,
    temperature: float = 1.0,
    max_pixels: int | None = 65536,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """The predictive distribution functions at the true values of `views`' pixels (the PIT
    values recalibration is fitted on) and the colour channels' marginal log densities there.

    Only the distribution functions are computed (no quantile solve). With `max_pixels`, that
    many pixels are drawn at random (by `seed`) from all of the views' pixels.

    **Returns:**

    `colour_cdf` and `colour_log_density` of shape `(pixels, channels)`, and `depth_cdf` of
    shape `(depth_pixels,)` over the drawn pixels whose true depth is known and finite (empty
    where the views have no true depth, or where their camera z-depths are not distances along
    the rendered rays: NDC scenes, origins moved onto a plane).
    """
    _check_temperature(temperature)
    if views.num_views == 0:
        raise ValueError("no calibration views: calibration needs at least one view the model did not train on")
    if max_pixels is not None and max_pixels < 1:
        raise ValueError(f"max_pixels must be at least 1, got {max_pixels}")
    per_view = views.height * views.width
    total = views.num_views * per_view
    chosen = np.arange(total)
    if max_pixels is not None and max_pixels < total:
        chosen = np.sort(np.random.default_rng(seed).choice(total, size=max_pixels, replace=False))
    with_depths = depths_are_ray_distances(views)
    pieces, colours, depths = [], [], []
    # One view's rays at a time: only the drawn pixels' rays are kept.
    for index in range(views.num_views):
        mine = chosen[(chosen >= index * per_view) & (chosen < (index + 1) * per_view)] - index * per_view
        if mine.size == 0:
            continue
        one = views.select([index])
        rays = rays_for_views(one, near, far).reshape(-1)
        pieces.append(jax.tree_util.tree_map(lambda x: np.asarray(x)[mine], rays))
        colours.append(one.images.reshape(-1, 3)[mine])
        depths.append(one.depths.reshape(-1)[mine] if with_depths else np.full(mine.size, np.nan))
    rays = jax.tree_util.tree_map(lambda *xs: jnp.asarray(np.concatenate(xs)), *pieces)
    colours = np.concatenate(colours).astype(np.float32)
    depths = np.concatenate(depths).astype(np.float32)
    known = np.isfinite(depths)
    targets = np.concatenate([colours, np.where(known, depths, 0.0)[:, None]], axis=1)
    scale = jnp.asarray(temperature, jnp.float32)
    parts, count = map_ray_chunks(lambda piece, real, extra: _pit_chunk(model, piece, scale, extra), rays, chunk, targets)
    joined = {name: join_chunks([part[name] for part in parts], count) for name in parts[0]}
    return {
        "colour_cdf": joined["colour_cdf"].astype(np.float64),
        "colour_log_density": joined["colour_log_density"].astype(np.float64),
        "depth_cdf": joined["depth_cdf"][known].astype(np.float64),
    }


def fit_recalibration(
    model: MixNeRF,
    views: Views,
    near: float,
    far: float,
    method: str = "conformal",
    masses: Sequence[float] = DEFAULT_MASSES,
    chunk: int = 4096,
    *,
    temperature: float = 1.0,
    max_pixels: int | None = 65536,
    seed: int = 0,
    description: str | None = None,
) -> Recalibration:
    """Fits `method` (`"isotonic"`, `"conformal"` or `"raw"`) on `views`, which must be views
    the model did not train on and that no result is reported on (a scene's validation views):
    see `mixnerf_eqx._predictive.recalibration`. `temperature` scales the mixture first, as it
    will be scaled where the recalibration is used; `max_pixels` and `seed` as in
    `calibration_pit`."""
    pit = calibration_pit(
        model, views, near, far, chunk, temperature=temperature, max_pixels=max_pixels, seed=seed
    )
    where = description or f"{views.num_views} views"
    depth = pit["depth_cdf"] if pit["depth_cdf"].size else None
    return Recalibration.fit(
        method, pit["colour_cdf"], depth, masses, fitted_on=f"{where}, {pit['colour_cdf'].shape[0]} pixels"
    )


def coverage_report(
    maps: dict[str, np.ndarray],
    images: Float[np.ndarray, "num_views height width channels"],
    depths: Float[np.ndarray, "num_views height width"] | None = None,
    recalibration: Recalibration | None = None,
) -> dict:
    """How well the intervals and distribution functions of `maps` (from `predict_views`
    with targets, whose intervals were bounded by `recalibration`'s levels) hold on `images`
    (and `depths`, `inf` where a ray hits nothing: left out).

    **Returns:**

    A JSON-ready dict: the method and what it was fitted on, the masses whose intervals have
    an end without bound (`Recalibration.unbounded_masses`); per interval mass, the colour
    coverage pooled over every pixel and channel, its range over the views, and the mean
    interval width; the same for depth where true depths are known; FlipNeRF's NLL (the
    per-channel marginal densities, recalibrated for isotonic, averaged over pixels and
    channels, nats) and calibration error (mean over the channels, and per channel).
    """
    recalibration = recalibration or Recalibration.raw(tuple(float(m) for m in maps["masses"]))
    if len(recalibration.masses) != len(maps["masses"]) or not np.allclose(recalibration.masses, maps["masses"]):
        raise ValueError(
            f"the maps hold intervals of masses {tuple(maps['masses'])}, the recalibration {recalibration.masses}: "
            "pass the recalibration the maps were made with (predict_views(levels=recalibration.interval_levels()))"
        )
    num_views = images.shape[0]
    colour = {}
    for index, mass in enumerate(maps["masses"]):
        lower, upper = maps["colour_lower"][index], maps["colour_upper"][index]
        inside = (images >= lower) & (images <= upper)
        per_view = inside.reshape(num_views, -1).mean(axis=1)
        colour[f"{mass:g}"] = {
            "pooled": float(inside.mean()),
            "per_view_min": float(per_view.min()),
            "per_view_max": float(per_view.max()),
            "width": float(np.mean(upper - lower)),
        }
    depth_coverage = None
    if depths is not None and np.isfinite(depths).any():
        depth_coverage = {}
        known = np.isfinite(depths)
        for index, mass in enumerate(maps["masses"]):
            lower, upper = maps["depth_lower"][index], maps["depth_upper"][index]
            inside = (depths >= lower) & (depths <= upper)
            per_view = [inside[v][known[v]].mean() for v in range(num_views) if known[v].any()]
            depth_coverage[f"{mass:g}"] = {
                "pooled": float(inside[known].mean()),
                "per_view_min": float(min(per_view)),
                "per_view_max": float(max(per_view)),
                "width": float(np.mean((upper - lower)[known])),
            }
    cdf = maps["colour_cdf"].reshape(-1, maps["colour_cdf"].shape[-1]).astype(np.float64)
    log_density = maps["colour_channel_log_prob"].reshape(cdf.shape).astype(np.float64)
    if recalibration.colour_map is not None:
        log_density = log_density + recalibration.colour_map.log_slope(cdf)
    errors = calibration_error(recalibration.calibrated_pit(cdf))
    return {
        "method": recalibration.method,
        "fitted_on": recalibration.fitted_on,
        "unbounded": recalibration.unbounded_masses(),
        "colour_coverage": colour,
        "depth_coverage": depth_coverage,
        "nll_per_channel": float(-np.mean(log_density)),
        "calibration_error": float(errors.mean()),
        "calibration_error_per_channel": errors.tolist(),
    }


def calibration_report(
    maps: dict[str, np.ndarray],
    images: Float[np.ndarray, "*batch channels"],
    depths: Float[np.ndarray, "*batch"] | None = None,
) -> dict:
    """How well `maps` (from `predict_views` or `predict_rays`, with `log_prob`) match the true
    `images` and, where known, the true `depths` (`inf` where a ray hits nothing: left out).

    **Returns:**

    A JSON-ready dict: for each interval mass, the coverage per channel and its mean; the mean
    held-out NLL per pixel (the joint colour density, nats); the colour AUSE (error: the fine
    render's absolute error averaged over the channels, spread: the colour mixture's standard
    deviation averaged over the channels), and the depth AUSE (error: the rendered depth's
    absolute error, spread: the termination distance's standard deviation).
    """
    coverage = {}
    for index, mass in enumerate(maps["masses"]):
        per_channel = interval_coverage(maps["colour_lower"][index], maps["colour_upper"][index], images)
        coverage[f"{mass:g}"] = {"per_channel": per_channel.tolist(), "mean": float(per_channel.mean())}
    colour_error = np.abs(maps["rgb"] - images).mean(axis=-1)
    colour = sparsification(maps["colour_std"].mean(axis=-1), colour_error)
    report = {
        "pixels": int(colour_error.size),
        "coverage": coverage,
        "nll": float(-np.mean(maps["log_prob"])),
        "colour_ause": colour.ause,
        "colour_random_area": colour.random_area,
        "depth_ause": None,
        "depth_random_area": None,
    }
    if depths is not None:
        known = np.isfinite(depths)
        depth = sparsification(maps["depth_std"][known], np.abs(maps["render_depth"] - depths)[known])
        report["depth_ause"], report["depth_random_area"] = depth.ause, depth.random_area
    return report


def write_uncertainty_maps(
    folder: Path, views: Views, maps: dict[str, np.ndarray], *, near: float, far: float
) -> None:
    """Per view, greyscale PNGs (white: large) of the colour spread beside the colour error, on
    one scale (0 to 0.5), and of the depth spread beside the depth error where the true depth
    is known, on one scale (0 to a quarter of `far - near`)."""
    depth_scale = 0.25 * (far - near)
    for index, view_id in enumerate(views.ids):
        stem = folder / f"test_{view_id:03d}"
        colour_error = np.abs(maps["rgb"][index] - views.images[index]).mean(axis=-1)
        save_png(f"{stem}_colour_spread.png", maps["colour_std"][index].mean(axis=-1) / 0.5)
        save_png(f"{stem}_colour_error.png", colour_error / 0.5)
        save_png(f"{stem}_depth_spread.png", maps["depth_std"][index] / depth_scale)
        if views.depths is not None:
            error = np.abs(maps["render_depth"][index] - views.depths[index])
            save_png(f"{stem}_depth_error.png", np.where(np.isfinite(error), error, 0.0) / depth_scale)
