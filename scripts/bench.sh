#!/usr/bin/env bash
# Benchmarks: lockstep tick rate and latency against N (scripted and learned robots, separate
# processes and all in one process, and with one robot behind the Zenoh bridges), the
# process-to-process floor (iceoryx2 events, the tick bell's futex, a Unix
# socket) and each lockstep cell's ratio to its N + 1 wake-up floor, the same tick shape in
# Python (multiprocessing pipes) as a same-machine anchor, real-time deadline misses, training
# throughput and memory. Prints a table and writes bench.json. Takes about 16 minutes
# (--quick: 5); run it on a quiet machine.
#
#   scripts/bench.sh [--quick] [--skip-realtime] [--skip-training] [--out DIR]
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
QUICK=0 OUT=runs/bench SKIP_REALTIME=0 SKIP_TRAINING=0
while [[ $# -gt 0 ]]; do
  case "$1" in
    --quick) QUICK=1; shift ;;
    --skip-realtime) SKIP_REALTIME=1; shift ;;
    --skip-training) SKIP_TRAINING=1; shift ;;
    --out) OUT=$2; shift 2 ;;
    -h|--help) sed -n '2,7p' "$0"; exit 0 ;;
    *) echo "bench.sh: unknown flag $1" >&2; exit 2 ;;
  esac
done
mkdir -p "$OUT"
cargo build --release --quiet --workspace --bins
export FORMATION_BIN_DIR=$ROOT/target/release
MODEL=$ROOT/models/formation.safetensors
SIZES=(3 6 12 24 48); (( QUICK )) && SIZES=(3 6)
# Each lockstep measurement ticks for this long (whole episodes, so a little longer).
MINUTES=0.25; (( QUICK )) && MINUTES=0.05
RESULTS=$OUT/results.jsonl
: >"$RESULTS"

record() { # json object
  echo "$1" >>"$RESULTS"
}

summary_field() { # file key
  python3 -c "import json,sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])" "$1" "$2"
}

# 1. The floor: one round trip between two processes, on one CPU and placed by the OS.
for placement in auto off; do
  for transport in iceoryx2 bell uds; do
    line=$("$FORMATION_BIN_DIR/formation-pingpong" --transport "$transport" --placement "$placement" --round-trips 20000)
    record "$(python3 -c "import json,sys; d=json.loads(sys.argv[1]); d['kind']='round_trip'; print(json.dumps(d))" "$line")"
  done
done

# 2. Lockstep across processes: sim + N agents + critic (eval), scripted and learned robots,
#    placed as the launcher does by default; then a few sizes with placement left to the OS.
lockstep() { # policy n placement[-label] [launcher flags...]
  local policy=$1 n=$2 placement=$3 dir
  shift 3
  dir=$OUT/lockstep-$policy-$n-$placement
  local args=("$n" --mode eval --episodes 1000000 --minutes "$MINUTES" --seed 7 --viewer off --placement "${placement%%-*}" --run-dir "$dir" "$@")
  [[ $policy == scripted ]] && args+=(--scripted all)
  scripts/run_swarm.sh "${args[@]}" >"$dir.log" 2>&1 || { echo "run failed: $dir.log" >&2; exit 1; }
  record "$(python3 - "$dir/summary.json" "$policy" "$n" "$placement" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(json.dumps({"kind": "lockstep", "processes": "separate", "placement": sys.argv[4], "policy": sys.argv[2],
                  "n": int(sys.argv[3]), "ticks_per_s": round(s["env_steps_per_s"]), "p50_us": s["tick_p50_us"],
                  "p99_us": s["tick_p99_us"], "missed_ticks": s["missed_ticks"], "lost_transitions": s["lost_transitions"],
                  "sim_wakeups_per_tick": s["sim_wakeups_per_tick"], "machine_switches_per_tick": s["machine_switches_per_tick"],
                  "bell_robots_per_tick": s.get("bell_robots_per_tick")}))
PY
)"
}
for policy in scripted learned; do
  [[ $policy == learned && ! -f "$MODEL" ]] && { echo "no $MODEL: skipping learned runs" >&2; continue; }
  for n in "${SIZES[@]}"; do lockstep "$policy" "$n" auto; done
done
OFF_SIZES=(3 12 48); (( QUICK )) && OFF_SIZES=(3)
for n in "${OFF_SIZES[@]}"; do lockstep scripted "$n" off; done
# Without the tick gate (every robot's command wakes the sim), for the difference it makes.
for n in 3 12; do FORMATION_TICK_GATE=off lockstep scripted "$n" auto-nogate; done
# Robots on their own events instead of the tick bell, for the difference the bell makes.
for n in 3 12; do FORMATION_TICK_BELL=off lockstep scripted "$n" auto-nobell; done
# Through the bridges: robot 0 on a host of its own (own iceoryx2), joined over Zenoh on TCP
# localhost, so each tick waits for one round trip through both bridges.
for n in 3 12; do lockstep scripted "$n" auto-remote1 --remote 0; done

# The same tick shape in Python (multiprocessing pipes), placed as the swarm and by the OS.
for placement in auto off; do
  record "$(python3 scripts/pipes_anchor.py --agents 3 --seconds "$(python3 -c "print($MINUTES * 60)")" --placement "$placement")"
done

# 3. The same loop in one process (threads on the lockstep CPU), local and ipc service types.
for transport in local ipc; do
  for n in "${SIZES[@]}"; do
    dir=$OUT/inproc-$transport-$n
    "$FORMATION_BIN_DIR/formation-inproc" --agents "$n" --episodes 1000000 --minutes "$MINUTES" --seed 7 --transport "$transport" --run-dir "$dir" >"$dir.log" 2>&1
    record "$(python3 - "$dir/summary.json" "$transport" "$n" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(json.dumps({"kind": "lockstep", "processes": "one (" + sys.argv[2] + ")", "placement": "auto", "policy": "scripted",
                  "n": int(sys.argv[3]), "ticks_per_s": round(s["env_steps_per_s"]), "p50_us": s["tick_p50_us"],
                  "p99_us": s["tick_p99_us"], "missed_ticks": s["missed_ticks"], "lost_transitions": None}))
PY
)"
  done
done

# 4. Real time at 10 Hz: deadline misses over about 1000 ticks, up to 64 robot processes.
RT_SIZES=(16 64); (( QUICK )) && RT_SIZES=(16); (( SKIP_REALTIME )) && RT_SIZES=()
RT_MINUTES=1.75; (( QUICK )) && RT_MINUTES=0.5
for n in "${RT_SIZES[@]+"${RT_SIZES[@]}"}"; do
  dir=$OUT/realtime-$n
  scripts/run_swarm.sh "$n" --scripted all --mode eval --realtime --episodes 1000000 --minutes "$RT_MINUTES" --seed 7 --viewer off --run-dir "$dir" >"$dir.log" 2>&1 &
  launcher=$!
  sleep 20
  # Memory while it runs: resident set of each agent process, and the run's shared memory.
  run_id=$(sed -n 's/^run \([^:]*\):.*/\1/p' "$dir.log" | head -n 1)
  rss_kb=$(for p in $(pgrep -f "formation-agent.*--run-id $run_id"); do awk '/VmRSS/ {print $2}' "/proc/$p/status"; done | sort -n | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}')
  shm_kb=$(du -ck /dev/shm/fc_"${run_id}"_* 2>/dev/null | tail -n 1 | cut -f1)
  wait "$launcher"
  record "$(python3 - "$dir/summary.json" "$n" "$rss_kb" "$shm_kb" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(json.dumps({"kind": "realtime_10hz", "n": int(sys.argv[2]), "ticks": s["env_steps"], "deadline_misses": s["deadline_misses"],
                  "missed_ticks": s["missed_ticks"], "tick_p99_us": s["tick_p99_us"],
                  "agent_rss_kib_median": int(sys.argv[3] or 0), "run_shm_kib": int(sys.argv[4] or 0)}))
PY
)"
done

# 5. Training throughput (default config, 2 minutes).
if (( ! SKIP_TRAINING )); then
dir=$OUT/train-3
scripts/run_swarm.sh 3 --minutes 2 --seed 7 --viewer off --run-dir "$dir" >"$dir.log" 2>&1
record "$(python3 - "$dir/summary.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
print(json.dumps({"kind": "training", "n": 3, "env_steps_per_wall_s": round(s["env_steps"] / s["wall_s"]),
                  "updates_per_s": round(s["updates_per_s"], 1), "lost_transitions": s["lost_transitions"]}))
PY
)"
fi

# 6. Single-observation actor inference.
if [[ -f "$MODEL" ]]; then
  line=$("$FORMATION_BIN_DIR/formation-agent" --checkpoint "$MODEL" --agent 0 --bench-inference 20000 --mode eval)
  record "$line"
fi

python3 - "$RESULTS" "$OUT/bench.json" <<'PY'
import json, sys, platform, os
rows = [json.loads(l) for l in open(sys.argv[1]) if l.strip()]
cpu = next((l.split(":", 1)[1].strip() for l in open("/proc/cpuinfo") if l.startswith("model name")), "?")
print(f"machine: {cpu}, {os.cpu_count()} cores")
# The N + 1 floor: one wake-up is half an iceoryx2 round trip on one CPU; a tick needs N + 1.
def half_round_trip(transport):
    return next((r["p50_us"] / 2 for r in rows if r["kind"] == "round_trip" and r["transport"].lower() == transport and r["placement"].lower() == "auto"), None)
wake_us, bell_us = half_round_trip("iceoryx2"), half_round_trip("bell")
python = max((r["ticks_per_s"] for r in rows if r["kind"] == "python_pipes"), default=None)
print(f"floor: one wake-up {wake_us} us (half the iceoryx2 round trip on one CPU; by the tick bell: {bell_us} us); Python pipes, N = 3, best placement: {python} ticks/s")
print(f"{'kind':<14} {'processes':<16} {'placement':<12} {'policy':<9} {'N':>3} {'ticks/s':>9} {'p50 us':>8} {'p99 us':>8} {'floor':>6} {'us/robot':>8}  other")
for r in rows:
    if r["kind"] == "lockstep":
        # A cell's share of its N + 1 floor at a given cost of one wake-up.
        of_floor = lambda wake: round(wake * (r["n"] + 1) * r["ticks_per_s"] / 1e6, 2)
        r["of_floor"] = of_floor(wake_us) if wake_us else None
        floor = f"{r['of_floor']:.2f}" if wake_us else "-"
        per_robot = 1e6 / r["ticks_per_s"] / r["n"]
        r["us_per_robot"] = round(per_robot, 2)
        other = f"missed {r['missed_ticks']} lost {r['lost_transitions']}"
        if bell_us:
            r["of_bell_floor"] = of_floor(bell_us)
            other += f" of bell floor {r['of_bell_floor']:.2f}"
        if r.get("bell_robots_per_tick") is not None:
            other += f" bell {r['bell_robots_per_tick']:.2f}/tick"
        if r.get("sim_wakeups_per_tick") is not None:
            other += f" sim wake-ups/tick {r['sim_wakeups_per_tick']:.2f} switches/tick {r['machine_switches_per_tick']:.1f}"
        if python and r["n"] == 3:
            other += f" {r['ticks_per_s'] / python:.1f}x Python"
        print(f"{'lockstep':<14} {r['processes']:<16} {r['placement']:<12} {r['policy']:<9} {r['n']:>3} {r['ticks_per_s']:>9} {r['p50_us']:>8.1f} {r['p99_us']:>8.1f} {floor:>6} {per_robot:>8.2f}  {other}")
    else:
        rest = {k: v for k, v in r.items() if k != "kind"}
        print(f"{r['kind']:<14} {json.dumps(rest)}")
json.dump({"machine": {"cpu": cpu, "cores": os.cpu_count()}, "results": rows}, open(sys.argv[2], "w"), indent=2)
print(f"written: {sys.argv[2]}")
PY
