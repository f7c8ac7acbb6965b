//! Robots killed and restarted under load: with every CPU busy with a hog, a robot's process is
//! SIGKILLed again and again in a running N = 6 swarm (lockstep and real time) and each time its
//! new process must be heard by the sim (a rejoin) within 50 ticks of the first tick it was told.
//! A binary of its own: the hog would disturb the timing of any test run beside it.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use formation_swarm::{assert_clean, pid_of, run_id_of, run_swarm_with, scratch_dir};

/// Robots of the swarm.
const N: usize = 6;
/// Ticks after its first observation within which a restarted robot must be heard.
const REJOIN_TICKS: i64 = 50;
/// The launcher gives up on a member that dies within 5 s of its start three times in a row:
/// a robot is killed again only this long after its last start.
const BETWEEN_KILLS_OF_ONE_ROBOT: Duration = Duration::from_millis(5500);
/// How long a restarted robot may take, on a loaded machine, to start and be heard.
const REJOIN_PATIENCE: Duration = Duration::from_secs(60);

/// One busy-looping process per CPU, killed when dropped.
struct CpuHog(Vec<Child>);

impl CpuHog {
    fn start() -> Self {
        let cpus = std::thread::available_parallelism().map_or(2, usize::from);
        Self(
            (0..cpus)
                .map(|_| {
                    Command::new("sh")
                        .args(["-c", "while :; do :; done"])
                        .stdin(Stdio::null())
                        .spawn()
                        .expect("hog starts")
                })
                .collect(),
        )
    }
}

impl Drop for CpuHog {
    fn drop(&mut self) {
        for child in &mut self.0 {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// `(episode, tick)` of every line of `path` that starts with `prefix` and continues
/// `"... episode E tick T ..."`.
fn ticks_logged(path: &Path, prefix: &str) -> Vec<(u32, u32)> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    text.lines()
        .filter_map(|line| {
            let rest = line.strip_prefix(prefix)?;
            let words: Vec<&str> = rest.split_whitespace().collect();
            let at = words.iter().position(|&w| w == "episode")?;
            let episode = words.get(at + 1)?.parse().ok()?;
            let tick = words
                .get(at + 3)?
                .trim_end_matches(|c: char| !c.is_ascii_digit())
                .parse()
                .ok()?;
            (words.get(at + 2) == Some(&"tick")).then_some((episode, tick))
        })
        .collect()
}

/// Ticks from `from` to `to` (negative when `to` came first), with the steps of each finished
/// episode from `episodes.csv` (an episode of S steps tells S + 1 ticks).
fn ticks_between(run_dir: &Path, from: (u32, u32), to: (u32, u32)) -> i64 {
    let steps: Vec<i64> = std::fs::read_to_string(run_dir.join("episodes.csv"))
        .unwrap_or_default()
        .lines()
        .skip(1)
        .map(|line| line.split(',').nth(2).and_then(|s| s.parse().ok()).unwrap_or(0))
        .collect();
    let position = |(episode, tick): (u32, u32)| -> i64 {
        steps.iter().take(episode as usize).map(|s| s + 1).sum::<i64>() + i64::from(tick)
    };
    position(to) - position(from)
}

/// What one kill-and-restart came to.
#[derive(Debug)]
struct Restart {
    robot: usize,
    /// Ticks from the restarted robot's first observation to the sim's rejoin (None: never).
    ticks: Option<i64>,
    /// Wall time from the kill to the rejoin.
    took: Duration,
}

/// Kills robot after robot of run `run_id` `restarts` times, each once its predecessor has
/// rejoined (or was given up on), and says how each went.
fn kill_and_restart(run_dir: &Path, run_id: &str, restarts: usize) -> Vec<Restart> {
    let sim_log = run_dir.join("logs/sim.log");
    let mut started = [Instant::now(); N];
    let mut results = Vec::new();
    for k in 0..restarts {
        let robot = k % N;
        let agent_log = run_dir.join(format!("logs/agent-{robot}.log"));
        let rejoin_prefix = format!("sim: agent {robot} rejoined");
        let first_prefix = format!("agent {robot}: first observation");
        let rejoins_before = ticks_logged(&sim_log, &rejoin_prefix).len();
        let firsts_before = ticks_logged(&agent_log, &first_prefix).len();
        std::thread::sleep(BETWEEN_KILLS_OF_ONE_ROBOT.saturating_sub(started[robot].elapsed()));
        let Some(pid) = pid_of(run_id, &format!("--agent {robot} ")) else {
            results.push(Restart {
                robot,
                ticks: None,
                took: Duration::ZERO,
            });
            break;
        };
        // SAFETY: kill(2) on a pid of our own run.
        unsafe { libc::kill(pid as i32, libc::SIGKILL) };
        let killed = Instant::now();
        started[robot] = killed;
        let ticks = loop {
            let rejoin = ticks_logged(&sim_log, &rejoin_prefix).get(rejoins_before).copied();
            let first = ticks_logged(&agent_log, &first_prefix).get(firsts_before).copied();
            if let (Some(rejoin), Some(first)) = (rejoin, first) {
                break Some(ticks_between(run_dir, first, rejoin));
            }
            if killed.elapsed() > REJOIN_PATIENCE {
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let failed = ticks.is_none_or(|t| t > REJOIN_TICKS);
        results.push(Restart {
            robot,
            ticks,
            took: killed.elapsed(),
        });
        if failed {
            break;
        }
    }
    results
}

/// Runs an N = 6 scripted evaluation (`realtime` or lockstep) under a CPU hog, kills and
/// restarts a robot `restarts` times, and checks each was heard again within 50 ticks.
fn restarted_robots_rejoin_under_load(name: &str, realtime: bool, restarts: usize) {
    let dir = scratch_dir(name);
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let mut args = vec![
        "6",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--episodes",
        "1000000",
        "--viewer",
        "off",
    ];
    if realtime {
        args.push("--realtime");
    }
    let mut results = Vec::new();
    let hog = CpuHog::start();
    let watchdog = Duration::from_secs(120 + 30 * restarts as u64);
    let run = run_swarm_with(&args, &run_dir, watchdog, |launcher| {
        let run_id = run_id_of(&log);
        // Under way: every robot has been heard and an episode is on record.
        let deadline = Instant::now() + Duration::from_secs(120);
        while std::fs::read_to_string(run_dir.join("episodes.csv")).map_or(true, |text| text.lines().count() < 2)
            && Instant::now() < deadline
        {
            std::thread::sleep(Duration::from_millis(50));
        }
        results = kill_and_restart(&run_dir, &run_id, restarts);
        // Ctrl-C ends the run cleanly, whatever happened.
        // SAFETY: kill(2) on the process group the test created.
        unsafe { libc::kill(-(launcher as i32), libc::SIGINT) };
    })
    .expect("launch");
    drop(hog);
    let report: Vec<String> = results
        .iter()
        .map(|r| {
            format!(
                "robot {}: {} ({:.1} s)",
                r.robot,
                r.ticks.map_or("never heard".into(), |t| format!("{t} ticks")),
                r.took.as_secs_f64()
            )
        })
        .collect();
    eprintln!("{name}: {}", report.join(", "));
    assert_eq!(results.len(), restarts, "{report:?}\n{}", run.output);
    for r in &results {
        assert!(
            r.ticks.is_some_and(|t| t <= REJOIN_TICKS),
            "robot {} was not heard within {REJOIN_TICKS} ticks of its restart: {report:?}\n{}",
            r.robot,
            run.output
        );
    }
    assert_eq!(run.status, Some(0), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert_eq!(summary["rejoined_agents"], serde_json::json!(restarts), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn restarted_robots_rejoin_under_load_in_lockstep_and_real_time() {
    restarted_robots_rejoin_under_load("restarts-lockstep", false, 5);
    restarted_robots_rejoin_under_load("restarts-realtime", true, 5);
}

/// The full check (about two minutes a mode): `cargo test --test restarts -- --ignored`.
#[test]
#[ignore = "long: 20 restarts in each mode"]
fn twenty_restarted_robots_in_a_row_rejoin_under_load_in_lockstep_and_real_time() {
    restarted_robots_rejoin_under_load("restarts-lockstep-20", false, 20);
    restarted_robots_rejoin_under_load("restarts-realtime-20", true, 20);
}
