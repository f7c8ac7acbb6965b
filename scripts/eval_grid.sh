#!/usr/bin/env bash
# Evaluates one team (a checkpoint, or the scripted baseline) over several swarm sizes and
# formation shapes on held-out episodes, and prints a Markdown table of the summaries.
set -euo pipefail

usage() {
  cat <<'USAGE'
Usage: scripts/eval_grid.sh TEAM [flags]

  TEAM                    a checkpoint file, or "scripted" for the baseline on every robot

Flags:
  --n LIST                swarm sizes, comma-separated (default 3,4,6,8,12,16,32)
  --shapes LIST           formation shapes, comma-separated (default random)
  --episodes E            episodes per cell (default 100)
  --seed S                episode seed (default 1000; no training run of this project uses it)
  --config FILE           configuration of every run (e.g. configs/paper-observation.toml)
  --out DIR               where the run directories go (default runs/eval-grid-<timestamp>-<pid>: two grids started in the same second do not share it)
  -h, --help              this help

Every cell is a real multi-process run of scripts/run_swarm.sh --mode eval --viewer off.
Environment: FORMATION_BIN_DIR=DIR uses prebuilt binaries (as scripts/run_swarm.sh does).
USAGE
}

die() { echo "eval_grid.sh: error: $*" >&2; exit 2; }
[[ $# -ge 1 ]] || { usage >&2; exit 2; }
case "$1" in -h|--help) usage; exit 0 ;; esac
TEAM=$1; shift
NS=3,4,6,8,12,16,32 SHAPES=random EPISODES=100 SEED=1000 CONFIG="" OUT=""
while [[ $# -gt 0 ]]; do
  [[ $# -ge 2 ]] || die "$1 needs a value"
  case "$1" in
    --n) NS=$2 ;;
    --shapes) SHAPES=$2 ;;
    --episodes) EPISODES=$2 ;;
    --seed) SEED=$2 ;;
    --config) CONFIG=$2 ;;
    --out) OUT=$2 ;;
    *) die "unknown flag '$1'" ;;
  esac
  shift 2
done
[[ "$TEAM" == scripted || -f "$TEAM" ]] || die "no checkpoint file '$TEAM' (or say 'scripted')"

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
OUT=${OUT:-runs/eval-grid-$(date +%Y%m%d-%H%M%S)-$$}
mkdir -p "$OUT"
declare -a TEAM_ARGS
if [[ "$TEAM" == scripted ]]; then TEAM_ARGS=(--scripted all); else TEAM_ARGS=(--checkpoint "$TEAM"); fi
[[ -n "$CONFIG" ]] && TEAM_ARGS+=(--config "$CONFIG")

echo "| N | shape | success | collisions | timeouts | final edge error | steps to goal | formation held |"
echo "|---|---|---|---|---|---|---|---|"
IFS=',' read -ra ns <<<"$NS"
IFS=',' read -ra shapes <<<"$SHAPES"
for shape in "${shapes[@]}"; do
  for n in "${ns[@]}"; do
    dir="$OUT/n$n-$shape"
    if ! "$ROOT/scripts/run_swarm.sh" "$n" --mode eval --episodes "$EPISODES" --seed "$SEED" --shape "$shape" \
        --viewer off --run-dir "$dir" "${TEAM_ARGS[@]}" >"$OUT/n$n-$shape.log" 2>&1; then
      echo "| $n | $shape | run failed: see $OUT/n$n-$shape.log | | | | | |"
      continue
    fi
    python3 - "$dir/summary.json" "$n" "$shape" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
steps = s.get("mean_steps_to_goal")
print(f"| {sys.argv[2]} | {sys.argv[3]} | {s['success_rate']:.2f} | {s['collision_rate']:.2f} | "
      f"{s['timeout_rate']:.2f} | {s['mean_final_edge_error_m']:.3f} m | "
      f"{'-' if steps is None else f'{steps:.1f}'} | {s['formation_hold_rate']:.2f} |")
PY
  done
done
echo "runs: $OUT"
