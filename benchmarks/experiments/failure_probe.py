"""What a white-background run's geometry does, checkpoint by checkpoint.

For every checkpoint folder given (or every one under each `--keep` folder), renders a
strided subset of the pixels of the training views and of the validation views and prints,
per split: PSNR on those pixels (one squared error pooled over them), the mean opacity on
background pixels (where the true colour is white) and on the object's, and the mean
termination distance on each. A box filled with floaters shows as opacity near 1 on the
background. Each checkpoint is rendered with its field as its training step saw it (a grid's
coarse-to-fine levels), over the rays' whole near-far range (training narrows it during its
first `train.anneal_steps` steps).

    python benchmarks/experiments/failure_probe.py --run runs/diag/np1 --keep runs/diag/keep_np1 \
        --data-dir ../shared/data --stride 8 --out benchmarks/results/NAME.json
"""

import argparse
import json
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import mixnerf_eqx as mx
from mixnerf_eqx.data import rays_for_views
from mixnerf_eqx.inference import render_rays


def _subset(views, near: float, far: float, stride: int):
    rays = rays_for_views(views, near, far)
    rays = jax.tree_util.tree_map(lambda a: a[:, ::stride, ::stride], rays)
    colour = views.images[:, ::stride, ::stride]
    return rays, colour


def as_trained(model, step: int):
    """`model` with its field as training step `step` saw it (a grid's coarse-to-fine levels):
    the stored model keeps every level revealed."""
    return eqx.tree_at(lambda m: m.field, model, model.field.at_step(max(step, 1)))


def _figures(model, rays, colour: np.ndarray, white: float) -> dict[str, float]:
    out = render_rays(model, rays)
    rgb, acc, depth = np.asarray(out.rgb), np.asarray(out.acc), np.asarray(out.depth)
    background = np.all(colour >= white, axis=-1)
    mse = float(np.mean((rgb - colour) ** 2))
    return {
        "psnr": -10.0 * np.log10(mse),
        "acc_background": float(acc[background].mean()),
        "acc_object": float(acc[~background].mean()),
        "depth_background": float(depth[background].mean()),
        "depth_object": float(depth[~background].mean()),
        "background_share": float(background.mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", required=True, help="the run folder (its config.json)")
    parser.add_argument("--keep", nargs="*", default=[], help="folders of copied checkpoint folders")
    parser.add_argument("--checkpoints", nargs="*", default=[], help="checkpoint folders")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--stride", type=int, default=8, help="every this many pixels on both axes")
    parser.add_argument(
        "--white", type=float, default=0.99, help="a channel value at or above this is background"
    )
    parser.add_argument("--out", default=None, help="a JSON file for the figures")
    args = parser.parse_args()

    folders = [Path(c) for c in args.checkpoints]
    for keep in args.keep:
        folders += sorted(p for p in Path(keep).iterdir() if (p / "state.eqx").is_file())
    if not folders:
        raise SystemExit("no checkpoint folder given: pass --checkpoints or --keep")
    first = mx.runs.restore_run(args.run, checkpoint=folders[0], data_dir=args.data_dir)
    dataset = first.dataset
    splits = {"train": dataset.train, "val": dataset.val}
    subsets = {name: _subset(views, dataset.near, dataset.far, args.stride) for name, views in splits.items()}
    rows = []
    header = f"{'step':>6} | " + " | ".join(
        f"{name}: psnr acc_bg acc_obj depth_bg depth_obj" for name in splits
    )
    print(header)
    for folder in folders:
        run = mx.runs.restore_run(args.run, checkpoint=folder, dataset=dataset)
        row = {"step": run.step, "checkpoint": str(folder)}
        for name, (rays, colour) in subsets.items():
            row[name] = _figures(as_trained(run.model, run.step), rays, colour, args.white)
        rows.append(row)
        print(
            f"{run.step:>6} | "
            + " | ".join(
                f"{name}: {f['psnr']:5.2f} {f['acc_background']:.3f} {f['acc_object']:.3f} "
                f"{f['depth_background']:5.2f} {f['depth_object']:5.2f}"
                for name, f in ((n, row[n]) for n in splits)
            ),
            flush=True,
        )
    if args.out:
        Path(args.out).write_text(
            json.dumps({"run": args.run, "stride": args.stride, "rows": rows}, indent=1)
        )


if __name__ == "__main__":
    main()
