#!/usr/bin/env bash
# A longer chaos soak than `make test-long` runs: RUNS runs of lqr_2_1 (H = 50) under FAULTS random faults each
# (pauses of 5-90 s, kills of a node or of npp-run, restarts), seeded; every run must end as the
# uninterrupted run. The report goes to results/reliability/chaos-soak-seed<SEED>.txt.
# Usage: scripts/chaos_soak.sh [RUNS (default 10)] [SEED (default 1)] [FAULTS (default 3)]
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
runs="${1:-10}" seed="${2:-1}" faults="${3:-3}"
out="$repo/results/reliability/chaos-soak-seed${seed}.txt"
mkdir -p "$(dirname "$out")"
{
  echo "command: scripts/chaos_soak.sh $runs $seed $faults"
  echo "machine: $(nproc) cores, $(uname -m), $(date -u +%Y-%m-%d)"
} > "$out"
cd "$repo"
NPP_CHAOS_RUNS="$runs" NPP_CHAOS_SEED="$seed" NPP_CHAOS_FAULTS="$faults" NPP_CHAOS_REPORT="$out" \
  .venv/bin/python -m pytest tests/ros/test_chaos.py -k random -q -p no:cacheprovider
echo "report: $out"
