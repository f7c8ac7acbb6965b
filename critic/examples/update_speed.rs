//! Times the critic's two costs per gradient update, sampling a batch and the update itself,
//! on a replay filled with random-action episodes (no IPC):
//! `cargo run --release -p formation-critic --example update_speed -- [BATCH] [UPDATES] [HISTORY]`.

use std::time::Instant;

use formation_critic::learner::Learner;
use formation_protocol::config::{EnvConfig, LearnConfig};
use formation_replay::buffer::{Episode, ReplayBuffer, Tick};
use formation_replay::sample::Sampler;
use formation_sim::formation::random_episode;
use formation_sim::world::World;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn main() -> anyhow::Result<()> {
    formation_critic::tune_allocator();
    let mut args = std::env::args().skip(1);
    let batch_size: usize = args.next().map_or(Ok(128), |a| a.parse())?;
    let updates: usize = args.next().map_or(Ok(200), |a| a.parse())?;
    let history: usize = args.next().map_or(Ok(15), |a| a.parse())?;
    let env = EnvConfig {
        history,
        ..EnvConfig::default()
    };
    let learn = LearnConfig {
        batch_size,
        ..LearnConfig::default()
    };
    let n = 3;
    let mut rng = StdRng::seed_from_u64(1);
    let mut replay = ReplayBuffer::new(learn.replay_capacity);
    for number in 0..200 {
        let mut world = World::new(&env, random_episode(n, &env, &mut rng));
        let snapshot = |w: &World| Tick {
            poses: w
                .poses
                .iter()
                .map(|p| [p.x as f32, p.y as f32, p.theta as f32])
                .collect(),
            observations: (0..n).map(|a| w.observation(a)).collect(),
            actions: vec![[0.0; 2]; n],
            reward: 0.0,
        };
        let mut ticks = vec![snapshot(&world)];
        for _ in 0..env.max_steps {
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
                break;
            }
        }
        let desired = world.desired.iter().map(|d| [d[0] as f32, d[1] as f32]).collect();
        replay.push(Episode {
            number,
            desired,
            goal: [world.goal[0] as f32, world.goal[1] as f32],
            ticks,
            terminal: false,
        });
    }
    let sampler = Sampler {
        history: env.history,
        her_probability: learn.her_probability,
        env: env.clone(),
    };
    let mut learner = Learner::new(n, &env, &learn, 1)?;
    let (mut sampling, mut updating) = (0.0, 0.0);
    for _ in 0..updates {
        let t0 = Instant::now();
        let batch = sampler.sample(&replay, batch_size, &mut rng).expect("batch");
        let t1 = Instant::now();
        learner.update(&batch)?;
        sampling += (t1 - t0).as_secs_f64();
        updating += t1.elapsed().as_secs_f64();
    }
    println!(
        "H = {history}, B = {batch_size}: sample {:.2} ms, update {:.2} ms, {:.0} updates/s",
        1e3 * sampling / updates as f64,
        1e3 * updating / updates as f64,
        updates as f64 / (sampling + updating)
    );
    Ok(())
}
