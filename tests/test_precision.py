"""Mixed precision: the field's matrix products in bfloat16, everything after them float32."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mixnerf_eqx._nn.field.mip_mlp import MipNeRFField
from mixnerf_eqx._runs.loop import fit

# One bfloat16 product of a 32-wide layer rounds its inputs and kernel to 8 bits of mantissa
# (relative 2^-9 each) and accumulates in float32: ~sqrt(32) * 2^-8 of the typical |term|.
# Through the small untrained network below the outputs move by at most a few 1e-3; measured
# worst 4e-3 (density), so 2e-2 is a clear bound yet far below the outputs' own size (~0.5).
FIELD_ATOL = 2e-2
# Held-out PSNR after 150 steps of the tiny scene, bfloat16 minus float32 (same seed), measured:
# seed 0: 12.561 vs 13.056 dB (-0.50), seed 1: 13.246 vs 13.257 (-0.01), seed 2: 12.383 vs
# 12.334 (+0.05). Float32 alone spreads over 0.92 dB across those seeds, so a 1.0 dB bound is
# about twice the worst measured gap and the size of the seed noise: it catches a broken bf16
# path (which loses many dB) without flagging the rounding.
PSNR_TOLERANCE_DB = 1.0


def _field(matmul_dtype):
    return MipNeRFField(
        width=32,
        depth=3,
        view_width=16,
        skip_layer=1,
        max_deg=8,
        matmul_dtype=matmul_dtype,
        key=jax.random.key(0),
    )


def test_bfloat16_field_outputs_are_float32_and_close():
    key = jax.random.key(1)
    means = jax.random.uniform(key, (64, 3), minval=-1.0, maxval=1.0)
    covs = jnp.full((64, 3), 1e-4)
    viewdirs = jnp.tile(jnp.asarray([0.0, 0.6, 0.8]), (64, 1))
    full = jax.vmap(_field("float32"))(means, covs, viewdirs)
    # The same parameters: the dtype is a static switch, not a different initialisation.
    mixed_field = _field("bfloat16")
    mixed = jax.vmap(mixed_field)(means, covs, viewdirs)
    for name in ("density", "rgb", "beta", "ray_depth"):
        value, reference = getattr(mixed, name), getattr(full, name)
        assert value.dtype == jnp.float32, name
        assert bool(jnp.all(jnp.isfinite(value))), name
        np.testing.assert_allclose(
            np.asarray(value), np.asarray(reference), rtol=0, atol=FIELD_ATOL, err_msg=name
        )
    # And the products really are rounded: bit-identical outputs would mean bf16 is not in use.
    assert not np.array_equal(np.asarray(mixed.rgb), np.asarray(full.rgb))
    grads = jax.grad(lambda f: jnp.sum(jax.vmap(f)(means, covs, viewdirs).rgb))(mixed_field)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(leaf.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(leaf))) for leaf in leaves)


def test_unknown_matmul_dtype_is_rejected():
    # The jaxtyping hook rejects it at the annotation (in tests); without it, `__init__` does.
    with pytest.raises((TypeError, ValueError), match="matmul_dtype"):
        _field("float16")


@pytest.mark.slow
def test_bfloat16_training_matches_float32_psnr(tiny_config, tiny_scene):
    psnr = {}
    for matmul_dtype in ("float32", "bfloat16"):
        config = dataclasses.replace(
            tiny_config,
            mlp=dataclasses.replace(tiny_config.mlp, matmul_dtype=matmul_dtype),
            train=dataclasses.replace(
                tiny_config.train, run_dir=f"{tiny_config.train.run_dir}_{matmul_dtype}"
            ),
        )
        result = fit(config, dataset=tiny_scene, progress=False, write_renders=False)
        assert result.metrics["skipped_steps"] == 0
        psnr[matmul_dtype] = result.metrics["test"]["psnr"]
    assert abs(psnr["bfloat16"] - psnr["float32"]) <= PSNR_TOLERANCE_DB, psnr
