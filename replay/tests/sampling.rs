//! The replay's public contract: sequences stay inside one episode, every robot's window covers
//! the same ticks, the replay's ticks are the sim's scenes (with the commands applied), HER
//! relabelling equals recomputing everything from them with the sim's own code, and under
//! sensor noise it keeps the noise the robots were told.

use formation_core::config::{CriticArchitecture, EnvConfig, ObservationModel};
use formation_core::features::CriticFeatures;
use formation_core::formation::random_episode;
use formation_core::observation::Observer;
use formation_core::obstacles::{Obstacle, Obstacles};
use formation_core::reality::{Reality, RealityConfig, Spread};
use formation_core::task::{Outcome, score};
use formation_core::world::World;
use formation_protocol::ACTION_DIM;
use formation_replay::buffer::{Episode, ReplayBuffer};
use formation_replay::record::record_episode;
use formation_replay::sample::Sampler;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Plays random episodes in-process, recording what the critic would assemble.
fn recorded_episodes(env: &EnvConfig, count: usize, n: usize, seed: u64) -> Vec<Episode> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..count)
        .map(|number| {
            let world = World::new(env, random_episode(n, env, &mut rng));
            // Short episodes keep the test quick.
            record_episode(number as u32, world, 30, |w| {
                (0..w.n_agents())
                    .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
                    .collect()
            })
        })
        .collect()
}

/// Reward and terminal flag of reaching tick `s + 1` of `episode` with `goal`: the sim's code.
fn recomputed(episode: &Episode, s: usize, goal: [f64; 2], env: &EnvConfig) -> (f32, bool) {
    let scored = score(&episode.scene(s + 1, goal), (s + 1) as u32, env);
    (scored.reward as f32, scored.outcome.is_terminal())
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
    let env = EnvConfig::default();
    let episodes = recorded_episodes(&env, 20, n, 1);
    let buffer = buffer_of(&episodes);
    let sampler = Sampler {
        history: h,
        her_probability: 0.0,
        n_step: 1,
        gamma: 0.98,
        env: env.clone(),
        critic: CriticArchitecture::Mlp,
        critic_map_points: 0,
    };
    let od = batch_obs_dim(&env);
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
                let offset = ((b * n + agent) * h + k) * od;
                assert_eq!(
                    &batch.observations[offset..offset + od],
                    &episode.ticks[tick].observations[agent][..od]
                );
                let next_tick = (t + k + 2).saturating_sub(h);
                assert_eq!(
                    &batch.next_observations[offset..offset + od],
                    &episode.ticks[next_tick].observations[agent][..od]
                );
                let a = ((b * h + k) * n + agent) * ACTION_DIM;
                assert_eq!(&batch.actions[a..a + ACTION_DIM], &episode.action(tick, agent, &env));
            }
        }
        assert_eq!(batch.rewards[b], episode.ticks[t + 1].reward);
        assert_eq!(batch.discounts[b], 0.98);
        assert_eq!(
            batch.terminals[b] == 1.0,
            episode.terminal && t + 2 == episode.ticks.len()
        );
    }
    assert_eq!(
        batch.bootstrap_actions, batch.actions,
        "one step: the target's history is t's"
    );
    assert_eq!(batch.states.len(), batch.batch_size * h * sampler.features(n).dim());
}

fn batch_obs_dim(env: &EnvConfig) -> usize {
    Observer::new(env).dim()
}

/// A sampler that relabels every sample, one-step, with windows of `history` ticks.
fn relabelling_sampler(env: &EnvConfig, history: usize) -> Sampler {
    Sampler {
        history,
        her_probability: 1.0,
        n_step: 1,
        gamma: 0.98,
        env: env.clone(),
        critic: CriticArchitecture::Mlp,
        critic_map_points: 0,
    }
}

#[test]
fn her_relabelling_equals_recomputation_from_true_states() {
    for observation in [ObservationModel::Paper, ObservationModel::SlotProximity] {
        her_relabelling_matches(&EnvConfig {
            observation,
            ..EnvConfig::default()
        });
    }
}

fn her_relabelling_matches(env: &EnvConfig) {
    let n = 5;
    let h = 4;
    let env = env.clone();
    let observer = Observer::new(&env);
    let layout = observer.layout;
    let od = observer.dim();
    let episodes = recorded_episodes(&env, 10, n, 5);
    let buffer = buffer_of(&episodes);
    let sampler = relabelling_sampler(&env, h);
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
            (t + 1..episode.ticks.len()).any(|r| episode.scene(r, episode.goal).centroid() == goal),
            "goal {goal:?} was never reached after t = {t}"
        );
        for agent in 0..n {
            for k in 0..h {
                let tick = (t + k + 1).saturating_sub(h);
                let offset = ((b * n + agent) * h + k) * od;
                // Up to f32 rounding, what the sim would have told the robot with that goal.
                let expected = observer.observation(agent, &episode.scene(tick, goal));
                let got = &batch.observations[offset..offset + od];
                for i in 0..od {
                    assert!(
                        (got[i] - expected[i]).abs() < 1e-5,
                        "float {i}: {} vs {}",
                        got[i],
                        expected[i]
                    );
                }
                // The neighbours (and the proximity term) are exactly what the robot was told;
                // the goal and the slot moved.
                let seen = &episode.ticks[tick].observations[agent];
                let unchanged = (0..layout.goal()).chain(layout.proximity().map_or(0..0, |at| at..at + 2));
                for i in unchanged {
                    assert_eq!(got[i], seen[i], "float {i}");
                }
                // The goal and the slot in the robot's frame, checked by hand: rotate (g - p)
                // by -theta.
                let p = episode.ticks[tick].poses[agent];
                let (s, c) = p.theta.sin_cos();
                let in_frame = |point: [f64; 2]| {
                    let (dx, dy) = (point[0] - p.x, point[1] - p.y);
                    [(c * dx + s * dy) as f32, (-s * dx + c * dy) as f32]
                };
                let g = in_frame(goal);
                let at = layout.goal();
                assert!((got[at] - g[0]).abs() < 1e-4 && (got[at + 1] - g[1]).abs() < 1e-4);
                if let Some(at) = layout.slot() {
                    let slot = episode.formation(tick).slots[agent];
                    let expected = in_frame([goal[0] + slot[0], goal[1] + slot[1]]);
                    assert!((got[at] - expected[0]).abs() < 1e-4 && (got[at + 1] - expected[1]).abs() < 1e-4);
                }
            }
        }
        let (reward, terminal) = recomputed(episode, t, goal, &env);
        assert_eq!(batch.rewards[b], reward);
        assert_eq!(batch.terminals[b] == 1.0, terminal);
        saw_success |= reward == env.r_goal as f32;
    }
    assert!(
        saw_success,
        "relabelling to a reached centroid should produce some successes"
    );
}

/// Under sensor noise a relabelled observation is the one the robot was told with its goal and
/// slot moved: the noise on every block stays (recomputing from the true state would drop it).
#[test]
fn her_relabelling_keeps_the_noise_the_robots_were_told() {
    let n = 4;
    let h = 3;
    let env = EnvConfig {
        observation: ObservationModel::SlotProximity,
        ..EnvConfig::default()
    };
    let observer = Observer::new(&env);
    let layout = observer.layout;
    let od = observer.dim();
    let noise = RealityConfig {
        position_noise_m: Spread::range(0.05, 0.1),
        heading_noise_rad: Spread::fixed(0.05),
        ..RealityConfig::default()
    };
    // What the collector stores under noise: each tick's observation as the robot was told it.
    let mut episodes = recorded_episodes(&env, 6, n, 11);
    for episode in &mut episodes {
        let mut reality = Reality::new(&noise, &env, 11, u64::from(episode.number), n);
        for tick in &mut episode.ticks {
            for (agent, obs) in tick.observations.iter_mut().enumerate() {
                reality.tell(agent, layout, obs);
            }
        }
    }
    let buffer = buffer_of(&episodes);
    let sampler = relabelling_sampler(&env, h);
    let mut rng = StdRng::seed_from_u64(12);
    let batch = sampler.sample(&buffer, 64, &mut rng).expect("batch");
    let mut goal_noise = 0.0f64;
    for b in 0..batch.batch_size {
        let (number, t) = batch.origins[b];
        let episode = &episodes[number as usize];
        let goal = batch.goals[b];
        for agent in 0..n {
            for k in 0..h {
                let tick = (t + k + 1).saturating_sub(h);
                let offset = ((b * n + agent) * h + k) * od;
                let got = &batch.observations[offset..offset + od];
                let told = &episode.ticks[tick].observations[agent];
                let truth = observer.observation(agent, &episode.scene(tick, goal));
                for at in std::iter::once(layout.goal()).chain(layout.slot()) {
                    // Told with the old goal, moved to the new one: the told noise stays.
                    let was_told_noise = f64::from(told[at])
                        - f64::from(observer.observation(agent, &episode.scene(tick, episode.goal))[at]);
                    let noise_now = f64::from(got[at]) - f64::from(truth[at]);
                    assert!(
                        (was_told_noise - noise_now).abs() < 1e-4,
                        "block at {at}: {was_told_noise} vs {noise_now}"
                    );
                    goal_noise = goal_noise.max(noise_now.abs());
                }
                for i in (0..layout.goal()).chain(layout.proximity().map_or(0..0, |at| at..at + 2)) {
                    assert_eq!(got[i], told[i], "float {i} is what the robot was told");
                }
            }
        }
    }
    assert!(
        goal_noise > 0.03,
        "the relabelled goals carry the told noise (largest {goal_noise})"
    );
}

#[test]
fn recomputed_reward_matches_the_sim() {
    // Without relabelling, the sim's reward code on the recorded next scene gives the sim's
    // reward (the poses went through f32 on the wire, which moves no tolerance boundary here).
    let env = EnvConfig::default();
    for episode in recorded_episodes(&env, 10, 4, 9) {
        for t in 0..episode.ticks.len() - 1 {
            let (reward, _) = recomputed(&episode, t, episode.goal, &env);
            assert_eq!(reward, episode.ticks[t + 1].reward, "episode {} t {t}", episode.number);
        }
    }
}

#[test]
fn eviction_keeps_capacity() {
    let episodes = recorded_episodes(&EnvConfig::default(), 20, 3, 4);
    let mut buffer = ReplayBuffer::new(100);
    for e in &episodes {
        buffer.push(e.clone());
        assert!(buffer.transitions() <= 100 || buffer.episodes().len() == 1);
    }
    assert_eq!(buffer.episodes().back().map(|e| e.number), Some(19));
}

#[test]
fn n_step_samples_sum_discounted_rewards_up_to_a_terminal_or_the_end() {
    let (n, h, steps, gamma) = (3, 4, 5, 0.9);
    let env = EnvConfig::default();
    let od = batch_obs_dim(&env);
    let episodes = recorded_episodes(&env, 12, n, 7);
    let buffer = buffer_of(&episodes);
    for her_probability in [0.0, 1.0] {
        let sampler = Sampler {
            history: h,
            her_probability,
            n_step: steps,
            gamma,
            env: env.clone(),
            critic: CriticArchitecture::Mlp,
            critic_map_points: 0,
        };
        let mut rng = StdRng::seed_from_u64(8);
        let batch = sampler.sample(&buffer, 512, &mut rng).expect("batch");
        let (mut full, mut cut) = (0, 0);
        for b in 0..batch.batch_size {
            let (number, t) = batch.origins[b];
            let episode = &episodes[number as usize];
            let goal = batch.goals[b];
            // The reference: one reward per tick, from the sim or recomputed for the goal.
            let step = |s: usize| {
                if batch.relabelled[b] {
                    recomputed(episode, s, goal, &env)
                } else {
                    (episode.ticks[s + 1].reward, episode.is_terminal_transition(s))
                }
            };
            let (mut reward, mut k, mut terminal) = (0.0f64, 0, false);
            while k < steps && t + k + 1 < episode.ticks.len() && !terminal {
                let (r, done) = step(t + k);
                reward += gamma.powi(k as i32) * f64::from(r);
                terminal = done;
                k += 1;
            }
            if k == steps {
                full += 1
            } else {
                cut += 1
            }
            assert!(
                (f64::from(batch.rewards[b]) - reward).abs() < 1e-4,
                "sample {b}: {} vs {reward}",
                batch.rewards[b]
            );
            assert!((f64::from(batch.discounts[b]) - gamma.powi(k as i32)).abs() < 1e-6);
            assert_eq!(batch.terminals[b] == 1.0, terminal);
            for agent in 0..n {
                for w in 0..h {
                    // The next window ends k ticks on; the target's action history one before.
                    let next_tick = (t + k + w + 1).saturating_sub(h);
                    let offset = ((b * n + agent) * h + w) * od;
                    let expected = sampler.observer().observation(agent, &episode.scene(next_tick, goal));
                    let got = &batch.next_observations[offset..offset + od];
                    assert!(got.iter().zip(&expected[..od]).all(|(g, e)| (g - e).abs() < 1e-4));
                    let acted = (t + k + w).saturating_sub(h);
                    let a = ((b * h + w) * n + agent) * ACTION_DIM;
                    assert_eq!(
                        &batch.bootstrap_actions[a..a + ACTION_DIM],
                        &episode.action(acted, agent, &env)
                    );
                }
            }
        }
        assert!(
            full > 0 && cut > 0,
            "both whole and shortened sums were drawn ({full}, {cut})"
        );
    }
}

#[test]
fn replayed_scenes_carry_the_commands_the_world_applied() {
    // What the policy asked and the world applied, tick by tick, next to what the replay holds.
    let env = EnvConfig::default();
    let mut rng = StdRng::seed_from_u64(11);
    let world = World::new(&env, random_episode(4, &env, &mut rng));
    let mut asked = Vec::new();
    let episode = record_episode(0, world, 30, |w| {
        let actions: Vec<[f32; ACTION_DIM]> = (0..w.n_agents())
            .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
            .collect();
        asked.push(actions.clone());
        actions
    });
    assert_eq!(
        episode.scene(0, episode.goal).commands,
        &[(0.0, 0.0); 4],
        "nothing led to tick 0"
    );
    for (t, actions) in asked.iter().enumerate() {
        let scene = episode.scene(t + 1, episode.goal);
        for (agent, &action) in actions.iter().enumerate() {
            let (v, w) = env.command_from_action(action);
            // The command the world applied into t + 1, through the wire's f32.
            assert_eq!(scene.commands[agent], (f64::from(v as f32), f64::from(w as f32)));
            // The learner's action from t is the robot's own, up to that rounding.
            let replayed = episode.action(t, agent, &env);
            assert!((replayed[0] - action[0]).abs() < 1e-5 && (replayed[1] - action[1]).abs() < 1e-5);
        }
    }
}

#[test]
fn critic_features_are_the_same_floats_from_the_world_and_from_the_replay() {
    let env = EnvConfig::default();
    for critic in [CriticArchitecture::Mlp, CriticArchitecture::Pooled] {
        let features = CriticFeatures::new(5, env.observation, critic);
        let mut rng = StdRng::seed_from_u64(12);
        let world = World::new(&env, random_episode(5, &env, &mut rng));
        let mut live = Vec::new();
        let episode = record_episode(0, world, 20, |w| {
            let mut out = vec![0.0; features.dim()];
            features.write(&mut out, &w.scene(), w.poses[0].theta as f32);
            live.push(out);
            (0..w.n_agents())
                .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
                .collect()
        });
        for (t, expected) in live.iter().enumerate() {
            let mut out = vec![0.0; features.dim()];
            let frame = episode.ticks[t].poses[0].theta as f32;
            features.write(&mut out, &episode.scene(t, episode.goal), frame);
            assert_eq!(&out, expected, "{critic:?} tick {t}");
        }
    }
}

#[test]
fn batches_carry_the_recorded_presence_at_t_and_t_plus_1_relabelled_or_not() {
    let n = 4;
    let env = EnvConfig::default();
    let mut episodes = recorded_episodes(&env, 6, n, 9);
    // Robot 2 leaves the formation at tick 10 of the even episodes (it then observes itself,
    // as the collector records a robot out).
    for episode in episodes.iter_mut().step_by(2) {
        let mut out = episode.formations[0].clone();
        out.from_tick = 10;
        out.present[2] = false;
        out.observed[2] = [2, 2];
        episode.formations.push(out);
    }
    let buffer = buffer_of(&episodes);
    let sampler = Sampler {
        her_probability: 0.5,
        ..relabelling_sampler(&env, 3)
    };
    let mut rng = StdRng::seed_from_u64(4);
    let batch = sampler.sample(&buffer, 512, &mut rng).expect("batch");
    let mask = |episode: &Episode, t: usize| -> Vec<f32> {
        episode.present(t).iter().map(|&p| if p { 1.0 } else { 0.0 }).collect()
    };
    let (mut out_at_t, mut relabelled_out) = (0, 0);
    for b in 0..batch.batch_size {
        let (number, t) = batch.origins[b];
        let episode = &episodes[number as usize];
        assert_eq!(
            &batch.present[b * n..(b + 1) * n],
            mask(episode, t).as_slice(),
            "sample {b}"
        );
        assert_eq!(
            &batch.next_present[b * n..(b + 1) * n],
            mask(episode, t + 1).as_slice(),
            "sample {b}"
        );
        if batch.present[b * n + 2] == 0.0 {
            out_at_t += 1;
            relabelled_out += usize::from(batch.relabelled[b]);
        }
    }
    assert!(
        out_at_t > 0 && relabelled_out > 0,
        "{out_at_t} samples with robot 2 out, {relabelled_out} relabelled"
    );
    assert!(batch.present.contains(&1.0));
}

#[test]
fn a_relabelled_transition_into_an_obstacle_stays_terminal_with_r_collision() {
    let env = EnvConfig::default();
    let mut rng = StdRng::seed_from_u64(11);
    let mut init = random_episode(3, &env, &mut rng);
    // A long wall across the robots' common heading, just beyond the formation's reach.
    let centre = formation_core::task::centroid(&init.poses);
    let reach = init
        .poses
        .iter()
        .map(|p| (p.x - centre[0]).hypot(p.y - centre[1]))
        .fold(0.0, f64::max);
    let heading = init.poses[0].theta;
    let (u, v) = ([heading.cos(), heading.sin()], [-heading.sin(), heading.cos()]);
    let at = |along: f64, across: f64| {
        [
            centre[0] + along * u[0] + across * v[0],
            centre[1] + along * u[1] + across * v[1],
        ]
    };
    init.obstacles = Obstacles::new(vec![Obstacle::Wall {
        a: at(reach + 0.4, -4.0),
        b: at(reach + 0.4, 4.0),
        thickness: 0.1,
    }]);
    let straight = env.action_from_command(env.v_max, 0.0);
    let episode = record_episode(0, World::new(&env, init), 100, |w| vec![straight; w.n_agents()]);
    assert!(episode.terminal, "the robots drove into the wall");
    let last = episode.transitions() - 1;
    let hit = score(&episode.scene(last + 1, episode.goal), (last + 1) as u32, &env);
    assert!(hit.conditions.obstacle_collision && hit.outcome == Outcome::Collision);
    let buffer = buffer_of(std::slice::from_ref(&episode));
    let sampler = relabelling_sampler(&env, 1);
    let batch = sampler
        .sample(&buffer, 512, &mut StdRng::seed_from_u64(3))
        .expect("batch");
    let mut into_the_wall = 0;
    for b in 0..batch.batch_size {
        assert!(batch.relabelled[b]);
        let (_, t) = batch.origins[b];
        if t == last {
            // Whatever goal HER gives it, the transition into the wall ends the episode.
            assert_eq!(batch.terminals[b], 1.0);
            assert_eq!(batch.rewards[b], env.r_collision as f32);
            into_the_wall += 1;
        }
    }
    assert!(into_the_wall > 0, "the last transition was sampled");
}

#[test]
fn each_robot_s_own_reward_is_the_shared_one_with_its_own_approach_in_place_of_the_mean() {
    let n = 4;
    let env = EnvConfig {
        r_progress: 10.0,
        ..EnvConfig::default()
    };
    let episodes = recorded_episodes(&env, 10, n, 91);
    let buffer = buffer_of(&episodes);
    let sampler = |her_probability, n_step| Sampler {
        history: 2,
        her_probability,
        n_step,
        gamma: 0.98,
        env: env.clone(),
        critic: CriticArchitecture::Pooled,
        critic_map_points: 0,
    };
    let mut rng = StdRng::seed_from_u64(92);
    // One step: r_i = r + r_progress (a_i - mean a), a_i from the scene's poses and commands.
    let batch = sampler(0.5, 1).sample(&buffer, 128, &mut rng).expect("batch");
    let mut spread = 0.0f32;
    for b in 0..batch.batch_size {
        let (number, t) = batch.origins[b];
        let scene = episodes[number as usize].scored_scene(t + 1, batch.goals[b]);
        let approach: Vec<f64> = (0..n)
            .map(|i| {
                let (pose, (v, _)) = (scene.poses[i], scene.commands[i]);
                let (dx, dy) = (
                    scene.goal[0] + scene.slots[i][0] - pose.x,
                    scene.goal[1] + scene.slots[i][1] - pose.y,
                );
                v * env.dt_s * (pose.theta.cos() * dx + pose.theta.sin() * dy) / dx.hypot(dy)
            })
            .collect();
        let mean = approach.iter().sum::<f64>() / n as f64;
        for (i, a) in approach.iter().enumerate() {
            let expected = batch.rewards[b] as f64 + env.r_progress * (a - mean);
            let own = batch.robot_rewards[b * n + i];
            assert!(
                (f64::from(own) - expected).abs() < 1e-4,
                "sample {b} robot {i}: {own} vs {expected}"
            );
            spread = spread.max((own - batch.rewards[b]).abs());
        }
    }
    assert!(
        spread > 0.01,
        "robots that move differently earn differently ({spread})"
    );
    // n-step and relabelled: the robots' mean is still the shared reward.
    let batch = sampler(1.0, 3).sample(&buffer, 128, &mut rng).expect("batch");
    for (b, own) in batch.robot_rewards.chunks_exact(n).enumerate() {
        let mean = own.iter().sum::<f32>() / n as f32;
        assert!(
            (mean - batch.rewards[b]).abs() < 1e-4,
            "sample {b}: {mean} vs {}",
            batch.rewards[b]
        );
    }
    // Without a progress term every robot's reward is the shared one.
    let plain = Sampler {
        env: EnvConfig::default(),
        ..sampler(0.5, 3)
    };
    let batch = plain.sample(&buffer, 64, &mut rng).expect("batch");
    for (b, own) in batch.robot_rewards.chunks_exact(n).enumerate() {
        assert!(own.iter().all(|&r| r == batch.rewards[b]), "sample {b}");
    }
}
