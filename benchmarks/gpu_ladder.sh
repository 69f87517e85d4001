#!/usr/bin/env bash
# The MLP capacity ladder of the fidelity protocol, for a lent GPU: the built-in scene (4 views
# at 32x32), 500 epochs, MixNeRF and its baseline, seeds 0, 1, 2, at MLP sizes from the
# protocol's 4 x 64 up to the paper's 8 x 256. The question: from which size on does the
# baseline overfit or collapse (held-out PSNR falling while training PSNR rises), and does
# MixNeRF hold there? On the 2-core CPU the smallest rung alone is 6 runs of 4,000 steps, and
# its first 500 steps took 86 s with two other trainings on the cores: a GPU job.
#
# Each rung is one `fidelity.py` result file, `fidelity_<backend>_ladder_<depth>x<width>.jsonl`
# (and its table, summary and curves); runs append as they finish and a second call resumes
# where the first stopped, so the ladder may take several calls. Rungs run largest first.
#
# On the device machine, from the repository root (the built-in scene needs no data):
#     bash benchmarks/gpu_ladder.sh                     # carry: .whl
# On a CPU, with tiny settings that only check every command runs (a minute or two):
#     GPU_LADDER_TINY=1 GPU_LADDER_OUT=/tmp/gpu_ladder bash benchmarks/gpu_ladder.sh
set -euo pipefail
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ -d .whl ] && ! python -c "import beartype" 2>/dev/null; then
    python -m pip install --quiet --no-index --find-links .whl beartype
fi

OUT="${GPU_LADDER_OUT:-benchmarks/results}"
mkdir -p "$OUT"
# depth width skip_layer view_width
RUNGS=("8 256 4 128" "4 256 2 128" "8 128 4 64" "4 128 2 64")
if [ "${GPU_LADDER_TINY:-0}" = 1 ]; then
    RUNGS=("2 16 1 8")
    RUN=(--epochs 2 --evals 2 --seeds 0)
else
    RUN=(--epochs 500 --seeds 0 1 2)
fi
started=$(date +%s)
say() { echo "[gpu_ladder $(($(date +%s) - started)) s] $*"; }
backend=$(python -c "import jax; print(jax.default_backend())")
for rung in "${RUNGS[@]}"; do
    read -r depth width skip view <<<"$rung"
    say "rung ${depth} x ${width}"
    python benchmarks/fidelity.py --scenes builtin "${RUN[@]}" --out "$OUT" \
        --tag "${backend}_ladder_${depth}x${width}" \
        --set "mlp.depth=$depth" "mlp.width=$width" "mlp.skip_layer=$skip" "mlp.view_width=$view"
done
say "done; results in $OUT"
