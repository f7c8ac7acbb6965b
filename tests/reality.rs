//! The reality model (`[reality]`, issue 28) in a running swarm: real processes started by the
//! launcher, with robot 0 played by this test (`--external 0`, the scripted baseline over the
//! same agent code) so that the test is subscribed to the sim's state stream before the first
//! tick, and reads every state the sim publishes.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use formation_agent::run::{AgentOptions, AgentPolicy, run as run_agent};
use formation_core::baseline::ScriptedBaseline;
use formation_core::config::{LearnConfig, RunConfig};
use formation_core::formation::Episodes;
use formation_core::mission::observed_robots;
use formation_core::observation::{Layout, Observer};
use formation_core::obstacles::Obstacles;
use formation_core::physics::{Pose, integrate};
use formation_core::reality::{Reality, RealityConfig};
use formation_core::scene::Scene;
use formation_critic::selection::Selector;
use formation_ipc::services::{self, RunIdentity, Sizing};
use formation_model::checkpoint;
use formation_protocol::wire::{FLAG_RUN_END, ObservationMsg, StateMsg};
use formation_protocol::{MAX_OBS_DIM, NEIGHBOURS};
use formation_swarm::{
    RunOutcome, assert_clean, repo_root, run_id_of, run_swarm, run_swarm_with, scratch_dir, shm_leftovers,
};
use iceoryx2::prelude::*;

/// Robots in every run here.
const N: usize = 3;

/// What a run streamed: every state by (episode, tick), and robot 1's observations.
struct Streamed {
    states: BTreeMap<(u32, u32), StateMsg>,
    observations: BTreeMap<(u32, u32), ObservationMsg>,
    config: RunConfig,
}

/// Runs `N` robots in eval mode, all scripted, robot 0 played here, under the `[reality]`
/// section `reality`; returns the launcher's outcome and the streams.
fn run_with_reality(name: &str, reality: &str, seed: u64, episodes: u32) -> (RunOutcome, Streamed) {
    run_with_config(name, &format!("[reality]\n{reality}"), seed, episodes)
}

/// [`run_with_reality`] with a whole config file's text.
fn run_with_config(name: &str, config_text: &str, seed: u64, episodes: u32) -> (RunOutcome, Streamed) {
    let dir = scratch_dir(name);
    std::fs::create_dir_all(&dir).expect("scratch dir");
    let config_path = dir.join("reality.toml");
    std::fs::write(&config_path, config_text).expect("config");
    let config = RunConfig::from_toml_file(&config_path).expect("valid config");
    let run_dir = dir.join("run");
    let log = run_dir.with_extension("log");
    let mut streamed = None;
    let (seed_arg, episodes_arg) = (seed.to_string(), episodes.to_string());
    let run = run_swarm_with(
        &[
            &N.to_string(),
            "--mode",
            "eval",
            "--scripted",
            "all",
            "--external",
            "0",
            "--episodes",
            &episodes_arg,
            "--seed",
            &seed_arg,
            "--viewer",
            "off",
            "--config",
            config_path.to_str().expect("utf-8 path"),
        ],
        &run_dir,
        Duration::from_secs(240),
        |_| streamed = Some(observe(&log, &config)),
    )
    .expect("launch");
    let streamed = streamed.expect("observed");
    (run, streamed)
}

/// Subscribes to the state stream and robot 1's observations of the run announced in `log`,
/// plays robot 0 until the run ends, and returns what was streamed.
fn observe(log: &Path, config: &RunConfig) -> Streamed {
    let identity = RunIdentity::new(&run_id_of(log)).expect("identity");
    let sizing = Sizing::new(N, config.ticks.critic_window, Layout::of(config.env.observation).dim());
    let node = services::create_node::<ipc::Service>(&identity, "reality-test").expect("node");
    let states = services::state_stream(&node, &sizing)
        .expect("state stream")
        .subscriber_builder()
        .buffer_size(sizing.stream_buffer)
        .create()
        .expect("state subscriber");
    let observations = services::observation_stream(&node, &sizing, 1)
        .expect("observation stream")
        .subscriber_builder()
        .buffer_size(sizing.stream_buffer)
        .create()
        .expect("observation subscriber");
    let wake = services::critic_wake_event(&node, &sizing)
        .expect("critic wake")
        .listener_builder()
        .create()
        .expect("listener");
    let robot = {
        let options = AgentOptions {
            agent: 0,
            n_agents: N,
            weights_from: None,
            config: config.clone(),
        };
        let policy = AgentPolicy::Fixed(Box::new(ScriptedBaseline::new(&config.env, config.baseline)));
        let identity = identity.clone();
        std::thread::spawn(move || run_agent::<ipc::Service>(&identity, &options, policy))
    };
    let mut streamed = Streamed {
        states: BTreeMap::new(),
        observations: BTreeMap::new(),
        config: config.clone(),
    };
    let deadline = Instant::now() + Duration::from_secs(200);
    'run: while Instant::now() < deadline {
        // The sim wakes the critic every half window and at each episode's end; the stream
        // holds two windows, so nothing is lost between wake-ups.
        services::wait_for_event(&wake, Duration::from_millis(200)).expect("wait");
        while let Some(sample) = observations.receive().expect("receive") {
            let msg = *sample.payload();
            streamed.observations.insert((msg.header.episode, msg.header.tick), msg);
        }
        while let Some(sample) = states.receive().expect("receive") {
            let state = *sample.payload();
            if state.header.has(FLAG_RUN_END) {
                break 'run;
            }
            streamed.states.insert((state.header.episode, state.header.tick), state);
        }
    }
    robot.join().expect("robot 0 thread").expect("robot 0");
    streamed
}

/// A state's true tick, owned: what the sim's scene of that tick is built from.
struct TrueTick {
    poses: Vec<Pose>,
    /// The velocities that acted in the transition into the tick.
    acting: Vec<(f64, f64)>,
    desired: Vec<[f64; NEIGHBOURS]>,
    observed: Vec<[usize; NEIGHBOURS]>,
    goal: [f64; 2],
    slots: Vec<[f64; 2]>,
}

impl TrueTick {
    fn of(state: &StateMsg) -> Self {
        let slot_of: Vec<usize> = state.slot[..N].iter().map(|&s| s as usize).collect();
        Self {
            poses: state.poses[..N].iter().map(|&p| Pose::from(p)).collect(),
            acting: state.acting[..N]
                .iter()
                .map(|&[v, w]| (f64::from(v), f64::from(w)))
                .collect(),
            desired: state.desired[..N].iter().map(|d| d.map(f64::from)).collect(),
            observed: observed_robots(&slot_of),
            goal: state.goal.map(f64::from),
            slots: state.slots[..N].iter().map(|s| s.map(f64::from)).collect(),
        }
    }

    /// The tick as the sim's scene among `obstacles` in an arena of side `arena_m`.
    fn scene<'a>(&'a self, obstacles: &'a Obstacles, arena_m: f64) -> Scene<'a> {
        Scene {
            obstacles,
            arena_m,
            ways: None,
            poses: &self.poses,
            commands: &self.acting,
            desired: &self.desired,
            observed: &self.observed,
            goal: self.goal,
            slots: &self.slots,
        }
    }
}

/// Removes the scratch directory of `run` (the test passed).
fn remove_scratch(run: &RunOutcome) {
    std::fs::remove_dir_all(run.run_dir.parent().expect("scratch dir")).expect("cleanup");
}

/// The run finished cleanly and left nothing behind.
fn assert_finished(run: &RunOutcome) -> serde_json::Value {
    assert_eq!(run.status, Some(0), "{}", run.output);
    assert_clean(run);
    run.summary().expect("summary.json")
}

#[test]
fn with_two_ticks_of_delay_each_robots_acting_velocity_is_its_command_of_two_ticks_before() {
    let (run, streamed) = run_with_reality("reality-delay", "actuation_delay_ticks = [2, 2]\n", 3, 3);
    let summary = assert_finished(&run);
    let states = &streamed.states;
    assert!(states.len() > 100, "only {} states streamed", states.len());
    let (mut checked, mut differing) = (0, 0);
    for (&(episode, tick), state) in states {
        for agent in 0..N {
            assert_eq!(state.queued_len[agent], 2, "episode {episode} tick {tick}");
            if tick < 2 {
                assert_eq!(state.acting[agent], [0.0, 0.0], "nothing acts before two ticks");
                continue;
            }
            let Some(before) = states.get(&(episode, tick - 2)) else {
                continue;
            };
            assert_eq!(
                state.acting[agent], before.applied[agent],
                "episode {episode} tick {tick} robot {agent}: acting is the command in use two ticks before"
            );
            // Next to act: the command in use one tick before this one.
            if let Some(last) = states.get(&(episode, tick - 1)) {
                assert_eq!(state.queued[agent][0], last.applied[agent]);
            }
            assert_eq!(state.queued[agent][1], state.applied[agent]);
            checked += 1;
            differing += usize::from(state.acting[agent] != state.applied[agent]);
        }
    }
    assert!(checked > 200, "only {checked} robot-ticks checked");
    assert!(differing > checked / 2, "the delay shows: {differing} of {checked}");
    // Lockstep: every command on time; nothing lost with the losses off.
    for key in ["missed_ticks", "late_commands", "lost_commands", "lost_observations"] {
        assert_eq!(summary[key], 0, "{key}");
    }
    remove_scratch(&run);
}

#[test]
fn a_failed_controller_with_stop_comes_to_rest_within_v_max_over_the_acceleration_limit() {
    let reality = "controller_failure = 1.0\ndead_robot = \"stop\"\nmax_linear_accel_mps2 = 1.0\nmax_angular_accel_radps2 = 3.0\n";
    let seed = 4;
    let (run, streamed) = run_with_reality("reality-stop", reality, seed, 2);
    assert_finished(&run);
    let config = &streamed.config;
    let env = &config.env;
    // v_max / max_linear_accel_mps2 seconds, in ticks (w_max / max_angular is shorter).
    let braking_ticks = (env.v_max / 1.0 / env.dt_s).ceil() as u32;
    assert!(env.w_max / 3.0 <= env.v_max / 1.0);
    let mut episodes_checked = 0;
    for episode in 0..2u32 {
        let reality = Reality::new(&config.reality, env, seed, u64::from(episode), N);
        let failure = reality
            .failure()
            .expect("controller_failure = 1 always draws a failure");
        let ticks: Vec<&StateMsg> = streamed
            .states
            .range((episode, 0)..(episode + 1, 0))
            .map(|(_, s)| s)
            .collect();
        // The state after round `failure.tick + k` is that of tick `failure.tick + k + 1`.
        let at_rest_from = failure.tick + braking_ticks;
        let last = ticks.last().expect("episode streamed").header.tick;
        if last <= at_rest_from {
            continue;
        }
        let moving_before = ticks
            .iter()
            .filter(|s| s.header.tick <= failure.tick)
            .any(|s| s.acting[failure.agent][0] > 0.0);
        assert!(moving_before, "episode {episode}: robot {} moved before", failure.agent);
        for state in ticks.iter().filter(|s| s.header.tick >= at_rest_from) {
            assert_eq!(
                state.acting[failure.agent],
                [0.0, 0.0],
                "episode {episode} tick {}: robot {} at rest {braking_ticks} ticks after its controller died at tick {}",
                state.header.tick,
                failure.agent,
                failure.tick
            );
        }
        // While braking, the acting speed falls by at most the limit per tick.
        for pair in ticks.windows(2) {
            let (a, b) = (pair[0].acting[failure.agent][0], pair[1].acting[failure.agent][0]);
            assert!(
                (a - b).abs() <= (1.0 * env.dt_s) as f32 + 1e-6,
                "tick {}: {a} -> {b}",
                pair[1].header.tick
            );
        }
        episodes_checked += 1;
    }
    assert!(episodes_checked >= 1, "no episode ran past its failure's braking time");
    remove_scratch(&run);
}

#[test]
fn position_noise_reaches_what_robots_are_told_with_the_configured_spread_and_leaves_the_state_true() {
    let sigma = 0.05;
    let (run, streamed) = run_with_reality("reality-noise", &format!("position_noise_m = {sigma}\n"), 5, 8);
    let summary = assert_finished(&run);
    let config = &streamed.config;
    let layout = Layout::of(config.env.observation);
    let observer = Observer::new(&config.env);
    let mut errors = Vec::new();
    let mut compared_with_obs_stream = 0;
    let mut checked_physics = 0;
    for (&(episode, tick), state) in &streamed.states {
        let truth = TrueTick::of(state);
        let poses = &truth.poses;
        let scene = truth.scene(&formation_core::obstacles::NO_OBSTACLES, 10.0);
        for agent in 0..N {
            let truth = observer.observation(agent, &scene);
            let told = state.observations[agent];
            let mut positions = vec![layout.goal()];
            positions.extend((0..NEIGHBOURS).map(|k| layout.neighbour(k)));
            positions.extend(layout.slot());
            for at in positions {
                for i in at..at + 2 {
                    errors.push(f64::from(told[i]) - f64::from(truth[i]));
                }
            }
            // Headings and desired distances are not touched by position noise.
            for k in 0..NEIGHBOURS {
                let at = layout.neighbour(k);
                for i in at + 2..at + 5 {
                    assert!((told[i] - truth[i]).abs() < 1e-4, "float {i} of robot {agent}");
                }
            }
            assert_eq!(told[layout.dim()..], [0.0; MAX_OBS_DIM][layout.dim()..]);
        }
        // What robot 1's obs stream carried is what the state says it was told.
        if let Some(msg) = streamed.observations.get(&(episode, tick)) {
            assert_eq!(msg.obs, state.observations[1]);
            compared_with_obs_stream += 1;
        }
        // The state is the physics' own: each pose follows from the last by the acting velocity.
        if let Some(next) = streamed.states.get(&(episode, tick + 1)) {
            for (agent, pose) in poses.iter().enumerate() {
                let [v, w] = next.acting[agent];
                let expected = integrate(*pose, f64::from(v), f64::from(w), config.env.dt_s);
                let got = Pose::from(next.poses[agent]);
                assert!(
                    (expected.x - got.x).abs() < 1e-4 && (expected.y - got.y).abs() < 1e-4,
                    "episode {episode} tick {tick} robot {agent}"
                );
            }
            checked_physics += 1;
        }
    }
    assert!(errors.len() > 5000, "{} noise samples", errors.len());
    assert!(compared_with_obs_stream > 50 && checked_physics > 50);
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    let spread = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / errors.len() as f64).sqrt();
    assert!(mean.abs() < 0.005, "mean {mean}");
    assert!(
        (spread - sigma).abs() < 0.1 * sigma,
        "spread {spread} for sigma {sigma}"
    );
    assert_eq!(summary["lost_observations"], 0);
    remove_scratch(&run);
}

#[test]
fn range_noise_and_dropout_reach_the_told_scan_with_the_configured_spread_and_rate() {
    let (sigma, dropout) = (0.05, 0.05);
    let text = format!(
        "[env]\nobservation = \"slot_proximity_scan\"\n[obstacles]\nkind = \"forest\"\n\
         [reality]\nrange_noise_m = {sigma}\nrange_dropout = {dropout}\n"
    );
    let (run, streamed) = run_with_config("reality-ranging", &text, 7, 4);
    assert_finished(&run);
    let config = &streamed.config;
    let env = &config.env;
    let at = Layout::of(env.observation).scan().expect("a scan");
    let range = env.scan_range_m;
    let observer = Observer::new(env);
    // The episodes' obstacles, drawn as the sim draws them from the run's seed.
    let episodes: Vec<_> = Episodes::new(N, env, 7).take(4).collect();
    let (mut errors, mut near_rays, mut dropped, mut compared) = (Vec::new(), 0usize, 0usize, 0usize);
    let mut from_obs_stream = 0;
    for (&(episode, tick), state) in &streamed.states {
        // What robot 1's obs stream carried is what the state says it was told.
        if let Some(msg) = streamed.observations.get(&(episode, tick)) {
            assert_eq!(msg.obs, state.observations[1]);
            from_obs_stream += 1;
        }
        let truth = TrueTick::of(state);
        let scene = truth.scene(&episodes[episode as usize].obstacles, env.effective_arena_m(N));
        for agent in 0..N {
            let truth = observer.observation(agent, &scene);
            let told = state.observations[agent];
            for k in at..at + 16 {
                let (truth_m, told_m) = (f64::from(truth[k]) * range, f64::from(told[k]) * range);
                // Six sigmas from both ends: the clamp to [0, range] never acts.
                if (6.0 * sigma..range - 6.0 * sigma).contains(&truth_m) {
                    near_rays += 1;
                    if told[k] == 1.0 {
                        dropped += 1;
                    } else {
                        errors.push(told_m - truth_m);
                    }
                }
            }
        }
        compared += 1;
    }
    assert!(
        compared > 100 && near_rays > 2000,
        "{compared} states, {near_rays} rays in range"
    );
    assert!(from_obs_stream > 50, "{from_obs_stream} ticks of robot 1's obs stream");
    let rate = dropped as f64 / near_rays as f64;
    assert!((rate - dropout).abs() < 0.015, "dropout rate {rate} for {dropout}");
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    let spread = (errors.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / errors.len() as f64).sqrt();
    assert!(mean.abs() < 0.005, "mean {mean}");
    assert!(
        (spread - sigma).abs() < 0.1 * sigma,
        "spread {spread} for sigma {sigma}"
    );
    remove_scratch(&run);
}

#[test]
fn lost_messages_are_counted_apart_near_their_probability_and_never_as_missed() {
    let (p_obs, p_cmd) = (0.1, 0.2);
    let reality = format!("observation_loss = {p_obs}\ncommand_loss = {p_cmd}\n");
    let (run, streamed) = run_with_reality("reality-loss", &reality, 6, 6);
    let summary = assert_finished(&run);
    let count = |key: &str| {
        summary[key]
            .as_u64()
            .unwrap_or_else(|| panic!("{key}: {}", summary[key]))
    };
    let asked = count("env_steps") * N as u64;
    let (lost_obs, lost_cmd) = (count("lost_observations"), count("lost_commands"));
    let within_4_sigma = |lost: u64, messages: u64, p: f64| {
        let (mean, sigma) = (p * messages as f64, (messages as f64 * p * (1.0 - p)).sqrt());
        assert!(
            (lost as f64 - mean).abs() <= 4.0 * sigma,
            "{lost} lost of {messages} at p = {p}"
        );
    };
    // Every robot told a tick answers it once, in lockstep.
    within_4_sigma(lost_obs, asked, p_obs);
    within_4_sigma(lost_cmd, asked - lost_obs, p_cmd);
    assert_eq!(count("missed_ticks"), 0, "a loss is not a miss");
    assert_eq!(count("late_commands"), 0);
    // The state stream marks the robots whose observation was lost.
    let marked: u64 = streamed
        .states
        .values()
        .map(|s| u64::from(s.observation_lost.count_ones()))
        .sum();
    assert!(marked > 0 && marked <= lost_obs, "{marked} marked, {lost_obs} lost");
    // episodes.csv counts the same.
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    let header: Vec<&str> = csv.lines().next().expect("header").split(',').collect();
    let column = |name: &str| header.iter().position(|h| *h == name).expect(name);
    let (obs_col, cmd_col) = (column("lost_observations"), column("lost_commands"));
    let sum = |col: usize| -> u64 {
        csv.lines()
            .skip(1)
            .map(|l| l.split(',').nth(col).expect("field").parse::<u64>().expect("count"))
            .sum()
    };
    assert_eq!((sum(obs_col), sum(cmd_col)), (lost_obs, lost_cmd));
    remove_scratch(&run);
}

#[test]
fn in_real_time_a_robot_behind_a_50_ms_link_reaches_the_goal_on_late_commands() {
    let dir = scratch_dir("reality-remote-late");
    let run = run_swarm(
        &[
            "3",
            "--scripted",
            "all",
            "--mode",
            "eval",
            "--remote",
            "2",
            "--net-delay-ms",
            "50",
            "--realtime",
            "--episodes",
            "5",
            "--seed",
            "1000",
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    let summary = assert_finished(&run);
    let host = format!("{}h2", run.run_id.as_deref().expect("run id"));
    assert!(shm_leftovers(&host).is_empty(), "{:?}", shm_leftovers(&host));
    // A round trip of 100 ms is a whole tick: robot 2's answers come late and are used from
    // the next tick on (before the accounting rule they were dropped and it never moved).
    let late = summary["late_commands"].as_u64().expect("late_commands");
    let steps = summary["env_steps"].as_u64().expect("env_steps");
    assert!(late > steps / 2, "{late} late commands in {steps} ticks: {summary}");
    assert!(
        summary["success_rate"].as_f64().expect("success_rate") >= 0.8,
        "{summary}"
    );
    std::fs::remove_dir_all(&dir).expect("cleanup");
}

/// Model selection under a reality plays what a lockstep run under it plays: an eval run of the
/// shipped model under the field preset, from the selection seed, measures the score the critic
/// selects checkpoints by under that reality, episode for episode (every step count must agree,
/// so each robot's noise, losses, delays and motors must).
#[test]
fn an_eval_run_under_the_field_preset_measures_the_selection_score_under_it() {
    let dir = scratch_dir("field-selection");
    let preset = repo_root().join("configs/reality-field.toml");
    let model_path = repo_root().join("models/formation.safetensors");
    let learn = LearnConfig {
        selection_episodes: 30,
        ..LearnConfig::default()
    };
    let seed = learn.selection_seed.to_string();
    let run = run_swarm(
        &[
            "3",
            "--mode",
            "eval",
            "--checkpoint",
            model_path.to_str().expect("utf-8 path"),
            "--reality",
            preset.to_str().expect("utf-8 path"),
            "--episodes",
            "30",
            "--seed",
            &seed,
            "--viewer",
            "off",
        ],
        &dir.join("run"),
        Duration::from_secs(240),
    )
    .expect("launch");
    assert_eq!(run.status, Some(0), "launcher failed:\n{}", run.output);
    let csv = std::fs::read_to_string(run.run_dir.join("episodes.csv")).expect("episodes.csv");
    // episode,outcome,steps,...
    let rows: Vec<Vec<&str>> = csv.lines().skip(1).map(|line| line.split(',').collect()).collect();
    assert_eq!(rows.len(), 30);
    let successes = rows.iter().filter(|row| row[1] == "success").count();
    let steps: u64 = rows.iter().map(|row| row[2].parse::<u64>().expect("steps")).sum();

    let reality = RealityConfig::from_toml_str(&std::fs::read_to_string(&preset).expect("preset")).expect("valid");
    let model = checkpoint::load(&model_path).expect("model");
    let actors = [model.actor_weights(0).expect("weights")];
    let scored = Selector::new(&RunConfig::default().env, &learn, &reality, &[3])
        .score(&actors, &model.meta.actor)
        .expect("score");
    assert_eq!(scored.sizes[0].success, successes as f64 / 30.0, "{scored:?}");
    assert!(
        (scored.sizes[0].mean_steps - steps as f64 / 30.0).abs() < 1e-9,
        "{scored:?} against {steps} steps in the run"
    );
    // The ideal world beside it plays the same episodes differently.
    let ideal = scored.ideal.as_ref().expect("the ideal world is reported");
    assert_ne!(ideal[0].mean_steps, scored.sizes[0].mean_steps);
    assert_clean(&run);
    std::fs::remove_dir_all(&dir).expect("cleanup");
}
