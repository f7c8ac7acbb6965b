//! `formation-agent`: one robot's process. Usually started by `scripts/run_swarm.sh`.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Result, bail};
use clap::{Parser, ValueEnum};
use formation_agent::oracle::Oracle;
use formation_agent::policy::{Exploration, LearnedPolicy};
use formation_agent::run::{AgentOptions, AgentPolicy, run};
use formation_core::baseline::ScriptedBaseline;
use formation_core::observation::Layout;
use formation_ipc::cli::{Mode, RunArgs};
use formation_ipc::placement::Role;
use formation_model::actor::{ActorHead, ActorShape};
use formation_model::checkpoint;
use iceoryx2::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;

/// Which controller drives this robot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum PolicyKind {
    /// The classical distance-based formation controller.
    Scripted,
    /// The learned actor (weights from the critic in train mode, from --checkpoint in eval).
    Learned,
    /// The privileged planner that knows the map: reads the sim's true poses and the episode's
    /// obstacles, not its observation (a rival to measure against, not a robot's controller).
    Oracle,
}

/// One robot: reads only its own observations over iceoryx2, keeps the last H, and publishes
/// (v, w) every tick.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// This robot's index, 0..agents.
    #[arg(long)]
    agent: usize,
    /// Controller of this robot.
    #[arg(long, value_enum, default_value_t = PolicyKind::Learned)]
    policy: PolicyKind,
    /// Actor weights to start from: a checkpoint file or a run directory. Required for a
    /// learned policy in eval mode; in train mode the critic streams weights.
    #[arg(long)]
    checkpoint: Option<PathBuf>,
    /// Only validate the flags, the configuration and the checkpoint, then exit.
    #[arg(long)]
    check: bool,
    /// Benchmark: time this many single-window inferences of the learned actor (from
    /// --checkpoint), print one JSON line and exit.
    #[arg(long, value_name = "COUNT")]
    bench_inference: Option<usize>,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match try_main(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-agent: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, mut config) = cli.run.load()?;
    let n_agents = cli.run.agents;
    if cli.agent >= n_agents {
        bail!(
            "--agent {} does not exist in a swarm of {n_agents} (robots are 0..{n_agents})",
            cli.agent
        );
    }
    set_log_level_from_env_or(LogLevel::Warn);
    let rng = StdRng::seed_from_u64(cli.run.seed.wrapping_mul(1_000_003).wrapping_add(cli.agent as u64));
    let (policy, weights_from) = match cli.policy {
        PolicyKind::Scripted => (
            AgentPolicy::Fixed(Box::new(ScriptedBaseline::new(&config.env, config.baseline))),
            None,
        ),
        PolicyKind::Oracle => (
            AgentPolicy::Oracle(Box::new(Oracle::new(cli.agent, &config.env, config.baseline))),
            None,
        ),
        PolicyKind::Learned => {
            let obs_dim = Layout::of(config.env.observation).dim();
            let loaded = match &cli.checkpoint {
                Some(path) => Some(checkpoint::load(&checkpoint::resolve(path)?)?),
                None => None,
            };
            if let Some(loaded) = &loaded {
                loaded
                    .meta
                    .check_observation(&loaded.path, config.env.observation, obs_dim)?;
                // An evaluation reads the window (H) and widths the checkpoint was trained with,
                // whatever the config says; training must match the critic's config instead.
                if cli.run.mode == Mode::Eval {
                    config.env.history = loaded.meta.actor.history;
                    config.learn.actor_hidden = loaded.meta.actor.hidden.clone();
                }
            }
            // Training streams command actors; an evaluation runs whatever head it was given.
            let head = match (&loaded, cli.run.mode) {
                (Some(loaded), Mode::Eval) => loaded.meta.actor.head,
                _ => ActorHead::Command,
            };
            let shape = ActorShape {
                obs_dim,
                history: config.env.history,
                hidden: config.learn.actor_hidden.clone(),
                head,
            };
            let exploration = (cli.run.mode == Mode::Train).then_some(Exploration {
                std_start: config.learn.noise_std,
                std_end: config.learn.noise_std_min,
                decay_episodes: config.learn.noise_decay_episodes,
                correlation_ticks: config.learn.noise_correlation_ticks,
                stall_std: config.learn.stall_noise_std,
                stall_ticks: config.learn.stall_noise_ticks,
            });
            let mut learned = LearnedPolicy::new(&config.env, shape.clone(), exploration, rng);
            let actor_index = if config.learn.shared_actor { 0 } else { cli.agent };
            match (&loaded, cli.run.mode) {
                (Some(loaded), _) => {
                    if loaded.meta.actor != shape {
                        bail!(
                            "checkpoint {} holds actors of shape {:?}, the config asks for {:?} (env.history, learn.actor_hidden; training carries on command actors only)",
                            loaded.path.display(),
                            loaded.meta.actor,
                            shape
                        );
                    }
                    learned.load(&loaded.actor_weights(cli.agent)?, 1)?;
                }
                (None, Mode::Eval) => bail!("a learned agent in eval mode needs --checkpoint FILE|RUN_DIR"),
                (None, Mode::Train) => {}
            }
            let follow = (cli.run.mode == Mode::Train).then_some(actor_index);
            (AgentPolicy::Learned(Box::new(learned)), follow)
        }
    };
    if cli.check {
        return Ok(());
    }
    if let (Some(count), AgentPolicy::Learned(learned)) = (cli.bench_inference, &policy) {
        return bench_inference(learned, count);
    }
    cli.run.place(Role::Agent {
        index: cli.agent,
        of: n_agents,
    })?;
    let options = AgentOptions {
        agent: cli.agent,
        n_agents,
        weights_from,
        config,
    };
    let explores_stalls = cli.run.mode == Mode::Train && options.config.learn.stall_noise_std > 0.0;
    let stats = run::<ipc::Service>(&identity, &options, policy)?;
    if explores_stalls {
        eprintln!("agent {}: explored {} stalls", cli.agent, stats.stall_bursts);
    }
    Ok(())
}

/// Times `count` single-window actions of the learned actor (the per-tick inference cost).
fn bench_inference(policy: &LearnedPolicy, count: usize) -> Result<()> {
    use formation_agent::policy::Policy;
    use formation_model::history::ObservationHistory;
    let mut policy_copy = policy.clone();
    let mut history = ObservationHistory::new(policy.shape().history, policy.shape().obs_dim);
    history.reset(&[0.3; formation_protocol::MAX_OBS_DIM]);
    let mut samples = Vec::with_capacity(count);
    for i in 0..count + 1000 {
        let started = std::time::Instant::now();
        std::hint::black_box(policy_copy.command(&history)?);
        if i >= 1000 {
            samples.push(started.elapsed().as_secs_f64() * 1e6);
        }
    }
    samples.sort_by(f64::total_cmp);
    let q = |p: f64| samples[((samples.len() - 1) as f64 * p) as usize];
    println!(
        "{{\"kind\": \"inference\", \"calls\": {count}, \"p50_us\": {:.2}, \"p99_us\": {:.2}, \"input\": {}}}",
        q(0.5),
        q(0.99),
        policy.shape().input_dim()
    );
    Ok(())
}
