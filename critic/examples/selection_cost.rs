//! Times one model selection (what every checkpoint costs the critic) and prints the score:
//! `cargo run --release -p formation-critic --example selection_cost -- [CHECKPOINT] [SIZES] [EPISODES] [SHAPE]`,
//! e.g. `models/formation.safetensors 3,4,6,16,32 50 mixed`. One matrix-product thread, as
//! the critic runs by default (`learn.threads`).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::ValueEnum;
use formation_core::config::{EnvConfig, FormationShape, LearnConfig};
use formation_core::reality::RealityConfig;
use formation_critic::selection::Selector;
use formation_model::checkpoint;

fn main() -> anyhow::Result<()> {
    // SAFETY: no other thread runs yet; candle reads this for its matmul thread count.
    unsafe { std::env::set_var("RAYON_NUM_THREADS", "1") };
    let mut args = std::env::args().skip(1);
    let path = PathBuf::from(args.next().unwrap_or_else(|| "models/formation.safetensors".into()));
    let sizes: Vec<usize> = args
        .next()
        .unwrap_or_else(|| "3".into())
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()
        .context("SIZES: comma-separated robot counts")?;
    let episodes: usize = args.next().map_or(Ok(50), |a| a.parse())?;
    let shape = match args.next() {
        Some(name) => FormationShape::from_str(&name, true).map_err(anyhow::Error::msg)?,
        None => FormationShape::Random,
    };
    let model = checkpoint::load(&path)?;
    let env = EnvConfig {
        observation: model.meta.observation,
        history: model.meta.actor.history,
        shape,
        ..EnvConfig::default()
    };
    let learn = LearnConfig {
        selection_episodes: episodes,
        ..LearnConfig::default()
    };
    let actors = (0..model.meta.n_actors)
        .map(|k| model.actor_weights(k))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let selector = Selector::new(&env, &learn, &RealityConfig::default(), &sizes);
    let mut times = Vec::new();
    let mut score = None;
    for _ in 0..5 {
        let started = Instant::now();
        score = Some(selector.score(&actors, &model.meta.actor)?);
        times.push(started.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    let score = score.context("no selection ran")?;
    println!(
        "{} sizes {sizes:?}, {episodes} episodes each, shape {}: median {:.1} ms (min {:.1}, max {:.1}); score {:.3}",
        path.display(),
        shape.as_str(),
        times[times.len() / 2],
        times[0],
        times[times.len() - 1],
        score.success()
    );
    for size in &score.sizes {
        println!(
            "  N={}: success {:.3}, formation held {:.3}, {:.1} steps",
            size.n_agents, size.success, size.formation_held, size.mean_steps
        );
    }
    Ok(())
}
