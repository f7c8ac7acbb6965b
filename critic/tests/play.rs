//! `formation-play` as a user runs it: the episodes' CSV rows and, for the episodes asked,
//! their traces (what docs' pictures and scripts/failure_census.py read).

mod common;

use std::process::{Command, Output};

fn play(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_formation-play"))
        .args(args)
        .output()
        .expect("runs")
}

#[test]
fn traces_every_episode_asked_with_one_pose_a_tick_and_refuses_one_past_the_last() {
    let dir = common::tempdir("formation-play");
    let out = dir.to_str().expect("utf-8");
    let common = [
        "--team",
        "scripted",
        "--obstacles",
        "forest",
        "--n",
        "4",
        "--episodes",
        "3",
        "--seed",
        "7",
        "--out",
        out,
    ];
    let traced = play(&[&common[..], &["--trace-episode", "0,2"]].concat());
    assert!(traced.status.success(), "{}", String::from_utf8_lossy(&traced.stderr));
    let rows: Vec<csv::StringRecord> = csv::Reader::from_path(dir.join("n4.csv"))
        .expect("the CSV")
        .records()
        .map(|row| row.expect("a row"))
        .collect();
    assert_eq!(rows.len(), 3);
    for episode in [0, 2] {
        let trace: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.join(format!("trace-n4-e{episode}.json"))).expect("traced"),
        )
        .expect("JSON");
        let steps: usize = rows[episode][2].parse().expect("steps");
        let poses = trace["poses"].as_array().expect("poses");
        assert_eq!(poses.len(), steps + 1, "the start and one pose a tick");
        assert!(poses.iter().all(|tick| tick.as_array().expect("robots").len() == 4));
        assert_eq!(trace["slots"].as_array().expect("slots").len(), 4);
        assert!(!trace["obstacles"].as_array().expect("obstacles").is_empty());
    }
    assert!(!dir.join("trace-n4-e1.json").exists(), "only the episodes asked");
    let past = play(&[&common[..], &["--trace-episode", "3"]].concat());
    assert!(!past.status.success());
    assert!(
        String::from_utf8_lossy(&past.stderr).contains("--trace-episode 3: there are only 3 episodes"),
        "{}",
        String::from_utf8_lossy(&past.stderr)
    );
    std::fs::remove_dir_all(dir).ok();
}
