"""Recalibration of the predictive distribution, fitted on pixels the model did not train on.

Everything here reads the probability integral transform (PIT) of held-out truths: `u =
F(y)`, the predictive distribution function at the true value, per colour channel (and for
the termination distance where the true depth is known). A calibrated model's PIT values
are uniform on (0, 1); the central interval of mass `m` covers `y` exactly when `|2u - 1|
<= m`, so interval coverage, the calibration error and both recalibrations are functions of
the PIT values alone.

- **Isotonic** (Kuleshov et al. 2018, as FlipNeRF recalibrates): the calibrated
  distribution function is `A(F(y))`, where `A` is the isotonic regression of the empirical
  frequency `#{u_i <= p} / n` on the predicted level `p` over the calibration pixels. Those
  frequencies never decrease in `p`, so the regression is the calibration set's empirical
  CDF of its PIT values, linear between points (as scikit-learn's `IsotonicRegression`
  predicts between its fitted points); here it is kept at `ISOTONIC_KNOTS` quantiles.
  Intervals move to the raw levels `A^-1((1 -+ m) / 2)`.
- **Split conformal, equal-tailed**: each end of the interval of nominal mass `m` is an
  order statistic of the `n` calibration PIT values, the lower the
  `floor((n + 1)(1 - m) / 2)`-th smallest and the upper the `ceil((n + 1)(1 + m) / 2)`-th: a
  new pixel exchangeable with the calibration pixels falls below the first with probability
  at most `(1 - m) / 2` and above the second with at most as much, so it is covered with
  probability at least `m` (Romano et al. 2019's two-sided conformalised quantile intervals),
  and below `m + 2 / (n + 1)` without ties. Each end moves on its own, so pixels whose truths
  lean to one side of the distribution do not widen the other end (a central interval, one
  score `|2u - 1|` for both ends, over-covers on views that lean less: chosen on validation
  views, `benchmarks/uncertainty.md`).

Pixels of one view are correlated, and test views are not exchangeable with validation views
in general: the guarantee is marginal over exchangeable pixels, which held-out views
approximate; coverage is reported per view as well as pooled (`calibration_report`).
"""

import dataclasses
import json
import math
from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .distribution import DEFAULT_MASSES, IntervalLevels

METHODS = ("raw", "isotonic", "conformal")

# The isotonic map keeps this many quantiles of the calibration set's PIT values (plus the
# ends 0 and 1): finer than any coverage figure reads, and small enough to store in JSON.
ISOTONIC_KNOTS = 512

# How far past [0, 1] a float32 distribution function may round.
_ROUNDING = 1e-4


def _pit_array(pit, name: str) -> np.ndarray:
    """`pit` as a float64 `(pixels, columns)` array of finite values in [0, 1]."""
    values = np.asarray(pit, np.float64)
    if values.ndim == 1:
        values = values[:, None]
    if values.ndim != 2:
        raise ValueError(f"{name} must have shape (pixels,) or (pixels, channels), got {values.shape}")
    # A float32 sum of coefficients may round a little past 1: that much is clipped.
    if not np.all(np.isfinite(values)) or np.any(values < -_ROUNDING) or np.any(values > 1 + _ROUNDING):
        bad = values[~(np.isfinite(values) & (values >= -_ROUNDING) & (values <= 1 + _ROUNDING))]
        raise ValueError(f"{name} must hold distribution-function values in [0, 1], got {bad.ravel()[0]}")
    return np.clip(values, 0.0, 1.0)


def _check_masses(masses: Sequence[float]) -> tuple[float, ...]:
    if isinstance(masses, str) or not isinstance(masses, Sequence) or not masses:
        raise ValueError(f"masses must be a non-empty sequence of interval masses, got {masses!r}")
    out = tuple(float(mass) for mass in masses)
    bad = [mass for mass in out if not 0.0 < mass < 1.0]
    if bad:
        raise ValueError(f"interval masses must lie in (0, 1), got {bad[0]:g}")
    return out


def minimum_calibration_pixels(mass: float) -> int:
    """The fewest calibration pixels that give the conformal interval of `mass` two bounded
    ends: both order statistics fall inside `1..n` from `(n + 1)(1 - mass) / 2 >= 1` on, that
    is `n >= 2 / (1 - mass) - 1`."""
    return max(1, math.ceil(2.0 / (1.0 - mass) - 1.0 - 1e-9))


def _ranks(count: int, mass: float) -> tuple[int, int]:
    """The 1-based ranks of the equal-tailed interval's ends among `count` calibration values."""
    return (
        math.floor((count + 1) * (1.0 - mass) / 2.0 + 1e-9),
        math.ceil((count + 1) * (1.0 + mass) / 2.0 - 1e-9),
    )


def conformal_levels(pit, masses: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The raw quantile levels `(lower, upper)` of the equal-tailed split-conformal interval of
    each nominal mass, per column of `pit` (each of shape `(masses, columns)`): the
    `floor((n + 1)(1 - m) / 2)`-th and `ceil((n + 1)(1 + m) / 2)`-th smallest PIT values."""
    values = _pit_array(pit, "pit")
    masses = _check_masses(masses)
    count = values.shape[0]
    needed = max(minimum_calibration_pixels(mass) for mass in masses)
    if count < needed:
        raise ValueError(
            f"{count} calibration pixels are too few for conformal intervals of mass {max(masses):g}: at least "
            f"{needed} are needed; calibrate on more validation views or pixels, or ask for smaller masses"
        )
    ordered = np.sort(values, axis=0)
    ends = [_ranks(count, mass) for mass in masses]
    # `count >= needed` puts both ranks in 1..count; a rank of 0 would index the largest value.
    assert all(1 <= low and high <= count for low, high in ends), (count, masses, ends)
    return np.stack([ordered[low - 1] for low, _ in ends]), np.stack([ordered[high - 1] for _, high in ends])


@dataclasses.dataclass(frozen=True)
class IsotonicMap:
    """A monotone map `A` of predicted levels to calibrated ones, per column (channel), linear
    between knots: `A(knots[c, k]) = targets[k]`, from `A(0) = 0` to `A(1) = 1`."""

    knots: np.ndarray  # (columns, K + 2), non-decreasing along the last axis
    targets: np.ndarray  # (K + 2,), strictly increasing from 0 to 1

    @staticmethod
    def fit(pit, knots: int = ISOTONIC_KNOTS) -> "IsotonicMap":
        """The isotonic regression of the empirical frequencies on the levels of `pit`."""
        values = _pit_array(pit, "pit")
        if values.shape[0] < 2:
            raise ValueError(f"isotonic recalibration needs at least 2 calibration pixels, got {values.shape[0]}")
        inner = np.linspace(0.0, 1.0, min(knots, values.shape[0]) + 2)[1:-1]
        quantiles = np.quantile(values, inner, axis=0).T  # (columns, K)
        columns = values.shape[1]
        points = np.concatenate([np.zeros((columns, 1)), quantiles, np.ones((columns, 1))], axis=1)
        return IsotonicMap(knots=np.maximum.accumulate(points, axis=1), targets=np.concatenate([[0.0], inner, [1.0]]))

    @property
    def columns(self) -> int:
        return self.knots.shape[0]

    def __call__(self, pit) -> np.ndarray:
        """`A(u)` per column of `pit` (shape `(pixels, columns)`)."""
        values = _pit_array(pit, "pit")
        return np.stack([np.interp(values[:, c], self.knots[c], self.targets) for c in range(values.shape[1])], 1)

    def inverse(self, level: float) -> np.ndarray:
        """The raw level `p` with `A(p) = level`, per column."""
        return np.array([np.interp(level, self.targets, self.knots[c]) for c in range(self.columns)])

    def log_slope(self, pit) -> np.ndarray:
        """`log A'(u)` per pixel and column: the log factor that the calibrated density
        `A'(F(y)) f(y)` puts on the raw one. Knots that several quantiles share (an atom of
        the calibration PIT values, such as values rounded to 1) are merged: `A` jumps there,
        and a `u` on such a knot takes the slope of the segment after it (the last one: before
        it), the continuous part of `A` on either side."""
        values = _pit_array(pit, "pit")
        out = np.empty_like(values)
        for c in range(values.shape[1]):
            knots, first = np.unique(self.knots[c], return_index=True)
            last = np.unique(self.knots[c][::-1], return_index=True)[1]
            last = self.knots.shape[1] - 1 - last
            # The segment from knot k to k + 1 rises from A's value as it leaves k (the largest
            # target there) to its value as it reaches k + 1 (the smallest).
            slope = (self.targets[first[1:]] - self.targets[last[:-1]]) / np.diff(knots)
            segment = np.clip(np.searchsorted(knots, values[:, c], side="right") - 1, 0, slope.size - 1)
            out[:, c] = np.log(slope[segment])
        return out


def calibration_error(pit) -> np.ndarray:
    """FlipNeRF's calibration error per column: with the PIT values sorted, the mean squared
    gap between each value `p` and the fraction of values at or below it."""
    values = np.sort(_pit_array(pit, "pit"), axis=0)
    count = values.shape[0]
    errors = []
    for c in range(values.shape[1]):
        column = values[:, c]
        at_or_below = np.searchsorted(column, column, side="right") / count
        errors.append(float(np.mean((column - at_or_below) ** 2)))
    return np.asarray(errors)


@dataclasses.dataclass(frozen=True)
class Recalibration:
    """How a model's intervals and distribution functions are recalibrated, and on what.

    **Fields:**

    - `method`: `"raw"` (the model's own), `"isotonic"` or `"conformal"`.
    - `masses`: the nominal interval masses.
    - `colour_lower`, `colour_upper`: `(masses, channels)` raw quantile levels of each interval.
    - `depth_lower`, `depth_upper`: `(masses,)` the same for the termination distance.
    - `colour_map`, `depth_map`: the isotonic maps (`None` unless isotonic; the depth's also
      `None` where no true depth was known).
    - `pixels`, `depth_pixels`: how many calibration pixels (with a known depth) it was fitted on.
    - `fitted_on`: a line saying which views.
    """

    method: str
    masses: tuple[float, ...]
    colour_lower: np.ndarray
    colour_upper: np.ndarray
    depth_lower: np.ndarray
    depth_upper: np.ndarray
    colour_map: IsotonicMap | None = None
    depth_map: IsotonicMap | None = None
    pixels: int = 0
    depth_pixels: int = 0
    fitted_on: str = "nothing: the model's own intervals"

    @staticmethod
    def raw(masses: Sequence[float] = DEFAULT_MASSES, channels: int = 3) -> "Recalibration":
        masses = _check_masses(masses)
        lower = 0.5 * (1.0 - np.asarray(masses))
        upper = 0.5 * (1.0 + np.asarray(masses))
        return Recalibration(
            "raw", masses, np.repeat(lower[:, None], channels, 1), np.repeat(upper[:, None], channels, 1), lower, upper
        )

    @staticmethod
    def fit(
        method: str,
        colour_pit,
        depth_pit=None,
        masses: Sequence[float] = DEFAULT_MASSES,
        *,
        fitted_on: str = "calibration pixels",
    ) -> "Recalibration":
        """Fits `method` on calibration pixels' PIT values: `colour_pit` of shape `(pixels,
        channels)`, and `depth_pit` of shape `(pixels,)` where true depths are known (the
        depth intervals stay raw without them, or with fewer than the masses need: see
        `depth_pixels`)."""
        if method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
        masses = _check_masses(masses)
        colour = _pit_array(colour_pit, "colour_pit")
        depth = None if depth_pit is None else _pit_array(depth_pit, "depth_pit")
        if colour.shape[0] == 0:
            raise ValueError("no calibration pixels: calibrate on at least one validation view")
        raw = Recalibration.raw(masses, colour.shape[1])
        if method == "raw":
            return dataclasses.replace(raw, pixels=colour.shape[0], fitted_on=fitted_on)
        depth_count = 0 if depth is None else depth.shape[0]
        if method == "isotonic":
            colour_map = IsotonicMap.fit(colour)
            depth_map = IsotonicMap.fit(depth) if depth_count >= 2 else None
            colour_lower = np.stack([colour_map.inverse(0.5 * (1 - m)) for m in masses])
            colour_upper = np.stack([colour_map.inverse(0.5 * (1 + m)) for m in masses])
            depth_lower, depth_upper = raw.depth_lower, raw.depth_upper
            if depth_map is not None:
                depth_lower = np.array([depth_map.inverse(0.5 * (1 - m))[0] for m in masses])
                depth_upper = np.array([depth_map.inverse(0.5 * (1 + m))[0] for m in masses])
        else:
            colour_map = depth_map = None
            colour_lower, colour_upper = conformal_levels(colour, masses)
            depth_lower, depth_upper = raw.depth_lower, raw.depth_upper
            if depth_count and depth_count >= max(minimum_calibration_pixels(m) for m in masses):
                depth_lower, depth_upper = (end[:, 0] for end in conformal_levels(depth, masses))
        # A level of 0 or 1 is an end without bound (`IntervalLevels`): a conformal end whose
        # order statistic is a calibration truth outside the distribution's support (a PIT
        # value of 0 or 1) must cover such truths too.
        clip = lambda x: np.clip(x, 0.0, 1.0)  # noqa: E731
        return Recalibration(
            method,
            masses,
            clip(colour_lower),
            clip(colour_upper),
            clip(depth_lower),
            clip(depth_upper),
            colour_map,
            depth_map,
            pixels=colour.shape[0],
            depth_pixels=depth_count,
            fitted_on=fitted_on,
        )

    def unbounded_masses(self) -> dict[str, list[float]]:
        """The masses whose colour (any channel) or depth interval has an end without bound
        (`IntervalLevels`): more of the calibration truths lay beyond that end of the
        predictive distribution's support (PIT values of 0 or 1) than the end may miss."""
        colour = (self.colour_lower <= 0).any(axis=1) | (self.colour_upper >= 1).any(axis=1)
        depth = (self.depth_lower <= 0) | (self.depth_upper >= 1)
        return {
            "colour": [mass for mass, full in zip(self.masses, colour) if full],
            "depth": [mass for mass, full in zip(self.masses, depth) if full],
        }

    def interval_levels(self) -> IntervalLevels:
        """The levels `predict_rays` and `summarise` bound the intervals with."""
        return IntervalLevels(
            masses=self.masses,
            colour_lower=jnp.asarray(self.colour_lower, jnp.float32),
            colour_upper=jnp.asarray(self.colour_upper, jnp.float32),
            depth_lower=jnp.asarray(self.depth_lower, jnp.float32),
            depth_upper=jnp.asarray(self.depth_upper, jnp.float32),
        )

    def calibrated_pit(self, colour_pit) -> np.ndarray:
        """The recalibrated distribution function at the truths: `A(u)` for isotonic; the PIT
        values unchanged otherwise (conformal moves intervals, not the distribution)."""
        values = _pit_array(colour_pit, "colour_pit")
        return self.colour_map(values) if self.colour_map is not None else values

    def to_json(self) -> dict:
        def listed(x):
            return None if x is None else np.asarray(x).tolist()

        return {
            "method": self.method,
            "masses": list(self.masses),
            "colour_lower": listed(self.colour_lower),
            "colour_upper": listed(self.colour_upper),
            "depth_lower": listed(self.depth_lower),
            "depth_upper": listed(self.depth_upper),
            "colour_map": None if self.colour_map is None else {"knots": listed(self.colour_map.knots), "targets": listed(self.colour_map.targets)},
            "depth_map": None if self.depth_map is None else {"knots": listed(self.depth_map.knots), "targets": listed(self.depth_map.targets)},
            "pixels": self.pixels,
            "depth_pixels": self.depth_pixels,
            "fitted_on": self.fitted_on,
        }

    @staticmethod
    def from_json(data: dict | str) -> "Recalibration":
        data = json.loads(data) if isinstance(data, str) else data

        def isotonic(entry):
            return None if entry is None else IsotonicMap(np.asarray(entry["knots"]), np.asarray(entry["targets"]))

        return Recalibration(
            data["method"],
            tuple(data["masses"]),
            np.asarray(data["colour_lower"]),
            np.asarray(data["colour_upper"]),
            np.asarray(data["depth_lower"]),
            np.asarray(data["depth_upper"]),
            isotonic(data["colour_map"]),
            isotonic(data["depth_map"]),
            int(data["pixels"]),
            int(data["depth_pixels"]),
            data["fitted_on"],
        )
