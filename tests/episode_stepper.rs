//! One set of tick rules: a multi-process lockstep eval and the core's episode stepper played
//! in-process (as model selection and distillation play it) write the same `episodes.csv`
//! rows, under the field preset's reality, with two shape changes and one controller failure
//! per episode.

use std::path::Path;
use std::time::Duration;

use formation_core::config::RunConfig;
use formation_critic::selection::{Played, Team, episode_records};
use formation_model::actor::FrozenActor;
use formation_model::checkpoint;
use formation_swarm::{RunOutcome, assert_clean, repo_root, run_swarm, scratch_dir};

const ROBOTS: usize = 6;
const EPISODES: usize = 12;
const SEED: u64 = 5;
/// Columns that depend on the transport's timing, not on the rules of a tick.
const TIMING_COLUMNS: [&str; 3] = ["wall_s", "missed_ticks", "late_commands"];

/// The field preset with two shape changes and a controller failure in every episode.
fn config_text() -> String {
    let field = std::fs::read_to_string(repo_root().join("configs/reality-field.toml")).expect("field preset");
    let reality = field
        .lines()
        .filter(|line| {
            !line.trim_start().starts_with("controller_failure") && !line.trim_start().starts_with("dead_robot")
        })
        .collect::<Vec<_>>()
        .join("\n");
    format!("[env]\nshape_changes = 2\n\n{reality}\ncontroller_failure = 1.0\ndead_robot = \"stop\"\n")
}

/// Runs the eval until no tick was missed and no answer came late (a loaded machine may make
/// a robot late; those counts are the transport's, so such a run cannot be compared).
fn eval_run(dir: &Path, config: &Path, team: &[&str]) -> (RunOutcome, String) {
    for attempt in 0..3 {
        let seed = SEED.to_string();
        let episodes = EPISODES.to_string();
        let mut args = vec![
            "6",
            "--mode",
            "eval",
            "--config",
            config.to_str().expect("utf-8 path"),
            "--episodes",
            &episodes,
            "--seed",
            &seed,
            "--viewer",
            "off",
        ];
        args.extend_from_slice(team);
        let run = run_swarm(&args, &dir.join(format!("run-{attempt}")), Duration::from_secs(300)).expect("launch");
        assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
        let summary = run.summary().expect("summary.json");
        if summary["missed_ticks"] == 0 && summary["late_commands"] == 0 {
            let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
            return (run, csv);
        }
        eprintln!("attempt {attempt}: ticks were missed or answered late ({summary}); running again");
    }
    panic!("three runs in a row missed ticks: cannot compare");
}

/// The rows of `csv` without the timing columns.
fn comparable(csv: &str) -> Vec<Vec<String>> {
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let keep: Vec<usize> = (0..header.len())
        .filter(|&i| !TIMING_COLUMNS.contains(&header[i]))
        .collect();
    lines
        .map(|line| {
            let cells: Vec<&str> = line.split(',').collect();
            keep.iter().map(|&i| format!("{}={}", header[i], cells[i])).collect()
        })
        .collect()
}

/// The in-process rows as the sim writes them (the same CSV serialiser and float format).
fn as_csv(records: &[formation_core::stepper::EpisodeRecord]) -> String {
    let mut writer = csv::Writer::from_writer(Vec::new());
    for record in records {
        writer.serialize(record).expect("row");
    }
    String::from_utf8(writer.into_inner().expect("flush")).expect("utf-8")
}

fn assert_same_rows(run_csv: &str, in_process: &str) {
    let (run, played) = (comparable(run_csv), comparable(in_process));
    assert_eq!(run.len(), EPISODES, "{run_csv}");
    for (episode, (a, b)) in run.iter().zip(&played).enumerate() {
        assert_eq!(a, b, "episode {episode}: the multi-process run and the stepper differ");
    }
}

#[test]
fn a_lockstep_eval_and_the_in_process_stepper_write_the_same_episodes() {
    let dir = scratch_dir("episode-stepper");
    std::fs::create_dir_all(&dir).expect("dir");
    let text = config_text();
    let config_path = dir.join("field-changes-failure.toml");
    std::fs::write(&config_path, &text).expect("write");
    let config = RunConfig::from_toml_str(&text).expect("valid");
    let played = Played {
        seed: SEED,
        count: EPISODES,
        reality: &config.reality,
    };

    // The scripted team.
    let (run, csv) = eval_run(&dir.join("scripted"), &config_path, &["--scripted", "all"]);
    let records = episode_records(&config.env, ROBOTS, &played, Team::Scripted(&config.baseline)).expect("play");
    assert!(
        records.iter().all(|r| r.departures == 1),
        "a failure in every episode: {records:?}"
    );
    assert!(
        records.iter().any(|r| r.lost_commands > 0 && r.lost_observations > 0),
        "the field's losses: {records:?}"
    );
    assert_same_rows(&csv, &as_csv(&records));
    assert_clean(&run);

    // The shipped model.
    let model_path = repo_root().join("models/formation.safetensors");
    let model = checkpoint::load(&model_path).expect("model");
    let shape = model.meta.actor.clone();
    let mut actors = [FrozenActor::from_flat(&model.actor_weights(0).expect("weights"), &shape).expect("actor")];
    let model_arg = model_path.to_str().expect("utf-8 path");
    let (run, csv) = eval_run(&dir.join("learned"), &config_path, &["--checkpoint", model_arg]);
    let records = episode_records(&config.env, ROBOTS, &played, Team::Actors(&mut actors, &shape)).expect("play");
    assert_same_rows(&csv, &as_csv(&records));
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
