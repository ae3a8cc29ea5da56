#!/usr/bin/env bash
# Interleaved timing-trace A/B of two git revisions: the same short terrain-demo runs (A, B, A,
# B...) with TERRAIN_TIMING_DIR set, then per side the pooled capture-to-plan (summary.json,
# each run's first plan dropped as start-up) and the stage medians of timing_report.
#
#   scripts/ab-trace.sh REV_A REV_B OUT_PREFIX FIRST_SEED N_SEEDS [terrain-demo options]
#
# e.g. scripts/ab-trace.sh 96ef4f1 ef84cf7 runs/ab-trace-s52b 100 3 --max-sim-time 30
#
# Run i of REV_A goes to OUT_PREFIX-a-SEED (its trace in trace/), of REV_B to OUT_PREFIX-b-SEED;
# the summary is printed and written to OUT_PREFIX-summary.txt. Each revision is checked out
# into a temporary worktree sharing this checkout's build/. ROS_AUTOMATIC_DISCOVERY_RANGE
# defaults to LOCALHOST and ROS_DOMAIN_ID to 47. About 3.3 min per 30 s run on a 2-core Xeon.
set -euo pipefail
if [ $# -lt 5 ]; then
  sed -n '2,13p' "$0" >&2
  exit 2
fi
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
REV_A=$1 REV_B=$2 OUT=$3 FIRST=$4 N=$5
shift 5
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-47}"
PY="$ROOT/.venv/bin/python"
DEMO="$ROOT/.venv/bin/terrain-demo"
case "$OUT" in /*) ;; *) OUT="$PWD/$OUT" ;; esac

# worktrees $TMP/a and $TMP/b of REV_A and REV_B, removed on exit
source "$ROOT/scripts/ab-worktrees.sh"

for ((s = FIRST; s < FIRST + N; s++)); do
  for side in a b; do
    run="$OUT-$side-$s"
    rm -rf "$run"
    echo "[ab-trace] seed $s: revision $([ $side = a ] && echo "$REV_A" || echo "$REV_B") -> $run"
    (cd "$TMP/$side" && PYTHONPATH="$TMP/$side" TERRAIN_TIMING_DIR="$run/trace" \
       "$DEMO" --seed "$s" --no-bag --run-dir "$run" --quiet "$@" > "$run.log" 2>&1) \
      || echo "[ab-trace] run failed, see $run.log"
  done
done
PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}" "$PY" - "$OUT" "$FIRST" "$N" <<'PYEOF' | tee "$OUT-summary.txt"
import json, statistics, sys
from pathlib import Path
from terrain_ros.tools.timing_report import load, stage_parts
out, first, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
for side in 'ab':
    lat, per, parts = [], [], {}
    for s in range(first, first + n):
        d = Path(f'{out}-{side}-{s}')
        try:
            ms = json.loads((d / 'summary.json').read_text())['capture_to_plan_ms_all'][1:]
        except (OSError, KeyError, ValueError):
            print(f'side {side} seed {s}: no summary.json with latencies in {d}')
            continue
        lat += ms
        per.append(round(statistics.median(ms), 1))
        for st, pp in stage_parts(load(d / 'trace')).items():
            for k, v in pp.items():
                parts.setdefault(st, {}).setdefault(k, []).extend(v)
    if not lat:
        continue
    lat.sort()
    print(f'side {side}: capture-to-plan median {statistics.median(lat):.1f} ms, p95 '
          f'{lat[int(0.95 * (len(lat) - 1))]:.1f} ms over {len(lat)} plans; per seed {per}')
    for st, pp in parts.items():
        print(f'   {st:18s}' + ' '.join(f'{k} {statistics.median(v):5.1f}'
                                        for k, v in pp.items() if v))
PYEOF
