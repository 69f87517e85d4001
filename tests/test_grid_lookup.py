"""The batched grid lookup (`weighted_rows`, `encode_batch`, `GridField.evaluate_batch`) against
a float64 numpy reference and against the per-point formulation, values and gradients, on
every level, with points on cell borders, on the box's faces and outside it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import TINY_SHARED_OVERRIDES

import mixnerf_eqx as mx
from mixnerf_eqx.nn import GridField, HashEncoding, TriPlaneEncoding
from mixnerf_eqx._nn.field._lookup import resolve_lookup, weighted_rows


def _float64(tree):
    return jax.tree_util.tree_map(lambda x: x.astype(jnp.float64) if eqx.is_inexact_array(x) else x, tree)


def _border_points(resolutions, seed):
    """Random points in [-1.2, 1.2]^3, then points whose coordinates sit exactly on the texel
    or cell borders of every level, on the box's faces and corners, and outside it."""
    rng = np.random.default_rng(seed)
    points = [rng.uniform(-1.2, 1.2, (24, 3))]
    for res in resolutions:
        # Texel centres of a tri-plane level (res - 1 intervals) and cell borders of a hash
        # level (res intervals), mixed with random coordinates.
        for intervals in (res - 1, res):
            ticks = -1.0 + 2.0 * np.arange(intervals + 1) / intervals
            on_border = rng.choice(ticks, (6, 3))
            on_border[:3, 1:] = rng.uniform(-1, 1, (3, 2))
            points.append(on_border)
    points.append(
        np.array(
            [
                [1.0, 1.0, 1.0],
                [-1.0, -1.0, -1.0],
                [1.0, -0.3, 0.2],
                [-1.0, 0.5, 1.0],
                [1.5, 0.0, -2.0],
                [0.0, -1.0000001, 0.3],
            ]
        )
    )
    return np.concatenate(points)


def _np_weighted_rows(table, indices, weights, cotangent):
    """Values and both gradients of `sum_k w[k] * table[i[k]]` in float64, written directly."""
    table, weights, cotangent = (np.asarray(a, np.float64) for a in (table, weights, cotangent))
    indices = np.asarray(indices)
    values = np.einsum("kn,knf->nf", weights, table[indices])
    table_grad = np.zeros_like(table)
    for k in range(indices.shape[0]):
        np.add.at(table_grad, indices[k], weights[k][:, None] * cotangent)
    weights_grad = np.einsum("knf,nf->kn", table[indices], cotangent)
    return values, table_grad, weights_grad


def test_weighted_rows_matches_a_float64_reference_with_shared_rows():
    rng = np.random.default_rng(0)
    table = rng.normal(size=(7, 5)).astype(np.float32)
    # 300 points reading 4 rows each of a 7-row table: every row is shared many times.
    indices = rng.integers(0, 7, (4, 300)).astype(np.int32)
    weights = rng.uniform(-1, 1, (4, 300)).astype(np.float32)
    cotangent = rng.normal(size=(300, 5)).astype(np.float32)

    def loss(table, weights):
        return jnp.sum(weighted_rows(table, jnp.asarray(indices), weights) * cotangent)

    values = weighted_rows(jnp.asarray(table), jnp.asarray(indices), jnp.asarray(weights))
    table_grad, weights_grad = jax.grad(loss, argnums=(0, 1))(jnp.asarray(table), jnp.asarray(weights))
    want_values, want_table, want_weights = _np_weighted_rows(table, indices, weights, cotangent)
    np.testing.assert_allclose(values, want_values, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(table_grad, want_table, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(weights_grad, want_weights, rtol=1e-5, atol=1e-5)


def _both_formulations(encoding, points, cotangent):
    """Values and gradients (encoding parameters, points) of the per-point and the batched
    formulation, in float64."""

    def per_point(encoding, points):
        return jax.vmap(encoding)(points)

    def batched(encoding, points):
        return encoding.encode_batch(points)

    results = []
    for lookup in (per_point, batched):

        def total(encoding, points, lookup=lookup):
            return jnp.sum(lookup(encoding, points) * cotangent)

        grads = eqx.filter_jit(eqx.filter_grad(total))(encoding, points)
        point_grads = eqx.filter_jit(jax.grad(total, argnums=1))(encoding, points)
        results.append((eqx.filter_jit(lookup)(encoding, points), grads, point_grads))
    return results


@pytest.mark.parametrize("kind", ["triplane", "hash-dense", "hash-hashed"])
def test_batched_lookup_equals_the_per_point_lookup_in_float64(kind):
    with jax.enable_x64(True):
        key = jax.random.key(0)
        if kind == "triplane":
            encoding = TriPlaneEncoding((3, 5, 9), 4, key=key)
        elif kind == "hash-dense":
            encoding = HashEncoding((2, 3, 4), 3, 2**12, key=key)  # every level one to one
        else:
            encoding = HashEncoding((2, 6, 11), 3, 64, key=key)  # the finer levels hashed
        # Features well away from zero, so that products and gradients are all exercised.
        encoding = jax.tree_util.tree_map(
            lambda x: jax.random.normal(jax.random.key(x.size), x.shape) if eqx.is_inexact_array(x) else x,
            encoding,
        )
        encoding = _float64(encoding)
        points = jnp.asarray(_border_points(encoding.resolutions, seed=1), jnp.float64)
        shape = (points.shape[0], encoding.num_levels, encoding.features_per_level)
        cotangent = jax.random.normal(jax.random.key(7), shape, jnp.float64)
        (plain, plain_grads, plain_points), (fast, fast_grads, fast_points) = _both_formulations(
            encoding, points, cotangent
        )
        assert fast.dtype == jnp.float64
        np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=1e-12)
        for got, want in zip(
            jax.tree_util.tree_leaves(eqx.filter(fast_grads, eqx.is_array)),
            jax.tree_util.tree_leaves(eqx.filter(plain_grads, eqx.is_array)),
            strict=True,
        ):
            assert np.abs(want).max() > 0  # every level receives gradient
            np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-11)
        np.testing.assert_allclose(fast_points, plain_points, rtol=1e-11, atol=1e-11)
        # Outside the box the clamp stops the points' gradient in both formulations.
        outside = np.any(np.abs(np.asarray(points)) > 1, axis=-1)
        assert np.all(np.asarray(fast_points)[outside][np.abs(np.asarray(points))[outside] > 1] == 0)


def _grid_field(encoding, lookup, mixture_heads=True):
    return GridField(
        encoding,
        box_min=(-1.0, -2.0, -0.5),
        box_max=(1.0, 2.0, 1.5),
        bounded=True,
        scale_weighting=True,
        density_noise=1.0,
        density_activation="exp",
        mixture_heads=mixture_heads,
        lookup=lookup,
        key=jax.random.key(3),
    )


@pytest.mark.parametrize("encoding_kind", ["triplane", "hash"])
def test_grid_field_batched_equals_vmap_with_noise_and_gradients(encoding_kind):
    with jax.enable_x64(True):
        key = jax.random.key(2)
        encoding = (
            TriPlaneEncoding((4, 8), 3, key=key)
            if encoding_kind == "triplane"
            else HashEncoding((3, 7), 3, 64, key=key)
        )
        fields = {lookup: _float64(_grid_field(encoding, lookup)) for lookup in ("vmap", "batched")}
        assert fields["vmap"].lookup == "vmap" and fields["batched"].lookup == "batched"
        rng = np.random.default_rng(4)
        count = 64
        means = jnp.asarray(rng.uniform([-1.2, -2.2, -0.7], [1.2, 2.2, 1.7], (count, 3)))
        covs = jnp.asarray(rng.uniform(1e-4, 1e-2, (count, 3)))
        viewdirs = rng.normal(size=(count, 3))
        viewdirs = jnp.asarray(viewdirs / np.linalg.norm(viewdirs, axis=-1, keepdims=True))
        keys = jax.random.split(jax.random.key(5), count)

        def total(field, keys):
            outputs = field.evaluate_batch(means, covs, viewdirs, keys)
            return sum(jnp.sum(jnp.sin(leaf)) for leaf in jax.tree_util.tree_leaves(outputs))

        evaluate = eqx.filter_jit(lambda f, k: f.evaluate_batch(means, covs, viewdirs, k))
        gradient = eqx.filter_jit(eqx.filter_grad(total))
        for keys_or_none in (keys, None):
            values = {k: evaluate(f, keys_or_none) for k, f in fields.items()}
            leaves = {k: jax.tree_util.tree_leaves(v) for k, v in values.items()}
            for got, want in zip(leaves["batched"], leaves["vmap"], strict=True):
                np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
            grads = {k: gradient(f, keys_or_none) for k, f in fields.items()}
            for got, want in zip(
                jax.tree_util.tree_leaves(eqx.filter(grads["batched"], eqx.is_array)),
                jax.tree_util.tree_leaves(eqx.filter(grads["vmap"], eqx.is_array)),
                strict=True,
            ):
                np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_lookup_choice_per_backend_and_bad_names():
    assert resolve_lookup("auto", "cpu") == "batched"
    assert resolve_lookup("auto", "gpu") == "vmap"
    assert resolve_lookup("auto", "tpu") == "vmap"
    assert resolve_lookup("vmap", "cpu") == "vmap"
    assert resolve_lookup("batched", "gpu") == "batched"
    with pytest.raises(ValueError, match="grid.lookup must be one of auto, vmap, batched"):
        resolve_lookup("fast", "cpu")


def test_the_model_uses_the_fields_batched_evaluation(tiny_scene):
    overrides = [
        *TINY_SHARED_OVERRIDES,
        "model.field=grid",
        "grid.levels=2",
        "grid.min_resolution=8",
        "grid.max_resolution=16",
        "grid.features=4",
        "grid.box_radius=1.3",
    ]
    outputs = {}
    for lookup in ("vmap", "batched"):
        config = mx.load_config("builtin", [*overrides, f'grid.lookup="{lookup}"'])
        model = mx.training.init_train_state(config, tiny_scene).model
        assert model.field.lookup == lookup
        rays = mx.training.training_rays(tiny_scene).rays[0, :16]
        outputs[lookup] = eqx.filter_jit(lambda m, r: m(r, key=jax.random.key(0)))(model, rays)
    for got, want in zip(
        jax.tree_util.tree_leaves(outputs["batched"]), jax.tree_util.tree_leaves(outputs["vmap"]), strict=True
    ):
        np.testing.assert_allclose(got, want, rtol=2e-4, atol=2e-5)
