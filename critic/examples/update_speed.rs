//! Times the critic's two costs per gradient update, sampling a batch and the update itself,
//! on a replay filled with random-action episodes (no IPC):
//! `cargo run --release -p formation-critic --example update_speed -- [BATCH] [UPDATES] [HISTORY] [ROBOTS] [mlp|pooled]`.

use std::time::Instant;

use formation_core::formation::random_episode;
use formation_core::world::World;
use formation_critic::learner::Learner;
use formation_protocol::config::{CriticArchitecture, EnvConfig, LearnConfig};
use formation_replay::buffer::ReplayBuffer;
use formation_replay::record::record_episode;
use formation_replay::sample::Sampler;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

fn main() -> anyhow::Result<()> {
    formation_critic::tune_allocator();
    let mut args = std::env::args().skip(1);
    let batch_size: usize = args.next().map_or(Ok(128), |a| a.parse())?;
    let updates: usize = args.next().map_or(Ok(200), |a| a.parse())?;
    let history: usize = args.next().map_or(Ok(15), |a| a.parse())?;
    let n: usize = args.next().map_or(Ok(3), |a| a.parse())?;
    let critic = match args.next().as_deref() {
        None | Some("mlp") => CriticArchitecture::Mlp,
        Some("pooled") => CriticArchitecture::Pooled,
        Some(other) => anyhow::bail!("critic must be mlp or pooled, got {other}"),
    };
    let env = EnvConfig {
        history,
        ..EnvConfig::default()
    };
    let learn = LearnConfig {
        batch_size,
        critic,
        ..LearnConfig::default()
    };
    let mut rng = StdRng::seed_from_u64(1);
    let mut replay = ReplayBuffer::new(learn.replay_capacity);
    for number in 0..200 {
        let world = World::new(&env, random_episode(n, &env, &mut rng));
        replay.push(record_episode(number, world, env.max_steps, |w| {
            (0..w.n_agents())
                .map(|_| [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)])
                .collect()
        }));
    }
    let sampler = Sampler {
        history: env.history,
        her_probability: learn.her_probability,
        env: env.clone(),
        critic: learn.critic,
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
        "N = {n}, H = {history}, B = {batch_size}, {critic:?} critic: sample {:.2} ms, update {:.2} ms, {:.0} updates/s",
        1e3 * sampling / updates as f64,
        1e3 * updating / updates as f64,
        updates as f64 / (sampling + updating)
    );
    Ok(())
}
