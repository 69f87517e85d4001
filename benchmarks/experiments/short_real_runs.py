"""Short MixNeRF and mip-NeRF-baseline runs on real scenes, scored by the evaluation protocol.

    python benchmarks/short_real_runs.py --data-dir ../shared/data            # lego 4-view, fern 3-view
    python benchmarks/short_real_runs.py --data-dir DIR --steps 2000 --size paper

Each paper config (blender4.toml, llff3.toml and their mip-NeRF twins) is trained with `mx.fit`
for `--steps` steps with everything else as the paper says, except the schedules that would
not fit the run (warm-up, lambda_C ramp, annealing: cut by `harness.schedule_overrides`) and,
with `--size small`, a CPU-sized model (the built-in scene's: 4 x 64 MLP, 32 + 32 samples, 512
rays per step). The test views are then rendered and scored (PSNR, SSIM, LPIPS, average;
`--max-test-views` evenly spaced views of the protocol's test set). Prints a table with the
load and training times and writes it as JSON
(`benchmarks/results/short_real_runs_<backend>.json` unless `--out` says otherwise). Existing
run folders are resumed.
"""

import argparse
import json
import time
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # harness.py, one floor up

import harness  # noqa: E402

import mixnerf_eqx as mx
from mixnerf_eqx.data import load_dataset

SCENES = {"lego": "blender4.toml", "fern": "llff3.toml"}
SMALL = [
    "mlp.width=64",
    "mlp.depth=4",
    "mlp.skip_layer=2",
    "mlp.view_width=32",
    "mlp.max_deg=10",
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
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--runs-root", default="runs/short_real")
    parser.add_argument(
        "--out", default=None, help="JSON path (default: results/short_real_runs_<backend>.json)"
    )
    parser.add_argument("overrides", nargs="*", help="config overrides for every run, section.key=value")
    args = parser.parse_args()
    rows = []
    for scene in args.scenes:
        for model in ("mixnerf", "mipnerf"):
            name = SCENES[scene] if model == "mixnerf" else f"mipnerf_{SCENES[scene]}"
            config_file = harness.REPO / "configs" / name
            run_dir = Path(args.runs_root) / f"{model}_{scene}_{args.size}_{args.steps}"
            overrides = [
                *(SMALL if args.size == "small" else []),
                *args.overrides,
                "train.eval_every=0",
                f"train.checkpoint_every={args.steps}",
                f"data.max_test_views={args.max_test_views}",
                *harness.data_dir_override(args.data_dir),
                f"train.run_dir={json.dumps(str(run_dir))}",
            ]
            config = mx.load_config(config_file, overrides)
            explicit = harness.override_keys(args.overrides)
            config = mx.load_config(
                config_file, [*overrides, *harness.schedule_overrides(config, args.steps, explicit)]
            )
            started = time.perf_counter()
            dataset = load_dataset(config.data)
            load_s = time.perf_counter() - started
            started = time.perf_counter()
            result = mx.fit(config, dataset=dataset, progress=False, write_renders=True)
            row = {
                "scene": scene,
                "model": model,
                "config": f"configs/{name}",
                "steps": args.steps,
                "size": args.size,
                "test_views": dataset.test.num_views,
                "load_s": load_s,
                "train_and_eval_s": time.perf_counter() - started,
                **result.metrics["test"],  # fit ends by scoring the test views
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
    print()
    harness.print_table(
        ("scene", "model", "steps", "PSNR", "SSIM", "LPIPS", "average", "load s", "train+eval s"),
        [
            (
                row["scene"],
                row["model"],
                row["steps"],
                row["psnr"],
                row["ssim"],
                row["lpips"],
                row["average"],
                row["load_s"],
                row["train_and_eval_s"],
            )
            for row in rows
        ],
    )
    out = Path(args.out) if args.out else harness.RESULTS / f"short_real_runs_{harness.platform_tag()}.json"
    harness.write_json(out, {"args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
