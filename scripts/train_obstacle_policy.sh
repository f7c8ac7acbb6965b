#!/usr/bin/env bash
# The recipe of the forest-and-trap policy (models/formation-obstacles.safetensors), one seed, each
# stage's RL length given in gradient updates, so it is the same amount of learning on any machine
# (configs/obstacles-memory.toml; this script's seed 22 is the shipped file, 4e6ec666):
#   D1  a DAgger student of the detouring field with every robot's recovery behaviour on, the ticks
#       it takes over labelled with its command (formation-distill --teach-recovery 30: a teacher
#       with memory), reading a window of 4 observations (60 rounds, sizes 4, 8, 16)
#   D2  12,000 updates of the critic's RL (TD3 + HER + BC, the imitation term pulling towards D1)
#       from swarms of 4, 8 and 16 robot processes
# The result is RUN_ROOT/d2/best.safetensors (the critic's own pick on its selection episodes);
# each stage's wall time is printed and written to RUN_ROOT/times.txt. Measured on a 2-core
# machine: docs/RESULTS.md, "A teacher with memory". The recipe before it (a student of the
# field alone, H = 1, and three RL stages): `git show c686a66:scripts/train_obstacle_policy.sh`.
#
#   scripts/train_obstacle_policy.sh SEED [RUN_ROOT]     # RUN_ROOT default: runs/recipe-sSEED
#
# FORMATION_BIN_DIR=DIR uses prebuilt binaries from DIR (else it builds the release binaries).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [[ $# -lt 1 || $# -gt 2 || ! $1 =~ ^[0-9]+$ ]]; then
  sed -n '2,17p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//' >&2
  exit 2
fi
SEED=$1
RUNS=${2:-$ROOT/runs/recipe-s$SEED}
CONFIG=$ROOT/configs/obstacles-memory.toml
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
  --teach-recovery 30 --out "$RUNS/d1-student.safetensors" --seed "$SEED"
stage d2 "$ROOT/scripts/run_swarm.sh" 4 --extra-swarms 8,16 --mode train --config "$CONFIG" \
  --checkpoint "$RUNS/d1-student.safetensors" --updates 12000 --seed $((200 + 10#$SEED)) --viewer off \
  --run-dir "$RUNS/d2"
echo "total $(( $(date +%s) - START )) s" | tee -a "$RUNS/times.txt"
echo "the policy: $RUNS/d2/best.safetensors"
