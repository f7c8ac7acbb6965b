//! The lockstep loop with every role in one process: the sim on the main thread and one thread
//! per robot (scripted baseline), over the same code as the multi-process swarm but with the
//! iceoryx2 `local` service (or `ipc`, still in one process). Used by `scripts/bench.sh` to put a
//! number on the cost of process isolation.

use std::path::PathBuf;

use anyhow::{Result, anyhow};
use clap::{Parser, ValueEnum};
use formation_agent::run::{AgentOptions, AgentPolicy, run as run_agent};
use formation_core::baseline::ScriptedBaseline;
use formation_core::config::{RunConfig, validate_agent_count};
use formation_ipc::cli::Mode;
use formation_ipc::placement::{self, Placement, Role};
use formation_ipc::services::{FileDescriptorBased, RunIdentity};
use formation_sim::lockstep::{SimOptions, run as run_sim};
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

/// Which iceoryx2 service type carries the messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Transport {
    /// Process-local (no shared memory files, no sockets).
    Local,
    /// Inter-process shared memory, used between threads of this process.
    Ipc,
}

/// Runs sim and N scripted robots as threads of one process and prints the sim's figures.
#[derive(Debug, Parser)]
#[command(version, about)]
struct Cli {
    /// Robots in the swarm (3 to 64).
    #[arg(long, default_value_t = 3)]
    agents: usize,
    /// Episodes to run.
    #[arg(long, default_value_t = 100)]
    episodes: u64,
    /// Stop after this many minutes of wall clock, even with episodes left.
    #[arg(long)]
    minutes: Option<f64>,
    /// Seed of the episodes.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// iceoryx2 service type.
    #[arg(long, value_enum, default_value_t = Transport::Local)]
    transport: Transport,
    /// Where episodes.csv and summary.json go.
    #[arg(long, default_value = "runs/inproc")]
    run_dir: PathBuf,
    /// auto: every thread on the lockstep CPU, as the sim and robots of a swarm; off: the OS
    /// places the threads.
    #[arg(long, value_enum, default_value_t = Placement::Auto)]
    placement: Placement,
}

fn run<S: Service>(cli: &Cli, identity: &RunIdentity, config: &RunConfig) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    let agents = std::thread::scope(|scope| -> Result<formation_ipc::summary::Summary> {
        let handles: Vec<_> = (0..cli.agents)
            .map(|agent| {
                let options = AgentOptions {
                    agent,
                    n_agents: cli.agents,
                    weights_from: None,
                    config: config.clone(),
                };
                let policy = AgentPolicy::Fixed(Box::new(ScriptedBaseline::new(&config.env, config.baseline)));
                std::thread::Builder::new()
                    .name(format!("agent{agent}"))
                    .spawn_scoped(scope, move || run_agent::<S>(identity, &options, policy))
            })
            .collect::<std::io::Result<_>>()?;
        let options = SimOptions {
            n_agents: cli.agents,
            mode: Mode::Eval,
            episodes: Some(cli.episodes),
            minutes: cli.minutes,
            seed: cli.seed,
            realtime: false,
            expect_critic: false,
            expect_recorder: false,
            scripted: (0..cli.agents).collect(),
            external: Vec::new(),
            run_dir: cli.run_dir.clone(),
            config: config.clone(),
            plots: false,
        };
        let summary = run_sim::<S>(identity, &options, None)?;
        for handle in handles {
            handle.join().map_err(|_| anyhow!("an agent thread panicked"))??;
        }
        Ok(summary)
    })?;
    print!("{}", agents.table());
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    validate_agent_count(cli.agents)?;
    std::fs::create_dir_all(&cli.run_dir)?;
    // Before any thread starts, so the robots' threads share the sim's CPU.
    placement::apply(cli.placement, Role::Sim)?;
    let identity = RunIdentity::new(&format!("inproc{}", std::process::id()))?;
    let config = RunConfig::default();
    let result = match cli.transport {
        Transport::Local => run::<local_threadsafe::Service>(&cli, &identity, &config),
        Transport::Ipc => run::<ipc_threadsafe::Service>(&cli, &identity, &config),
    };
    identity.remove_leftovers();
    result
}
