//! `formation-critic`: the central critic and replay process. Usually started by
//! `scripts/run_swarm.sh`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result, bail};
use clap::Parser;
use formation_core::config::{CriticArchitecture, validate_agent_count};
use formation_core::run_dir::prepare_run_dir;
use formation_critic::run::{CriticOptions, run};
use formation_ipc::cli::ViewerMode;
use formation_ipc::cli::{Mode, RunArgs};
use formation_ipc::placement::Role;
use formation_ipc::services::RunIdentity;
use formation_model::checkpoint;
use iceoryx2::prelude::*;

/// Subscribes to the sim's state and every agent's observations and commands, assembles them
/// into a central replay and, in train mode, trains the critic and actors, streaming the
/// actors' weights back to the agents.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// Resume training from this checkpoint (a file or a run directory).
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Do not draw the progress line.
    #[arg(long)]
    quiet: bool,
    /// Training curves: spawn|connect=URL (join the run's viewer), save (training.rrd), off.
    #[arg(long, default_value = "off")]
    viewer: String,
    /// Another swarm to train on as well, `RUN_ID:N`: a sim and N robots started under that run
    /// id (repeatable). Needs `learn.critic = "pooled"`, whose one critic serves every size.
    #[arg(long, value_name = "RUN_ID:N", value_parser = parse_swarm)]
    extra_swarm: Vec<(RunIdentity, usize)>,
    /// The run's length as given to the sim (`--minutes`): shows the time left.
    #[arg(long)]
    minutes: Option<f64>,
    /// Train mode: stop updating after this many gradient updates in this run (counted on from
    /// the checkpoint it starts from; a critic restarted in the same run directory keeps the
    /// first one's target), then print `UPDATE_BUDGET_SPENT` and acknowledge every tick.
    #[arg(long, value_name = "U", value_parser = clap::value_parser!(u64).range(1..))]
    updates: Option<u64>,
    /// Only validate the flags, the configuration and the checkpoint to resume, then exit.
    #[arg(long)]
    check: bool,
}

fn parse_swarm(text: &str) -> Result<(RunIdentity, usize)> {
    let (run_id, n) = text
        .split_once(':')
        .with_context(|| format!("--extra-swarm takes RUN_ID:N, got {text:?}"))?;
    let n: usize = n
        .parse()
        .with_context(|| format!("--extra-swarm {text:?}: N must be a whole number"))?;
    validate_agent_count(n)?;
    Ok((RunIdentity::new(run_id)?, n))
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match try_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-critic: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, config) = cli.run.load()?;
    // SAFETY: no other thread runs yet; candle reads this for its matmul thread count.
    unsafe { std::env::set_var("RAYON_NUM_THREADS", config.learn.threads.to_string()) };
    formation_critic::tune_allocator();
    let resume = match (&cli.checkpoint, cli.run.mode) {
        (Some(path), Mode::Train) => Some(checkpoint::resolve(path)?),
        _ => None,
    };
    let viewer = ViewerMode::parse(&cli.viewer)?;
    if !cli.extra_swarm.is_empty() {
        if cli.run.mode != Mode::Train {
            bail!("--extra-swarm is for training: evaluate each swarm size on its own");
        }
        if config.learn.critic != CriticArchitecture::Pooled {
            bail!(
                "--extra-swarm needs learn.critic = \"pooled\" (an mlp critic is sized by N), e.g. --config configs/any-n.toml"
            );
        }
        if !config.learn.shared_actor {
            bail!(
                "--extra-swarm needs learn.shared_actor = true: independent actors (one per robot) cannot drive swarms of other sizes"
            );
        }
    }
    if cli.updates.is_some() && cli.run.mode != Mode::Train {
        bail!("--updates is for training: an eval does no updates");
    }
    if cli.run.mode == Mode::Train {
        config.learn.check_training_seeds(cli.run.seed, cli.extra_swarm.len())?;
        config.check_training_critic()?;
        config.learn.check_imitation_start(resume.is_some())?;
    }
    if cli.check {
        if let Some(path) = &resume {
            let mut learner =
                formation_critic::learner::Learner::new(cli.run.agents, &config.env, &config.learn, cli.run.seed)?;
            learner.load(path)?;
        }
        return Ok(());
    }
    prepare_run_dir(&cli.run.run_dir, &config)?;
    set_log_level_from_env_or(LogLevel::Warn);
    // Before any worker thread starts, so they all inherit the critic's CPUs.
    cli.run.place(Role::Background)?;
    let options = CriticOptions {
        n_agents: cli.run.agents,
        mode: cli.run.mode,
        seed: cli.run.seed,
        run_dir: cli.run.run_dir.clone(),
        config,
        resume,
        progress: !cli.quiet,
        viewer,
        run_id: identity.run_id.clone(),
        minutes: cli.minutes,
        updates: cli.updates,
        extra_swarms: cli.extra_swarm,
    };
    let summary = run::<ipc::Service>(&identity, &options)?;
    println!("\nRun summary ({}):", options.run_dir.join("summary.json").display());
    print!("{}", summary.table());
    Ok(())
}
