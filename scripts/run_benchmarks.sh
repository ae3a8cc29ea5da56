#!/usr/bin/env bash
# Run every benchmark suite and regenerate docs/BENCHMARKS.md from their printed tables and JSON.
#   scripts/run_benchmarks.sh            full runs
#   QUICK=1 scripts/run_benchmarks.sh    --quick runs (smaller problems)
#   SUITES="stereo fill" scripts/run_benchmarks.sh
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
OUT="$ROOT/runs/bench"
SUITES_GIVEN="${SUITES:-}"
SUITES="${SUITES:-stereo icp fill plan sim latency closed-loop}"
mkdir -p "$OUT"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
for s in $SUITES; do
  echo "=== terrain-bench $s ${QUICK:+--quick}"
  cmd=("$VENV/bin/terrain-bench" "$s" --json "$OUT/$s.json")
  [ -n "${QUICK:-}" ] && cmd+=(--quick)
  printf '%s\n' "${cmd[*]#"$VENV/bin/"}" > "$OUT/$s.cmd"
  if ! "${cmd[@]}" 2>&1 | tee "$OUT/$s.txt"; then
    echo "terrain-bench $s failed (see $OUT/$s.txt)" >&2
  fi
done
# A partial run (SUITES set) keeps the other suites' sections of the current document.
keep=()
[ -n "${SUITES_GIVEN:-}" ] && [ -f "$ROOT/docs/BENCHMARKS.md" ] && keep=(--keep "$ROOT/docs/BENCHMARKS.md")
"$VENV/bin/python" -m terrain_perception.bench._report "$OUT" "${keep[@]}" > "$ROOT/docs/BENCHMARKS.md.new"
mv "$ROOT/docs/BENCHMARKS.md.new" "$ROOT/docs/BENCHMARKS.md"
echo "docs/BENCHMARKS.md regenerated from $OUT"
