#!/usr/bin/env bash
# One bounded GPU check of the update (issue #12), for a bare CUDA machine (an H100/H200 box, no internet):
# installs what the image lacks, runs benchmarks/throughput.py --device cuda --quick (updates/s, ops/update and
# syncs/update of every update path, at the thesis shapes and the cpu_learning and cpu_pixels32_bounded presets) and
# two short pixel training runs (thesis_fast at 64x64, cpu_pixels32_bounded at 32x32), then prints one table. Under 8
# minutes: every step has a timeout.
#
#   bash benchmarks/gpu_check.sh --fetch     # here, with internet: wheels into .whl/, EGL debs into .gl/
#   bash benchmarks/gpu_check.sh             # on the GPU machine, from the repository root
#   DEVICE=cpu bash benchmarks/gpu_check.sh  # a tiny version of the same steps on the CPU, installing nothing
#
# With this workplace's device tool: --fetch here, then run(command="bash benchmarks/gpu_check.sh",
# carry=[".whl", ".gl"], timeout_s=540); the results come back from $OUT.
#
# Wheels: WHEELS (default .whl) if it holds any, else PyPI; torch is never installed or replaced. EGL: the debs in
# .gl/ are unpacked into / first when run as root. Results: OUT_DIR (default $OUT if set, else /tmp/gpu_check).
set -uo pipefail

cd "$(dirname "$0")/.."
REPO=$(pwd)
WHEELS=${WHEELS:-.whl}
DEVICE=${DEVICE:-cuda}
OUT_DIR=${OUT_DIR:-${OUT:-/tmp/gpu_check}}
SITE=${SITE:-/tmp/gpu_check_site}
PYTHON=${PYTHON:-python3}
# What the CUDA image lacks (its python3 has torch, numpy, cloudpickle, tqdm, rich, pyyaml, pandas, matplotlib)
PACKAGES=(stable_baselines3==2.9.2 sb3_contrib==2.9.2 gymnasium==1.4.0 farama-notifications==0.0.6 mujoco==4.0.1 mujoco-core==4.0.1
    mujoco-studio==4.0.1 mujoco-studio-wasm==4.0.1 websockets==17.4 glfw==2.11.0 pyopengl==3.1.10)

if [[ "${1:-}" == "--fetch" ]]; then
    "$PYTHON" -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d "$WHEELS" "${PACKAGES[@]}" || exit
    apt_options=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    mkdir -p .gl /tmp/amd64/partial
    apt-get "${apt_options[@]}" update -qq || exit
    (cd .gl && apt-get "${apt_options[@]}" download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2) || exit
    du -sh "$WHEELS" .gl
    exit 0
fi

mkdir -p "$OUT_DIR"
if [[ "$DEVICE" == cpu ]]; then
    # The tiny version: this machine's environment as it is, small sizes
    export PYTHONPATH="$REPO:$REPO/benchmarks${PYTHONPATH:+:$PYTHONPATH}"
    throughput_args=(--device cpu --quick --threads 1 --no-thesis --presets cpu_learning --preset-updates 4)
    train_args=(--preset cpu --obs-type state --device cpu --threads 1 --sim-steps 8000 --learning-starts 200
        --latent-pretrain-steps 5)
    # Eager: compiling the preset's update on a CPU takes minutes, longer than the run's timeout
    small_train_args=(--preset cpu_pixels32_bounded --device cpu --threads 1 --sim-steps 8000 --learning-starts 200
        --latent-pretrain-steps 5 --hyperparams compile_updates=false)
else
    if [[ $(id -u) == 0 ]] && compgen -G ".gl/*.deb" >/dev/null; then
        for deb in .gl/*.deb; do dpkg -x "$deb" /; done
        ldconfig
    fi
    if compgen -G "$WHEELS/*.whl" >/dev/null; then
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" \
            "$WHEELS"/*.whl || exit
    else
        # PyPI, into the environment of the installed torch, pinned so that no CPU build replaces the CUDA one
        "$PYTHON" -c "import torch; print(f'torch=={torch.__version__}')" >"$OUT_DIR/constraints.txt" || exit
        "$PYTHON" -m pip install -q -c "$OUT_DIR/constraints.txt" "${PACKAGES[@]}" || exit
    fi
    # The checkout, not an installed copy, is what runs
    export PYTHONPATH="$REPO:$REPO/benchmarks:$SITE"
    throughput_args=(--device cuda --quick --presets cpu_learning cpu_pixels32_bounded)
    train_args=(--preset thesis_fast --device cuda --sim-steps 8000 --learning-starts 500 --latent-pretrain-steps 100)
    small_train_args=(--preset cpu_pixels32_bounded --device cuda --sim-steps 40000 --learning-starts 1000
        --latent-pretrain-steps 100)
fi
export PYTHONUNBUFFERED=1 MUJOCO_GL=${MUJOCO_GL:-egl}
nvidia_egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [[ -f $nvidia_egl && -z ${__EGL_VENDOR_LIBRARY_FILENAMES:-} ]]; then
    export __EGL_VENDOR_LIBRARY_FILENAMES=$nvidia_egl
fi
render_check="import mujoco; context = mujoco.GLContext(64, 64); context.make_current(); context.free()"
if ! "$PYTHON" -c "$render_check" 2>/dev/null; then
    echo "MUJOCO_GL=$MUJOCO_GL cannot render here, trying osmesa"
    export MUJOCO_GL=osmesa PYOPENGL_PLATFORM=osmesa
    "$PYTHON" -c "$render_check" || { echo "no headless rendering (egl, osmesa)"; exit 1; }
fi
"$PYTHON" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
[[ "$DEVICE" == cpu ]] || "$PYTHON" -c "import torch; assert torch.cuda.is_available(), 'no CUDA device'" || exit

echo "== throughput ($(date +%T))"
timeout 240 "$PYTHON" benchmarks/throughput.py "${throughput_args[@]}" --out "$OUT_DIR" 2>&1 | tee "$OUT_DIR/throughput.log"
throughput_status=${PIPESTATUS[0]}

train_run() {  # train_run NAME TIMEOUT ARGS...: one short training run into $OUT_DIR/NAME
    local name=$1 seconds=$2
    shift 2
    echo "== training run $name ($(date +%T))"
    rm -rf "${OUT_DIR:?}/$name"
    timeout "$seconds" "$PYTHON" -m sb3_dsslac train --env SafetyGym/PointGoal1-v0 "$@" --out "$OUT_DIR/$name" \
        --eval-every 1000000000 --checkpoint-every 1000000000 --quiet --no-progress-bar 2>&1 | tee "$OUT_DIR/$name.log"
    return "${PIPESTATUS[0]}"
}
train_run train_run 120 "${train_args[@]}"
train_status=$?
train_run small_train_run 90 "${small_train_args[@]}"
small_train_status=$?

echo
echo "== $(date +%T): throughput exit $throughput_status, training exits $train_status and $small_train_status (124: timed out)"
cat "$OUT_DIR"/throughput_*.md 2>/dev/null || echo "(no throughput table)"
# Agent steps/s and updates/s of each training run between its first and last progress rows after the warm-up and the
# latent pre-training (train logs one row every 4 episodes, time/time_elapsed in whole seconds)
"$PYTHON" - "$OUT_DIR/train_run/progress.csv" "${train_args[*]}" "$OUT_DIR/small_train_run/progress.csv" \
    "${small_train_args[*]}" <<'EOF'
import csv
import sys

print("| real training | agent steps | updates | agent steps/s | updates/s |\n|---|---:|---:|---:|---:|")
for path, args in zip(sys.argv[1::2], sys.argv[2::2], strict=True):
    try:
        with open(path) as file:
            rows = [row for row in csv.DictReader(file) if row.get("train/n_updates")]
    except FileNotFoundError:
        rows = []
    if len(rows) < 2:
        print(f"| {args} | fewer than 2 progress rows after the warm-up | | | |")
        continue
    first, last = rows[0], rows[-1]
    steps = float(last["time/total_timesteps"]) - float(first["time/total_timesteps"])
    seconds = float(last["time/time_elapsed"]) - float(first["time/time_elapsed"])
    updates = float(last["train/n_updates"]) - float(first["train/n_updates"])
    print(f"| {args} | {first['time/total_timesteps']} to {last['time/total_timesteps']} | {updates:.0f} | "
          f"{steps / seconds:.1f} | {updates / seconds:.1f} |")
EOF
