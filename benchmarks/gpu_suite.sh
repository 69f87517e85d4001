#!/usr/bin/env bash
# The measurements a lent GPU is for, as one script of at most 12 minutes:
#   1. seconds per training step of the paper config, of the quick start's grid config and of
#      the LLFF 3-view grid config (fern), each against the bare field's forward + backward over
#      the same points on the same device (step_time.py: variants bare-mlp and mixnerf);
#      the grid configs with both lookups (grid.lookup = vmap, what "auto" takes on a GPU, and
#      batched, what it takes on a CPU), so the per-backend choice can be checked;
#   2. the paper's model's training step with skipping, by buffer share, against its dense
#      step (skipping_step.py);
#   3. the fern 3-view grid config at full resolution (504 x 378) trained for 8 minutes of step
#      time, scored on every test view each minute: its PSNR curve (error_vs_time.py).
# Results go to benchmarks/results/gpu_*.json (and the curve's .jsonl and .png).
#
# On the device machine, from the repository root, with fern copied to an ignored folder that
# travels with the call (`carry`), and the wheels of ../shared/tools/device-wheels.sh in .whl/:
#     mkdir -p .devdata/nerf_llff_data && cp -r ../shared/data/nerf_llff_data/fern .devdata/nerf_llff_data/
#     bash benchmarks/gpu_suite.sh                         # carry: .devdata, .whl
# On a CPU, with tiny settings that only check every command runs (a minute or two):
#     GPU_SUITE_TINY=1 GPU_SUITE_DATA=../shared/data GPU_SUITE_OUT=/tmp/gpu_suite bash benchmarks/gpu_suite.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ -d .whl ] && ! python -c "import beartype" 2>/dev/null; then
    python -m pip install --quiet --no-index --find-links .whl beartype
fi

DATA="${GPU_SUITE_DATA:-.devdata}"
OUT="${GPU_SUITE_OUT:-benchmarks/results}"
mkdir -p "$OUT"
if [ "${GPU_SUITE_TINY:-0}" = 1 ]; then
    REPEATS=1
    SMALL=(train.batch_size=64 model.num_coarse_samples=8 model.num_fine_samples=8)
    PAPER=("${SMALL[@]}" mlp.width=16 mlp.depth=2 mlp.skip_layer=1 mlp.view_width=8)
    FERN=(data.image_downscale=8 grid.levels=2 grid.max_resolution=64)
    CURVE=(--budget-s 4 --eval-every-s 2 --eval-views 1 --calibrate-steps 1)
else
    REPEATS=5
    SMALL=()
    PAPER=()
    FERN=()
    CURVE=(--budget-s 480 --eval-every-s 60 --eval-views 0)
fi
started=$(date +%s)
say() { echo "[gpu_suite $(($(date +%s) - started)) s] $*"; }

say "step time: the paper config (4096 rays, 128 + 128 samples, 8 x 256 MLP)"
python benchmarks/step_time.py --repeats "$REPEATS" --variants bare-mlp mixnerf \
    --out "$OUT/gpu_step_paper.json" "${PAPER[@]}"
for lookup in vmap batched; do
    say "step time: the quick start's grid config, grid.lookup=$lookup"
    python benchmarks/step_time.py --config configs/builtin_grid.toml --repeats "$REPEATS" \
        --variants bare-mlp mixnerf --out "$OUT/gpu_step_builtin_grid_$lookup.json" \
        "${SMALL[@]}" "grid.lookup=\"$lookup\""
    say "step time: the LLFF 3-view grid config on fern, grid.lookup=$lookup"
    python benchmarks/step_time.py --config configs/llff3_grid.toml --repeats "$REPEATS" \
        --variants bare-mlp mixnerf --out "$OUT/gpu_step_llff3_grid_$lookup.json" \
        "${SMALL[@]}" "${FERN[@]}" "data.data_dir=\"$DATA\"" "grid.lookup=\"$lookup\""
done

say "step time by skipping buffer share: the paper's model (8 x 256 MLP, 4096 rays, 128 + 128 samples)"
python benchmarks/skipping_step.py --config builtin --repeats "$REPEATS" --out "$OUT/gpu_skipping_step_paper.json" \
    mlp.width=256 mlp.depth=8 mlp.skip_layer=4 mlp.view_width=128 mlp.max_deg=16 \
    model.num_coarse_samples=128 model.num_fine_samples=128 train.batch_size=4096 \
    occupancy.box_radius=1.3 ${PAPER[@]:+"${PAPER[@]}"}

# llff3_grid has trained without the lambda_C ramp and with the distortion loss since 2026-12-06;
# the CPU grid-fern curves of benchmarks/grid_field.md were made with the ramp and without the
# loss (add loss.lambda_colour_start=4.0 and loss.distortion_weight=0 to FERN to compare).
say "fern 3-view, grid config, full resolution: PSNR against step time"
fern_overrides=$(IFS=,; echo "${FERN[*]}")
python benchmarks/error_vs_time.py --data-dir "$DATA" \
    --scene "fern=configs/llff3_grid.toml${fern_overrides:+:$fern_overrides}" \
    --variant grid=scene ${SMALL[@]:+--set "${SMALL[@]}"} "${CURVE[@]}" \
    --out "$OUT" --tag gpu_fern_grid
say "done; results in $OUT"
