"""Short MixNeRF and mip-NeRF-baseline runs on real scenes, scored by the evaluation protocol.

    python benchmarks/short_real_runs.py --data-dir ../shared/data            # lego 4-view, fern 3-view
    python benchmarks/short_real_runs.py --data-dir DIR --steps 2000 --size paper

Each paper config (blender4.toml, llff3.toml and their mip-NeRF twins) is trained for
`--steps` steps with everything else as the paper says, except, with `--size small`, a CPU-sized
model (the built-in scene's: 4 x 64 MLP, 32 + 32 samples, 512 rays per step; the schedules are
shortened to the run). The test views are then rendered and scored (PSNR, SSIM, LPIPS, average;
`--max-test-views` evenly spaced views of the protocol's test set). Prints a table with the
load and training times and writes it as JSON. Existing run folders are resumed.
"""

import argparse
import json
import platform
import time
from pathlib import Path

import jax

from mixnerf_eqx import load_config
from mixnerf_eqx._train import fit
from mixnerf_eqx.data import load_dataset

SCENES = {"lego": "blender4.toml", "fern": "llff3.toml"}
SMALL = [
    "model.width=64",
    "model.depth=4",
    "model.skip_layer=2",
    "model.view_width=32",
    "model.max_deg=10",
    "model.num_coarse_samples=32",
    "model.num_fine_samples=32",
    "train.batch_size=512",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data-dir", required=True)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--size", choices=["small", "paper"], default="small")
    parser.add_argument("--max-test-views", type=int, default=8)
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--runs-root", default="runs/short_real")
    parser.add_argument("--out", default="benchmarks/results/short_real_runs_cpu.json")
    args = parser.parse_args()
    rows = []
    for scene in args.scenes:
        for model in ("mixnerf", "mipnerf"):
            config_file = Path("configs") / (
                SCENES[scene] if model == "mixnerf" else f"mipnerf_{SCENES[scene]}"
            )
            steps = args.steps
            schedule = [
                f"train.max_steps={steps}",
                f"optim.warmup_steps={max(1, steps // 10)}",
                f"loss.lambda_colour_steps={max(1, steps // 10)}",
                f"train.anneal_steps={max(1, steps // 5)}",
                "train.eval_every=0",
                f"train.checkpoint_every={steps}",
                f"data.max_test_views={args.max_test_views}",
                f'data.data_dir="{args.data_dir}"',
                f'train.run_dir="{args.runs_root}/{model}_{scene}_{args.size}_{steps}"',
            ]
            overrides = (SMALL if args.size == "small" else []) + schedule
            config = load_config(config_file, overrides)
            started = time.perf_counter()
            dataset = load_dataset(config.data)
            load_seconds = time.perf_counter() - started
            started = time.perf_counter()
            result = fit(config, dataset=dataset, progress=False, write_renders=True)
            train_seconds = time.perf_counter() - started
            means = result.metrics["test"]  # fit ends by scoring the test views
            row = {
                "scene": scene,
                "model": model,
                "config": str(config_file),
                "steps": steps,
                "size": args.size,
                "test_views": dataset.test.num_views,
                "load_s": load_seconds,
                "train_and_eval_s": train_seconds,
                **means,
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    header = ("scene", "model", "steps", "PSNR", "SSIM", "LPIPS", "average", "load s", "train+eval s")
    print("\n| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for row in rows:
        cells = [row["scene"], row["model"], str(row["steps"])]
        for name in ("psnr", "ssim", "lpips", "average"):
            cells.append("n/a" if row[name] is None else f"{row[name]:.4f}")
        cells += [f"{row['load_s']:.2f}", f"{row['train_and_eval_s']:.0f}"]
        print("| " + " | ".join(cells) + " |")
    machine = {
        "platform": platform.platform(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps({"machine": machine, "args": vars(args), "rows": rows}, indent=2))
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
