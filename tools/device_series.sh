#!/bin/bash
# One round of a timing series on the lent device machine's CPU (issue 41; series K of
# docs/performance.md): ours in `auto` and f32 against PyTorch's f32 and bf16 scripts, alternating,
# at 1, 2 and 16 threads, with the CPU named and its FMA peak. TensorFlow is not installed there
# (and its wheel is larger than what a call may carry), so PyTorch is the only reference.
#
# Prepare here (B is a folder that .git/info/exclude ignores, carried with the call):
#   mkdir -p .dev && strip -o .dev/invaders target/release/invaders &&
#   cp ../shared/bench/torch_step.py ../shared/bench/torch_step_bf16.py ../shared/bench/peak.c .dev/
# then run there: `R=1 B=.dev bash tools/device_series.sh`, and again with R=2 on the same warm
# machine. Each bench call is bounded (timeout) and every line goes to $OUT/series.log at once,
# so a call stopped at its limit still brings back what it measured.
set -u
B=${B:-.dev}
R=${R:-1}
L=${OUT:-.}/series.log
{
  date
  lscpu | grep -E "Model name|^CPU\(s\)|Thread|CPU family|^Model:|Hypervisor|L2|L3|MHz"
  grep -o -w -E "avx2|avx512f|avx512_bf16|amx_tile|amx_bf16|amx_int8" /proc/cpuinfo | sort -u | tr '\n' ' '
  echo
  python3 -c "import torch; print('torch', torch.__version__, torch.backends.mkldnn.is_available())"
  gcc -O2 -mavx512f -mfma -fopenmp "$B/peak.c" -o /tmp/peak &&
    for t in 1 2 16; do OMP_NUM_THREADS=$t /tmp/peak; done
} >> "$L" 2>&1
for t in 1 2 16; do
  echo "round $R ours-auto threads=$t $(timeout 150 "$B/invaders" bench --json --threads $t --precision auto --steps 20 2>/dev/null)" >> "$L"
  echo "round $R torch threads=$t $(timeout 60 python3 "$B/torch_step.py" $t 20 2>/dev/null | tail -1)" >> "$L"
  echo "round $R torch-bf16 threads=$t $(timeout 60 python3 "$B/torch_step_bf16.py" $t 20 2>/dev/null | tail -1)" >> "$L"
  echo "round $R ours-f32 threads=$t $(timeout 150 "$B/invaders" bench --json --threads $t --precision f32 --steps 20 2>/dev/null)" >> "$L"
done
date >> "$L"
