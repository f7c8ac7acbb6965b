//! `formation-mcap`: records a run as `<run dir>/run.mcap`, ROS 2 messages in CDR with their
//! full `ros2msg` schemas, for ROS tools (Foxglove, `ros2 bag`, rosbags). Started by the
//! launcher with `--record mcap` before the rest of the run; docs/ROS2.md, "Runs as MCAP".

use std::io::Write;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Parser;
use formation_core::observation::Layout;
use formation_ipc::cli::RunArgs;
use formation_ipc::placement::Role;
use formation_ipc::services::Sizing;
use formation_ros2::record::{self, Options, READY_LINE};
use formation_ros2::side::Names;
use formation_ros2::surroundings::ScanLayout;
use iceoryx2::prelude::*;

/// Records the run's states as ROS 2 messages in an MCAP file.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// Topics are /NAMESPACE/robot_<i>/... and /NAMESPACE/....
    #[arg(long, default_value = "formation")]
    namespace: String,
}

fn main() -> ExitCode {
    match try_main(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-mcap: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, config) = cli.run.load()?;
    // Off the CPU of the sim's tick thread and the robots, as the critic.
    cli.run.place(Role::Background)?;
    set_log_level_from_env_or(LogLevel::Warn);
    let options = Options {
        identity,
        run_dir: cli.run.run_dir.clone(),
        n_agents: cli.run.agents,
        mode: cli.run.mode,
        sizing: Sizing::new(
            cli.run.agents,
            config.ticks.critic_window,
            Layout::of(config.env.observation).dim(),
        ),
        names: Names::new(0, &cli.namespace)?,
        scan: ScanLayout::of(&config.env),
        obstacles: config.env.has_obstacles(),
        dt_s: config.env.dt_s,
        sim_silence: Duration::from_millis(config.ticks.sim_silence_ms),
        startup_timeout: Duration::from_secs(config.ticks.startup_timeout_s),
    };
    let recorded = record::run(&options, || {
        let mut out = std::io::stdout().lock();
        writeln!(out, "{READY_LINE}")?;
        out.flush().context("cannot tell the launcher the recorder is ready")
    })?;
    eprintln!(
        "mcap: wrote {} states of {} episodes to {}",
        recorded.states,
        recorded.episodes,
        options.run_dir.join(record::MCAP_FILE).display()
    );
    if recorded.lost > 0 {
        eprintln!(
            "mcap: warning: {} states were lost before they were read (the recorder fell behind)",
            recorded.lost
        );
    }
    Ok(())
}
