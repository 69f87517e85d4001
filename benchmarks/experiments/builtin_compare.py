"""MixNeRF against the mip-NeRF baseline on the built-in scene, with the same steps.

    python benchmarks/builtin_compare.py [--config configs/builtin.toml] [--seeds 0 1] [section.key=value ...]

Trains both with `mx.fit` (the baseline is the same config with `method = "mipnerf"`), prints
a table of test PSNR / SSIM / depth error and wall time, and writes it as JSON
(`benchmarks/results/builtin_compare_<backend>.json` unless `--out` says otherwise). Existing
run folders under `--runs-root` are resumed.
"""

import argparse
import json
import time
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # harness.py, one floor up

import harness  # noqa: E402

import mixnerf_eqx as mx

METHODS = {"mixnerf": [], "mipnerf": ["method=mipnerf"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="configs/builtin.toml")
    parser.add_argument(
        "--out", default=None, help="JSON path (default: results/builtin_compare_<backend>.json)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument(
        "--runs-root", default="runs/compare", help="run dirs go here (existing ones are resumed)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides for both methods, section.key=value")
    args = parser.parse_args()
    rows = []
    for seed in args.seeds:
        for name, extra in METHODS.items():
            run_dir = Path(args.runs_root) / f"{name}_seed{seed}"
            config = mx.load_config(
                args.config,
                [
                    *args.overrides,
                    *extra,
                    f"train.seed={seed}",
                    f"train.run_dir={json.dumps(str(run_dir))}",
                    "train.eval_every=0",
                ],
            )
            started = time.perf_counter()
            result = mx.fit(config, resume=True, progress=False, write_renders=True)
            rows.append(
                {
                    "model": name,
                    "seed": seed,
                    "seconds": time.perf_counter() - started,
                    "steps": result.metrics["step"],
                    **result.metrics["test"],
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    print()
    harness.print_table(
        ("model", "seed", "steps", "PSNR", "SSIM", "depth MAE", "seconds"),
        [
            (
                row["model"],
                row["seed"],
                row["steps"],
                row["psnr"],
                row["ssim"],
                row.get("depth_mae"),
                row["seconds"],
            )
            for row in rows
        ],
    )
    out = Path(args.out) if args.out else harness.RESULTS / f"builtin_compare_{harness.platform_tag()}.json"
    harness.write_json(out, {"config": args.config, "overrides": args.overrides, "rows": rows})


if __name__ == "__main__":
    main()
