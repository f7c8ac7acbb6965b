//! A robot "on another computer": its own iceoryx2 (prefix and root path), joined to the sim's
//! host only through two `formation-bridge` processes over Zenoh on TCP localhost. Real
//! processes under a watchdog; nothing of either host may be left behind.

use std::sync::{RwLock, RwLockReadGuard, RwLockWriteGuard};
use std::time::Duration;

use formation_swarm::{
    RunOutcome, announced, assert_clean, pid_of, run_id_of, run_swarm, run_swarm_with, scratch_dir, shm_leftovers,
};

/// The machine, as the tests of this file share it: each swarm holds it shared, the real-time
/// test alone (its deadlines are the machine's; two swarms with four bridges on two cores are
/// not the condition it checks).
static MACHINE: RwLock<()> = RwLock::new(());

/// Holds the machine shared with the other swarms of this file.
fn machine_shared() -> RwLockReadGuard<'static, ()> {
    MACHINE.read().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Holds the machine alone among the tests of this file.
fn machine_alone() -> RwLockWriteGuard<'static, ()> {
    MACHINE.write().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Asserts that neither the sim's host nor remote robot `robot`'s host left anything.
fn assert_both_hosts_clean(run: &RunOutcome, robot: usize) {
    assert_clean(run);
    let host = format!("{}h{robot}", run.run_id.as_deref().expect("run id"));
    assert!(shm_leftovers(&host).is_empty(), "{:?}", shm_leftovers(&host));
    let root = std::env::temp_dir().join("formation-iox2").join(&host);
    assert!(
        !root.exists(),
        "the remote host's root path is left: {}",
        root.display()
    );
}

/// The last line of a bridge's log that reports what it forwarded.
fn bridge_report(log: &std::path::Path) -> String {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    text.lines()
        .rfind(|line| line.contains("forwarded"))
        .unwrap_or_default()
        .to_string()
}

/// The count of `what` in a bridge's report: the number before it ("forwarded 12
/// observations") or, for "rejected", after it ("rejected 3").
fn count(report: &str, what: &str) -> u64 {
    let words: Vec<&str> = report
        .split_whitespace()
        .map(|w| w.trim_end_matches([',', ';']))
        .collect();
    let (number, word) = if what == "rejected" { (1, 0) } else { (0, 1) };
    words
        .windows(2)
        .find(|w| w[word] == what)
        .and_then(|w| w[number].parse().ok())
        .expect("the bridge reports it")
}

#[test]
fn a_scripted_swarm_with_a_remote_robot_succeeds_as_a_local_one_does() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-scripted");
    let run = run_swarm(
        &[
            "3",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--remote",
            "2",
            "--episodes",
            "20",
            "--seed",
            "1",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(180),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(
        run.output.contains("robot 2 runs as if on another computer"),
        "{}",
        run.output
    );
    let summary = run.summary().expect("summary");
    assert!(summary["success_rate"].as_f64().expect("success") >= 0.95, "{summary}");
    assert_eq!(summary["collision_rate"].as_f64(), Some(0.0), "{summary}");
    // Robot 2's observations left through the sim's bridge and its commands came back.
    let sim_bridge = bridge_report(&run.run_dir.join("logs/bridge.log"));
    let robot_bridge = bridge_report(&run.run_dir.join("host-2/logs/bridge.log"));
    let steps = summary["env_steps"].as_u64().expect("steps");
    assert!(
        count(&sim_bridge, "commands") >= steps - summary["missed_ticks"].as_u64().unwrap_or(0),
        "{sim_bridge}"
    );
    assert!(count(&robot_bridge, "observations") >= steps, "{robot_bridge}");
    assert_eq!(count(&sim_bridge, "rejected"), 0, "{sim_bridge}");
    // Robot 2's process ran with the remote host's run id, never the sim's.
    let agent_log = std::fs::read_to_string(run.run_dir.join("host-2/logs/agent-2.log")).unwrap_or_default();
    assert!(!agent_log.contains("error"), "{agent_log}");
    assert_both_hosts_clean(&run, 2);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn killed_bridges_are_restarted_and_the_remote_robot_rejoins() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-kill-bridge");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "3",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--remote",
        "2",
        "--episodes",
        "600",
        "--seed",
        "2",
        "--viewer",
        "off",
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(240), |_| {
        let run_id = run_id_of(&log);
        for side in ["--side sim", "--side robot"] {
            std::thread::sleep(Duration::from_millis(1500));
            let pid = pid_of(&run_id, side).unwrap_or_else(|| panic!("no bridge with {side}"));
            // SAFETY: kill(2) on a process of this test's run.
            unsafe { libc::kill(pid as i32, libc::SIGKILL) };
        }
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("the sim's bridge died"), "{}", run.output);
    assert!(run.output.contains("robot 2's bridge died"), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert_eq!(summary["episodes"].as_u64(), Some(600), "{summary}");
    // The link's loss is counted as missed ticks, and the robot drives again after it.
    assert!(summary["missed_ticks"].as_u64().expect("missed") > 0, "{summary}");
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    let last_ten: Vec<&str> = csv.lines().rev().take(10).collect();
    let successes = last_ten.iter().filter(|line| line.contains("success")).count();
    assert!(successes >= 9, "after the rejoin:\n{}", last_ten.join("\n"));
    assert_both_hosts_clean(&run, 2);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_learning_remote_robot_gets_the_critics_weights_through_the_bridges() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-train");
    let run = run_swarm(
        &[
            "3",
            "--remote",
            "1",
            "--minutes",
            "0.4",
            "--seed",
            "5",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let robot_bridge = bridge_report(&run.run_dir.join("host-1/logs/bridge.log"));
    assert!(count(&robot_bridge, "weights") > 0, "{robot_bridge}");
    let summary = run.summary().expect("summary");
    assert!(summary["updates"].as_u64().unwrap_or(0) > 0, "{summary}");
    assert_both_hosts_clean(&run, 1);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn the_weights_reach_a_remote_robot_again_after_its_bridge_reconnects() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-reconnect-weights");
    // The critic publishes its weights once (after its first update) and never again, so a
    // robot host that reconnects later gets them only from the sim bridge's re-send.
    std::fs::create_dir_all(&dir).expect("scratch dir");
    let config = dir.join("publish-once.toml");
    std::fs::write(&config, "[learn]\npublish_every_updates = 1000000000\n").expect("config");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "3",
        "--remote",
        "1",
        "--minutes",
        "0.75",
        "--seed",
        "6",
        "--viewer",
        "off",
        "--config",
        config.to_str().expect("utf-8 path"),
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(240), |_| {
        let run_id = run_id_of(&log);
        let published = std::time::Instant::now();
        // training.csv gets a row every 10 s; wait for one with updates (weights published).
        while !std::fs::read_to_string(run_dir.join("training.csv"))
            .unwrap_or_default()
            .lines()
            .skip(1)
            .any(|row| row.split(',').nth(3).is_some_and(|updates| updates != "0"))
        {
            assert!(
                published.elapsed() < Duration::from_secs(120),
                "no update after 2 minutes"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        let pid = pid_of(&run_id, "--side robot").expect("robot 1's bridge");
        // SAFETY: kill(2) on a process of this test's run.
        unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("robot 1's bridge died"), "{}", run.output);
    // The killed bridge never reported; the last report is its successor's.
    let robot_bridge = bridge_report(&run.run_dir.join("host-1/logs/bridge.log"));
    assert!(count(&robot_bridge, "weights") >= 1, "{robot_bridge}");
    let sim_bridge = bridge_report(&run.run_dir.join("logs/bridge.log"));
    assert!(
        count(&sim_bridge, "weights") >= 2,
        "published once, re-sent once: {sim_bridge}"
    );
    assert_both_hosts_clean(&run, 1);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn real_time_with_a_remote_robot_misses_no_deadline() {
    let _machine = machine_alone();
    let dir = scratch_dir("remote-realtime");
    let run = run_swarm(
        &[
            "3",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--remote",
            "1",
            "--realtime",
            "--episodes",
            "2",
            "--seed",
            "4",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert_eq!(summary["deadline_misses"].as_u64(), Some(0), "{summary}");
    assert_eq!(summary["missed_ticks"].as_u64(), Some(0), "{summary}");
    assert_both_hosts_clean(&run, 1);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn over_a_delayed_or_lossy_link_the_remote_robot_ends_on_the_runs_end_by_itself() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-run-end");
    std::fs::create_dir_all(&dir).expect("scratch dir");
    // Short episodes: at a loss of 0.5 three ticks in four wait out the command timeout.
    let config = dir.join("short.toml");
    std::fs::write(&config, "[env]\nmax_steps = 40\n").expect("config");
    for (flag, value) in [("--net-delay-ms", "50"), ("--net-loss", "0.5")] {
        let run = run_swarm(
            &[
                "3",
                "--scripted",
                "all",
                "--mode",
                "eval",
                "--remote",
                "2",
                "--episodes",
                "2",
                "--seed",
                "8",
                "--viewer",
                "off",
                "--config",
                config.to_str().expect("utf-8 path"),
                flag,
                value,
            ],
            &dir.join(flag.trim_start_matches('-')),
            Duration::from_secs(180),
        )
        .expect("launch");
        assert_eq!(run.status, Some(0), "{flag} {value}:\n{}", run.output);
        assert_eq!(run.summary().expect("summary")["episodes"].as_u64(), Some(2));
        // The remote robot and its bridge heard the run's end and left by themselves: the
        // launcher had nobody to stop after its wind-down.
        assert!(
            !run.output.contains("still running at the end of the run"),
            "{flag} {value}:\n{}",
            run.output
        );
        assert!(!run.output.contains("died"), "{flag} {value}:\n{}", run.output);
        let agent_log = std::fs::read_to_string(run.run_dir.join("host-2/logs/agent-2.log")).unwrap_or_default();
        assert!(
            !agent_log.contains("error") && !agent_log.contains("panicked"),
            "{flag} {value}: {agent_log}"
        );
        assert_both_hosts_clean(&run, 2);
    }
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn remote_flags_are_checked_before_anything_starts() {
    let _machine = machine_shared();
    let dir = scratch_dir("remote-bad");
    for (args, needle) in [
        (vec!["3", "--remote", "3"], "robot 3 does not exist"),
        (
            vec!["3", "--remote", "1", "--external", "1"],
            "both --remote and --external",
        ),
        (vec!["3", "--net-delay-ms", "20"], "name them with --remote"),
        (
            vec!["3", "--remote", "1", "--net-loss", "2"],
            "--net-loss must be a probability",
        ),
    ] {
        let run = run_swarm(&args, &dir.join("run"), Duration::from_secs(60)).expect("launch");
        assert_eq!(run.status, Some(2), "{args:?}:\n{}", run.output);
        assert!(
            run.output.contains(needle),
            "{args:?}: expected {needle:?} in\n{}",
            run.output
        );
        assert!(run.run_id.is_none());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_command_injected_by_another_zenoh_peer_for_a_robot_not_carried_is_rejected_and_counted() {
    let _machine = machine_shared();
    use formation_protocol::wire::{CommandMsg, Header};
    use zenoh::Wait;
    let dir = scratch_dir("remote-inject");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "3",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--remote",
        "2",
        "--episodes",
        "300",
        "--seed",
        "3",
        "--viewer",
        "off",
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(240), |_| {
        let run_id = run_id_of(&log);
        let endpoint = announced(&log, "bridge endpoint", |line| {
            line.split("joined over Zenoh at ")
                .nth(1)
                .and_then(|rest| rest.split(';').next())
                .map(str::to_string)
        });
        // A stranger dials the sim's bridge and commands robot 0 (local, not carried) and
        // robot 2 with garbage.
        let mut config = zenoh::Config::default();
        for (key, value) in [
            ("listen/endpoints", "[]".to_string()),
            ("connect/endpoints", format!("[{endpoint:?}]")),
            ("scouting/multicast/enabled", "false".to_string()),
        ] {
            config.insert_json5(key, &value).expect("zenoh config");
        }
        let session = zenoh::open(config).wait().expect("zenoh session");
        std::thread::sleep(Duration::from_millis(1500));
        let forged = CommandMsg {
            header: Header::new(0, 1, 0),
            agent: 0,
            v: 0.5,
            ..CommandMsg::default()
        };
        for _ in 0..5 {
            session
                .put(
                    format!("formation/{run_id}/agent/0/command"),
                    bytemuck::bytes_of(&forged).to_vec(),
                )
                .wait()
                .expect("put");
            session
                .put(format!("formation/{run_id}/agent/2/command"), vec![1u8, 2, 3])
                .wait()
                .expect("put");
            std::thread::sleep(Duration::from_millis(100));
        }
        session.close().wait().expect("close");
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let sim_bridge = bridge_report(&run.run_dir.join("logs/bridge.log"));
    assert!(count(&sim_bridge, "rejected") >= 10, "{sim_bridge}");
    let summary = run.summary().expect("summary");
    assert_eq!(
        summary["rejected_commands"].as_u64(),
        Some(0),
        "nothing reached the sim: {summary}"
    );
    assert!(summary["success_rate"].as_f64().expect("success") >= 0.95, "{summary}");
    assert_both_hosts_clean(&run, 2);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
