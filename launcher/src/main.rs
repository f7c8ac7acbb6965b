//! `formation`: starts one formation-control run (the sim, one process per robot, the central
//! critic, and any extra swarms), supervises it and cleans up after it. `scripts/run_swarm.sh`
//! builds the binaries and runs this with the same flags.

mod plan;
mod supervise;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::error::ErrorKind;
use clap::{CommandFactory, Parser, ValueEnum};
use formation_core::config::{FormationShape, validate_agent_count};
use formation_core::obstacles::ObstacleKind;
use formation_ipc::cli::{Mode, ViewerMode};
use formation_ipc::placement::Placement;
use formation_protocol::{MAX_AGENTS, MIN_AGENTS};

use crate::plan::Plan;

const EXAMPLES: &str = "\
Before any process starts, the run directory gets run.json (run id, N, shared-memory prefix,
iceoryx2 root path, protocol version, observation model and size, the service sizing inputs and
the robot limits): an external client needs only the run directory.

Environment: FORMATION_BIN_DIR=DIR runs the sim, agent and critic binaries from DIR (default:
beside this launcher).

Examples:
  scripts/run_swarm.sh 3 --scripted all --mode eval --episodes 50 --seed 1 --viewer off
  scripts/run_swarm.sh 3 --minutes 20
  scripts/run_swarm.sh 6 --mode eval --checkpoint runs/my-training
  scripts/run_swarm.sh 3 --mode eval --scripted 0,1 --external 2 --run-dir runs/py
  scripts/run_swarm.sh 3 --mode eval --scripted 0,1 --ros2 2   (then: python3 -m formation_swarm ros2-node 2)
  scripts/run_swarm.sh 4 --extra-swarms 3,8,16 --config configs/any-n.toml --minutes 30
  scripts/run_swarm.sh 12 --mode eval --reality configs/reality-field.toml --episodes 100 --seed 1000
  scripts/run_swarm.sh 8 --mode eval --obstacles passage --oracle all --episodes 100 --seed 1000
  scripts/run_swarm.sh 8 --mode eval --obstacles passage --scripted all --episodes 100 --seed 1000";

/// Starts the physics process, N robot processes and the central critic, lockstep over
/// iceoryx2 shared memory, and leaves results in a run directory. Ctrl-C ends the run cleanly:
/// the sim closes the episode and tells every process.
#[derive(Debug, Parser)]
#[command(name = "formation", version, after_help = EXAMPLES)]
pub struct LaunchArgs {
    /// Robots in the swarm, 3 to 64.
    #[arg(value_name = "N", value_parser = swarm_size)]
    pub n: usize,
    /// train: explore and learn; eval: act without noise and record.
    #[arg(long, value_enum, default_value_t = Mode::Train)]
    pub mode: Mode,
    /// Stop after E episodes (eval default: 100).
    #[arg(long, value_name = "E", value_parser = clap::value_parser!(u64).range(1..))]
    pub episodes: Option<u64>,
    /// Stop after M minutes of wall clock (train default: 30, none with --updates).
    #[arg(long, value_name = "M", value_parser = positive_minutes)]
    pub minutes: Option<f64>,
    /// Train: end the run once the critic has done U gradient updates (counted on from the
    /// checkpoint it starts from). A length of training that is the same on any machine, where
    /// --minutes buys fewer updates on a slower or busier one; without --minutes no time limit.
    #[arg(long, value_name = "U", value_parser = clap::value_parser!(u64).range(1..))]
    pub updates: Option<u64>,
    /// Robots that run the scripted baseline instead of the learned actor: all, or i,j,...
    #[arg(long, value_name = "all|i,j")]
    pub scripted: Option<String>,
    /// Robots driven by the privileged planner that knows the map (a rival to measure against:
    /// it reads the sim's true poses and the obstacles, not its observation): all, or i,j,...
    /// Not with --remote, --ros2 or --external on the same robot; with --scripted, each flag
    /// takes its own robots ("all" for one of them leaves the other's robots out).
    #[arg(long, value_name = "all|i,j")]
    pub oracle: Option<String>,
    /// Obstacles between the start and the goal of every episode (overrides the config's
    /// [obstacles] kind): forest, passage (a wall with one narrow gap), trap (a U opening
    /// towards the start), mixed (one of the three per episode) or none. Without learned
    /// robots the robots observe slot_proximity_scan (their range sensor) unless the config
    /// names another model.
    #[arg(long, value_enum)]
    pub obstacles: Option<ObstacleKind>,
    /// Robots this launcher does not start: you attach them yourself, e.g. from Python
    /// (pip install ./python; python3 -m formation_swarm robot RUN_DIR i); the sim waits
    /// ticks.startup_timeout_s (60 s) for them to greet. See README.md, "From Python".
    #[arg(long, value_name = "all|i,j")]
    pub external: Option<String>,
    /// Checkpoint file or run directory: eval loads it into the agents, train resumes the critic
    /// from it (eval default: models/formation.safetensors, the shipped model for any N and any
    /// world, ideal or under a [reality]).
    #[arg(long, value_name = "PATH")]
    pub checkpoint: Option<PathBuf>,
    /// Seed of episodes, noise and networks.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Where results go (default runs/<timestamp>).
    #[arg(long, value_name = "DIR")]
    pub run_dir: Option<PathBuf>,
    /// spawn | save | off | connect=URL (default: spawn when a `rerun` viewer and a display are
    /// present, else save).
    #[arg(long, value_name = "MODE", value_parser = ViewerMode::parse)]
    pub viewer: Option<ViewerMode>,
    /// Pace ticks at dt of wall-clock time instead of as fast as possible.
    #[arg(long)]
    pub realtime: bool,
    /// TOML overrides of the defaults (see config.toml in any run directory).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// The robots' real world: the [reality] section of FILE (sensor noise, actuation delay,
    /// motor lag, lost messages, dying controllers; its other sections are not read) replaces
    /// any [reality] of --config. Presets: configs/reality-lab.toml, configs/reality-field.toml.
    /// Every member reads the result, RUN_DIR/launch-config.toml.
    #[arg(long, value_name = "FILE")]
    pub reality: Option<PathBuf>,
    /// Formation of every episode (default: the config's env.shape, random): every observed
    /// edge 0.8-2.0 m, any N; mixed draws a kind per episode.
    #[arg(long, value_enum)]
    pub shape: Option<FormationShape>,
    /// auto: the sim's tick thread and the robots share the last CPU this process may use, the
    /// critic and the view get the others (measured: 2.6x the tick rate of letting the OS place
    /// them at N = 3, 1.3x at N = 12, docs/BENCHMARKS.md); 24 robots or more split into groups
    /// of at least 12 per CPU. off: the OS places every process.
    #[arg(long, value_enum, default_value_t = Placement::Auto)]
    pub placement: Placement,
    /// Train mode: besides the N-robot swarm, one swarm of each of these sizes (its own sim and
    /// robots, all learned, results in RUN_DIR/swarm-K-nNK), every one feeding this run's one
    /// critic, so one actor learns all the sizes at once; needs learn.critic = "pooled"
    /// (configs/multi-size.toml).
    #[arg(long, value_name = "N1,N2", value_delimiter = ',', value_parser = extra_swarm_size)]
    pub extra_swarms: Vec<usize>,
    /// Robots that run as if on another computer: each with its own iceoryx2 (its own prefix and
    /// root path) and a bridge, joined to the sim's host only over Zenoh on TCP localhost (the
    /// same binaries a real second computer runs: docs/REMOTE.md).
    #[arg(long, value_name = "all|i,j")]
    pub remote: Option<String>,
    /// With --remote: every message a bridge sends leaves this many milliseconds late (an
    /// emulated network; the round trip grows by twice this).
    #[arg(long, value_name = "MS", default_value_t = 0.0, value_parser = non_negative_ms)]
    pub net_delay_ms: f64,
    /// With --remote: every message a bridge sends is lost with this probability.
    #[arg(long, value_name = "P", default_value_t = 0.0, value_parser = probability)]
    pub net_loss: f64,
    /// Robots played by ROS 2 nodes: one `formation-ros2` process carries them as ROS 2 topics
    /// over rmw_zenoh's wire format (/NAMESPACE/robot_<i>/odom, observation, cmd_vel and
    /// /clock); the sim waits ticks.startup_timeout_s for each robot's node. See docs/ROS2.md.
    #[arg(long, value_name = "all|i,j")]
    pub ros2: Option<String>,
    /// With --ros2: the topics' namespace.
    #[arg(long, value_name = "NS", default_value = "formation")]
    pub ros2_namespace: String,
    /// With --ros2: the ROS_DOMAIN_ID of the keys.
    #[arg(long, value_name = "ID", default_value_t = 0)]
    pub ros2_domain: u32,
    /// With --ros2: where ROS 2 nodes reach the swarm: a Zenoh endpoint to listen on as a peer
    /// (the default, where rmw_zenoh nodes look for their router), or connect=ENDPOINT to dial
    /// a router (`ros2 run rmw_zenoh_cpp rmw_zenohd`).
    #[arg(long, value_name = "ENDPOINT", default_value = "tcp/127.0.0.1:7447")]
    pub ros2_endpoint: String,
    /// Restart an agent or the critic that dies mid-run (a restarted agent rejoins at once with
    /// the latest weights, a restarted critic resumes from the run's last checkpoint).
    #[arg(long, value_enum, default_value_t = Switch::On)]
    pub restart: Switch,
    /// mcap: write the primary swarm's run as RUN_DIR/run.mcap (ROS 2 messages in CDR with their
    /// schemas: each robot's odometry and applied command, the goal and target formation, reward
    /// and outcome; in train mode only the evaluation episodes). See docs/ROS2.md.
    #[arg(long, value_enum)]
    pub record: Option<Record>,
}

/// What `--record` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Record {
    /// RUN_DIR/run.mcap, by the `formation-mcap` member.
    Mcap,
}

/// An on/off flag value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Switch {
    /// Enabled.
    On,
    /// Disabled.
    Off,
}

fn swarm_size(text: &str) -> Result<usize, String> {
    let n: usize = text
        .parse()
        .map_err(|_| format!("N must be a whole number, got {text:?}"))?;
    validate_agent_count(n).map_err(|_| {
        format!(
            "N must be between {MIN_AGENTS} and {MAX_AGENTS} (each robot observes two distinct neighbours), got {n}"
        )
    })?;
    Ok(n)
}

fn extra_swarm_size(text: &str) -> Result<usize, String> {
    text.parse()
        .ok()
        .filter(|n| validate_agent_count(*n).is_ok())
        .ok_or_else(|| format!("--extra-swarms takes sizes {MIN_AGENTS} to {MAX_AGENTS} like 3,8; got {text:?}"))
}

fn non_negative_ms(text: &str) -> Result<f64, String> {
    text.parse::<f64>()
        .ok()
        .filter(|ms| (0.0..=60_000.0).contains(ms))
        .ok_or_else(|| format!("--net-delay-ms must be 0 to 60000, got {text:?}"))
}

fn probability(text: &str) -> Result<f64, String> {
    text.parse::<f64>()
        .ok()
        .filter(|p| (0.0..=1.0).contains(p))
        .ok_or_else(|| format!("--net-loss must be a probability (0 to 1), got {text:?}"))
}

fn positive_minutes(text: &str) -> Result<f64, String> {
    text.parse::<f64>()
        .ok()
        .filter(|m| m.is_finite() && *m > 0.0)
        .ok_or_else(|| format!("--minutes must be a positive number, got {text:?}"))
}

fn main() -> ExitCode {
    let args = LaunchArgs::parse();
    let plan = match Plan::new(args) {
        Ok(plan) => plan,
        Err(refusal) => {
            // Named as invoked (scripts/run_swarm.sh execs this as `run_swarm.sh`), like clap's own errors.
            let invoked = std::env::args_os().next().map(PathBuf::from);
            let name = invoked
                .as_deref()
                .and_then(|path| path.file_name())
                .map_or("formation".into(), |name| name.to_string_lossy().into_owned());
            LaunchArgs::command()
                .bin_name(name)
                .error(ErrorKind::ValueValidation, format!("{refusal:#}"))
                .exit()
        }
    };
    match supervise::launch(&plan) {
        Ok(code) => ExitCode::from(code),
        Err(err) => {
            eprintln!("run_swarm.sh: error: {err:#}");
            ExitCode::from(1)
        }
    }
}
