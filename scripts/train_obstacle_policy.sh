#!/usr/bin/env bash
# The recipe of the forest-and-trap policy (models/formation-obstacles.safetensors), one seed,
# each stage's length given in gradient updates (those of 093812fc, the file before; this
# script's seed 5 is the shipped file), so it is the same amount of learning on any machine:
#   D1  a DAgger student of the detouring field (formation-distill, 60 rounds, sizes 4, 8, 16)
#   D2  12,103 updates of the critic's RL (TD3 + HER + BC) from swarms of 4, 8 and 16 robots
#   D3  14,053 more, from D2's best.safetensors (the critic's own pick on its selection episodes)
#   D4  20,554 more, from D3's best.safetensors
# The result is RUN_ROOT/d4/best.safetensors; each stage's wall time is printed and written to
# RUN_ROOT/times.txt. Measured alone on a 2-core machine: docs/RESULTS.md, "The recipe in updates".
#
#   scripts/train_obstacle_policy.sh SEED [RUN_ROOT]     # RUN_ROOT default: runs/recipe-sSEED
#
# FORMATION_BIN_DIR=DIR uses prebuilt binaries from DIR (else it builds the release binaries).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [[ $# -lt 1 || $# -gt 2 || ! $1 =~ ^[0-9]+$ ]]; then
  sed -n '2,14p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//' >&2
  exit 2
fi
SEED=$1
RUNS=${2:-$ROOT/runs/recipe-s$SEED}
CONFIG=$ROOT/configs/obstacles-detouring.toml
if [[ -e $RUNS ]]; then
  echo "train_obstacle_policy.sh: error: $RUNS exists; give another RUN_ROOT" >&2
  exit 2
fi
mkdir -p "$RUNS"
if [[ -z "${FORMATION_BIN_DIR:-}" ]]; then
  (cd "$ROOT" && cargo build --release --quiet --workspace --bins)
  export FORMATION_BIN_DIR=${CARGO_TARGET_DIR:-$ROOT/target}/release
fi

START=$(date +%s)
stage() { # NAME COMMAND...: runs one stage, logs it, prints and records its wall time
  local name=$1 t0
  shift
  t0=$(date +%s)
  echo "== $name: $*"
  "$@" > "$RUNS/$name.log" 2>&1 || { echo "stage $name failed; see $RUNS/$name.log" >&2; exit 1; }
  echo "$name $(( $(date +%s) - t0 )) s" | tee -a "$RUNS/times.txt"
}

stage d1 "$FORMATION_BIN_DIR/formation-distill" --config "$CONFIG" --sizes 4,8,16 --rounds 60 \
  --out "$RUNS/d1-student.safetensors" --seed "$SEED"
from=$RUNS/d1-student.safetensors
for spec in d2:12103:110 d3:14053:120 d4:20554:130; do
  IFS=: read -r name updates base <<< "$spec"
  stage "$name" "$ROOT/scripts/run_swarm.sh" 4 --extra-swarms 8,16 --mode train --config "$CONFIG" \
    --checkpoint "$from" --updates "$updates" --seed $((base + 10#$SEED)) --viewer off --run-dir "$RUNS/$name"
  from=$RUNS/$name/best.safetensors
done
echo "total $(( $(date +%s) - START )) s" | tee -a "$RUNS/times.txt"
echo "the policy: $from"
