//! The replay's public contract: sequences stay inside one episode, every robot's window covers
//! the same ticks, and HER relabelling equals recomputing everything from the true states.

use formation_protocol::config::EnvConfig;
use formation_protocol::{ACTION_DIM, OBS_DIM};
use formation_replay::buffer::{Episode, ReplayBuffer, Tick};
use formation_replay::features::{centroid, observation, state_dim, transition_reward};
use formation_replay::sample::Sampler;
use formation_sim::formation::random_episode;
use formation_sim::world::World;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Plays random episodes in-process, recording what the critic would assemble.
fn recorded_episodes(count: usize, n: usize, seed: u64) -> Vec<Episode> {
    let env = EnvConfig::default();
    let mut rng = StdRng::seed_from_u64(seed);
    (0..count)
        .map(|number| {
            let mut world = World::new(&env, random_episode(n, &env, &mut rng));
            let desired: Vec<[f32; 2]> = world.desired.iter().map(|d| [d[0] as f32, d[1] as f32]).collect();
            let goal = [world.goal[0] as f32, world.goal[1] as f32];
            let snapshot = |w: &World| Tick {
                poses: w
                    .poses
                    .iter()
                    .map(|p| [p.x as f32, p.y as f32, p.theta as f32])
                    .collect(),
                observations: (0..n).map(|a| w.observation(a)).collect(),
                actions: vec![[0.0; ACTION_DIM]; n],
                reward: 0.0,
            };
            let mut ticks = vec![snapshot(&world)];
            let mut terminal = false;
            // Short episodes keep the test quick; a random walk with a forward bias.
            for _ in 0..30 {
                let actions: Vec<[f32; 2]> = (0..n)
                    .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
                    .collect();
                let commands: Vec<(f64, f64)> = actions.iter().map(|a| env.command_from_action(*a)).collect();
                let result = world.step(&commands);
                let last = ticks.last_mut().expect("tick");
                last.actions = actions;
                last.reward = result.reward as f32;
                ticks.push(snapshot(&world));
                if result.outcome.is_terminal() {
                    terminal = true;
                    break;
                }
            }
            Episode {
                number: number as u32,
                desired,
                goal,
                ticks,
                terminal,
            }
        })
        .collect()
}

fn buffer_of(episodes: &[Episode]) -> ReplayBuffer {
    let mut buffer = ReplayBuffer::new(1_000_000);
    for e in episodes {
        buffer.push(e.clone());
    }
    buffer
}

#[test]
fn sequences_never_cross_episodes_and_share_ticks() {
    let n = 3;
    let h = 5;
    let episodes = recorded_episodes(20, n, 1);
    let buffer = buffer_of(&episodes);
    let sampler = Sampler {
        history: h,
        her_probability: 0.0,
        env: EnvConfig::default(),
    };
    let mut rng = StdRng::seed_from_u64(2);
    let batch = sampler.sample(&buffer, 256, &mut rng).expect("batch");
    for b in 0..batch.batch_size {
        let (number, t) = batch.origins[b];
        let episode = &episodes[number as usize];
        assert!(t + 1 < episode.ticks.len());
        for agent in 0..n {
            for k in 0..h {
                // Window ending at t: tick max(t + k + 1 - h, 0) of the same episode.
                let tick = (t + k + 1).saturating_sub(h);
                let offset = ((b * n + agent) * h + k) * OBS_DIM;
                assert_eq!(
                    &batch.observations[offset..offset + OBS_DIM],
                    &episode.ticks[tick].observations[agent]
                );
                let next_tick = (t + k + 2).saturating_sub(h);
                assert_eq!(
                    &batch.next_observations[offset..offset + OBS_DIM],
                    &episode.ticks[next_tick].observations[agent]
                );
                let a = ((b * h + k) * n + agent) * ACTION_DIM;
                assert_eq!(&batch.actions[a..a + ACTION_DIM], &episode.ticks[tick].actions[agent]);
            }
        }
        assert_eq!(batch.rewards[b], episode.ticks[t].reward);
        assert_eq!(
            batch.terminals[b] == 1.0,
            episode.terminal && t + 2 == episode.ticks.len()
        );
    }
    assert_eq!(batch.states.len(), batch.batch_size * h * state_dim(n));
}

#[test]
fn her_relabelling_equals_recomputation_from_true_states() {
    let n = 3;
    let h = 4;
    let env = EnvConfig::default();
    let episodes = recorded_episodes(10, n, 5);
    let buffer = buffer_of(&episodes);
    let sampler = Sampler {
        history: h,
        her_probability: 1.0,
        env: env.clone(),
    };
    let mut rng = StdRng::seed_from_u64(6);
    let batch = sampler.sample(&buffer, 128, &mut rng).expect("batch");
    let mut saw_success = false;
    for b in 0..batch.batch_size {
        assert!(batch.relabelled[b]);
        let (number, t) = batch.origins[b];
        let episode = &episodes[number as usize];
        let goal = batch.goals[b];
        // The new goal is a centroid the formation reached later in the same episode.
        assert!(
            episode.ticks[t + 1..].iter().any(|tick| centroid(&tick.poses) == goal),
            "goal {goal:?} was never reached after t = {t}"
        );
        for agent in 0..n {
            for k in 0..h {
                let tick = (t + k + 1).saturating_sub(h);
                let offset = ((b * n + agent) * h + k) * OBS_DIM;
                let expected = observation(agent, &episode.ticks[tick].poses, &episode.desired, goal);
                let got = &batch.observations[offset..offset + OBS_DIM];
                assert_eq!(got, &expected);
                // Only the goal part changed; the neighbour part is what the robot saw (up to the
                // f32 rounding of the poses on the wire).
                for (a, b) in got[..OBS_DIM - 2]
                    .iter()
                    .zip(&episode.ticks[tick].observations[agent][..OBS_DIM - 2])
                {
                    assert!((a - b).abs() < 1e-5, "{a} vs {b}");
                }
                // The goal in the robot's frame, checked by hand: rotate (g - p) by -theta.
                let p = episode.ticks[tick].poses[agent];
                let (s, c) = p[2].sin_cos();
                let (dx, dy) = (goal[0] - p[0], goal[1] - p[1]);
                assert!((got[OBS_DIM - 2] - (c * dx + s * dy)).abs() < 1e-4);
                assert!((got[OBS_DIM - 1] - (-s * dx + c * dy)).abs() < 1e-4);
            }
        }
        let (reward, terminal) = transition_reward(
            &episode.ticks[t + 1].poses,
            &episode.desired,
            goal,
            (t + 1) as u32,
            &env,
        );
        assert_eq!(batch.rewards[b], reward);
        assert_eq!(batch.terminals[b] == 1.0, terminal);
        saw_success |= reward == env.r_goal as f32;
    }
    assert!(
        saw_success,
        "relabelling to a reached centroid should produce some successes"
    );
}

#[test]
fn recomputed_reward_matches_the_sim() {
    // Without relabelling, transition_reward on the recorded next state gives the sim's reward.
    let env = EnvConfig::default();
    for episode in recorded_episodes(10, 4, 9) {
        for t in 0..episode.ticks.len() - 1 {
            let (reward, _) = transition_reward(
                &episode.ticks[t + 1].poses,
                &episode.desired,
                episode.goal,
                (t + 1) as u32,
                &env,
            );
            // Poses went through f32 on the wire; allow the rare tie at a tolerance boundary.
            assert_eq!(reward, episode.ticks[t].reward, "episode {} t {t}", episode.number);
        }
    }
}

#[test]
fn eviction_keeps_capacity() {
    let episodes = recorded_episodes(20, 3, 4);
    let mut buffer = ReplayBuffer::new(100);
    for e in &episodes {
        buffer.push(e.clone());
        assert!(buffer.transitions() <= 100 || buffer.episodes().len() == 1);
    }
    assert_eq!(buffer.episodes().back().map(|e| e.number), Some(19));
}
