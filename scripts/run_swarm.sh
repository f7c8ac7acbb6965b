#!/usr/bin/env bash
# Starts one formation-control run. The launcher is the `formation` binary (launcher/): it
# checks the flags, declares the run's processes and their restart policy, and supervises them.
# This script only builds the binaries (release) and hands every flag over:
#   scripts/run_swarm.sh 3                  train three robots, watch in Rerun
#   scripts/run_swarm.sh --help             every flag
# FORMATION_BIN_DIR=DIR uses prebuilt binaries from DIR instead of building.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
if [[ -n "${FORMATION_BIN_DIR:-}" ]]; then
  BIN=$FORMATION_BIN_DIR
else
  BIN=${CARGO_TARGET_DIR:-$ROOT/target}/release
  if [[ ! -x "$BIN/formation" ]]; then
    echo "building the release binaries (about 16 minutes the first time on 2 cores)..." >&2
  fi
  (cd "$ROOT" && cargo build --release --quiet --workspace --bins) || {
    echo "run_swarm.sh: error: the build failed" >&2
    exit 2
  }
fi
[[ -x "$BIN/formation" ]] || { echo "run_swarm.sh: error: missing binary $BIN/formation" >&2; exit 2; }
export FORMATION_BIN_DIR=$BIN
exec -a run_swarm.sh "$BIN/formation" "$@"
