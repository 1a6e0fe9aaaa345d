#!/usr/bin/env bash
# The GPU checks of issues 13 and 14 in one pass, on a machine with a CUDA GPU and a python3 that has
# torch (e.g. a lent device machine; run from the repository root):
#
#   bench/gpu_session.sh LEGO OUT [SECONDS] [PHASE]
#
# LEGO: the NeRF-synthetic lego at 400 x 400 (../shared/data/nerf_synthetic_lego_400); OUT: where
# logs and results go; SECONDS: a budget after which no stage starts and a running one is stopped
# (default 540); PHASE: "first" (default: the GPU tests, the 400 x 400 rsir i32 dataset, the
# protocol's spikelik run with the default 9000 iterations, a profile of its steps, the same run with
# 27000 iterations) or "more" (the 27000-iteration run resumed if the first phase was cut, then the
# baselines at i32). Every stage's log lands in OUT; the protocol's rows in OUT/protocol_gpu.jsonl
# (bench/bench_protocol.py --results), to be copied to bench/results/protocol_gpu.jsonl.
set -u
LEGO=$1
OUT=$2
BUDGET=${3:-540}
PHASE=${4:-first}
T0=$(date +%s)
mkdir -p "$OUT"
left() { echo $((BUDGET - ($(date +%s) - T0))); }
stage() {  # stage NAME CMD...: run CMD with what is left of the budget, its output in OUT/NAME.log
    local name=$1; shift
    local t=$(left)
    if [ "$t" -lt 15 ]; then echo "[$((BUDGET - t)) s] $name: skipped (budget spent)"; return 1; fi
    echo "[$((BUDGET - t)) s] $name: start ($t s left)"
    timeout "$t" "$@" >"$OUT/$name.log" 2>&1
    local rc=$?
    echo "[$((BUDGET - $(left))) s] $name: exit $rc"; tail -n 4 "$OUT/$name.log"
    return $rc
}

# the project installed into the machine's python3 (no index: everything it needs is there or carried)
if ! command -v spikenerf >/dev/null; then
    python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >"$OUT/install.log" 2>&1 \
        || { echo "install failed:"; tail -n 5 "$OUT/install.log"; exit 1; }
fi
# bench_protocol.py reads the lego from ../shared/data beside the checkout
if [ ! -e ../shared/data/nerf_synthetic_lego_400 ]; then
    mkdir -p ../shared/data && ln -s "$(realpath "$LEGO")" ../shared/data/nerf_synthetic_lego_400
fi
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  python3 -c "import sys, numpy, torch; print('python', sys.version.split()[0], 'numpy', numpy.__version__, 'torch', \
torch.__version__, 'cuda', torch.version.cuda)"
  nproc; uptime; } | tee "$OUT/env.txt"

P="python3 bench/bench_protocol.py --resolution 400 --sensors rsir --intensities 32 --device cuda --workers $(nproc)
   --results $OUT/protocol_gpu.jsonl --out bench_out/protocol"
RUN=bench_out/protocol/runs_400/lego_rsir_32_spikelik_true-maps_400_0_9000_0_grid-fitted-box
if [ "$PHASE" = first ]; then
    stage gpu_tests python3 -m pytest -q -p no:cacheprovider -m gpu tests/test_trainer_gpu.py
    stage protocol_9000 $P --methods spikelik --seeds 0
    if [ -n "${REF_MANIFEST:-}" ]; then  # the dataset made here against one made elsewhere: the same bytes?
        python3 -c "import json, sys; a, b = (json.load(open(f))['files'] for f in sys.argv[1:]); \
print('dataset files', len(a), 'identical to the reference' if a == b else 'DIFFER from the reference:', \
sum(x != y for x, y in zip(a, b)), 'of', len(b))" bench_out/protocol/data_lego_rsir_400/nerf_synthetic_lego_400_i32/manifest.json \
            "$REF_MANIFEST" | tee "$OUT/dataset_check.txt"
    fi
    stage profile python3 bench/bench_trainer_profile.py "$RUN" --steps 200 --device cuda
    stage protocol_27000 $P --methods spikelik --seeds 0 --iters 27000
else
    stage protocol_27000b $P --methods spikelik --seeds 0 --iters 27000
    stage protocol_baselines $P --methods tfp32,tfi,spikenerf-paper --seeds 0
fi
echo "[$((BUDGET - $(left))) s] done"
