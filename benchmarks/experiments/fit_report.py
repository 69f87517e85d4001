"""How well a trained run fits its own training views, and where its held-out error lies.

`python benchmarks/fit_report.py RUN_DIR [--montage PATH]` renders every training view of the
run and prints their PSNR, then splits the held-out views' squared error between background
pixels (pure white in the ground truth: the built-in scene and Blender) and the rest, prints
the PSNR the run would score if its background were perfect and the mean rendered opacity of
each part. `--montage` writes the training views beside their renders.
"""

import argparse

import imageio.v3 as iio
import numpy as np

import mixnerf_eqx as mx


def _psnr(mse: float) -> float:
    return float(-10.0 * np.log10(mse))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir")
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--montage", default=None, help="PNG of training views (left) and renders (right)")
    args = parser.parse_args()
    run = mx.runs.restore_run(args.run_dir, data_dir=args.data_dir)
    dataset, model = run.dataset, run.model

    train = mx.render_views(model, dataset.train, dataset.near, dataset.far)
    train_mse = float(np.mean((train.rgb - dataset.train.images) ** 2))
    print(f"training views: PSNR {_psnr(train_mse):.2f} ({dataset.train.num_views} views rendered in full)")

    test = mx.render_views(model, dataset.test, dataset.near, dataset.far)
    truth = dataset.test.images
    squared = np.mean((test.rgb - truth) ** 2, axis=-1)
    background = np.min(truth, axis=-1) >= 1.0 - 1e-6
    total = float(np.mean(squared))
    # metrics.json reports the mean of the per-view PSNRs; this is the PSNR of the pooled error.
    print(f"held-out views: PSNR of the pooled squared error {_psnr(total):.2f}")
    if background.any() and (~background).any():
        print(
            f"  background: {background.mean():.1%} of the pixels, mean squared error "
            f"{squared[background].mean():.4f}; objects: {squared[~background].mean():.4f}"
        )
        print(f"  PSNR with a perfect background: {_psnr(squared[~background].sum() / squared.size):.2f}")
        print(
            f"  mean opacity: background {test.acc[background].mean():.3f} (haze; 0 is right), "
            f"objects {test.acc[~background].mean():.3f}"
        )

    if args.montage:
        pairs = zip(dataset.train.images, train.rgb, strict=True)
        rows = [np.concatenate([truth_view, rendered], axis=1) for truth_view, rendered in pairs]
        image = (np.clip(np.concatenate(rows, axis=0), 0.0, 1.0) * 255).astype(np.uint8)
        iio.imwrite(args.montage, image)
        print(f"montage: {args.montage}")


if __name__ == "__main__":
    main()
