//! The tick path allocates nothing: the sim's observations, step and score, and an agent's
//! window update and action (scripted baseline, learned actor with and without exploration
//! noise), counted by a global allocator per thread, so that the test harness's own threads
//! (which allocate now and then on a busy machine) are not counted.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

use formation_agent::policy::{Exploration, LearnedPolicy, Policy};
use formation_core::baseline::{BaselineGains, ScriptedBaseline};
use formation_core::config::{EnvConfig, ObservationModel, RunConfig};
use formation_core::formation::random_episode;
use formation_core::world::World;
use formation_model::actor::{ActorHead, ActorShape};
use formation_model::history::ObservationHistory;
use formation_protocol::MAX_OBS_DIM;
use rand::SeedableRng;
use rand::rngs::StdRng;

struct Counting;

thread_local! {
    /// Allocations made by this thread (a const-initialised thread local never allocates).
    static ALLOCATIONS: Cell<usize> = const { Cell::new(0) };
}

fn count_one() {
    ALLOCATIONS.with(|count| count.set(count.get() + 1));
}

/// Allocations made so far by the calling thread.
fn allocations() -> usize {
    ALLOCATIONS.with(Cell::get)
}

// SAFETY: forwards to the system allocator, only counting.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count_one();
        // SAFETY: same contract as ours.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as ours.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count_one();
        // SAFETY: same contract as ours.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Allocations made by 500 ticks of `policy` (after one warm-up tick) on observations of
/// `dim` floats.
fn allocations_per_500_ticks(policy: &mut dyn Policy, history_length: usize, dim: usize) -> usize {
    let mut history = ObservationHistory::new(history_length, dim);
    let obs = |t: usize| -> [f32; MAX_OBS_DIM] { std::array::from_fn(|i| ((t * MAX_OBS_DIM + i) as f32 * 0.1).sin()) };
    history.reset(&obs(0));
    policy.begin_episode(1, true);
    policy.command(&history).expect("warm-up");
    let before = allocations();
    for t in 1..=500 {
        history.push(&obs(t));
        std::hint::black_box(policy.command(&history).expect("command"));
    }
    allocations() - before
}

#[test]
fn ticks_allocate_nothing() {
    sim_observing_and_stepping_allocate_nothing();
    agent_ticks_allocate_nothing();
}

/// The environment of every observation model.
fn environments() -> impl Iterator<Item = EnvConfig> {
    [
        ObservationModel::Paper,
        ObservationModel::Slot,
        ObservationModel::SlotProximity,
    ]
    .into_iter()
    .map(|observation| EnvConfig {
        observation,
        ..EnvConfig::default()
    })
}

fn agent_ticks_allocate_nothing() {
    let config = RunConfig::default();
    for env in environments() {
        let mut scripted = ScriptedBaseline::new(&env, BaselineGains::default());
        let dim = formation_core::observation::Layout::of(env.observation).dim();
        assert_eq!(
            allocations_per_500_ticks(&mut scripted, env.history, dim),
            0,
            "scripted, {:?}",
            env.observation
        );
    }

    for history in [1, 15] {
        let shape = ActorShape {
            obs_dim: 16,
            history,
            hidden: config.learn.actor_hidden.clone(),
            head: ActorHead::Command,
        };
        let weights: Vec<f32> = (0..shape.parameter_count())
            .map(|i| (i as f32 * 0.013).sin() * 0.1)
            .collect();
        for exploration in [
            None,
            Some(Exploration {
                std_start: 0.3,
                std_end: 0.1,
                decay_episodes: 10,
                correlation_ticks: 0.0,
                stall_std: 0.0,
                stall_ticks: 30,
            }),
            Some(Exploration {
                std_start: 0.3,
                std_end: 0.1,
                decay_episodes: 10,
                correlation_ticks: 10.0,
                stall_std: 0.0,
                stall_ticks: 30,
            }),
        ] {
            let mut learned = LearnedPolicy::new(&config.env, shape.clone(), exploration, StdRng::seed_from_u64(3));
            learned.load(&weights, 1).expect("weights");
            assert_eq!(
                allocations_per_500_ticks(&mut learned, history, shape.obs_dim),
                0,
                "learned, H = {history}, exploration {exploration:?}"
            );
            // The counter does count: installing new weights for the first time allocates.
            let before = allocations();
            let mut fresh = LearnedPolicy::new(&config.env, shape.clone(), None, StdRng::seed_from_u64(4));
            fresh.load(&weights, 1).expect("weights");
            assert!(allocations() > before);
        }
        // A gain schedule runs the baseline's law on its outputs, in eval mode.
        let gains = ActorShape {
            head: ActorHead::Gains,
            ..shape.clone()
        };
        let weights: Vec<f32> = (0..gains.parameter_count())
            .map(|i| (i as f32 * 0.013).sin() * 0.1)
            .collect();
        let mut learned = LearnedPolicy::new(&config.env, gains.clone(), None, StdRng::seed_from_u64(3));
        learned.load(&weights, 1).expect("weights");
        assert_eq!(
            allocations_per_500_ticks(&mut learned, history, gains.obs_dim),
            0,
            "gain schedule, H = {history}"
        );
    }
}

fn sim_observing_and_stepping_allocate_nothing() {
    let mut rng = StdRng::seed_from_u64(11);
    for (env, n) in environments().flat_map(|env| [3, 12, 48].map(|n| (env.clone(), n))) {
        let mut world = World::new(&env, random_episode(n, &env, &mut rng));
        let commands: Vec<(f64, f64)> = (0..n).map(|i| (0.3, 0.2 * (i as f64).sin())).collect();
        let before = allocations();
        let mut checksum = 0.0f32;
        for _ in 0..200 {
            for agent in 0..n {
                checksum += world.observation(agent)[0];
            }
            std::hint::black_box(world.step(&commands));
        }
        assert_eq!(allocations() - before, 0, "N = {n}, {:?}", env.observation);
        assert!(checksum.is_finite() && world.steps == 200);
    }
    // The counter does count: a new episode allocates its poses.
    let before = allocations();
    std::hint::black_box(random_episode(3, &EnvConfig::default(), &mut rng));
    assert!(allocations() > before);
}
