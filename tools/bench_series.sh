#!/bin/bash
# One timing series (issues 19 and 41): `invaders bench` in f32 and bf16 against TensorFlow and
# PyTorch in f32 and bf16 (the scripts of ../shared/bench), alternating, ROUNDS rounds at 1 and 2
# threads, with the CPU named and its FMA peak. Never while a training run is going.
#
# usage: tools/bench_series.sh [ROUNDS] [OUT]      (from the repository's root, after
#        `cargo build --release`; PY is the Python with tensorflow-cpu and torch installed;
#        CKPT, if set, is a trained network whose acting `bench` times too, e.g.
#        models/strong/model.safetensors)
#
# SCRIPTS names the reference scripts to run (default: all four), e.g. SCRIPTS="tf_step
# torch_step" for a shorter series once the bf16 ones are known to be far behind.
# Ours runs in f32, bf16 and auto (what a run resolves to here) and, on a CPU with AMX tiles,
# bf16 under INVADERS_NO_AMX=1 as well (the vdpbf16ps kernel; series H).
# ISA=avx2 times what a CPU without AVX-512 runs, on any host: ours under INVADERS_NO_AVX512=1
# (in f32: bf16 needs AVX512-BF16),
# the frameworks under ONEDNN_MAX_CPU_ISA=AVX2 (TensorFlow and PyTorch) and
# ATEN_CPU_CAPABILITY=avx2 (PyTorch's own kernels), and the peak of 256-bit FMAs.
# BIN times another build of ours (say, the one before a change, copied aside); PRECISIONS
# names ours to run (default "f32 bf16 auto"); NO_AMX=0 leaves out the run under INVADERS_NO_AMX.
set -u
ROUNDS=${1:-3}
OUT=${2:-bench-series.log}
BIN=${BIN:-target/release/invaders}
PY=${PY:-python3}
B=${BENCH:-../shared/bench}
ISA=${ISA:-native}
OURS_ENV=()
PY_ENV=()
if [ "$ISA" = avx2 ]; then
  OURS_ENV=(INVADERS_NO_AVX512=1)
  PY_ENV=(ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2)
fi
{
  date
  echo "binary: $BIN, $(git rev-parse --short HEAD 2>/dev/null)"
  echo "ISA=$ISA"
  lscpu | grep -E "Model name|^CPU\(s\)|Thread|CPU family|^Model:"
  grep -o -w -E "avx2|avx512f|avx512_bf16|amx_tile|amx_bf16" /proc/cpuinfo | sort -u | tr '\n' ' '
  echo
  if [ "$ISA" = avx2 ]; then
    sed 's/__m512/__m256/g; s/_mm512_/_mm256_/g; s/\*16\*2/*8*2/; s/float out\[16\]/float out[8]/' \
      "$B/peak.c" > /tmp/peak_avx2.c &&
      gcc -O2 -mavx2 -mfma -fopenmp /tmp/peak_avx2.c -o /tmp/peak
  else
    gcc -O2 -mavx512f -mfma -fopenmp "$B/peak.c" -o /tmp/peak
  fi && OMP_NUM_THREADS=1 /tmp/peak && OMP_NUM_THREADS=2 /tmp/peak
} >> "$OUT" 2>&1
for r in $(seq 1 "$ROUNDS"); do
  for t in 1 2; do
    # Under ISA=avx2 ours has no bf16 kernels (they need AVX512-BF16): f32 only.
    precisions=${PRECISIONS:-f32 bf16 auto}
    [ "$ISA" = avx2 ] && precisions=f32
    for p in $precisions; do
      echo "round $r ours-$p threads=$t $(env "${OURS_ENV[@]}" $BIN bench --json --threads "$t" --precision $p --steps 30 ${CKPT:+--checkpoint "$CKPT"} 2>/dev/null)" >> "$OUT"
    done
    if [ "$ISA" != avx2 ] && [ "${NO_AMX:-1}" != 0 ] && grep -q -w amx_bf16 /proc/cpuinfo; then
      echo "round $r ours-bf16-noamx threads=$t $(INVADERS_NO_AMX=1 $BIN bench --json --threads "$t" --precision bf16 --steps 30 ${CKPT:+--checkpoint "$CKPT"} 2>/dev/null)" >> "$OUT"
    fi
    for script in ${SCRIPTS:-tf_step tf_step_bf16 torch_step torch_step_bf16}; do
      echo "round $r $(env "${PY_ENV[@]}" $PY "$B/$script.py" "$t" 30 2>/dev/null | tail -1)" >> "$OUT"
    done
  done
done
date >> "$OUT"
