#!/usr/bin/env bash
# The GPU check of the update, correctness first: the sub-pixel op and the fused rollout's backward on CUDA,
# a seeded burst on the CPU and on CUDA from the same weights agreeing, no host sync inside a burst, save -> load on
# CUDA -> a burst, and compiled bursts replayed as CUDA graphs (torch >= 2.13); then the speed table, each row saying
# whether it compiled. About 3 minutes of checks and 5 of speed rows on one GPU, every step under a timeout; no
# simulator (benchmarks/tools/gpu_check.py says what each step does).
#
#   bash benchmarks/tools/gpu_check.sh --fetch   # here, with a package index: the wheels a bare CUDA image lacks, into .whl/
#   bash benchmarks/tools/gpu_check.sh           # on the GPU machine, from the repository root; no package index needed
#   bash benchmarks/tools/gpu_check.sh --cpu     # the same steps on this machine's CPU at small sizes, every CUDA step
#                                          # skipped and said so, installing nothing (tests/test_gpu_path.py runs it)
#
# With this workplace's device tool: --fetch here, then run(command="bash benchmarks/tools/gpu_check.sh", carry=[".whl"],
# timeout_s=600); the tables come back in $OUT. torch is never installed or replaced: the image's is the one checked.
# Wheels: WHEELS (default .whl), installed without an index into SITE. Results: OUT_DIR (default $OUT, else
# /tmp/gpu_check). Exit status: that of the checks (1 if one failed or timed out).
set -uo pipefail

cd "$(dirname "$0")/../.."
REPO=$(pwd)
WHEELS=${WHEELS:-.whl}
OUT_DIR=${OUT_DIR:-${OUT:-/tmp/gpu_check}}
SITE=${SITE:-/tmp/gpu_check_site}
PYTHON=${PYTHON:-python3}
# What a CUDA image with torch, numpy, cloudpickle, pandas and matplotlib lacks to import the package (pure Python)
PACKAGES=(stable_baselines3==2.9.2 sb3_contrib==2.9.2 gymnasium==1.4.0 farama-notifications==0.0.6)

MODE=cuda
case "${1:-}" in
--fetch)
    "$PYTHON" -m pip download --no-deps --only-binary=:all: -d "$WHEELS" "${PACKAGES[@]}" || exit
    du -sh "$WHEELS"
    exit 0
    ;;
--cpu) MODE=cpu ;;
"") ;;
*)
    echo "usage: bash benchmarks/tools/gpu_check.sh [--fetch | --cpu]" >&2
    exit 2
    ;;
esac

rm -rf "$OUT_DIR"/checks.jsonl "$OUT_DIR"/speed.jsonl "$OUT_DIR"/work
mkdir -p "$OUT_DIR"
if [[ $MODE == cuda ]] && compgen -G "$WHEELS/*.whl" >/dev/null; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" \
        "$WHEELS"/*.whl || exit
fi
# The checkout, not an installed copy, is what runs
export PYTHONPATH="$REPO:$REPO/benchmarks:$SITE${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
"$PYTHON" -c "import sb3_dsslac" || { echo "cannot import sb3_dsslac: run --fetch where there is an index, carry $WHEELS"; exit 1; }
"$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available(),
      torch.cuda.get_device_name() if torch.cuda.is_available() else '')"
if [[ $MODE == cuda ]]; then
    "$PYTHON" -c "import torch; assert torch.cuda.is_available(), 'no CUDA device (--cpu for the dry mode)'" || exit
    speed_rows=(cpu_pixels32_bounded cpu_pixels32_bounded+compile thesis thesis+compile)
    flags=()
else
    speed_rows=(small small+compile)
    flags=(--cpu)
fi

echo "== checks ($(date +%T))"
timeout 200 "$PYTHON" benchmarks/tools/gpu_check.py checks "${flags[@]}" --out "$OUT_DIR" 2>"$OUT_DIR/checks.log"
checks_status=$?
[[ $checks_status == 0 ]] || tail -n 30 "$OUT_DIR/checks.log"

for row in "${speed_rows[@]}"; do
    echo "== speed: $row ($(date +%T))"
    seconds=60
    [[ $row == *compile ]] && seconds=150
    timeout "$seconds" "$PYTHON" benchmarks/tools/gpu_check.py speed "$row" "${flags[@]}" --out "$OUT_DIR" \
        2>"$OUT_DIR/speed_$row.log" || echo "speed row $row: exit $? (124: timed out after $seconds s)"
done

echo
echo "== $(date +%T): checks exit $checks_status (124: timed out)"
"$PYTHON" benchmarks/tools/gpu_check.py table --out "$OUT_DIR" | tee "$OUT_DIR/tables.md"
[[ $checks_status == 0 ]]
