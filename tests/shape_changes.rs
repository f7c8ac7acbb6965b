//! Formations that change on the move (issue #29): real multi-process runs whose episodes
//! carry shape changes, the sim's mission planner reassigning the slots.

use std::time::Duration;

use formation_core::config::{LearnConfig, RunConfig};
use formation_critic::selection::Selector;
use formation_model::checkpoint;
use formation_swarm::{assert_clean, repo_root, run_swarm, scratch_dir};

#[test]
fn eight_scripted_robots_re_form_after_two_shape_changes_per_episode_and_reach_the_goal() {
    let dir = scratch_dir("shape-changes-8");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("changes.toml");
    std::fs::write(&config, "[env]\nshape_changes = 2\n").expect("write");
    let run = run_swarm(
        &[
            "8",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--episodes",
            "20",
            "--seed",
            "1000",
            "--viewer",
            "off",
            "--config",
            config.to_str().expect("utf8"),
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(summary["episodes"], serde_json::json!(20), "{summary}");
    assert!(summary["success_rate"].as_f64().expect("success") >= 0.9, "{summary}");
    // Success means holding the last formation at the goal: a successful episode met both.
    let changes = summary["reconfigurations"].as_u64().expect("reconfigurations");
    assert!((36..=40).contains(&changes), "{summary}");
    assert!(summary["reforms"].as_u64().expect("reforms") > 0, "{summary}");
    assert!(
        summary["mean_reform_ticks"].as_f64().expect("mean_reform_ticks") > 0.0,
        "{summary}"
    );
    // episodes.csv: the per-episode counts add up to the summary's.
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let (at_changes, at_reforms) = (column("reconfigurations"), column("reforms"));
    let _ = column("mean_reform_ticks");
    let rows: Vec<Vec<String>> = lines.map(|l| l.split(',').map(str::to_string).collect()).collect();
    assert_eq!(rows.len(), 20);
    let sum = |at: usize| rows.iter().map(|r| r[at].parse::<u64>().expect("count")).sum::<u64>();
    assert_eq!(sum(at_changes), changes);
    assert_eq!(Some(sum(at_reforms)), summary["reforms"].as_u64());
    let at_outcome = column("outcome");
    assert!(
        rows.iter()
            .filter(|r| r[at_outcome] == "success")
            .all(|r| r[at_changes] == "2"),
        "{csv}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// Model selection plays episodes with changes as the sim does: an eval run of the shipped
/// model from the selection seed, two shape changes and one controller failure per episode,
/// measures the score the critic selects checkpoints by, episode for episode (every step count
/// must agree: the changes at their ticks, no success before the last, the longer time limit,
/// the failed robot out of the formation and standing still).
#[test]
fn an_eval_run_with_changes_and_a_failure_measures_the_selection_score() {
    let dir = scratch_dir("changes-selection");
    std::fs::create_dir_all(&dir).expect("dir");
    let text = "[env]\nshape_changes = 2\n\n[reality]\ncontroller_failure = 1.0\ndead_robot = \"stop\"\n";
    let config_path = dir.join("changes.toml");
    std::fs::write(&config_path, text).expect("write");
    let config = RunConfig::from_toml_str(text).expect("valid");
    let model_path = repo_root().join("models/formation.safetensors");
    let episodes = 20;
    let learn = LearnConfig {
        selection_episodes: episodes,
        ..LearnConfig::default()
    };
    let seed = learn.selection_seed.to_string();
    let run = run_swarm(
        &[
            "6",
            "--mode",
            "eval",
            "--checkpoint",
            model_path.to_str().expect("utf-8 path"),
            "--config",
            config_path.to_str().expect("utf-8 path"),
            "--episodes",
            &episodes.to_string(),
            "--seed",
            &seed,
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(300),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(summary["departures"], serde_json::json!(episodes), "{summary}");
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    // episode,outcome,steps,...
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|line| line.split(',').collect()).collect();
    assert_eq!(rows.len(), episodes);
    let successes = rows.iter().filter(|row| row[1] == "success").count();
    let steps: u64 = rows.iter().map(|row| row[2].parse::<u64>().expect("steps")).sum();

    let model = checkpoint::load(&model_path).expect("model");
    let actors = [model.actor_weights(0).expect("weights")];
    let scored = Selector::new(&config.env, &learn, &config.reality, &[6])
        .score(&actors, &model.meta.actor)
        .expect("score");
    assert_eq!(
        scored.sizes[0].success,
        successes as f64 / episodes as f64,
        "{scored:?}"
    );
    assert!(
        (scored.sizes[0].mean_steps - steps as f64 / episodes as f64).abs() < 1e-9,
        "{scored:?} against {steps} steps in the run"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
