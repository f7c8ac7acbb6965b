//! Faults with real processes: killed agents, critic and sim, malformed commands, bad files,
//! two runs at once, and Ctrl-C. Each run is under a watchdog and must leave nothing behind.

use std::process::Command;
use std::time::{Duration, Instant};

use formation_swarm::{
    announced, assert_clean, bin_dir, pid_of, processes_of_run, repo_root, run_id_of, run_swarm, run_swarm_with,
    scratch_dir, shm_leftovers,
};

fn kill(pid: u32, signal: i32) {
    // SAFETY: kill(2) on a pid of our own run.
    unsafe { libc::kill(pid as i32, signal) };
}

/// A long scripted evaluation, so there is time to hurt it.
const LONG_EVAL: [&str; 9] = [
    "3",
    "--scripted",
    "all",
    "--mode",
    "eval",
    "--episodes",
    "1500",
    "--viewer",
    "off",
];

/// Runs [`LONG_EVAL`] in a fresh directory named `name`; 1.5 s after the run starts, calls
/// `hurt(run id, launcher pid)`. Returns the outcome and the directory to remove.
fn long_eval_hurt_by(name: &str, hurt: impl FnOnce(&str, u32)) -> (formation_swarm::RunOutcome, std::path::PathBuf) {
    let dir = scratch_dir(name);
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let run = run_swarm_with(&LONG_EVAL, &run_dir, Duration::from_secs(180), |launcher| {
        let run_id = run_id_of(&log);
        // Hurt a run that is under way (every member has heard the sim), however loaded the
        // machine: once its first episode is on record.
        announced(&run_dir.join("episodes.csv"), "a first episode", |line| {
            line.starts_with(|c: char| c.is_ascii_digit()).then_some(())
        });
        hurt(&run_id, launcher);
    })
    .expect("launch");
    (run, dir)
}

/// Kills the process of run `run_id` whose command line contains `needle`.
fn kill_process(run_id: &str, needle: &str) {
    let pid = pid_of(run_id, needle).unwrap_or_else(|| panic!("no process matching {needle:?} runs"));
    kill(pid, libc::SIGKILL);
}

#[test]
fn killed_agent_is_held_then_restarted_and_rejoins() {
    let (run, dir) = long_eval_hurt_by("kill-agent", |run_id, _| kill_process(run_id, "--agent 1"));
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("agent 1 died"), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert!(summary["missed_ticks"].as_u64().expect("missed") > 0, "{summary}");
    assert!(summary["rejoined_agents"].as_u64().expect("rejoined") >= 1, "{summary}");
    assert_eq!(summary["lost_transitions"], serde_json::json!(0), "{summary}");
    assert_eq!(summary["episodes"], serde_json::json!(1500));
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn killed_critic_does_not_stop_the_swarm() {
    let (run, dir) = long_eval_hurt_by("kill-critic", |run_id, _| kill_process(run_id, "formation-critic"));
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("the critic died"), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert_eq!(
        summary["episodes"],
        serde_json::json!(1500),
        "the swarm ran every episode: {summary}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_stalled_sim_is_waited_for_not_given_up() {
    let (run, dir) = long_eval_hurt_by("stall-sim", |run_id, _| {
        let pid = pid_of(run_id, "formation-sim").expect("sim runs");
        kill(pid, libc::SIGSTOP);
        std::thread::sleep(Duration::from_secs(4));
        kill(pid, libc::SIGCONT);
    });
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(!run.output.contains("the critic died"), "{}", run.output);
    let critic_log = std::fs::read_to_string(run.run_dir.join("logs/critic.log")).expect("critic log");
    assert!(critic_log.contains("but its process is alive"), "{critic_log}");
    let summary = run.summary().expect("summary");
    assert_eq!(summary["episodes"], serde_json::json!(1500), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_launcher_killed_outright_takes_every_member_with_it() {
    // SIGKILL to the launcher alone (its members run in their own process groups): the
    // kernel ends each member with it, so no robot, sim or critic outlives its run, and the
    // next launcher removes what the dead one could not.
    let (run, dir) = long_eval_hurt_by("kill-launcher", |run_id, launcher| {
        assert!(!processes_of_run(run_id).is_empty(), "the run is under way");
        kill(launcher, libc::SIGKILL);
        let deadline = Instant::now() + Duration::from_secs(10);
        while !processes_of_run(run_id).is_empty() {
            assert!(
                Instant::now() < deadline,
                "members outlived their launcher: {:?}",
                processes_of_run(run_id)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        // Nobody was left to clean up; the next launcher sweeps the run of a dead launcher.
        assert!(
            !shm_leftovers(run_id).is_empty(),
            "the killed run's shared memory is there"
        );
        let next_dir = scratch_dir("after-kill-launcher");
        let next = run_swarm(
            &[
                "3",
                "--scripted",
                "all",
                "--mode",
                "eval",
                "--episodes",
                "1",
                "--viewer",
                "off",
            ],
            &next_dir.join("run"),
            Duration::from_secs(120),
        )
        .expect("launch the next run");
        assert_eq!(next.status, Some(0), "{}", next.output);
        assert!(
            next.output
                .contains(&format!("files of run {run_id}, whose launcher is gone")),
            "{}",
            next.output
        );
        assert!(shm_leftovers(run_id).is_empty(), "{:?}", shm_leftovers(run_id));
        assert_clean(&next);
        std::fs::remove_dir_all(&next_dir).expect("cleanup");
    });
    assert_eq!(run.status, None, "the launcher was killed:\n{}", run.output);
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn killed_sim_is_noticed_by_everyone() {
    let started = Instant::now();
    let (run, dir) = long_eval_hurt_by("kill-sim", |run_id, _| kill_process(run_id, "formation-sim"));
    assert_ne!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("the sim exited"), "{}", run.output);
    assert!(
        run.output.contains("is it alive"),
        "agents or critic should say the sim is gone:\n{}",
        run.output
    );
    assert!(started.elapsed() < Duration::from_secs(60));
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn malformed_commands_are_rejected_and_never_integrated() {
    let dir = scratch_dir("bad-wire");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let injector = bin_dir().expect("bins").join("fault-injector");
    let run = run_swarm_with(&LONG_EVAL, &run_dir, Duration::from_secs(180), |_| {
        let run_id = run_id_of(&log);
        let status = Command::new(&injector)
            .args(["--run-id", &run_id, "--agents", "3", "--agent", "1", "--seconds", "1.5"])
            .status()
            .expect("injector runs");
        assert!(status.success());
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let summary = run.summary().expect("summary");
    assert!(
        summary["rejected_commands"].as_u64().expect("rejected") > 10,
        "{summary}"
    );
    // The real agents kept the swarm on task: nothing non-finite reached the physics.
    assert!(summary["success_rate"].as_f64().expect("success") > 0.9, "{summary}");
    assert!(summary["mean_final_edge_error_m"].as_f64().expect("error").is_finite());
    let sim_log = std::fs::read_to_string(run_dir.join("logs/sim.log")).expect("sim log");
    assert!(sim_log.contains("rejected a command from agent 1"), "{sim_log}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn two_runs_at_once_are_isolated() {
    let dir = scratch_dir("two-runs");
    let args = [
        "3",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--episodes",
        "300",
        "--viewer",
        "off",
    ];
    let (a, b) = std::thread::scope(|scope| {
        let a = scope.spawn(|| run_swarm(&args, &dir.join("a"), Duration::from_secs(180)).expect("launch a"));
        let b = scope.spawn(|| run_swarm(&args, &dir.join("b"), Duration::from_secs(180)).expect("launch b"));
        (a.join().expect("a"), b.join().expect("b"))
    });
    for run in [&a, &b] {
        assert_eq!(run.status, Some(0), "{}", run.output);
        let summary = run.summary().expect("summary");
        assert_eq!(summary["episodes"], serde_json::json!(300));
        assert_eq!(summary["lost_transitions"], serde_json::json!(0), "{summary}");
        assert_eq!(summary["missed_ticks"], serde_json::json!(0), "{summary}");
        assert_clean(run);
    }
    assert_ne!(a.run_id, b.run_id);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn ctrl_c_ends_the_run_cleanly() {
    let (run, dir) = long_eval_hurt_by("ctrl-c", |_, launcher| {
        // A terminal's Ctrl-C reaches the whole foreground process group.
        // SAFETY: kill(2) on the process group the test created.
        unsafe { libc::kill(-(launcher as i32), libc::SIGINT) };
    });
    assert_eq!(run.status, Some(0), "{}", run.output);
    let summary = run.summary().expect("summary written on Ctrl-C");
    let episodes = summary["episodes"].as_u64().expect("episodes");
    assert!(episodes < 1500, "the run stopped early: {summary}");
    assert!(
        summary["lost_transitions"].is_number(),
        "the critic merged its figures: {summary}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn bad_checkpoints_are_refused_before_anything_starts() {
    let dir = scratch_dir("bad-ckpt");
    std::fs::create_dir_all(&dir).expect("dir");
    let corrupt = dir.join("corrupt.safetensors");
    std::fs::write(&corrupt, b"\x10\x00\x00\x00\x00\x00\x00\x00{\"oops\": trunc").expect("write");
    for mode in ["eval", "train"] {
        let run = run_swarm(
            &[
                "3",
                "--mode",
                mode,
                "--checkpoint",
                corrupt.to_str().expect("utf8"),
                "--viewer",
                "off",
            ],
            &dir.join("run"),
            Duration::from_secs(60),
        )
        .expect("launch");
        assert_eq!(run.status, Some(2), "{mode}: {}", run.output);
        assert!(
            run.output.contains("corrupt.safetensors"),
            "{mode}: the error names the file:\n{}",
            run.output
        );
        assert!(run.run_id.is_none(), "{mode}: nothing may start:\n{}", run.output);
    }
    // A checkpoint trained on another observation model (the paper's 12 floats) is refused
    // by a run on the default observation, with both named; the same file runs with its own.
    let paper = repo_root().join("models/formation-3robots-paper.safetensors");
    let paper = paper.to_str().expect("utf8");
    let refused = run_swarm(
        &["3", "--mode", "eval", "--checkpoint", paper, "--viewer", "off"],
        &dir.join("run"),
        Duration::from_secs(60),
    )
    .expect("launch");
    assert_eq!(refused.status, Some(2), "{}", refused.output);
    assert!(
        refused.output.contains("\"paper\" observation (12 floats)")
            && refused.output.contains("\"slot_proximity\" (16 floats)"),
        "the refusal names both observation models:\n{}",
        refused.output
    );
    assert!(refused.run_id.is_none(), "nothing may start:\n{}", refused.output);
    let config = repo_root().join("configs/paper-observation.toml");
    let accepted = run_swarm(
        &[
            "3",
            "--mode",
            "eval",
            "--checkpoint",
            paper,
            "--config",
            config.to_str().expect("utf8"),
            "--episodes",
            "2",
            "--viewer",
            "off",
        ],
        &dir.join("run-paper"),
        Duration::from_secs(60),
    )
    .expect("launch");
    assert_eq!(accepted.status, Some(0), "{}", accepted.output);
    assert_clean(&accepted);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn killed_training_critic_resumes_from_its_checkpoint() {
    let dir = scratch_dir("kill-critic-train");
    std::fs::create_dir_all(&dir).expect("dir");
    // A small, fast learner that checkpoints every second.
    let config = dir.join("small.toml");
    std::fs::write(
        &config,
        "[learn]\nbatch_size = 16\nwarmup_transitions = 1000\nactor_hidden = [16]\ncritic_hidden = [32]\ncheckpoint_every_s = 1\n",
    )
    .expect("config");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let checkpoint = run_dir.join("checkpoint.safetensors");
    let run = run_swarm_with(
        &[
            "3",
            "--minutes",
            "0.5",
            "--viewer",
            "off",
            "--config",
            config.to_str().expect("utf8"),
        ],
        &run_dir,
        Duration::from_secs(240),
        |_| {
            let run_id = run_id_of(&log);
            let deadline = Instant::now() + Duration::from_secs(120);
            while !checkpoint.is_file() {
                assert!(Instant::now() < deadline, "no checkpoint was written");
                std::thread::sleep(Duration::from_millis(100));
            }
            std::thread::sleep(Duration::from_millis(1500));
            let pid = pid_of(&run_id, "formation-critic").expect("critic runs");
            kill(pid, libc::SIGKILL);
        },
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert!(run.output.contains("restarting it from"), "{}", run.output);
    let critic_log = std::fs::read_to_string(run_dir.join("logs/critic.log")).expect("critic log");
    assert!(critic_log.contains("critic: resumed from"), "{critic_log}");
    let summary = run.summary().expect("summary");
    assert!(summary["updates"].as_u64().expect("updates") > 0, "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_robot_of_another_protocol_version_is_refused_at_start_up() {
    use std::process::Stdio;

    let dir = scratch_dir("protocol-mismatch");
    let run_id = format!("pm{}", std::process::id());
    let bins = bin_dir().expect("bins");
    let mut sim = Command::new(bins.join("formation-sim"))
        .args([
            "--agents",
            "3",
            "--run-id",
            &run_id,
            "--no-critic",
            "--viewer",
            "off",
            "--run-dir",
        ])
        .arg(dir.join("run"))
        .stderr(Stdio::piped())
        .spawn()
        .expect("sim starts");
    let version = (formation_protocol::wire::PROTOCOL_VERSION + 1).to_string();
    let injector = Command::new(bins.join("fault-injector"))
        .args(["--run-id", &run_id, "--agents", "3", "--agent", "0", "--seconds", "3"])
        .args(["--greet-with-protocol", &version])
        .status()
        .expect("injector runs");
    assert!(injector.success());
    let deadline = Instant::now() + Duration::from_secs(30);
    let status = loop {
        if let Some(status) = sim.try_wait().expect("wait") {
            break Some(status);
        }
        if Instant::now() > deadline {
            let _ = sim.kill();
            let _ = sim.wait();
            break None;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut sim.stderr.take().expect("stderr"), &mut stderr).expect("read");
    let identity = formation_ipc::services::RunIdentity::new(&run_id).expect("id");
    identity.remove_leftovers();
    let status = status.expect("the sim should refuse the greeting at once, not wait for its start-up timeout");
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!("agent 0 speaks protocol version {version}")) && stderr.contains("rebuild"),
        "{stderr}"
    );
    assert!(formation_swarm::shm_leftovers(&run_id).is_empty());
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// `episodes.csv` of `run_dir` as (steps, missed_ticks) per episode, in order.
fn steps_and_misses(run_dir: &std::path::Path) -> Vec<(u64, u64)> {
    let text = std::fs::read_to_string(run_dir.join("episodes.csv")).expect("episodes.csv");
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let column = |name: &str| header.iter().position(|&h| h == name).expect(name);
    let (steps, missed) = (column("steps"), column("missed_ticks"));
    lines
        .map(|line| {
            let fields: Vec<&str> = line.split(',').collect();
            (
                fields[steps].parse().expect("steps"),
                fields[missed].parse().expect("missed_ticks"),
            )
        })
        .collect()
}

#[test]
fn a_dead_robot_under_restart_off_misses_its_ticks_alone() {
    // N = 6 lockstep with the tick gate: the five robots left answer quietly (only the last
    // one of a tick raises the sim's event), so a tick the dead robot never completes ends at
    // the deadline, and their on-time answers must still be read and applied.
    let dir = scratch_dir("kill-agent-restart-off");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "6",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--episodes",
        "3000",
        "--restart",
        "off",
        "--viewer",
        "off",
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(300), |_| {
        let run_id = run_id_of(&log);
        // Killed once the swarm is well under way (episodes 0..=49 played).
        announced(&run_dir.join("episodes.csv"), "50 episodes", |line| {
            line.starts_with("49,").then_some(())
        });
        kill_process(&run_id, "--agent 4");
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let episodes = steps_and_misses(&run_dir);
    assert_eq!(episodes.len(), 3000);
    // Episodes before the kill miss nothing; the kill's episode misses at most one command a
    // tick (the dead robot's); every episode after it exactly one a tick.
    let killed_in = episodes
        .iter()
        .position(|&(_, missed)| missed > 0)
        .expect("an episode with misses");
    let (steps, missed) = episodes[killed_in];
    assert!(
        missed <= steps,
        "episode {killed_in}: {missed} missed commands in {steps} ticks: robots other than the dead one missed"
    );
    let after = &episodes[killed_in + 1..];
    assert!(after.len() >= 10, "killed too late: {killed_in}");
    for (k, &(steps, missed)) in after.iter().enumerate() {
        assert_eq!(missed, steps, "episode {}", killed_in + 1 + k);
    }
    // Nobody but the dead robot was ever given up on.
    let sim_log = std::fs::read_to_string(run_dir.join("logs/sim.log")).expect("sim log");
    let given_up: Vec<&str> = sim_log.lines().filter(|l| l.contains("ticks in a row")).collect();
    assert_eq!(given_up.len(), 1, "{given_up:?}");
    assert!(given_up[0].contains("agent 4 missed"), "{given_up:?}");
    let summary = run.summary().expect("summary");
    let total: u64 = episodes.iter().map(|&(_, missed)| missed).sum();
    assert_eq!(summary["missed_ticks"], serde_json::json!(total), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn impossible_training_runs_are_refused_before_anything_starts() {
    let dir = scratch_dir("bad-training");
    std::fs::create_dir_all(&dir).expect("dir");
    // Independent actors (one per robot of the primary swarm) cannot drive extra swarms: the
    // critic's own check, run by the launcher's pre-flight, refuses them by the setting's name.
    let independent = dir.join("independent.toml");
    std::fs::write(&independent, "[learn]\ncritic = \"pooled\"\nshared_actor = false\n").expect("write");
    let config = independent.to_str().expect("utf8");
    for (args, needle) in [
        (
            vec!["4", "--extra-swarms", "3", "--config", config, "--minutes", "1"],
            "learn.shared_actor = true",
        ),
        // Seeds whose episodes training must never play: held out, or (extra swarm 1 here)
        // the selection's.
        (
            vec!["3", "--seed", "1000", "--minutes", "1"],
            "the run (--seed 1000) would train on seed 1000",
        ),
        (
            vec!["3", "--seed", "6160344", "--extra-swarms", "4", "--minutes", "1"],
            "extra swarm 1 (--seed 6160344 + 7919 x 1) would train on seed 6168263",
        ),
    ] {
        let mut args = args;
        args.extend(["--viewer", "off"]);
        let run = run_swarm(&args, &dir.join("run"), Duration::from_secs(60)).expect("launch");
        assert_eq!(run.status, Some(2), "{args:?}: {}", run.output);
        assert!(
            run.output.contains(needle),
            "{args:?}: should say {needle:?}:\n{}",
            run.output
        );
        assert!(run.run_id.is_none(), "{args:?}: nothing may start:\n{}", run.output);
    }
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
