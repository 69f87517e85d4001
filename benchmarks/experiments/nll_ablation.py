"""Why MixNeRF trails the mip-NeRF baseline after short runs: which part of the loss costs what.

    python benchmarks/nll_ablation.py [--config configs/builtin.toml] [--variants ...] [section.key=value ...]

Trains the same config (same seed, same steps) with parts of the MixNeRF objective switched
off or changed, and reports the test PSNR / SSIM / depth error of each. Along the way it
records, on a fixed batch of training rays rendered deterministically, how the density and
the opacity develop (median and 90th percentile of the coarse samples' density, mean
accumulated opacity, fine MSE), which shows what the strongly weighted colour NLL of the
first steps (lambda_C from 4.0) does to the geometry. Each run is the library's
`mx.training.init_train_state` and `mx.training.make_train_step`, driven step by step here.

Variants:

- `mixnerf`: the config as it is (all three NLL terms).
- `colour_only`: lambda_D = lambda_hat_C = 0.
- `nll_early_only`: colour NLL only during the lambda_C ramp (its end value set to 0).
- `nll_early_reset_adam`: as `nll_early_only`, and Adam's moments are reset when the ramp
  ends (tests whether the early gradients act through the optimiser's state).
- `mixnerf_noclip`: the config without the gradient clipping.
- `mipnerf`, `mipnerf_noclip`: the baseline (`method = "mipnerf"`), with and without clipping.

Writes `benchmarks/results/nll_ablation_<backend>.json` unless `--out` says otherwise.
"""

import argparse
import time
import sys
from pathlib import Path

import equinox as eqx
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # harness.py, one floor up

import harness  # noqa: E402
import jax
import jax.numpy as jnp
import optax

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset

NO_CLIP = ["optim.grad_max_norm=0.0", "optim.grad_max_value=0.0"]
EARLY_ONLY = ["loss.lambda_colour_end=0.0", "loss.lambda_depth=0.0", "loss.lambda_regen=0.0"]
VARIANTS = {  # name: (overrides, reset Adam's moments when the lambda_C ramp ends)
    "mixnerf": ([], False),
    "colour_only": (["loss.lambda_depth=0.0", "loss.lambda_regen=0.0"], False),
    "nll_early_only": (EARLY_ONLY, False),
    "nll_early_reset_adam": (EARLY_ONLY, True),
    "mixnerf_noclip": (NO_CLIP, False),
    "mipnerf": (["method=mipnerf"], False),
    "mipnerf_noclip": (["method=mipnerf", *NO_CLIP], False),
}
PROBE_RAYS = 2048


def reset_adam(opt_state):
    """Adam's count and moments set to zero; the learning-rate schedule's count is kept."""

    def reset(part):
        if isinstance(part, optax.ScaleByAdamState):
            zeros = jax.tree_util.tree_map(jnp.zeros_like, (part.mu, part.nu))
            return optax.ScaleByAdamState(count=jnp.zeros_like(part.count), mu=zeros[0], nu=zeros[1])
        return part

    return jax.tree_util.tree_map(reset, opt_state, is_leaf=lambda x: isinstance(x, optax.ScaleByAdamState))


@eqx.filter_jit
def probe(model: mx.MixNeRF, batch: mx.training.Batch) -> dict[str, jax.Array]:
    outputs = model(batch.rays)
    density = outputs.coarse.field.density
    return {
        "density_median": jnp.median(density),
        "density_p90": jnp.quantile(density, 0.9),
        "opacity_mean": jnp.mean(outputs.coarse.acc),
        "mse_fine": jnp.mean((outputs.fine.rgb - batch.rgb) ** 2),
    }


def run_variant(args: argparse.Namespace, name: str) -> dict:
    extra, reset = VARIANTS[name]
    config = mx.load_config(args.config, [*args.overrides, *extra])
    dataset = load_dataset(config.data)
    data = mx.training.training_rays(dataset)
    state = mx.training.init_train_state(config, dataset)
    step_fn = mx.training.make_train_step(config, max_traces=1)
    draw = eqx.filter_jit(mx.training.draw_batch)
    # The probe's rays: drawn once, with a key of their own, the same for every variant.
    probe_batch = draw(data, eqx.tree_at(lambda s: s.key, state, jax.random.key(7)), PROBE_RAYS)
    max_steps = config.train.max_steps
    trace = []
    started = time.perf_counter()
    for step in range(max_steps + 1):
        if step in args.probe_steps or step == max_steps:
            trace.append({"step": step, **{k: float(v) for k, v in probe(state.model, probe_batch).items()}})
        if step == max_steps:
            break
        if reset and step == config.loss.lambda_colour_steps:
            state = eqx.tree_at(lambda s: s.opt_state, state, reset_adam(state.opt_state))
        state, _ = step_fn(state, draw(data, state, config.train.batch_size))
    seconds = time.perf_counter() - started
    evaluation = mx.evaluate(state.model, dataset, chunk=config.train.render_chunk, with_lpips=False)
    return {"variant": name, "steps": max_steps, "seconds": seconds, "test": evaluation.means, "trace": trace}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="configs/builtin.toml")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--probe-steps", type=int, nargs="+", default=[0, 10, 25, 50, 100, 200, 500])
    parser.add_argument(
        "--out", default=None, help="JSON path (default: results/nll_ablation_<backend>.json)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides for every variant, section.key=value")
    args = parser.parse_args()
    rows = []
    for name in args.variants:
        row = run_variant(args, name)
        rows.append(row)
        test = row["test"]
        depth = test.get("depth_mae")
        print(
            f"{name:22s} PSNR {test['psnr']:6.2f}  SSIM {test['ssim']:.3f}  depth MAE "
            f"{float('nan') if depth is None else depth:.3f}  ({row['seconds']:.0f} s)",
            flush=True,
        )
        for point in row["trace"]:
            print(
                f"    step {point['step']:5d}: density median {point['density_median']:.2e}, "
                f"p90 {point['density_p90']:.3f}, opacity {point['opacity_mean']:.3f}, "
                f"MSE {point['mse_fine']:.4f}",
                flush=True,
            )
    out = Path(args.out) if args.out else harness.RESULTS / f"nll_ablation_{harness.platform_tag()}.json"
    harness.write_json(out, {"config": args.config, "overrides": args.overrides, "variants": rows})


if __name__ == "__main__":
    main()
