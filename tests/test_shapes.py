"""Shape and dtype contracts: a wrong argument fails while tracing, naming the argument."""

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import pytest
from helpers import make_ray
from jaxtyping import TypeCheckError

from mixnerf_eqx.nn import FieldOutputs, LaplaceMixture, RayBundle, VolumeRenderer, blend_weights, composite_rgb, frustum_gaussians, positional_encoding


def _ones(*shape, dtype=jnp.float32):
    return jnp.ones(shape, dtype)


def _edges(n):
    return jnp.linspace(2.0, 6.0, n)


def _ray_bundle(batch=4, **overrides):
    fields = dict(
        origins=_ones(batch, 3),
        directions=_ones(batch, 3),
        viewdirs=_ones(batch, 3),
        radii=_ones(batch, 1),
        near=_ones(batch, 1),
        far=_ones(batch, 1),
    )
    fields.update(overrides)
    return RayBundle(**fields)


def _blamed_argument(excinfo) -> str:
    """The argument the checker reports as the problem (not just any name in the message)."""
    match = re.search(r"typechecking parameter '(\w+)'", str(excinfo.value))
    assert match is not None, str(excinfo.value)
    return match.group(1)


mixture = LaplaceMixture()

# (description, call, the argument that must be blamed)
BAD_CALLS = [
    ("edges not one longer", lambda: blend_weights(_ones(5), _edges(5), jnp.float32(1.0)), "t_edges"),
    ("edges longer by two", lambda: blend_weights(_ones(5), _edges(7), jnp.float32(1.0)), "t_edges"),
    ("per-sample scale too short", lambda: blend_weights(_ones(5), _edges(6), _ones(4)), "step_scale"),
    ("density of rank 2", lambda: blend_weights(_ones(5, 1), _edges(6), jnp.float32(1.0)), "density"),
    (
        "integer density",
        lambda: blend_weights(_ones(5, dtype=jnp.int32), _edges(6), jnp.float32(1.0)),
        "density",
    ),
    ("ray batch mismatch", lambda: _ray_bundle(directions=_ones(5, 3)), "directions"),
    ("ray radii not (..., 1)", lambda: _ray_bundle(radii=_ones(4)), "radii"),
    ("integer ray origins", lambda: _ray_bundle(origins=_ones(4, 3, dtype=jnp.int32)), "origins"),
    (
        "four-channel rgb, three-channel background",
        lambda: composite_rgb(_ones(5), _ones(5, 4), _ones(3)),
        "background",
    ),
    ("rgb sample count mismatch", lambda: composite_rgb(_ones(5), _ones(4, 3)), "rgb"),
    (
        "beta sample count mismatch",
        lambda: mixture.colour_nll(_ones(5), _ones(5, 3), _ones(4, 3), _ones(3)),
        "beta",
    ),
    (
        "target channels mismatch",
        lambda: mixture.colour_nll(_ones(5), _ones(5, 3), _ones(5, 3), _ones(4)),
        "target",
    ),
    (
        "depth target not a scalar",
        lambda: mixture.depth_nll(_ones(5), _ones(5), _ones(5, 3), _ones(1)),
        "target",
    ),
    (
        "ray depth count mismatch",
        lambda: mixture.depth_nll(_ones(5), _ones(6), _ones(5, 3), _ones()),
        "ray_depth",
    ),
    (
        "integer weights",
        lambda: mixture.colour_nll(jnp.ones(5, jnp.int32), _ones(5, 3), _ones(5, 3), _ones(3)),
        "weights",
    ),
    ("scalar radius", lambda: frustum_gaussians(_edges(6), _ones(3), _ones(3), _ones(), "cone"), "radius"),
    ("2D direction", lambda: frustum_gaussians(_edges(6), _ones(3), _ones(2), _ones(1), "cone"), "direction"),
    ("encoding of a scalar", lambda: positional_encoding(_ones(), 0, 4), "x"),
    (
        "field outputs mismatch",
        lambda: FieldOutputs(density=_ones(5), rgb=_ones(4, 3), beta=None, ray_depth=None),
        "rgb",
    ),
]


@pytest.mark.parametrize("description, call, argument", BAD_CALLS, ids=[c[0] for c in BAD_CALLS])
def test_bad_call_names_the_argument(description, call, argument):
    with pytest.raises(TypeCheckError) as excinfo:
        call()
    assert _blamed_argument(excinfo) == argument


def test_bad_shapes_fail_at_trace_time_under_jit():
    # Lowering traces without compiling or running: the failure happens during the trace.
    with pytest.raises(TypeCheckError) as excinfo:
        jax.jit(blend_weights).lower(_ones(5), _edges(5), jnp.float32(1.0))
    assert _blamed_argument(excinfo) == "t_edges"
    with pytest.raises(TypeCheckError) as excinfo:
        jax.jit(blend_weights).lower(_ones(5, dtype=jnp.int32), _edges(6), jnp.float32(1.0))
    assert _blamed_argument(excinfo) == "density"
    with pytest.raises(TypeCheckError) as excinfo:
        eqx.filter_jit(mixture.colour_nll)(_ones(5), _ones(5, 3), _ones(4, 3), _ones(3))
    assert _blamed_argument(excinfo) == "beta"


def test_bad_shapes_fail_inside_vmap_and_jit():
    # A batch of rays whose per-ray edges have the wrong length: vmap strips the batch and
    # the per-ray contract still applies.
    batched = jax.jit(jax.vmap(blend_weights, in_axes=(0, 0, None)))
    with pytest.raises(TypeCheckError) as excinfo:
        batched(_ones(3, 5), jnp.ones((3, 5)), jnp.float32(1.0))
    assert _blamed_argument(excinfo) == "t_edges"


def test_renderer_rejects_mismatched_edges_under_jit():
    outputs = FieldOutputs(density=_ones(5), rgb=_ones(5, 3), beta=None, ray_depth=None)
    render = eqx.filter_jit(VolumeRenderer())
    with pytest.raises(TypeCheckError) as excinfo:
        render(outputs, _edges(5), make_ray())
    assert _blamed_argument(excinfo) == "t_edges"


def test_correct_calls_pass_eagerly_and_under_jit():
    assert blend_weights(_ones(5), _edges(6), jnp.float32(1.0)).shape == (5,)
    assert blend_weights(_ones(5), _edges(6), _ones(5)).shape == (5,)
    assert jax.jit(blend_weights)(_ones(5), _edges(6), jnp.float32(1.0)).shape == (5,)
    assert _ray_bundle().batch_shape == (4,)
    assert composite_rgb(_ones(5), _ones(5, 3), _ones(3)).shape == (3,)
    assert eqx.filter_jit(mixture.colour_nll)(_ones(5), _ones(5, 3), _ones(5, 3), _ones(3)).shape == ()
    assert mixture.depth_nll(_ones(5), _ones(5), _ones(5, 3), _ones()).shape == ()
    means, covs = frustum_gaussians(_edges(6), _ones(3), _ones(3), _ones(1), "cone")
    assert means.shape == covs.shape == (5, 3)
    assert positional_encoding(_ones(3), 0, 4).shape == (3 + 2 * 3 * 4,)
    outputs = FieldOutputs(density=_ones(5), rgb=_ones(5, 3), beta=None, ray_depth=None)
    level = eqx.filter_jit(VolumeRenderer())(outputs, _edges(6), make_ray())
    assert level.rgb.shape == (3,) and level.depth.shape == ()


def test_one_switch_turns_the_checks_off_and_on():
    """`set_typecheck` (what `--no-typecheck` calls) is the only switch, and it acts at call time."""
    import mixnerf_eqx as mx

    assert mx.runtime.typecheck_enabled()
    bad = lambda: blend_weights(_ones(5), _edges(7), jnp.float32(1.0))  # noqa: E731
    try:
        mx.set_typecheck(False)
        assert not mx.runtime.typecheck_enabled()
        # Unchecked, the call runs into the shape mismatch inside the function instead.
        with pytest.raises(Exception) as excinfo:
            bad()
        assert not isinstance(excinfo.value, TypeCheckError)
    finally:
        mx.set_typecheck(True)
    with pytest.raises(TypeCheckError):
        bad()


def test_command_lines_take_no_typecheck():
    import mixnerf_eqx as mx
    from mixnerf_eqx._util.typecheck import typecheck_argument
    from mixnerf_eqx.cli.train import parse_args

    with typecheck_argument(parse_args(["--no-typecheck"])):
        assert not mx.runtime.typecheck_enabled()
    # The switch is restored after the command, so calling `main` from Python changes nothing.
    assert mx.runtime.typecheck_enabled()
    with typecheck_argument(parse_args([])):
        assert mx.runtime.typecheck_enabled()
