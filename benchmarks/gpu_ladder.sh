#!/usr/bin/env bash
# The MLP capacity ladder of the fidelity protocol, for a lent GPU: the built-in scene (4 views
# at 32x32), 500 epochs, MixNeRF and its baseline, seeds 0, 1, 2, at MLP sizes from the
# protocol's 4 x 64 up to the paper's 8 x 256. The question: from which size on does the
# baseline overfit or collapse (held-out PSNR falling while training PSNR rises), and does
# MixNeRF hold there? On the 2-core CPU the first 500 of a 4 x 64 run's 4,000 steps took 86 s
# with two other trainings on the cores, and there are 24 such runs, most of them wider: a
# GPU job.
#
# Each rung is one `fidelity.py` result file in benchmarks/results/,
# `fidelity_<backend>_ladder_<depth>x<width>.jsonl` (with its table, summary and curves). A
# run is appended when it finishes, and a second call resumes where the first stopped if the
# .jsonl files are in the tree. The script stops itself after GPU_LADDER_BUDGET_S seconds
# (default 540: a device command's limit is 600) and, where $OUT is set (the device machine's
# return folder), packs every ladder file into $OUT/gpu_ladder.tar.gz after each rung and at
# the end: unpack it into benchmarks/results/ here to keep the runs or to resume.
# `python benchmarks/ladder_table.py --backend gpu` then puts the rungs side by side.
#
# On the device machine, from the repository root (the built-in scene needs no data):
#     bash benchmarks/gpu_ladder.sh                     # carry: .whl (beartype's wheels)
# On a CPU, with tiny settings that only check every command runs (a minute or two):
#     GPU_LADDER_TINY=1 bash benchmarks/gpu_ladder.sh
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}"
if [ -d .whl ] && ! "$PY" -c "import beartype" 2>/dev/null; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/site .whl/*.whl
    export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
"$PY" -c "import beartype" 2>/dev/null || { echo "gpu_ladder: beartype is missing (carry .whl)" >&2; exit 1; }

RESULTS=benchmarks/results
BUDGET_S="${GPU_LADDER_BUDGET_S:-540}"
# depth width skip_layer view_width, largest first
RUNGS=("8 256 4 128" "4 256 2 128" "8 128 4 64" "4 128 2 64" "4 64 2 32")
if [ "${GPU_LADDER_TINY:-0}" = 1 ]; then
    RESULTS="${TMPDIR:-/tmp}/gpu_ladder_tiny"
    RUNGS=("2 16 1 8")
    RUN=(--epochs 2 --evals 2 --seeds 0)
else
    RUN=(--epochs 500 --seeds 0 1 2)
fi
mkdir -p "$RESULTS"
started=$(date +%s)
say() { echo "[gpu_ladder $(($(date +%s) - started)) s] $*"; }
pack() {
    local files
    files=$(cd "$RESULTS" && ls | grep '_ladder_' || true)
    if [ -n "${OUT:-}" ] && [ -d "$OUT" ] && [ -n "$files" ]; then
        # shellcheck disable=SC2086  # one name per word: the names have no spaces
        tar -czf "$OUT/gpu_ladder.tar.gz" -C "$RESULTS" $files
        say "packed into $OUT/gpu_ladder.tar.gz"
    fi
}
backend=$("$PY" -c "import jax; print(jax.default_backend())")
for rung in "${RUNGS[@]}"; do
    read -r depth width skip view <<<"$rung"
    left=$((BUDGET_S - ($(date +%s) - started)))
    if [ "$left" -le 30 ]; then
        say "budget spent; run again to resume"
        break
    fi
    say "rung ${depth} x ${width} (${left} s left)"
    timeout --signal=INT "$left" "$PY" benchmarks/fidelity.py --scenes builtin "${RUN[@]}" \
        --out "$RESULTS" --tag "${backend}_ladder_${depth}x${width}" \
        --set "mlp.depth=$depth" "mlp.width=$width" "mlp.skip_layer=$skip" "mlp.view_width=$view" ||
        say "rung ${depth} x ${width} stopped (the runs it finished are kept)"
    pack
done
say "done; results in $RESULTS"
