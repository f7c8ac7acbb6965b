//! `formation-ros2`: the ROS 2 side of robot slots. For each robot it carries it stands in for
//! the robot's agent process on iceoryx2 (as a robot host's bridge or the Python `Robot` do)
//! and speaks rmw_zenoh's wire format on Zenoh, so a ROS 2 node (over `rmw_zenoh_cpp`, or any
//! program that writes the same bytes) drives the robot: odometry, observation, scan, obstacles
//! and `/clock` out, `cmd_vel` in (docs/ROS2.md).

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Result, anyhow, ensure};
use clap::Parser;
use formation_core::observation::Layout;
use formation_ipc::cli::{RunArgs, parse_robot_set};
use formation_ipc::services::Sizing;
use iceoryx2::prelude::*;
use zenoh::Wait;

use formation_ros2::side::{self, Names, Options};
use formation_ros2::surroundings::ScanLayout;

/// Plays robot slots of a swarm as ROS 2 topics over rmw_zenoh's wire format (started by the
/// launcher for `--ros2`; by hand: docs/ROS2.md).
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Cli {
    #[command(flatten)]
    run: RunArgs,
    /// The robots played by ROS 2 nodes (`2` or `2,3` or `all`).
    #[arg(long, value_name = "all|i,j")]
    robots: String,
    /// Topics are /NAMESPACE/robot_<i>/...
    #[arg(long, default_value = "formation")]
    namespace: String,
    /// ROS_DOMAIN_ID: the first chunk of every key.
    #[arg(long, default_value_t = 0)]
    domain: u32,
    /// Zenoh endpoint to accept ROS 2 nodes on, as their router would (repeatable), e.g.
    /// tcp/127.0.0.1:7447.
    #[arg(long, value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// Zenoh endpoint to dial, e.g. a router (`ros2 run rmw_zenoh_cpp rmw_zenohd`) at
    /// tcp/127.0.0.1:7447 (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Vec<String>,
}

fn main() -> ExitCode {
    match try_main(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("formation-ros2: error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn try_main(cli: Cli) -> Result<()> {
    let (identity, config) = cli.run.load()?;
    let robots = parse_robot_set("--robots", &cli.robots, cli.run.agents)?;
    ensure!(!robots.is_empty(), "--robots names no robot");
    ensure!(
        !cli.listen.is_empty() || !cli.connect.is_empty(),
        "formation-ros2 needs --listen or --connect (e.g. --listen tcp/127.0.0.1:7447)"
    );
    let names = Names::new(cli.domain, &cli.namespace)?;
    set_log_level_from_env_or(LogLevel::Warn);
    let observation = config.env.observation;
    let options = Options {
        identity,
        run_dir: cli.run.run_dir.clone(),
        robots,
        sizing: Sizing::new(
            cli.run.agents,
            config.ticks.critic_window,
            Layout::of(observation).dim(),
        ),
        names,
        observation_label: observation.as_str().to_string(),
        scan: ScanLayout::of(&config.env),
        obstacles: config.env.has_obstacles(),
        dt_s: config.env.dt_s,
        sim_silence: Duration::from_millis(config.ticks.sim_silence_ms),
        startup_timeout: Duration::from_secs(config.ticks.startup_timeout_s),
    };
    let session = side::open_session(&cli.listen, &cli.connect)?;
    eprintln!(
        "ros2: robots {:?} as ROS 2 topics /{}/robot_<i>/... on domain {}; zenoh {} listening on {:?}, dialling {:?}",
        options.robots,
        options.names.namespace(),
        cli.domain,
        session.zid(),
        cli.listen,
        cli.connect
    );
    let outcome = side::run(&options, &session);
    let closed = session.close().wait().map_err(|err| anyhow!("closing zenoh: {err}"));
    let counts = outcome?;
    eprintln!("ros2: {}", counts.report());
    counts.write(&options)?;
    closed
}
