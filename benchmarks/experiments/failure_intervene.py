"""Which loss term fills the box: a run continued from one checkpoint with one setting changed.

Loads a checkpoint of a run (the state before the box fills), continues it with the run's own
step function and batches (the steps draw from the state's key, so the unchanged arm repeats
the run to the digit) under each variant's overrides, and prints every `--every` steps the
training-batch PSNR and the mean opacity on a fixed strided subset of the training views'
background and object pixels and of the validation views. The overrides change only the loss
(`loss.*`; `stop=beta` or `stop=weights` cuts the colour NLL's (NLL_C, eq. 7) gradient to the
scales or to the blending weights; the other NLLs keep theirs): the optimiser and its state
are the checkpoint's. The
probe renders as `failure_probe.py` does, and its PSNR is one squared error pooled over the
strided pixels.

    python benchmarks/experiments/failure_intervene.py --run runs/diag/np1 \
        --checkpoint runs/diag/keep_np1/step_00000400 --steps 160 --data-dir ../shared/data \
        --variant unchanged --variant "no depth NLL" loss.lambda_depth=0 ...
"""

import argparse
import contextlib
import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from failure_probe import as_trained

import mixnerf_eqx as mx
from mixnerf_eqx.config import config_from_dict, config_to_dict
from mixnerf_eqx.data import rays_for_views
from mixnerf_eqx.inference import render_rays
from mixnerf_eqx.training import (
    LossInputs,
    LossTerm,
    LossWeights,
    draw_batch,
    init_train_state,
    loss_term_names,
    make_train_step,
    register_loss_term,
    training_rays,
    unregister_loss_term,
)


def _library_terms(config) -> list[LossTerm]:
    """Every registered loss term, in the order the objective adds them up."""
    names = loss_term_names()
    every = LossWeights.from_config(config.loss, config.method).replace(**{name: 1.0 for name in names})
    return list(every.active())


def _register(terms: list[LossTerm]) -> None:
    for name in loss_term_names():
        unregister_loss_term(name)
    for term in terms:
        register_loss_term(term)


def _parse_variants(raw: list[list[str]]) -> list[tuple[str, list[str]]]:
    return [(items[0], items[1:]) for items in raw] or [("unchanged", [])]


def _colour_nll_stopping(stop: str):
    """The colour NLL (eq. 7) with the gradient to `stop` ("beta" or "weights") cut."""

    def compute(inputs: LossInputs):
        total = 0.0
        for level in inputs.nll_levels:  # (no background component in these runs)
            mixture, outputs = inputs.model.mixture, level.field
            weights = jax.lax.stop_gradient(level.weights) if stop == "weights" else level.weights
            beta = jax.lax.stop_gradient(outputs.beta) if stop == "beta" else outputs.beta
            rgb = outputs.rgb if inputs.weights.nll_trains_colour else jax.lax.stop_gradient(outputs.rgb)
            nll = jax.vmap(mixture.colour_nll)(weights, rgb, beta, inputs.target_rgb)
            total = total + jnp.mean(nll)
        return total

    return compute


def _with_overrides(config, overrides: list[str]):
    """The config with the `loss.*` overrides, and the colour NLL's computation this variant
    uses instead of the library's (`None`: the library's)."""
    values = config_to_dict(config)
    term = None
    for item in overrides:
        key, value = item.split("=", 1)
        if key == "stop":
            if value not in ("beta", "weights"):
                raise SystemExit(f"stop={value}: say stop=beta or stop=weights")
            if config.loss.background_component:
                raise SystemExit("stop=...: the cut NLL has no background component; this run has one")
            term = _colour_nll_stopping(value)
            continue
        section, name = key.split(".", 1)
        if section != "loss":
            raise SystemExit(f"{key}: only loss.* settings can change mid-run here")
        values[section][name] = json.loads(value)
    return config_from_dict(values), term


@contextlib.contextmanager
def _colour_nll(library: list[LossTerm], compute):
    """The objective with `compute` as the colour NLL, in the same place of the sum (so that
    the library's own term repeats the run exactly), and the library's objective after."""
    if compute is None:
        yield
        return
    _register([dataclasses.replace(t, compute=compute) if t.name == "nll_colour" else t for t in library])
    try:
        yield
    finally:
        _register(library)


def _probe(model, subsets) -> dict[str, float]:
    figures = {}
    for name, (rays, colour) in subsets.items():
        out = render_rays(model, rays)
        acc = np.asarray(out.acc)
        background = np.all(colour >= 0.99, axis=-1)
        figures[f"{name}_acc_bg"] = float(acc[background].mean())
        figures[f"{name}_acc_obj"] = float(acc[~background].mean())
        figures[f"{name}_psnr"] = float(-10 * np.log10(np.mean((np.asarray(out.rgb) - colour) ** 2)))
    return figures


def _continue(state, config, data, subsets, args) -> list[dict]:
    step = make_train_step(config)
    draw = jax.jit(draw_batch, static_argnums=2)
    rows = [{"step": int(state.step), **_probe(as_trained(state.model, int(state.step)), subsets)}]
    batch_psnr = []
    for _ in range(args.steps):
        state, metrics = step(state, draw(data, state, config.train.batch_size))
        batch_psnr.append(float(metrics.psnr))
        if int(state.step) % args.every == 0:
            row = {
                "step": int(state.step),
                "batch_psnr": float(np.mean(batch_psnr[-args.every :])),
                **_probe(as_trained(state.model, int(state.step)), subsets),
            }
            rows.append(row)
            print(
                f"  {row['step']:>5}  batch {row['batch_psnr']:5.2f}  train acc bg/obj "
                f"{row['train_acc_bg']:.3f}/{row['train_acc_obj']:.3f}  val acc bg/obj "
                f"{row['val_acc_bg']:.3f}/{row['val_acc_obj']:.3f}  val psnr {row['val_psnr']:5.2f}",
                flush=True,
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True)
    parser.add_argument("--checkpoint", default=None, help="default: the run's initial state (step 0)")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--steps", type=int, default=160)
    parser.add_argument("--every", type=int, default=20)
    parser.add_argument("--stride", type=int, default=16)
    parser.add_argument("--variant", nargs="+", action="append", default=[], metavar="NAME [KEY=VALUE ...]")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()

    first = Path(args.checkpoint) if args.checkpoint else mx.runs.latest_checkpoint(args.run)
    start = mx.runs.restore_run(args.run, checkpoint=first, data_dir=args.data_dir)
    dataset = start.dataset
    if args.checkpoint is None:  # the run's own initialisation: the same seed, the same state
        start = dataclasses.replace(start, state=init_train_state(start.config, dataset))
    subsets = {}
    for name, views in (("train", dataset.train), ("val", dataset.val)):
        rays = rays_for_views(views, dataset.near, dataset.far)
        subsets[name] = (
            jax.tree_util.tree_map(lambda a, s=args.stride: a[:, ::s, ::s], rays),
            views.images[:, :: args.stride, :: args.stride],
        )
    data = training_rays(dataset, start.config.loss)
    library = _library_terms(start.config)
    results = {}
    for name, overrides in _parse_variants(args.variant):
        config, term = _with_overrides(start.config, overrides)
        print(f"[{name}] {' '.join(overrides) or '(the run as it was)'}", flush=True)
        with _colour_nll(library, term):
            results[name] = {
                "overrides": overrides,
                "rows": _continue(start.state, config, data, subsets, args),
            }
    if args.out:
        Path(args.out).write_text(
            json.dumps({"run": args.run, "checkpoint": args.checkpoint, "variants": results}, indent=1)
        )


if __name__ == "__main__":
    main()
