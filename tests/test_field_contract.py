"""One suite over every field: what `AbstractField` promises, checked on each implementation.

A new field is added to `FIELDS` (a name and the config overrides that build it through
`build_field`) and gets every test here. The tests that check a field's own numbers (float64
references of the lookups, the MLP's layers) stay in that field's test module.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mixnerf_eqx as mx
from mixnerf_eqx.nn import AbstractField, FieldOutputs, build_field
from mixnerf_eqx._nn.field.base import vmap_field
from mixnerf_eqx._nn.field.heads import MixtureHeads

SMALL_MLP = ["mlp.width=16", "mlp.depth=2", "mlp.skip_layer=1", "mlp.view_width=8", "mlp.max_deg=4"]
SMALL_GRID = ["grid.levels=3", "grid.min_resolution=4", "grid.max_resolution=16", "grid.features=4"]
SMALL_GRID += ["grid.decoder_width=16", "grid.view_width=8", "grid.coarse_to_fine_steps=20"]
# The batched lookup (the CPU's default) on every backend, so that the batch path is the
# grid's own formulation there too, not `vmap` of the point path.
SMALL_GRID += ['grid.lookup="batched"']
# name -> (packaged config, overrides). The unbounded grid spans the box given to `build_field`.
FIELDS = {
    "mlp": ("builtin", SMALL_MLP),
    "mlp-baseline": ("builtin_mipnerf", SMALL_MLP),
    "triplane": ("builtin_grid", SMALL_GRID),
    "triplane-baseline": ("builtin_mipnerf_grid", SMALL_GRID),
    "triplane-unbounded": (
        "builtin_grid",
        [*SMALL_GRID, "grid.box_radius=0", "grid.density_activation=softplus"],
    ),
    "hash": ("builtin_grid", [*SMALL_GRID, 'grid.encoding="hash"', "grid.hash_table_log2=6", "grid.tv_weight=0"]),
}
SCENE_BOX = ((-1.0, -0.5, -2.0), (1.5, 1.0, 0.5))
SCHEDULE_END = 20  # grid.coarse_to_fine_steps above; the MLP has no schedule


@pytest.fixture(scope="module", params=list(FIELDS))
def field(request) -> AbstractField:
    name, overrides = FIELDS[request.param]
    config = mx.load_config(name, overrides)
    built = build_field(config, key=jax.random.key(3), scene_box=SCENE_BOX)
    # Trained-looking parameters: the initial planes and tables are near zero, which would hide
    # differences between levels and between code paths. Arrays that `at_step` sets (a
    # schedule's, not parameters) keep their stored values.
    leaves, treedef = jax.tree_util.tree_flatten(eqx.filter(built, eqx.is_inexact_array))
    scheduled = jax.tree_util.tree_leaves(eqx.filter(built.at_step(1), eqx.is_inexact_array))
    keys = jax.random.split(jax.random.key(4), len(leaves))
    shaken = [
        leaf
        if not np.array_equal(leaf, at_first)
        else leaf + 0.3 * jax.random.normal(k, leaf.shape, leaf.dtype)
        for leaf, at_first, k in zip(leaves, scheduled, keys, strict=True)
    ]
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, shaken), built)


def _points(count: int, seed: int = 0):
    """Gaussians inside the box, on its faces, just outside and far away, with small and
    large covariances, and unit view directions."""
    rng = np.random.default_rng(seed)
    inside = rng.uniform(-1.0, 1.0, (count, 3))
    on_faces = inside.copy()
    on_faces[:, 0] = np.where(rng.random(count) < 0.5, -1.3, 1.3)  # the bounded grids' box_radius
    outside = inside * 1.6
    far = inside * 1e3
    means = np.concatenate([inside, on_faces, outside, far]).astype(np.float32)
    covs = np.exp(rng.uniform(np.log(1e-8), np.log(1.0), means.shape)).astype(np.float32)
    viewdirs = rng.normal(size=means.shape)
    viewdirs = (viewdirs / np.linalg.norm(viewdirs, axis=-1, keepdims=True)).astype(np.float32)
    return jnp.asarray(means), jnp.asarray(covs), jnp.asarray(viewdirs)


def _at_steps(field):
    return [field, field.at_step(1), field.at_step(SCHEDULE_END // 2), field.at_step(jnp.asarray(7))]


def test_density_is_the_call_without_its_view_branch(field):
    means, covs, viewdirs = _points(8)
    for seen in _at_steps(field):
        density = jax.vmap(seen.density)(means, covs)
        for turn in range(3):
            rolled = jnp.roll(viewdirs, turn, axis=0)
            called = vmap_field(seen, means, covs, rolled).density
            np.testing.assert_allclose(density, called, rtol=1e-5, atol=1e-6)


def test_outputs_have_the_contracted_shapes_dtypes_and_ranges(field):
    means, covs, viewdirs = _points(8)
    for seen in _at_steps(field):
        single = seen(means[0], covs[0], viewdirs[0])
        assert isinstance(single, FieldOutputs)
        assert single.density.shape == () and single.rgb.shape == (3,)
        out = seen.evaluate_batch(means, covs, viewdirs)
        assert out.density.shape == (len(means),) and out.rgb.shape == (len(means), 3)
        assert out.density.dtype == out.rgb.dtype == jnp.float32
        assert np.all(np.isfinite(out.density)) and np.all(np.asarray(out.density) >= 0)
        assert np.all(np.isfinite(out.rgb))
        if seen.has_mixture_heads:
            assert out.beta.shape == (len(means), 3) and out.ray_depth.shape == (len(means),)
            assert np.all(np.asarray(out.beta) > 0) and np.all(np.isfinite(out.beta))
            assert np.all(np.asarray(out.ray_depth) >= 0) and np.all(np.isfinite(out.ray_depth))
        else:
            assert out.beta is None and out.ray_depth is None


def test_the_batch_path_equals_the_point_path(field):
    means, covs, viewdirs = _points(8, seed=1)
    keys = jax.random.split(jax.random.key(5), len(means))
    for seen in _at_steps(field):
        for point_keys in (None, keys):
            batched = seen.evaluate_batch(means, covs, viewdirs, point_keys)
            pointwise = vmap_field(seen, means, covs, viewdirs, point_keys)
            for a, b in zip(
                jax.tree_util.tree_leaves(batched), jax.tree_util.tree_leaves(pointwise), strict=True
            ):
                np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_randomness_only_with_a_key_and_only_in_the_density(field):
    means, covs, viewdirs = _points(8, seed=2)
    keys = jax.random.split(jax.random.key(6), len(means))
    plain = field.evaluate_batch(means, covs, viewdirs)
    again = field.evaluate_batch(means, covs, viewdirs)
    noisy = field.evaluate_batch(means, covs, viewdirs, keys)
    same_keys = field.evaluate_batch(means, covs, viewdirs, keys)
    for a, b in zip(jax.tree_util.tree_leaves(plain), jax.tree_util.tree_leaves(again), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(jax.tree_util.tree_leaves(noisy), jax.tree_util.tree_leaves(same_keys), strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(noisy.density, plain.density)  # every field here has density noise
    np.testing.assert_allclose(noisy.rgb, plain.rgb, rtol=1e-6, atol=1e-7)
    if field.has_mixture_heads:
        np.testing.assert_allclose(noisy.beta, plain.beta, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(jax.vmap(field.density)(means, covs), plain.density, rtol=1e-5, atol=1e-6)


def test_gradients_are_finite_inside_on_and_outside_the_box(field):
    means, covs, viewdirs = _points(8, seed=3)
    keys = jax.random.split(jax.random.key(7), len(means))

    def total(field, means, covs):
        out = field.at_step(SCHEDULE_END // 2).evaluate_batch(means, covs, viewdirs, keys)
        heads = 0.0 if out.beta is None else jnp.sum(jnp.log(out.beta)) + jnp.sum(out.ray_depth)
        return jnp.sum(out.density) + jnp.sum(out.rgb) + heads + field.regulariser()

    parameters, points, scales = (
        eqx.filter_grad(total)(field, means, covs),
        *jax.grad(total, (1, 2))(field, means, covs),
    )
    for leaf in jax.tree_util.tree_leaves(eqx.filter(parameters, eqx.is_array)):
        assert np.all(np.isfinite(leaf))
    assert np.all(np.isfinite(points)) and np.all(np.isfinite(scales))
    # Something is learnt from the points themselves (the regulariser aside).
    outputs_only = eqx.filter_grad(lambda f: total(f, means, covs) - f.regulariser())(field)
    assert any(
        np.any(leaf != 0) for leaf in jax.tree_util.tree_leaves(eqx.filter(outputs_only, eqx.is_array))
    )


def test_at_step_keeps_the_structure_ends_at_the_field_and_traces_once(field):
    means, covs, viewdirs = _points(4, seed=4)
    shapes = jax.tree_util.tree_map(jnp.shape, eqx.filter(field, eqx.is_array))
    for seen in _at_steps(field):
        assert type(seen) is type(field)
        assert jax.tree_util.tree_map(jnp.shape, eqx.filter(seen, eqx.is_array)) == shapes
    # From the end of its schedule on, the field seen in training is the stored field.
    for step in (SCHEDULE_END, 10 * SCHEDULE_END):
        ended, stored = (
            vmap_field(field.at_step(step), means, covs, viewdirs),
            vmap_field(field, means, covs, viewdirs),
        )
        for a, b in zip(jax.tree_util.tree_leaves(ended), jax.tree_util.tree_leaves(stored), strict=True):
            np.testing.assert_array_equal(a, b)

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def density_at(field, step):
        return jax.vmap(field.at_step(step).density)(means, covs)

    for step in range(1, 5):
        assert np.all(np.isfinite(density_at(field, jnp.asarray(step))))


def test_the_regulariser_is_a_finite_non_negative_scalar(field):
    for seen in _at_steps(field):
        value = seen.regulariser()
        assert value.shape == () and np.isfinite(value) and value >= 0
    gradient = eqx.filter_grad(lambda f: f.regulariser())(field)
    assert all(
        np.all(np.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(eqx.filter(gradient, eqx.is_array))
    )


def test_every_field_has_the_one_set_of_heads(field, request):
    """The colour, `beta` and ray-depth heads are one `MixtureHeads` in every field, with the
    mixture heads exactly where the config's method is MixNeRF."""
    heads = field.heads
    assert isinstance(heads, MixtureHeads)
    baseline = request.node.callspec.params["field"].endswith("-baseline")
    assert field.has_mixture_heads is heads.has_mixture is (not baseline)
    assert (heads.beta_head is None) is (heads.depth_head is None) is baseline
    # The heads compute the outputs from the raw density and the view features alone.
    features = jnp.linspace(-1.0, 1.0, heads.rgb_head.in_features)
    outputs = heads(jnp.asarray(0.5), features, None)
    rgb = 1 / (1 + np.exp(-(np.asarray(heads.rgb_head.weight) @ np.asarray(features) + heads.rgb_head.bias)))
    np.testing.assert_allclose(outputs.rgb, rgb * (1 + 2 * heads.rgb_padding) - heads.rgb_padding, rtol=1e-5)
    assert float(outputs.density) == pytest.approx(float(heads.density(jnp.asarray(0.5))))


def test_a_field_without_a_builder_is_refused():
    """`build_field` is a table of constructors: a field name without one is an error."""
    config = mx.load_config("builtin", SMALL_MLP)
    removed = mx.nn.FIELD_BUILDERS.pop("mlp")
    try:
        with pytest.raises(ValueError, match="model.field = 'mlp' is none of grid"):
            build_field(config, key=jax.random.key(0))
    finally:
        mx.nn.FIELD_BUILDERS["mlp"] = removed
