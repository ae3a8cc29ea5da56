#!/usr/bin/env bash
# Closed-loop A/B of two git revisions of this repository: the same trials, interleaved
# (A, B, A, B...) so that a machine whose speed drifts over the hour affects both alike.
#
#   scripts/ab-closed-loop.sh REV_A REV_B OUT_PREFIX FIRST_SEED N_SEEDS [closed-loop options]
#
# e.g. scripts/ab-closed-loop.sh 267aa60 d0830dd runs/bench/ab-latency-s48 100 3 \
#          --courses rocks-6cm --variants full --front-gap 0.3 --max-sim-time 50
#
# Each revision is checked out into a temporary worktree (removed afterwards) sharing this
# checkout's build/ (the interface package and the fill library cache) and run with the venv's
# terrain-bench and its PYTHONPATH first; trial i of REV_A goes to OUT_PREFIX-a, of REV_B to
# OUT_PREFIX-b. At the end each side is tabulated (`--table-only`, which prints the success
# rates and the pooled capture-to-plan median / p95) into OUT_PREFIX-{a,b}.{txt,json}.
# ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST and ROS_DOMAIN_ID to 41.
set -euo pipefail
if [ $# -lt 5 ]; then
  sed -n '2,16p' "$0" >&2
  exit 2
fi
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REV_A=$1 REV_B=$2 OUT=$3 FIRST=$4 N=$5
shift 5
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-41}"
BENCH="$ROOT/.venv/bin/terrain-bench"
[ -x "$BENCH" ] || BENCH=terrain-bench
case "$OUT" in /*) ;; *) OUT="$PWD/$OUT" ;; esac

# worktrees $TMP/a and $TMP/b of REV_A and REV_B, removed on exit
source "$ROOT/scripts/ab-worktrees.sh"

for ((s = FIRST; s < FIRST + N; s++)); do
  for side in a b; do
    echo "[ab] seed $s: revision $([ $side = a ] && echo "$REV_A" || echo "$REV_B") -> $OUT-$side"
    (cd "$TMP/$side" && PYTHONPATH="$TMP/$side" "$BENCH" closed-loop --seeds 1 --first-seed "$s" \
       --resume any-code --out "$OUT-$side" "$@")
  done
done
for side in a b; do
  "$BENCH" closed-loop --table-only --seeds "$N" --first-seed "$FIRST" --out "$OUT-$side" \
    --json "$OUT-$side.json" "$@" | tee "$OUT-$side.txt"
done
