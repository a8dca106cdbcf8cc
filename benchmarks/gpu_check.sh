#!/usr/bin/env bash
# The GPU check (docs: Speed and precision, "Checking a GPU machine"): one prepared script for a machine with one
# CUDA GPU, about 10 minutes. From the repository root, after `bash scripts/setup.sh` (or with PYTHON set to a
# Python that has drago and a CUDA build of torch):
#
#     bash benchmarks/gpu_check.sh [OUT_DIR]        # default gpu-check/
#
# 1. the CUDA-marked tests (tests/test_cuda.py; pytest -m cuda);
# 2. a smoke run of every method on cuda in each of {eager, compiled} x {float32, bfloat16};
# 3. the speed benchmark at the paper's grid and cheetah configs, eager float32 against compiled bfloat16.
# Everything lands in OUT_DIR: JSON, logs, and summary.txt, a short text to paste on the benchmarks page.
# Without a GPU it runs what it can on the CPU (the tests are collected and skipped with their reason; one
# eager float32 smoke run per method on the CPU), says what it skipped and why, and exits 0.
set -uo pipefail

OUT=${1:-gpu-check}
PYTHON=${PYTHON:-.venv/bin/python}
RUN_LIMIT_S=${GPU_CHECK_RUN_LIMIT_S:-300}
mkdir -p "$OUT/runs"
SUMMARY="$OUT/summary.txt"
: > "$SUMMARY"
say() { echo "$*" | tee -a "$SUMMARY"; }
started=$(date +%s)

cuda=$("$PYTHON" -c "import torch; print(int(torch.cuda.is_available()))" 2>/dev/null || echo 0)
say "drago GPU check, $(date -u +%Y-%m-%dT%H:%M:%SZ), commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
say "$("$PYTHON" -c "import torch, platform; gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no CUDA GPU'; print(f'torch {torch.__version__} (CUDA {torch.version.cuda}), {gpu}, {platform.processor() or platform.machine()}')")"

# ---- 1. the CUDA-marked tests --------------------------------------------------------------------------------
"$PYTHON" -m pytest -m cuda -n 0 -q -rs -p no:cacheprovider > "$OUT/cuda-tests.txt" 2>&1
say "cuda tests: $(tail -n 1 "$OUT/cuda-tests.txt")"
if [ "$cuda" != 1 ]; then
    say "  (skipped, as the tests say: no CUDA GPU here)"
fi

# ---- 2. a smoke run of every method in every speed setting ----------------------------------------------------
methods=$("$PYTHON" -c "from drago.api import available_methods; print(' '.join(available_methods()))")
# Smoke runs side by side: their small networks leave a GPU mostly idle; on a CPU, one per core.
if [ "$cuda" = 1 ]; then
    device=cuda; combos="false:float32 false:bfloat16 true:float32 true:bfloat16"; parallel=${GPU_CHECK_PARALLEL:-8}
else
    device=cpu; combos="false:float32"; parallel=$(nproc)
    say "smoke runs: no CUDA GPU, so only eager float32 on the CPU (compiled and bfloat16 runs are for the GPU)"
fi
# Compiled runs share one kernel cache, so each shape compiles once for the whole check.
export TORCHINDUCTOR_CACHE_DIR=${TORCHINDUCTOR_CACHE_DIR:-$OUT/inductor-cache}
jobs_file="$OUT/runs/jobs.txt"
: > "$jobs_file"
for method in $methods; do
    for combo in $combos; do
        echo "$method ${combo%%:*} ${combo##*:}" >> "$jobs_file"
    done
done
smoke_one() {
    method=$1; compile=$2; precision=$3
    name="$method-$([ "$compile" = true ] && echo compiled || echo eager)-$precision"
    begin=$(date +%s)
    timeout "$RUN_LIMIT_S" "$PYTHON" -m drago train smoke --method "$method" --out "$OUT/runs/$name" --force \
        --no-progress train.tensorboard=false "train.device=$device" train.threads=1 \
        "agent.tdmpc.compile=$compile" "agent.tdmpc.precision=$precision" > "$OUT/runs/$name.log" 2>&1
    code=$?
    echo "$name $code $(( $(date +%s) - begin ))"
}
export -f smoke_one
export PYTHON OUT device RUN_LIMIT_S
xargs -P "$parallel" -L 1 bash -c 'smoke_one "$@"' _ < "$jobs_file" | sort > "$OUT/runs/results.txt"
total=$(wc -l < "$OUT/runs/results.txt")
failed=$(awk '$2 != 0' "$OUT/runs/results.txt")
say "smoke runs on $device: $((total - $(printf '%s' "$failed" | grep -c .))) of $total finished" \
    "(run, exit code, seconds in $OUT/runs/results.txt; logs in $OUT/runs/)"
if [ -n "$failed" ]; then
    say "  failed:"
    while read -r name code seconds; do
        say "    $name (exit $code after ${seconds}s): $(tail -n 1 "$OUT/runs/$name.log")"
    done <<< "$failed"
fi

# ---- 3. the benchmark at the paper's configs ---------------------------------------------------------------
if [ "$cuda" = 1 ]; then
    "$PYTHON" benchmarks/bench_speed.py --device cuda --presets minigrid cheetah --repeats 5 \
        --json "$OUT/bench-eager-float32.json" > "$OUT/bench-eager-float32.txt" 2>&1
    "$PYTHON" benchmarks/bench_speed.py --device cuda --presets minigrid cheetah --repeats 5 \
        --set agent.tdmpc.compile=true agent.tdmpc.precision=bfloat16 --json "$OUT/bench-compiled-bfloat16.json" \
        --compare "$OUT/bench-eager-float32.json" > "$OUT/bench-compiled-bfloat16.txt" 2>&1
    say "benchmark (minigrid and cheetah, cuda): eager float32 in $OUT/bench-eager-float32.txt;" \
        "compiled bfloat16, with new/old ratios, in $OUT/bench-compiled-bfloat16.txt"
    sed -n '/^new \/ old/,$p' "$OUT/bench-compiled-bfloat16.txt" >> "$SUMMARY"
else
    say "benchmark: skipped, no CUDA GPU (the CPU benchmark is benchmarks/bench_speed.py, see the benchmarks page)"
fi
say "took $(( $(date +%s) - started )) s; everything is in $OUT/"
