#!/usr/bin/env bash
# Launches one formation-control run: the sim, N agent processes and the critic, all talking
# over iceoryx2 shared memory under one run-unique prefix. Ctrl-C ends the run cleanly.
set -euo pipefail

usage() {
  cat <<'USAGE'
Usage: scripts/run_swarm.sh N [flags]

Starts the physics process, N robot processes and the central critic, lockstep over iceoryx2
shared memory, and leaves results in a run directory.

  N                       robots in the swarm, 3 to 64

Flags:
  --mode train|eval       train: explore and learn (default); eval: act without noise, record
  --episodes E            stop after E episodes (eval default: 100)
  --minutes M             stop after M minutes of wall clock (train default: 30)
  --scripted all|i,j,...  robots that run the scripted baseline instead of the learned actor
  --external all|i,j,...  robots this script does not start: you attach them yourself, e.g.
                          from Python (pip install ./python; python3 -m formation_swarm
                          robot RUN_DIR i); the sim waits ticks.startup_timeout_s (60 s) for
                          them to greet. See README.md, "From Python", and docs/PROTOCOL.md
  --checkpoint PATH       checkpoint file or run directory: eval loads it into the agents,
                          train resumes the critic from it (eval default: the shipped model
                          models/formation.safetensors, one model for any N)
  --seed S                seed of episodes, noise and networks (default 1)
  --run-dir DIR           where results go (default runs/<timestamp>)
  --viewer MODE           spawn | save | off | connect=URL (default: spawn when a `rerun`
                          viewer and a display are present, else save)
  --realtime              pace ticks at dt of wall-clock time instead of as fast as possible
  --config FILE           TOML overrides of the defaults (see config.toml in any run dir)
  --shape KIND            formation of every episode: random (default), ring, line, wedge,
                          grid, or mixed (a kind drawn per episode); every observed edge
                          0.8-2.0 m, any N
  --placement auto|off    auto (default): the sim's tick thread and the robots share the
                          last CPU this shell may use, the critic and the view get the
                          others (ticks are 2-4x faster than letting the OS place them);
                          24 robots or more split into groups of at least 12 per CPU.
                          off: the OS places every process
  --extra-swarms N1,N2,.. train mode: besides the N-robot swarm, run one swarm of each of these
                          sizes (its own sim and robots, all learned, results in
                          RUN_DIR/swarm-K-nNK), every one feeding this run's one critic, so that
                          one actor learns all the sizes at once; needs learn.critic = "pooled"
                          (configs/any-n.toml)
  --restart on|off        restart an agent or the critic that dies mid-run (default on; a
                          restarted agent rejoins at once with the latest weights, a restarted
                          critic resumes from the run's last checkpoint)
  -h, --help              this help

Environment: FORMATION_BIN_DIR=DIR uses prebuilt binaries from DIR instead of building.

Before any process starts, the run directory gets run.json: run id, N, shared-memory prefix,
iceoryx2 root path, protocol version, observation model and size, the service sizing inputs
and the robot limits; an external client needs only the run directory.

Examples:
  scripts/run_swarm.sh 3 --scripted all --mode eval --episodes 50 --seed 1 --viewer off
  scripts/run_swarm.sh 3 --minutes 20
  scripts/run_swarm.sh 6 --mode eval --checkpoint runs/my-training
  scripts/run_swarm.sh 3 --mode eval --scripted 0,1 --external 2 --run-dir runs/py
  scripts/run_swarm.sh 4 --extra-swarms 3,8,16 --config configs/any-n.toml --minutes 30
USAGE
}

die() { echo "run_swarm.sh: error: $*" >&2; echo "Try 'scripts/run_swarm.sh --help'." >&2; exit 2; }

[[ $# -ge 1 ]] || { usage >&2; exit 2; }
case "$1" in -h|--help) usage; exit 0 ;; esac
N=$1; shift
[[ "$N" =~ ^[0-9]+$ ]] || die "N must be a whole number, got '$N'"
(( N >= 3 && N <= 64 )) || die "N must be between 3 and 64 (each robot observes two distinct neighbours), got $N"

MODE=train EPISODES="" MINUTES="" SCRIPTED="" EXTERNAL="" EXTRA_SWARMS="" CHECKPOINT="" SEED=1 RUN_DIR="" VIEWER="" REALTIME="" CONFIG="" RESTART=on PLACEMENT=auto SHAPE=""
need() { [[ $# -ge 2 && -n "$2" ]] || die "$1 needs a value"; }
while [[ $# -gt 0 ]]; do
  case "$1" in
    --mode) need "$@"; MODE=$2; shift 2 ;;
    --episodes) need "$@"; EPISODES=$2; shift 2 ;;
    --minutes) need "$@"; MINUTES=$2; shift 2 ;;
    --scripted) need "$@"; SCRIPTED=$2; shift 2 ;;
    --external) need "$@"; EXTERNAL=$2; shift 2 ;;
    --extra-swarms) need "$@"; EXTRA_SWARMS=$2; shift 2 ;;
    --checkpoint) need "$@"; CHECKPOINT=$2; shift 2 ;;
    --seed) need "$@"; SEED=$2; shift 2 ;;
    --run-dir) need "$@"; RUN_DIR=$2; shift 2 ;;
    --viewer) need "$@"; VIEWER=$2; shift 2 ;;
    --realtime) REALTIME=1; shift ;;
    --config) need "$@"; CONFIG=$2; shift 2 ;;
    --restart) need "$@"; RESTART=$2; shift 2 ;;
    --placement) need "$@"; PLACEMENT=$2; shift 2 ;;
    --shape) need "$@"; SHAPE=$2; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) die "unknown flag '$1'" ;;
  esac
done

[[ "$MODE" == train || "$MODE" == eval ]] || die "--mode must be train or eval, got '$MODE'"
[[ -z "$EPISODES" || "$EPISODES" =~ ^[1-9][0-9]*$ ]] || die "--episodes must be a positive whole number, got '$EPISODES'"
[[ -z "$MINUTES" || "$MINUTES" =~ ^[0-9]*\.?[0-9]+$ ]] || die "--minutes must be a positive number, got '$MINUTES'"
[[ "$SEED" =~ ^[0-9]+$ ]] || die "--seed must be a whole number, got '$SEED'"
[[ -z "$CONFIG" || -f "$CONFIG" ]] || die "--config file '$CONFIG' does not exist"
[[ -z "$CHECKPOINT" || -e "$CHECKPOINT" ]] || die "--checkpoint '$CHECKPOINT' does not exist"
[[ "$RESTART" == on || "$RESTART" == off ]] || die "--restart must be on or off, got '$RESTART'"
[[ "$PLACEMENT" == auto || "$PLACEMENT" == off ]] || die "--placement must be auto or off, got '$PLACEMENT'"

# Which robots are scripted.
declare -a IS_SCRIPTED
for ((i = 0; i < N; i++)); do IS_SCRIPTED[i]=0; done
case "$SCRIPTED" in
  "") ;;
  all) for ((i = 0; i < N; i++)); do IS_SCRIPTED[i]=1; done ;;
  *)
    IFS=',' read -ra picks <<<"$SCRIPTED"
    for p in "${picks[@]}"; do
      [[ "$p" =~ ^[0-9]+$ ]] || die "--scripted takes 'all' or indices like 0,2; got '$SCRIPTED'"
      (( p < N )) || die "--scripted: robot $p does not exist (robots are 0..$((N - 1)))"
      IS_SCRIPTED[p]=1
    done ;;
esac
# Which robots are external (started by the user, not here). An index named by both
# --scripted and --external is a mistake; --scripted all leaves the external ones out.
declare -a IS_EXTERNAL
for ((i = 0; i < N; i++)); do IS_EXTERNAL[i]=0; done
case "$EXTERNAL" in
  "") ;;
  all) for ((i = 0; i < N; i++)); do IS_EXTERNAL[i]=1; done ;;
  *)
    IFS=',' read -ra picks <<<"$EXTERNAL"
    (( ${#picks[@]} > 0 )) || die "--external takes 'all' or indices like 0,2; got '$EXTERNAL'"
    for p in "${picks[@]}"; do
      [[ "$p" =~ ^[0-9]+$ ]] || die "--external takes 'all' or indices like 0,2; got '$EXTERNAL'"
      p=$((10#$p))
      (( p < N )) || die "--external: robot $p does not exist (robots are 0..$((N - 1)))"
      (( IS_EXTERNAL[p] == 0 )) || die "--external: robot $p is named twice"
      IS_EXTERNAL[p]=1
    done ;;
esac
if [[ -n "$EXTERNAL" && "$SCRIPTED" != all && -n "$SCRIPTED" ]]; then
  for ((i = 0; i < N; i++)); do
    (( IS_SCRIPTED[i] && IS_EXTERNAL[i] )) && die "robot $i cannot be both --scripted and --external"
  done
fi
EXTERNAL_LIST=""
for ((i = 0; i < N; i++)); do
  if (( IS_EXTERNAL[i] )); then IS_SCRIPTED[i]=0; EXTERNAL_LIST+="${EXTERNAL_LIST:+,}$i"; fi
done
# Extra swarms (train mode): one size each, numbered 1, 2, ...
declare -a EXTRA_N=()
if [[ -n "$EXTRA_SWARMS" ]]; then
  [[ "$MODE" == train ]] || die "--extra-swarms is for training; evaluate each size on its own"
  IFS=',' read -ra picks <<<"$EXTRA_SWARMS"
  for p in "${picks[@]}"; do
    [[ "$p" =~ ^[0-9]+$ ]] && (( 10#$p >= 3 && 10#$p <= 64 )) || die "--extra-swarms takes sizes 3 to 64 like 3,8; got '$EXTRA_SWARMS'"
    EXTRA_N+=("$((10#$p))")
  done
  (( ${#EXTRA_N[@]} <= 8 )) || die "--extra-swarms: at most 8 extra swarms"
fi
LEARNED=0
for ((i = 0; i < N; i++)); do (( IS_SCRIPTED[i] || IS_EXTERNAL[i] )) || LEARNED=$((LEARNED + 1)); done

ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
SHIPPED_MODEL="$ROOT/models/formation.safetensors"
if [[ "$MODE" == eval && $LEARNED -gt 0 && -z "$CHECKPOINT" ]]; then
  [[ -f "$SHIPPED_MODEL" ]] || die "eval with learned robots needs --checkpoint (no shipped model at $SHIPPED_MODEL)"
  CHECKPOINT=$SHIPPED_MODEL
fi

case "$VIEWER" in
  "") if command -v rerun >/dev/null 2>&1 && [[ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]]; then VIEWER=spawn; else VIEWER=save; fi
      echo "viewer: $VIEWER (choose with --viewer spawn|save|off|connect=URL)" ;;
  spawn|save|off|connect=*) ;;
  *) die "--viewer must be spawn, save, off or connect=URL, got '$VIEWER'" ;;
esac

if [[ -n "${FORMATION_BIN_DIR:-}" ]]; then
  BIN=$FORMATION_BIN_DIR
else
  echo "building (release)..."
  (cd "$ROOT" && cargo build --release --quiet -p formation-sim -p formation-agent -p formation-critic -p formation-protocol) || die "build failed"
  BIN=$ROOT/target/release
fi
for b in formation-sim formation-agent formation-critic; do
  [[ -x "$BIN/$b" ]] || die "missing binary $BIN/$b"
done

# One value of the run's configuration for run.json: KEY of [SECTION] in --config, else the
# default (the same defaults as protocol/src/config.rs; python/tests checks run.json against
# the config.toml the sim writes).
config_value() { # section key default
  local value=""
  if [[ -n "$CONFIG" ]]; then
    value=$(awk -v sec="$1" -v key="$2" '
      /^[[:space:]]*\[/ { cur = $0; gsub(/[][[:space:]]/, "", cur); next }
      cur == sec {
        line = $0; sub(/#.*/, "", line)
        if (match(line, "^[[:space:]]*" key "[[:space:]]*=")) {
          v = substr(line, RLENGTH + 1); gsub(/^[[:space:]]+|[[:space:]]+$/, "", v); gsub(/"/, "", v)
          print v; exit
        }
      }' "$CONFIG")
  fi
  echo "${value:-$3}"
}

RUN_DIR=${RUN_DIR:-runs/$(date +%Y%m%d-%H%M%S)}
RUN_ID="r$(date +%s | tail -c 7)p$$"
# Flags every process of every swarm of the run takes; COMMON adds this swarm's own.
SHARED=(--mode "$MODE" --placement "$PLACEMENT")
[[ -n "$CONFIG" ]] && SHARED+=(--config "$CONFIG")
[[ -n "$SHAPE" ]] && SHARED+=(--shape "$SHAPE")
COMMON=(--agents "$N" --run-id "$RUN_ID" --run-dir "$RUN_DIR" --seed "$SEED" "${SHARED[@]}")
# Extra swarm K: its own run id (its own shared memory), run directory and episode seed.
declare -a EXTRA_ID=() EXTRA_DIR=() EXTRA_ARGS=()
for ((k = 1; k <= ${#EXTRA_N[@]}; k++)); do
  n=${EXTRA_N[k - 1]}
  EXTRA_ID[k]="${RUN_ID}x$k"
  EXTRA_DIR[k]="$RUN_DIR/swarm-$k-n$n"
  EXTRA_ARGS[k]="--agents $n --run-id ${EXTRA_ID[k]} --run-dir ${EXTRA_DIR[k]} --seed $((SEED + 7919 * k))"
done

# Validate the configuration (and a checkpoint) once, before anything starts.
"$BIN/formation-sim" "${COMMON[@]}" --viewer "$VIEWER" --check-config || exit 2
if [[ -n "$CHECKPOINT" && "$MODE" == eval && $LEARNED -gt 0 ]]; then
  for ((i = 0; i < N; i++)); do
    (( IS_SCRIPTED[i] )) && continue
    "$BIN/formation-agent" "${COMMON[@]}" --agent "$i" --policy learned --checkpoint "$CHECKPOINT" --check || exit 2
  done
fi
CRITIC_EXTRA=()
for ((k = 1; k <= ${#EXTRA_N[@]}; k++)); do CRITIC_EXTRA+=(--extra-swarm "${EXTRA_ID[k]}:${EXTRA_N[k - 1]}"); done
if [[ ( -n "$CHECKPOINT" && "$MODE" == train ) || ${#EXTRA_N[@]} -gt 0 ]]; then
  "$BIN/formation-critic" "${COMMON[@]}" "${CRITIC_EXTRA[@]}" ${CHECKPOINT:+--checkpoint "$CHECKPOINT"} --check || exit 2
fi
mkdir -p "$RUN_DIR/logs"

# run.json: everything a client in another language needs to attach, given the run directory.
if [[ -x "$BIN/formation-layout" ]]; then
  PROTOCOL_VERSION=$("$BIN/formation-layout" --protocol-version)
else
  PROTOCOL_VERSION=$(sed -n 's/^pub const PROTOCOL_VERSION: u32 = \([0-9]*\);/\1/p' "$ROOT/protocol/src/wire.rs")
fi
OBSERVATION=$(config_value env observation slot_proximity)
case "$OBSERVATION" in
  paper) OBS_DIM=12 ;; slot) OBS_DIM=14 ;; slot_proximity) OBS_DIM=16 ;;
  *) die "unknown env.observation '$OBSERVATION' in $CONFIG" ;;
esac
TMP_ROOT=${TMPDIR:-/tmp}
STARTUP_TIMEOUT_S=$(config_value ticks startup_timeout_s 60)
cat >"$RUN_DIR/run.json.tmp" <<JSON
{
  "run_id": "$RUN_ID",
  "n_agents": $N,
  "shm_prefix": "fc_${RUN_ID}_",
  "root_path": "${TMP_ROOT%/}/formation-iox2/$RUN_ID/",
  "iceoryx2_config": "iceoryx2.toml",
  "protocol_version": ${PROTOCOL_VERSION:-0},
  "observation": "$OBSERVATION",
  "observation_dim": $OBS_DIM,
  "critic_window": $(config_value ticks critic_window 64),
  "startup_timeout_s": $STARTUP_TIMEOUT_S,
  "sim_silence_ms": $(config_value ticks sim_silence_ms 2000),
  "command_timeout_ms": $(config_value ticks command_timeout_ms 200),
  "v_max": $(config_value env v_max 0.5),
  "w_max": $(config_value env w_max 1.0),
  "proximity_range_m": $(config_value env proximity_range_m 1.0),
  "mode": "$MODE",
  "external": [${EXTERNAL_LIST}],
  "extra_swarms": [$(for ((k = 1; k <= ${#EXTRA_N[@]}; k++)); do
      printf '%s{"run_id": "%s", "n_agents": %d, "run_dir": "%s"}' "$( ((k > 1)) && echo ', ')" "${EXTRA_ID[k]}" "${EXTRA_N[k - 1]}" "${EXTRA_DIR[k]}"
    done)],
  "launcher_pid": $$
}
JSON
mv "$RUN_DIR/run.json.tmp" "$RUN_DIR/run.json"

declare -a PIDS=()
cleanup() {
  local pid
  for pid in "${PIDS[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
  sleep 0.5
  for pid in "${PIDS[@]}"; do kill -KILL "$pid" 2>/dev/null || true; wait "$pid" 2>/dev/null || true; done
  local id
  for id in "$RUN_ID" "${EXTRA_ID[@]}"; do
    rm -f /dev/shm/fc_"${id}"_* 2>/dev/null || true
    rm -rf "${TMPDIR:-/tmp}/formation-iox2/$id" 2>/dev/null || true
  done
}
trap cleanup EXIT

start_critic() { # [checkpoint to resume from]
  local args=("${COMMON[@]}" "${CRITIC_EXTRA[@]}" --viewer "$VIEWER")
  # The time left for the critic's display (a restarted critic gets what remains).
  [[ -n "$ENDS_AT" ]] && args+=(--minutes "$(awk -v end="$ENDS_AT" -v now="$(date +%s)" 'BEGIN { m = (end - now) / 60; print (m > 0.01 ? m : 0.01) }')")
  [[ "$MODE" == train && -n "${1:-}" ]] && args+=(--checkpoint "$1")
  # tee ignores Ctrl-C so the critic can still report while the run winds down.
  "$BIN/formation-critic" "${args[@]}" 2> >(trap '' INT; tee -a "$RUN_DIR/logs/critic.log" >&2) &
  CRITIC_PID=$!
  CRITIC_STARTED=$(date +%s)
  PIDS+=("$CRITIC_PID")
}

declare -a AGENT_PIDS=()
start_agent() { # index
  local i=$1 args=("${COMMON[@]}" --agent "$1")
  if (( IS_SCRIPTED[i] )); then
    args+=(--policy scripted)
  else
    args+=(--policy learned)
    [[ "$MODE" == eval ]] && args+=(--checkpoint "$CHECKPOINT")
  fi
  "$BIN/formation-agent" "${args[@]}" >>"$RUN_DIR/logs/agent-$i.log" 2>&1 &
  AGENT_PIDS[i]=$!
  PIDS+=("$!")
}

# Robot I of extra swarm K (always learned).
declare -A EXTRA_AGENT_PIDS=()
start_extra_agent() { # swarm index
  local k=$1 i=$2
  # shellcheck disable=SC2086 # EXTRA_ARGS holds flags and values without spaces
  "$BIN/formation-agent" ${EXTRA_ARGS[k]} "${SHARED[@]}" --agent "$i" --policy learned >>"${EXTRA_DIR[k]}/logs/agent-$i.log" 2>&1 &
  EXTRA_AGENT_PIDS[$k,$i]=$!
  PIDS+=("$!")
}

ENDS_AT=""
if [[ -n "$MINUTES" ]]; then
  ENDS_AT=$(awk -v m="$MINUTES" -v now="$(date +%s)" 'BEGIN { printf "%d", now + m * 60 }')
elif [[ "$MODE" == train && -z "$EPISODES" ]]; then
  ENDS_AT=$(($(date +%s) + 30 * 60))
fi
start_critic "$CHECKPOINT"
for ((i = 0; i < N; i++)); do
  if (( IS_EXTERNAL[i] )); then AGENT_PIDS[i]=""; else start_agent "$i"; fi
done
declare -a EXTRA_SIM_PIDS=()
for ((k = 1; k <= ${#EXTRA_N[@]}; k++)); do
  mkdir -p "${EXTRA_DIR[k]}/logs"
  for ((i = 0; i < EXTRA_N[k - 1]; i++)); do start_extra_agent "$k" "$i"; done
  x_args=("${SHARED[@]}" --viewer off)
  [[ -n "$MINUTES" ]] && x_args+=(--minutes "$MINUTES")
  [[ -n "$EPISODES" ]] && x_args+=(--episodes "$EPISODES")
  # shellcheck disable=SC2086
  "$BIN/formation-sim" ${EXTRA_ARGS[k]} "${x_args[@]}" >"${EXTRA_DIR[k]}/logs/sim.log" 2>&1 &
  EXTRA_SIM_PIDS[k]=$!
  PIDS+=("$!")
done

SIM_ARGS=("${COMMON[@]}" --viewer "$VIEWER")
[[ -n "$EPISODES" ]] && SIM_ARGS+=(--episodes "$EPISODES")
[[ -n "$MINUTES" ]] && SIM_ARGS+=(--minutes "$MINUTES")
[[ -n "$REALTIME" ]] && SIM_ARGS+=(--realtime)
[[ -n "$EXTERNAL_LIST" ]] && SIM_ARGS+=(--external "$EXTERNAL_LIST")
if [[ -n "$SCRIPTED" && -n "$EXTERNAL" ]]; then
  SIM_SCRIPTED=""
  for ((i = 0; i < N; i++)); do (( IS_SCRIPTED[i] )) && SIM_SCRIPTED+="${SIM_SCRIPTED:+,}$i"; done
  [[ -n "$SIM_SCRIPTED" ]] && SIM_ARGS+=(--scripted "$SIM_SCRIPTED")
elif [[ -n "$SCRIPTED" ]]; then
  SIM_ARGS+=(--scripted "$SCRIPTED")
fi
"$BIN/formation-sim" "${SIM_ARGS[@]}" >"$RUN_DIR/logs/sim.log" 2>&1 &
SIM_PID=$!
PIDS+=("$SIM_PID")

# Ctrl-C or SIGTERM: ask the sim to end the run; it tells everyone else.
trap 'echo; echo "stopping: the sim closes the episode and ends the run..."; kill -INT "$SIM_PID" "${EXTRA_SIM_PIDS[@]}" 2>/dev/null || true' INT TERM

if [[ -n "$EXTERNAL_LIST" ]]; then
  started=0
  for ((i = 0; i < N; i++)); do (( IS_EXTERNAL[i] )) || started=$((started + 1)); done
  echo "run $RUN_ID: sim, $started agents and the critic started; results in $RUN_DIR (logs in $RUN_DIR/logs)"
  echo "external robots $EXTERNAL_LIST: the sim waits ${STARTUP_TIMEOUT_S} s for them to greet. Attach each one with"
  for ((i = 0; i < N; i++)); do
    (( IS_EXTERNAL[i] )) && echo "  python3 -m formation_swarm robot $RUN_DIR $i        # the baseline in Python (pip install ./python)"
  done
  echo "or from your code: formation_swarm.run_robot(\"$RUN_DIR\", INDEX, policy)  (run.json in $RUN_DIR has the rest)"
else
  echo "run $RUN_ID: sim, $N agents and the critic started; results in $RUN_DIR (logs in $RUN_DIR/logs)"
fi
for ((k = 1; k <= ${#EXTRA_N[@]}; k++)); do
  echo "extra swarm $k: ${EXTRA_N[k - 1]} robots and their sim, run ${EXTRA_ID[k]}; results in ${EXTRA_DIR[k]}"
done
# Watch the run: the sim's end ends it; a dead agent or critic is restarted (--restart on).
status=0
QUICK_DEATHS=0
while kill -0 "$SIM_PID" 2>/dev/null; do
  sleep 0.5 || true # Ctrl-C interrupts the sleep; the trap has already told the sim
  [[ "$RESTART" == on ]] || continue
  kill -0 "$SIM_PID" 2>/dev/null || break
  for ((i = 0; i < N; i++)); do
    [[ -n "${AGENT_PIDS[i]}" ]] && ! kill -0 "${AGENT_PIDS[i]}" 2>/dev/null || continue
    rc=0; wait "${AGENT_PIDS[i]}" 2>/dev/null || rc=$?
    AGENT_PIDS[i]=""
    (( rc != 0 )) || continue # a clean exit: the run is ending
    echo "agent $i died (status $rc); restarting it"
    start_agent "$i"
  done
  for key in "${!EXTRA_AGENT_PIDS[@]}"; do
    [[ -n "${EXTRA_AGENT_PIDS[$key]}" ]] && ! kill -0 "${EXTRA_AGENT_PIDS[$key]}" 2>/dev/null || continue
    rc=0; wait "${EXTRA_AGENT_PIDS[$key]}" 2>/dev/null || rc=$?
    EXTRA_AGENT_PIDS[$key]=""
    (( rc != 0 )) || continue
    echo "extra swarm ${key%,*}: agent ${key#*,} died (status $rc); restarting it"
    start_extra_agent "${key%,*}" "${key#*,}"
  done
  if [[ -n "$CRITIC_PID" ]] && ! kill -0 "$CRITIC_PID" 2>/dev/null; then
    rc=0; wait "$CRITIC_PID" 2>/dev/null || rc=$?
    CRITIC_PID=""
    (( rc != 0 )) || continue
    # A critic that dies within seconds of every start (a bad binary, a broken checkpoint)
    # is not restarted forever.
    if (( $(date +%s) - CRITIC_STARTED < 5 )); then QUICK_DEATHS=$((QUICK_DEATHS + 1)); else QUICK_DEATHS=0; fi
    if (( QUICK_DEATHS >= 3 )); then
      echo "run_swarm.sh: the critic died at start three times in a row (see $RUN_DIR/logs/critic.log); stopping the run" >&2
      kill -INT "$SIM_PID" "${EXTRA_SIM_PIDS[@]}" 2>/dev/null || true
      status=1
      break
    fi
    resume=""
    [[ -f "$RUN_DIR/checkpoint.safetensors" ]] && resume="$RUN_DIR/checkpoint.safetensors"
    echo "the critic died (status $rc); restarting it${resume:+ from $resume}"
    start_critic "${resume:-$CHECKPOINT}"
  fi
done
wait "$SIM_PID" 2>/dev/null || status=$?
# Extra swarms were given the same length; a primary stopped early stops them too.
for pid in "${EXTRA_SIM_PIDS[@]}"; do
  kill -0 "$pid" 2>/dev/null && { sleep 2 || true; kill -INT "$pid" 2>/dev/null || true; }
  wait "$pid" 2>/dev/null || true
done
if (( status != 0 )); then
  echo "run_swarm.sh: the sim exited with status $status:" >&2
  tail -n 5 "$RUN_DIR/logs/sim.log" >&2
fi
# The others end on the sim's end-of-run message; give them a moment, then stop them.
for pid in "${PIDS[@]}"; do
  for _ in $(seq 1 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1 || true; done
done
for ((i = 0; i < N; i++)); do
  if grep -q "error" "$RUN_DIR/logs/agent-$i.log" 2>/dev/null; then
    echo "agent $i reported:" >&2; tail -n 3 "$RUN_DIR/logs/agent-$i.log" >&2
  fi
done
critic_status=0
[[ -z "$CRITIC_PID" ]] || wait "$CRITIC_PID" 2>/dev/null || critic_status=$?
if (( critic_status != 0 )); then
  echo "run_swarm.sh: the critic exited with status $critic_status" >&2
  (( status != 0 )) || status=$critic_status
fi
echo "results: $RUN_DIR (summary.json, episodes.csv, config.toml, logs/)"
exit "$status"
