//! `formation-critic-probe`: measures whether a trained critic knows how one robot's action
//! changes the team's value, against the true change measured by branching deterministic
//! in-process episodes (`formation_critic::probe`). Writes one CSV row per perturbation and
//! prints one JSON summary per action component.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, ensure};
use clap::Parser;
use formation_core::config::{RunConfig, validate_agent_count};
use formation_core::obstacles::ObstacleKind;
use formation_critic::probe::{ProbeOptions, learner_with_critic, probe, summarise, value_calibration};
use formation_model::actor::FrozenActor;
use formation_model::checkpoint;

/// Plays ideal-world episodes with an actor and, every `--every` ticks, moves one robot's
/// normalised speed and turn rate by ±`--delta` for one tick in copies of the episode. The
/// true change of the discounted return (`learn.gamma`, over `--horizon` ticks) is set beside
/// the change of the first critic's Q, on the transition as the replay samples it.
#[derive(Debug, Parser)]
#[command(version, about, long_about)]
struct Cli {
    /// A training run's full checkpoint (its checkpoint.safetensors or a file of its
    /// checkpoints/): the critic probed, and the actor played unless --actor is given. Several
    /// (comma-separated): the mean of their critics, the first one's actor.
    #[arg(long, value_delimiter = ',', required = true)]
    checkpoint: Vec<PathBuf>,
    /// Play this file's actor instead (a file or run directory; same observation and window).
    #[arg(long)]
    actor: Option<PathBuf>,
    /// The run config the checkpoint was trained with (its [learn] shapes the critic).
    #[arg(long)]
    config: Option<PathBuf>,
    /// Obstacles (overrides the config's [obstacles] kind).
    #[arg(long, value_enum)]
    obstacles: Option<ObstacleKind>,
    /// Robots.
    #[arg(long, default_value_t = 8)]
    n: usize,
    /// Episodes.
    #[arg(long, default_value_t = 20)]
    episodes: usize,
    /// The episodes' seed (a lockstep eval's --seed).
    #[arg(long, default_value_t = 7000)]
    seed: u64,
    /// A branch point every this many ticks.
    #[arg(long, default_value_t = 50)]
    every: u32,
    /// The move of a normalised action component, both ways.
    #[arg(long, default_value_t = 0.2)]
    delta: f32,
    /// Ticks the move is held from the branch point (the critic's change is that of the first
    /// tick's action alone).
    #[arg(long, default_value_t = 1)]
    hold: u32,
    /// Ticks each return is summed over.
    #[arg(long, default_value_t = 300)]
    horizon: u32,
    /// Gaussian noise of this std on every robot's normalised action at every tick, as an
    /// exploring robot's (the same draws in the episode and its branches); 0: the actor alone.
    #[arg(long, default_value_t = 0.0)]
    noise: f64,
    /// Where the rows go (CSV; nothing written without it).
    #[arg(long)]
    out: Option<PathBuf>,
}

fn main() -> ExitCode {
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-critic-probe: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> Result<()> {
    validate_agent_count(cli.n)?;
    let mut config = match &cli.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(kind) = cli.obstacles {
        config.env.obstacles.kind = kind;
    }
    let paths = cli
        .checkpoint
        .iter()
        .map(|path| checkpoint::resolve(path))
        .collect::<Result<Vec<_>>>()?;
    let trained = checkpoint::load(&paths[0])?;
    let mut env = config.env.clone();
    env.observation = trained.meta.observation;
    env.history = trained.meta.actor.history;
    let critics = paths
        .iter()
        .map(|path| learner_with_critic(path, cli.n, &env, &config.learn))
        .collect::<Result<Vec<_>>>()?;
    let learner = &critics[0];
    let played = match &cli.actor {
        Some(actor) => checkpoint::load(&checkpoint::resolve(actor)?)?,
        None => trained,
    };
    ensure!(
        played.meta.actor == *learner.actor_shape(),
        "--actor has shape {:?}; the critic was trained beside {:?}",
        played.meta.actor,
        learner.actor_shape()
    );
    let mut actors = (0..played.meta.n_actors)
        .map(|index| FrozenActor::from_flat(&played.actor_weights(index)?, &played.meta.actor))
        .collect::<Result<Vec<_>>>()?;
    let options = ProbeOptions {
        n_agents: cli.n,
        episodes: cli.episodes,
        seed: cli.seed,
        every: cli.every,
        delta: cli.delta,
        hold: cli.hold,
        horizon: cli.horizon,
        noise_std: cli.noise,
    };
    let rows = probe(&env, &config.learn, &critics, &mut actors, &options, |done, total| {
        eprint!("\rformation-critic-probe: episode {done}/{total}");
    })?;
    eprintln!();
    if let Some(out) = &cli.out {
        let mut writer = csv::Writer::from_path(out).with_context(|| format!("cannot create {}", out.display()))?;
        for row in &rows {
            writer.serialize(row)?;
        }
        writer.flush()?;
    }
    let (correlation, critic, truth) = value_calibration(&rows);
    println!(
        "{}",
        serde_json::json!({"values": {"correlation": correlation, "mean_critic": critic, "mean_true": truth}})
    );
    for summary in summarise(&rows) {
        println!("{}", serde_json::to_string(&summary)?);
    }
    Ok(())
}
