//! A robot lost on the way (issue #29, item 4): a real multi-process run in which one robot's
//! process is killed mid-run with `--restart off`; the sim takes it out of the formation after
//! 10 silent ticks and the others re-form the same formation for N - 1 and reach the goal.

use std::time::Duration;

use formation_model::checkpoint;
use formation_swarm::{announced, assert_clean, pid_of, run_id_of, run_swarm, run_swarm_with, scratch_dir};

/// `episodes.csv` of `run_dir`: the header's columns and the rows.
fn episodes(run_dir: &std::path::Path) -> (Vec<String>, Vec<Vec<String>>) {
    let text = std::fs::read_to_string(run_dir.join("episodes.csv")).expect("episodes.csv");
    let mut lines = text.lines();
    let header = lines.next().expect("header").split(',').map(str::to_string).collect();
    let rows = lines.map(|l| l.split(',').map(str::to_string).collect()).collect();
    (header, rows)
}

#[test]
fn a_robot_killed_mid_run_under_restart_off_leaves_and_the_rest_re_form_and_succeed() {
    let dir = scratch_dir("team-robot-killed");
    std::fs::create_dir_all(&dir).expect("dir");
    // A dead robot brakes and stands: an obstacle the others must keep clear of.
    let config = dir.join("stop.toml");
    std::fs::write(&config, "[reality]\ndead_robot = \"stop\"\n").expect("write");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "6",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--episodes",
        "120",
        "--seed",
        "1000",
        "--restart",
        "off",
        "--viewer",
        "off",
        "--config",
        config.to_str().expect("utf8"),
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(300), |_| {
        let run_id = run_id_of(&log);
        // Killed once the swarm is under way (episodes 0..=19 played).
        announced(&run_dir.join("episodes.csv"), "20 episodes", |line| {
            line.starts_with("19,").then_some(())
        });
        let pid = pid_of(&run_id, "--agent 4").expect("robot 4 runs");
        // SAFETY: kill(2) on a pid of our own run.
        unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let (header, rows) = episodes(&run_dir);
    assert_eq!(rows.len(), 120);
    let column = |name: &str| header.iter().position(|h| h == name).expect(name);
    let count = |row: &Vec<String>, name: &str| row[column(name)].parse::<u64>().expect(name);
    // Robot 4 left once, never came back; the episodes after start without it.
    let left_in: Vec<usize> = (0..rows.len()).filter(|&e| count(&rows[e], "departures") > 0).collect();
    assert_eq!(left_in.len(), 1, "one departure: {left_in:?}");
    let left_in = left_in[0];
    assert!(left_in >= 20, "no departure before the kill: {left_in}");
    assert_eq!(count(&rows[left_in], "departures"), 1);
    assert!(rows.iter().all(|row| count(row, "returns") == 0));
    // Its departure reassigned the slots of the five left (one reconfiguration, re-formed).
    assert!(count(&rows[left_in], "reconfigurations") >= 1);
    let sim_log = std::fs::read_to_string(run_dir.join("logs/sim.log")).expect("sim log");
    let out: Vec<&str> = sim_log.lines().filter(|l| l.contains("out of the formation")).collect();
    assert_eq!(out.len(), 1, "{out:?}");
    assert!(out[0].contains("robot 4 silent for 10 ticks"), "{out:?}");
    // The five left re-form and reach the goal, from the departure on.
    let after = &rows[left_in..];
    let successes = after.iter().filter(|row| row[column("outcome")] == "success").count();
    assert!(
        successes as f64 >= 0.9 * after.len() as f64,
        "{successes} of {} episodes from the departure on succeeded",
        after.len()
    );
    assert!(after.len() >= 50, "killed too late: {left_in}");
    let summary = run.summary().expect("summary");
    assert_eq!(summary["departures"], serde_json::json!(1), "{summary}");
    assert_eq!(summary["returns"], serde_json::json!(0), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_robot_silent_for_a_while_leaves_then_comes_back_after_five_answers() {
    let dir = scratch_dir("team-robot-paused");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let args = [
        "6",
        "--scripted",
        "all",
        "--mode",
        "eval",
        "--episodes",
        "400",
        "--seed",
        "1000",
        "--viewer",
        "off",
    ];
    let run = run_swarm_with(&args, &run_dir, Duration::from_secs(300), |_| {
        let run_id = run_id_of(&log);
        announced(&run_dir.join("episodes.csv"), "20 episodes", |line| {
            line.starts_with("19,").then_some(())
        });
        // Robot 4 falls silent (stopped, as a robot out of radio range), then answers again.
        let pid = pid_of(&run_id, "--agent 4").expect("robot 4 runs");
        // SAFETY: kill(2) on a pid of our own run.
        unsafe { libc::kill(pid as i32, libc::SIGSTOP) };
        let sim_log = run_dir.join("logs/sim.log");
        announced(&sim_log, "robot 4 out", |line| {
            line.contains("robot 4 silent for 10 ticks").then_some(())
        });
        // SAFETY: as above.
        unsafe { libc::kill(pid as i32, libc::SIGCONT) };
    })
    .expect("launch");
    assert_eq!(run.status, Some(0), "{}", run.output);
    let sim_log = std::fs::read_to_string(run_dir.join("logs/sim.log")).expect("sim log");
    let lines = |text: &str| sim_log.lines().filter(|l| l.contains(text)).count();
    assert_eq!(
        lines("robot 4 silent for 10 ticks: out of the formation"),
        1,
        "{sim_log}"
    );
    assert_eq!(
        lines("robot 4 answered 5 ticks in a row: back in the formation"),
        1,
        "{sim_log}"
    );
    let summary = run.summary().expect("summary");
    assert_eq!(summary["departures"], serde_json::json!(1), "{summary}");
    assert_eq!(summary["returns"], serde_json::json!(1), "{summary}");
    // With all six in again the swarm succeeds as before.
    let (header, rows) = episodes(&run_dir);
    let outcome = header.iter().position(|h| h == "outcome").expect("outcome");
    let returns = header.iter().position(|h| h == "returns").expect("returns");
    let back_in = rows
        .iter()
        .position(|row| row[returns] == "1")
        .expect("the return's episode");
    let after = &rows[back_in + 1..];
    assert!(after.len() >= 50, "came back too late: episode {back_in}");
    let successes = after.iter().filter(|row| row[outcome] == "success").count();
    assert!(
        successes as f64 >= 0.9 * after.len() as f64,
        "{successes} of {}",
        after.len()
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// Training with robots lost on the way (item 6): one controller failure per episode, the dead
/// robot stopped, the pooled critic masking it out. A short run trains (updates on batches with
/// robots out of the formation) and writes a checkpoint scored under the run's reality.
#[test]
fn a_short_training_run_with_a_controller_failure_per_episode_trains_the_pooled_critic() {
    let dir = scratch_dir("team-train-failure");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("failure.toml");
    std::fs::write(
        &config,
        "[reality]\ncontroller_failure = 1.0\ndead_robot = \"stop\"\n\n\
         [learn]\ncritic = \"pooled\"\nwarmup_transitions = 300\nbatch_size = 32\nselection_episodes = 10\n",
    )
    .expect("write");
    let run = run_swarm(
        &[
            "6",
            "--config",
            config.to_str().expect("utf8"),
            "--minutes",
            "0.5",
            "--seed",
            "7",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert!(summary["departures"].as_u64().expect("departures") > 0, "{summary}");
    assert!(summary["updates"].as_u64().expect("updates") > 0, "{summary}");
    let last = checkpoint::load(&run.run_dir.join("checkpoint.safetensors")).expect("checkpoint");
    assert!(
        last.tensors.keys().any(|name| name.starts_with("critic0.encoder.")),
        "a pooled critic"
    );
    assert_clean(&run);
    // The same run with the mlp critic, which cannot leave a robot out, is refused before
    // anything starts, naming the fields.
    let mlp = dir.join("mlp.toml");
    std::fs::write(&mlp, "[reality]\ncontroller_failure = 1.0\ndead_robot = \"stop\"\n").expect("write");
    let refused = run_swarm(
        &[
            "6",
            "--config",
            mlp.to_str().expect("utf8"),
            "--minutes",
            "0.5",
            "--viewer",
            "off",
        ],
        &dir.join("run-mlp"),
        Duration::from_secs(60),
    )
    .expect("launch");
    assert_eq!(refused.status, Some(2), "{}", refused.output);
    assert!(
        refused.output.contains("learn.critic") && refused.output.contains("reality.controller_failure"),
        "{}",
        refused.output
    );
    assert!(refused.run_id.is_none(), "nothing may start:\n{}", refused.output);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
