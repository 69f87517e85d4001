"""MixNeRF against the mip-NeRF baseline on the built-in scene, with the same steps.

    python benchmarks/builtin_compare.py [--config configs/builtin.toml] [section.key=value ...]

Trains both (the baseline is the same config with the three NLL weights at zero), prints a
table of test PSNR / SSIM / depth error and wall time, and writes it as JSON.
"""

import argparse
import json
import platform
import time
from pathlib import Path

import jax

from mixnerf_eqx import load_config
from mixnerf_eqx._train import fit

BASELINE = [
    "loss.lambda_colour_start=0.0",
    "loss.lambda_colour_end=0.0",
    "loss.lambda_depth=0.0",
    "loss.lambda_regen=0.0",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="configs/builtin.toml")
    parser.add_argument("--out", default="benchmarks/results/builtin_compare_cpu.json")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument(
        "--runs-root", default="runs/compare", help="run dirs go here (existing ones are resumed)"
    )
    parser.add_argument("overrides", nargs="*")
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        for name, extra in (("mixnerf", []), ("mipnerf", BASELINE)):
            run_dir = f"{args.runs_root}/{name}_seed{seed}"
            config = load_config(
                args.config,
                [
                    *args.overrides,
                    *extra,
                    f"train.seed={seed}",
                    f'train.run_dir="{run_dir}"',
                    "train.eval_every=0",
                ],
            )
            start = time.perf_counter()
            result = fit(config, resume=True, progress=False, write_renders=True)
            rows.append(
                {
                    "model": name,
                    "seed": seed,
                    "seconds": time.perf_counter() - start,
                    "steps": result.metrics["step"],
                    **result.metrics["test"],
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    header = ("model", "seed", "steps", "PSNR", "SSIM", "depth MAE", "seconds")
    print("\n" + " ".join(f"{h:>9s}" for h in header))
    for row in rows:
        cells = (
            row["model"],
            row["seed"],
            row["steps"],
            row["psnr"],
            row["ssim"],
            row["depth_mae"],
            row["seconds"],
        )
        print(" ".join(f"{c:>9.4g}" if isinstance(c, float) else f"{c!s:>9s}" for c in cells))
    machine = {
        "platform": platform.platform(),
        "processor": platform.processor(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(
        json.dumps(
            {"config": args.config, "overrides": args.overrides, "machine": machine, "rows": rows}, indent=2
        )
    )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
