//! HER under shape changes: a relabelled reward is judged as the sim judged the step, under
//! the formation in force when it was scored and with no success before the episode's last
//! change.

use formation_core::config::{CriticArchitecture, EnvConfig};
use formation_core::formation::{FormationSpec, ShapeChange, random_episode};
use formation_core::mission::Mission;
use formation_core::task::centroid;
use formation_core::world::World;
use formation_replay::buffer::{Episode, ReplayBuffer};
use formation_replay::record::record_mission_episode;
use formation_replay::sample::Sampler;
use rand::SeedableRng;
use rand::rngs::StdRng;

/// The tick of the episode's one shape change.
const CHANGE_TICK: u32 = 10;

/// Ticks recorded: the change's morph into the new formation ends well within them.
const TICKS: u32 = 200;

/// A swarm that starts in formation at its goal and never moves, its formation changed at
/// [`CHANGE_TICK`] to the same shape turned and half as large again: in formation at the goal
/// (C3) until the change, out of formation once the formation has morphed into the new one.
/// Played and recorded as the sim plays it.
fn standing_swarm(env: &EnvConfig, seed: u64) -> Episode {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut init = random_episode(4, env, &mut rng);
    init.goal = centroid(&init.poses);
    let offsets = init.slots.iter().map(|s| [-1.5 * s[1], 1.5 * s[0]]).collect();
    let turned = FormationSpec {
        orientation: init.spec.orientation + std::f64::consts::FRAC_PI_2,
        scale: 1.5,
        ..init.spec
    };
    let change = ShapeChange {
        tick: CHANGE_TICK,
        offsets,
        spec: turned,
    };
    let mission = Mission::new(vec![change], &init.slots, init.spec, seed);
    record_mission_episode(seed as u32, World::new(env, init), mission, TICKS, |w| {
        vec![env.action_from_command(0.0, 0.0); w.n_agents()]
    })
}

#[test]
fn relabelled_rewards_hold_success_until_the_last_change_as_the_sim_did() {
    let env = EnvConfig {
        shape_changes: 1,
        ..EnvConfig::default()
    };
    let episodes: Vec<Episode> = (0..4).map(|seed| standing_swarm(&env, seed)).collect();
    let mut buffer = ReplayBuffer::new(1_000_000);
    for episode in &episodes {
        // The sim's rewards: C3 held before the change scores r_edge and goes on (the change's
        // own tick was scored under the old formation); while the formation morphs (a new one
        // every tick from the change's) C3 of a morphing formation is no success either, and
        // the new formation is not held after.
        assert_eq!(episode.formations[1].from_tick, CHANGE_TICK as usize);
        let last = episode.formations.last().map_or(0, |f| f.from_tick);
        assert!(
            last > CHANGE_TICK as usize + 1 && last + 1 < episode.ticks.len(),
            "{last}"
        );
        assert!(!episode.terminal);
        assert_eq!(episode.ticks.len(), TICKS as usize + 1);
        for (t, tick) in episode.ticks.iter().enumerate().skip(1) {
            let expected: &[f64] = if t <= CHANGE_TICK as usize {
                &[env.r_edge]
            } else if t > last {
                &[env.r_penalty]
            } else {
                &[env.r_edge, env.r_penalty]
            };
            assert!(
                expected.iter().any(|&r| tick.reward == r as f32),
                "episode {} tick {t}: {}",
                episode.number,
                tick.reward
            );
        }
        // The morph starts from where the robots stand: its first formations are held.
        assert_eq!(episode.ticks[CHANGE_TICK as usize + 1].reward, env.r_edge as f32);
        buffer.push(episode.clone());
    }
    // Every sample relabelled: the goal is a later centroid, the same point for a swarm that
    // stands still, so the relabelled rewards must be the sim's.
    let sampler = Sampler {
        history: 2,
        her_probability: 1.0,
        n_step: 1,
        gamma: 0.98,
        env: env.clone(),
        critic: CriticArchitecture::Pooled,
        critic_map_points: 0,
    };
    let mut rng = StdRng::seed_from_u64(7);
    let batch = sampler.sample(&buffer, 512, &mut rng).expect("batch");
    let mut before_the_change = 0;
    for b in 0..batch.batch_size {
        let (number, t) = batch.origins[b];
        let episode = &episodes[number as usize];
        assert!(batch.relabelled[b]);
        assert_eq!(
            batch.rewards[b],
            episode.ticks[t + 1].reward,
            "episode {number} t {t}: relabelled against the sim"
        );
        assert_eq!(
            batch.terminals[b], 0.0,
            "episode {number} t {t}: no success before the change"
        );
        before_the_change += usize::from(t < CHANGE_TICK as usize);
    }
    assert!(before_the_change > 0);
}
