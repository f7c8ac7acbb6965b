//! Real multi-process runs: the launcher starts the sim, the agents and the critic as OS
//! processes over iceoryx2, exactly as a user would.

use std::time::Duration;

use formation_core::config::{LearnConfig, RunConfig};
use formation_core::reality::RealityConfig;
use formation_critic::selection::Selector;
use formation_model::checkpoint;
use formation_swarm::{assert_clean, processes_of_run, repo_root, run_swarm, scratch_dir, shm_leftovers};

fn scripted_eval(n: &str, episodes: &str) {
    let dir = scratch_dir(&format!("scripted-{n}"));
    let run = run_swarm(
        &[
            n,
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--episodes",
            episodes,
            "--seed",
            "3",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(120),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(
        summary["episodes"],
        serde_json::json!(episodes.parse::<u64>().expect("number"))
    );
    assert_eq!(
        summary["n_agents"],
        serde_json::json!(n.parse::<u64>().expect("number"))
    );
    for key in [
        "success_rate",
        "collision_rate",
        "timeout_rate",
        "mean_final_edge_error_m",
        "env_steps",
        "env_steps_per_s",
        "missed_ticks",
        "transitions_received",
    ] {
        assert!(summary[key].is_number(), "summary lacks {key}: {summary}");
    }
    assert_eq!(summary["lost_transitions"], serde_json::json!(0), "{summary}");
    assert_eq!(summary["missed_ticks"], serde_json::json!(0), "{summary}");
    assert!(summary["env_steps"].as_u64().expect("env_steps") > 0);
    // Every tick the sim published reached the critic (one state per step plus one per episode start).
    let expected = summary["env_steps"].as_u64().expect("steps") + summary["episodes"].as_u64().expect("episodes");
    assert_eq!(summary["transitions_received"].as_u64(), Some(expected), "{summary}");
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    assert_eq!(csv.lines().count(), 1 + episodes.parse::<usize>().expect("number"));
    assert!(run.run_dir.join("config.toml").is_file());
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn three_scripted_robots_finish_clean() {
    scripted_eval("3", "5");
}

#[test]
fn six_scripted_robots_finish_clean() {
    scripted_eval("6", "3");
}

#[test]
fn twelve_scripted_robots_with_slots_reach_the_goal_in_a_grid() {
    let dir = scratch_dir("scripted-12-slots");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("slots.toml");
    std::fs::write(&config, "[env]\nobservation = \"slot_proximity\"\n").expect("write");
    let run = run_swarm(
        &[
            "12",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--episodes",
            "6",
            "--seed",
            "4",
            "--shape",
            "grid",
            "--viewer",
            "off",
            "--config",
            config.to_str().expect("utf8"),
        ],
        &dir.join("run"),
        Duration::from_secs(180),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(summary["episodes"], serde_json::json!(6), "{summary}");
    assert!(summary["success_rate"].as_f64().expect("success") >= 0.8, "{summary}");
    assert_eq!(summary["collision_rate"].as_f64(), Some(0.0), "{summary}");
    let written = std::fs::read_to_string(run.run_dir.join("config.toml")).expect("config.toml");
    assert!(
        written.contains("shape = \"grid\"") && written.contains("observation = \"slot_proximity\""),
        "{written}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn the_shipped_model_drives_six_robots_to_the_goal() {
    let dir = scratch_dir("learned-6");
    // No --checkpoint: eval uses models/formation.safetensors, the one model for any N.
    let run = run_swarm(
        &[
            "6",
            "--mode",
            "eval",
            "--episodes",
            "10",
            "--seed",
            "9",
            "--shape",
            "mixed",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(180),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(summary["episodes"], serde_json::json!(10), "{summary}");
    assert!(summary["success_rate"].as_f64().expect("success") >= 0.8, "{summary}");
    assert_eq!(summary["scripted_agents"], serde_json::json!([]), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// A checkpoint knows its shape: an evaluation drives it with the window (H) and widths it was
/// trained with, without a config saying so (here a student reading 2 observations, from a
/// one-round distillation, evaluated under the default config's H = 1).
#[test]
fn an_eval_reads_the_window_its_checkpoint_was_trained_with() {
    use formation_critic::distill::{DistillOptions, Distiller};
    let dir = scratch_dir("eval-window");
    std::fs::create_dir_all(&dir).expect("dir");
    let mut config = RunConfig::default();
    config.env.history = 2;
    let options = DistillOptions {
        sizes: vec![3],
        rounds: 1,
        robots_per_round: 6,
        updates_per_round: 20,
        batch: 64,
        capacity: 10_000,
        ..DistillOptions::default()
    };
    let mut student = Distiller::new(&config, options, None).expect("a student");
    student.round().expect("a round");
    let path = dir.join("window-2.safetensors");
    student.save(&path, Default::default()).expect("saved");
    assert_eq!(checkpoint::load(&path).expect("loads").meta.actor.history, 2);
    let run = run_swarm(
        &[
            "3",
            "--mode",
            "eval",
            "--checkpoint",
            path.to_str().expect("utf-8 path"),
            "--episodes",
            "2",
            "--seed",
            "4",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(120),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert_eq!(summary["episodes"], serde_json::json!(2), "{summary}");
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn a_gain_schedule_drives_as_the_baseline_s_law_with_the_gains_it_outputs() {
    use formation_core::baseline::BaselineGains;
    use formation_core::observation::Layout;
    use formation_model::actor::{ActorHead, ActorShape};
    use formation_model::checkpoint::{CheckpointMeta, actor_prefix};
    let dir = scratch_dir("gain-schedule");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = RunConfig::default();
    let shape = ActorShape {
        obs_dim: Layout::of(config.env.observation).dim(),
        history: config.env.history,
        hidden: config.learn.actor_hidden.clone(),
        head: ActorHead::Gains,
    };
    // Zero weights and a last bias of atanh(gains): the actor outputs the field's fast gains
    // whatever it reads; `gains` is exactly what the agents decode.
    let bias = BaselineGains {
        k_form: 0.45,
        k_goal: 1.07,
        k_turn: 1.3,
        repulsion_range: 0.51,
        k_repulsion: 1.58,
        ..BaselineGains::default()
    }
    .to_unit()
    .map(f32::atanh);
    let gains = BaselineGains::from_unit(&bias.map(f32::tanh));
    let parameters = shape.parameters();
    let last = parameters.len() - 1;
    let tensors: Vec<(String, candle_core::Tensor)> = parameters
        .into_iter()
        .enumerate()
        .map(|(i, (name, dims))| {
            let len: usize = dims.iter().product();
            let values = if i == last { bias.to_vec() } else { vec![0.0f32; len] };
            let tensor = candle_core::Tensor::from_vec(values, dims, &candle_core::Device::Cpu).expect("tensor");
            (format!("{}{name}", actor_prefix(0)), tensor)
        })
        .collect();
    let model = dir.join("fast-gains.safetensors");
    let meta = CheckpointMeta {
        n_agents: 3,
        observation: config.env.observation,
        n_actors: 1,
        actor: shape,
        extra: Default::default(),
    };
    checkpoint::save(&model, &tensors, &meta).expect("saved");
    // The scripted baseline with the same gains, from a config.
    let scripted_config = dir.join("fast-gains.toml");
    std::fs::write(
        &scripted_config,
        format!(
            "[baseline]\nk_form = {:?}\nk_goal = {:?}\nk_turn = {:?}\nrepulsion_range = {:?}\nk_repulsion = {:?}\n",
            gains.k_form, gains.k_goal, gains.k_turn, gains.repulsion_range, gains.k_repulsion
        ),
    )
    .expect("config");
    let episodes = |name: &str, team: &[&str]| {
        let mut args = vec![
            "3",
            "--mode",
            "eval",
            "--episodes",
            "3",
            "--seed",
            "8",
            "--viewer",
            "off",
        ];
        args.extend_from_slice(team);
        let run = run_swarm(&args, &dir.join(name), Duration::from_secs(120)).expect("launch");
        assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
        assert_clean(&run);
        let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
        // Everything but the wall time.
        let wall = csv
            .lines()
            .next()
            .and_then(|header| header.split(',').position(|column| column == "wall_s"))
            .expect("a wall_s column");
        csv.lines()
            .map(|line| {
                let mut fields: Vec<&str> = line.split(',').collect();
                fields.remove(wall);
                fields.join(",")
            })
            .collect::<Vec<_>>()
    };
    let learned = episodes("learned", &["--checkpoint", model.to_str().expect("utf-8")]);
    let scripted = episodes(
        "scripted",
        &[
            "--scripted",
            "all",
            "--config",
            scripted_config.to_str().expect("utf-8"),
        ],
    );
    assert_eq!(learned.len(), 4, "{learned:?}");
    assert_eq!(learned, scripted);
    // And not as the default gains do.
    let default = episodes("default", &["--scripted", "all"]);
    assert_ne!(learned, default);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn one_critic_trains_one_actor_on_two_swarm_sizes_at_once_for_the_updates_asked() {
    let dir = scratch_dir("two-sizes");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("two-sizes.toml");
    let base = std::fs::read_to_string(repo_root().join("configs/multi-size.toml")).expect("config");
    // Short: updates start after 300 ticks of each swarm; every checkpoint kept.
    let quick = base.replace(
        "[learn]\n",
        "[learn]\nwarmup_transitions = 300\nbatch_size = 32\nkeep_checkpoints = true\n",
    );
    assert_ne!(quick, base, "configs/multi-size.toml has a [learn] section");
    std::fs::write(&config, quick).expect("write");
    let run = run_swarm(
        &[
            "3",
            "--extra-swarms",
            "4",
            "--config",
            config.to_str().expect("utf8"),
            "--updates",
            "300",
            "--seed",
            "5",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(180),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let summary = run.summary().expect("summary.json");
    assert!(summary["episodes"].as_u64().expect("episodes") > 0, "{summary}");
    // --updates ends the run by itself, after exactly that many updates.
    assert_eq!(summary["updates"].as_u64(), Some(300), "{summary}");
    assert!(
        run.output.contains("the critic has done its 300 updates"),
        "{}",
        run.output
    );
    let extra = run.run_dir.join("swarm-1-n4/summary.json");
    let extra: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&extra).expect("the extra swarm's summary")).expect("json");
    assert_eq!(extra["n_agents"], serde_json::json!(4), "{extra}");
    assert!(extra["episodes"].as_u64().expect("episodes") > 0, "{extra}");
    let last = checkpoint::load(&run.run_dir.join("checkpoint.safetensors")).expect("checkpoint");
    assert_eq!(last.meta.extra["swarm_sizes"], "3,4");
    assert_eq!(last.meta.extra["updates"], "300");
    // The last checkpoint is also kept, named by its updates.
    let kept = run.run_dir.join(format!(
        "checkpoints/updates-{:08}.safetensors",
        last.meta.extra["updates"].parse::<u64>().expect("updates")
    ));
    let kept = checkpoint::load(&kept).unwrap_or_else(|e| panic!("the last checkpoint kept: {e:#}"));
    assert_eq!(kept.meta.extra, last.meta.extra);
    let actor_steps: u64 = last.meta.extra["run_actor_steps"].parse().expect("run_actor_steps");
    assert!(actor_steps > 0, "the actor stepped in this run: {:?}", last.meta.extra);
    // Scored on each size's selection episodes; the first score is also the best so far.
    let path = run.run_dir.join("best.safetensors");
    let best = checkpoint::load(&path).expect("best.safetensors");
    let score = best.meta.selection(&path).expect("selection metadata").expect("scored");
    assert_eq!(score.sizes.iter().map(|s| s.n_agents).collect::<Vec<_>>(), [3, 4]);
    assert_clean(&run);
    let extra_id = format!("{}x1", run.run_id.as_deref().expect("run id"));
    assert!(shm_leftovers(&extra_id).is_empty(), "{:?}", shm_leftovers(&extra_id));
    assert!(processes_of_run(&extra_id).is_empty());
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn training_goes_on_while_a_checkpoint_is_scored_for_longer_than_the_sims_silence_limit() {
    // Selections of 800 forest episodes take tens of seconds, far beyond the 5 s a silent sim is
    // waited for: the sims must not wait for the critic meanwhile (robots and critic would give
    // them up and restart), the last checkpoint must be scored and saved before the launcher
    // stops the critic, and updates must go on while a checkpoint is scored.
    let dir = scratch_dir("long-selection");
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("long-selection.toml");
    std::fs::write(
        &config,
        "[env]\nobservation = \"slot_proximity_scan\"\n\n[obstacles]\nkind = \"forest\"\n\n\
         [learn]\nwarmup_transitions = 300\nbatch_size = 32\ncheckpoint_every_s = 4\nselection_episodes = 800\n\n\
         [ticks]\nstartup_timeout_s = 5\n",
    )
    .expect("write");
    let run = run_swarm(
        &[
            "4",
            "--config",
            config.to_str().expect("utf8"),
            "--minutes",
            "0.4",
            "--seed",
            "9",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(600),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    assert!(!run.output.contains("died"), "a member died:\n{}", run.output);
    // (updates, scored in ms) of every checkpoint the critic saved.
    let checkpoints: Vec<(u64, u64)> = run
        .output
        .lines()
        .filter_map(|line| {
            let updates = line
                .strip_prefix("critic: checkpoint at ")?
                .split(' ')
                .next()?
                .parse()
                .ok()?;
            let took = line.split("scored in ").nth(1)?.split(' ').next()?.parse().ok()?;
            Some((updates, took))
        })
        .collect();
    assert!(
        checkpoints.iter().any(|&(_, took)| took > 5_000),
        "a selection should outlast the silence limit: {checkpoints:?}\n{}",
        run.output
    );
    let summary = run.summary().expect("summary.json");
    let updates = summary["updates"]
        .as_u64()
        .expect("the critic's figures in summary.json");
    println!(
        "checkpoints (updates, ms to score): {checkpoints:?}; transitions {} received, {} lost",
        summary["transitions_received"], summary["lost_transitions"]
    );
    // The first checkpoint was copied when its selection started; the last holds every update.
    let (first, _) = checkpoints[0];
    let last = checkpoint::load(&run.run_dir.join("checkpoint.safetensors")).expect("checkpoint");
    assert_eq!(last.meta.extra["updates"], updates.to_string(), "{checkpoints:?}");
    assert!(
        updates > first,
        "no updates while the first checkpoint was scored: {checkpoints:?}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn an_eval_run_from_the_selection_seed_measures_the_selection_score() {
    // The 3-robot paper model misses a few of these episodes, so the two agree only if they
    // play the same episodes with the same actions.
    let dir = scratch_dir("selection-seed");
    let config_path = repo_root().join("configs/paper-observation.toml");
    let model_path = repo_root().join("models/formation-3robots-paper.safetensors");
    let learn = LearnConfig {
        selection_episodes: 200,
        ..LearnConfig::default()
    };
    let seed = learn.selection_seed.to_string();
    let run = run_swarm(
        &[
            "3",
            "--config",
            config_path.to_str().expect("utf8"),
            "--mode",
            "eval",
            "--checkpoint",
            model_path.to_str().expect("utf8"),
            "--episodes",
            "200",
            "--seed",
            &seed,
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(180),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    // episode,outcome,steps,...
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|line| line.split(',').collect()).collect();
    assert_eq!(rows.len(), 200);
    let successes = rows.iter().filter(|row| row[1] == "success").count();
    let steps: u64 = rows.iter().map(|row| row[2].parse::<u64>().expect("steps")).sum();

    let env = RunConfig::from_toml_file(&config_path).expect("config").env;
    let model = checkpoint::load(&model_path).expect("model");
    let actors = [model.actor_weights(0).expect("weights")];
    let scored = Selector::new(&env, &learn, &RealityConfig::default(), &[3])
        .score(&actors, &model.meta.actor)
        .expect("score");
    assert!(
        successes < 200,
        "the model should miss some episodes to tell them apart"
    );
    assert_eq!(scored.sizes[0].success, successes as f64 / 200.0, "{scored:?}");
    assert!(
        (scored.sizes[0].mean_steps - steps as f64 / 200.0).abs() < 1e-9,
        "{scored:?}"
    );
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

#[test]
fn bad_input_is_refused_before_anything_starts() {
    let dir = scratch_dir("bad-input");
    for (args, needle) in [
        (vec!["2"], "between 3 and 64"),
        (vec!["65"], "between 3 and 64"),
        (vec!["3", "--bogus"], "unexpected argument '--bogus'"),
        (vec!["3", "--mode", "fly"], "--mode"),
        (vec!["3", "--scripted", "0,7"], "robot 7 does not exist"),
        (vec!["3", "--shape", "blob"], "--shape"),
        (vec!["3", "--extra-swarms", "4,2"], "sizes 3 to 64"),
        (vec!["3", "--extra-swarms", "4", "--mode", "eval"], "for training"),
        (
            vec!["3", "--updates", "100", "--mode", "eval"],
            "--updates is for training",
        ),
        (vec!["3", "--updates", "0"], "--updates"),
        // The default critic is sized by N: it cannot serve several sizes.
        (vec!["3", "--extra-swarms", "4"], "pooled"),
    ] {
        let run = run_swarm(&args, &dir.join("run"), Duration::from_secs(60)).expect("launch");
        assert_eq!(
            run.status,
            Some(2),
            "{args:?} should fail with status 2:\n{}",
            run.output
        );
        assert!(
            run.output.contains(needle),
            "{args:?}: expected {needle:?} in:\n{}",
            run.output
        );
        assert!(run.run_id.is_none(), "{args:?} started a run:\n{}", run.output);
    }
    // A config with an impossible value names the field; nothing starts.
    std::fs::create_dir_all(&dir).expect("dir");
    let config = dir.join("bad.toml");
    std::fs::write(&config, "[env]\ndt_s = -0.1\n").expect("write");
    let run = run_swarm(
        &["3", "--config", config.to_str().expect("utf8")],
        &dir.join("run"),
        Duration::from_secs(60),
    )
    .expect("launch");
    assert_eq!(run.status, Some(2), "{}", run.output);
    assert!(run.output.contains("env.dt_s"), "{}", run.output);
    assert!(run.run_id.is_none());
    std::fs::write(&config, "[env\n").expect("write");
    let run = run_swarm(
        &["3", "--config", config.to_str().expect("utf8")],
        &dir.join("run"),
        Duration::from_secs(60),
    )
    .expect("launch");
    assert_eq!(run.status, Some(2));
    assert!(run.output.contains("does not parse"), "{}", run.output);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// CPUs in a `Cpus_allowed_list` line such as `0-1,3`.
fn parse_cpu_list(text: &str) -> Vec<usize> {
    text.trim()
        .split(',')
        .flat_map(|part| {
            let (first, last) = part.split_once('-').unwrap_or((part, part));
            first.parse::<usize>().expect("cpu")..=last.parse::<usize>().expect("cpu")
        })
        .collect()
}

/// The CPUs thread `tid` of process `pid` may run on.
fn thread_cpus(pid: u32, tid: u32) -> Option<Vec<usize>> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/task/{tid}/status")).ok()?;
    let list = status.lines().find_map(|l| l.strip_prefix("Cpus_allowed_list:"))?;
    Some(parse_cpu_list(list))
}

#[test]
fn robots_share_the_sim_cpu_and_the_critic_gets_the_others() {
    use std::collections::BTreeMap;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, Ordering};

    let dir = scratch_dir("placement");
    let run_dir = dir.join("run");
    let allowed = thread_cpus(std::process::id(), std::process::id()).expect("own affinity");
    // Watch the run's processes (their main threads) until it ends; keep what each showed last.
    let done = Arc::new(AtomicBool::new(false));
    let watcher = {
        let done = Arc::clone(&done);
        let needle = run_dir.to_string_lossy().into_owned();
        std::thread::spawn(move || {
            let mut seen: BTreeMap<String, Vec<usize>> = BTreeMap::new();
            while !done.load(Ordering::Relaxed) {
                for pid in formation_swarm::processes_of_run(&needle) {
                    let Ok(cmdline) = std::fs::read(format!("/proc/{pid}/cmdline")) else {
                        continue;
                    };
                    let args: Vec<String> = cmdline
                        .split(|&b| b == 0)
                        .map(|a| String::from_utf8_lossy(a).into_owned())
                        .collect();
                    if !args[0].contains("formation-") || args.iter().any(|a| a == "--check" || a == "--check-config") {
                        continue;
                    }
                    let role = match args.iter().position(|a| a == "--agent") {
                        Some(i) => format!("agent {}", args[i + 1]),
                        None => args[0].rsplit('/').next().expect("name").to_string(),
                    };
                    if let Some(cpus) = thread_cpus(pid, pid) {
                        seen.insert(role, cpus);
                    }
                }
                std::thread::sleep(Duration::from_millis(20));
            }
            seen
        })
    };
    let run = run_swarm(
        &[
            "4",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--episodes",
            "60",
            "--viewer",
            "off",
        ],
        &run_dir,
        Duration::from_secs(120),
    )
    .expect("launch");
    done.store(true, Ordering::Relaxed);
    let seen = watcher.join().expect("watcher");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    assert_eq!(seen.len(), 6, "expected sim, critic and 4 agents, saw {seen:?}");
    let (lockstep, others) = match allowed.split_last() {
        Some((&last, rest)) if !rest.is_empty() => (vec![last], rest.to_vec()),
        _ => (allowed.clone(), allowed.clone()),
    };
    for (role, cpus) in &seen {
        let expected = if role == "formation-critic" { &others } else { &lockstep };
        assert_eq!(
            cpus, expected,
            "{role} runs on {cpus:?} (this test may use {allowed:?})"
        );
    }
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
