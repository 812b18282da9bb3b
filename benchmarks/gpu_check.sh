#!/usr/bin/env bash
# One short session on a GPU machine: the CUDA tests, then the GPU benchmarks, everything written
# under OUT (default: gpu-check/). A few minutes in all; GPU time is scarce, so check it on CPU
# first, where the CUDA tests skip and the benchmarks run the same items on the CPU:
#
#   bash benchmarks/gpu_check.sh cpu /tmp/gpu-check-dry     # the dry run, here
#   bash benchmarks/gpu_check.sh cuda "$OUT"                 # on the GPU machine
#
# Writes device.txt (torch, CUDA, device name), cuda_tests.txt (pytest of the CUDA tests),
# bench/bench.{csv,md} (dslearn-bench: one GP consensus configuration, ms per step of GP
# learning + hybrid consensus on 10-200 nodes, peak host and CUDA memory) and bench.txt.
set -euo pipefail
DEVICE="${1:-cuda}"
OUT="${2:-${OUT:-gpu-check}}"
case "$DEVICE" in cpu|cuda|cuda:*) ;; *) echo "gpu_check.sh: DEVICE must be cpu or cuda[:i], got '$DEVICE'" >&2; exit 2 ;; esac
cd "$(dirname "$0")/.."
mkdir -p "$OUT"
python - "$DEVICE" <<'PY' | tee "$OUT/device.txt"
import sys, torch
dev = sys.argv[1]
print("torch", torch.__version__, "| CUDA available:", torch.cuda.is_available(),
      "|", torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU")
if dev.startswith("cuda") and not torch.cuda.is_available():
    sys.exit("gpu_check.sh: DEVICE=cuda but torch sees no CUDA device")
PY
# the CUDA tests (they skip without a device; test_study's CPU-side check runs instead)
timeout 300 python -m pytest -q -p no:cacheprovider -rs tests/test_perf_paths.py tests/test_study.py -k "cuda" \
  2>&1 | tee "$OUT/cuda_tests.txt"
# the GPU benchmarks: network sizes (GP learning + hybrid consensus per step) and one GP consensus
# configuration of the Yu protocol (50 + 50 episodes in --quick)
timeout 420 dslearn-bench network protocol --quick --models gp_increment --fusions hybrid --workers 1 \
  --device "$DEVICE" --out "$OUT/bench" 2>&1 | tee "$OUT/bench.txt"
echo "gpu_check.sh: done; results in $OUT"
