#!/usr/bin/env bash
# Runs on the lent GPU machine (see docs/benchmarks.md for how the figures were made).
# The machine has torch/lightning/scipy but not taichi, warp, hydra, trimesh, zarr: they travel as
# wheels under .whl/ (warp split in three parts, one per call). Usage: bash benchmarks/gpu.sh <phase>
set -uo pipefail
phase=${1:-wheels}
W=/tmp/w
mkdir -p "$W" /tmp/site
for f in .whl/*/*; do [ -f "$f" ] && cp -n "$f" "$W/"; done
if ls "$W"/warp.part0{0,1,2} >/dev/null 2>&1 && [ ! -f "$W/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl" ]; then
  cat "$W"/warp.part00 "$W"/warp.part01 "$W"/warp.part02 > "$W/warp_lang-1.19.0-py3-none-manylinux_2_28_x86_64.whl"
fi
for whl in "$W"/*.whl; do
  stamp="$W/.done-$(basename "$whl")"
  [ -f "$stamp" ] && continue
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$whl" && touch "$stamp"
done
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 WANDB_MODE=disabled
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
case "$phase" in
  wheels) ls /tmp/site | head -50 ;;
  bench-sim)
    python3 benchmarks/sim_throughput.py --device cuda 2>&1 | tee "$OUT/bench_sim.txt" ;;
  bench-rest)
    for b in topology reward train train_policy; do
      [ -f benchmarks/$b.py ] && timeout 150 python3 benchmarks/$b.py --device cuda 2>&1 | tee "$OUT/bench_$b.txt"
    done
    timeout 120 python3 benchmarks/mppi.py --device cuda --K 16 --n-grid 128 2>&1 | tee "$OUT/bench_mppi.txt" ;;
  *) echo "unknown phase $phase"; exit 2 ;;
esac
