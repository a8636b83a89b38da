#!/bin/bash
# One timing series (issue 19): `invaders bench` in f32 and bf16 against TensorFlow and PyTorch in
# f32 and bf16 (the scripts of ../shared/bench), alternating, ROUNDS rounds at 1 and 2 threads,
# with the CPU named and its FMA peak. Never while a training run is going.
#
# usage: tools/bench_series.sh [ROUNDS] [OUT]      (from the repository's root, after
#        `cargo build --release`; PY is the Python with tensorflow-cpu and torch installed;
#        CKPT, if set, is a trained network whose acting `bench` times too, e.g.
#        models/strong/model.safetensors)
set -u
ROUNDS=${1:-3}
OUT=${2:-bench-series.log}
BIN=target/release/invaders
PY=${PY:-python3}
B=${BENCH:-../shared/bench}
{
  date
  lscpu | grep -E "Model name|^CPU\(s\)|Thread"
  grep -o -w -E "avx512_bf16|amx_tile|amx_bf16" /proc/cpuinfo | sort -u | tr '\n' ' '
  echo
  gcc -O2 -mavx512f -mfma -fopenmp "$B/peak.c" -o /tmp/peak &&
    OMP_NUM_THREADS=1 /tmp/peak && OMP_NUM_THREADS=2 /tmp/peak
} >> "$OUT" 2>&1
for r in $(seq 1 "$ROUNDS"); do
  for t in 1 2; do
    for p in f32 bf16; do
      echo "round $r ours-$p threads=$t $($BIN bench --json --threads "$t" --precision $p --steps 30 ${CKPT:+--checkpoint "$CKPT"} 2>/dev/null)" >> "$OUT"
    done
    for script in tf_step tf_step_bf16 torch_step torch_step_bf16; do
      echo "round $r $($PY "$B/$script.py" "$t" 30 2>/dev/null | tail -1)" >> "$OUT"
    done
  done
done
date >> "$OUT"
