//! What a run is, declared once: its swarms, its process set, each member's restart policy and
//! the flags each member starts with. `supervise` runs a plan and decides nothing of this.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, anyhow, bail, ensure};
use clap::ValueEnum;
use formation_core::config::{EnvConfig, FormationShape, RunConfig, extra_swarm_seed};
use formation_core::observation::Layout;
use formation_core::reality::RealityConfig;
use formation_ipc::cli::{Mode, ViewerMode, parse_robot_set, robot_set_arg};
use formation_ipc::placement::Placement;
use formation_ipc::services::{ICEORYX_CONFIG_FILE, RunIdentity};
use formation_protocol::wire::PROTOCOL_VERSION;

use crate::{LaunchArgs, Switch};

/// At most this many extra swarms feed one critic.
const MAX_EXTRA_SWARMS: usize = 8;

/// With `--reality`: the run's config (`--config` with the file's `[reality]`), written into the
/// run directory before anything starts; every member reads it as its `--config`.
pub const LAUNCH_CONFIG_FILE: &str = "launch-config.toml";

/// One swarm of the run: a sim and its robots under their own run id (own shared memory).
#[derive(Debug)]
pub struct Swarm {
    /// Robots.
    pub n: usize,
    /// Its run id, shared-memory prefix and iceoryx2 root path.
    pub identity: RunIdentity,
    /// Where its results go.
    pub run_dir: PathBuf,
    /// Seed of its episodes, noise and networks.
    pub seed: u64,
    /// Robots that run the scripted baseline.
    pub scripted: Vec<usize>,
    /// Robots driven by the privileged planner (`formation-agent --policy oracle`).
    pub oracle: Vec<usize>,
    /// Robots started by someone else (not members of the process set).
    pub external: Vec<usize>,
    /// Robots on a host of their own, joined over Zenoh (see [`RemoteHost`]).
    pub remote: Vec<RemoteHost>,
    /// Robots played by ROS 2 nodes through the `formation-ros2` member.
    pub ros2: Vec<usize>,
}

/// A robot "on another computer": its own iceoryx2 (run id, prefix, root path) and run
/// directory, where its bridge recreates its services; here the other computer is this one.
#[derive(Debug)]
pub struct RemoteHost {
    /// The robot.
    pub robot: usize,
    /// The host's run id, shared-memory prefix and iceoryx2 root path.
    pub identity: RunIdentity,
    /// The host's logs and files.
    pub run_dir: PathBuf,
}

/// One process of the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Member {
    /// The central critic (one for every swarm).
    Critic,
    /// The physics process of swarm `swarm` (0 is the primary swarm).
    Sim {
        /// Index into [`Plan::swarms`].
        swarm: usize,
    },
    /// The bridge of the sim's host (`None`) or of remote robot `host`'s host.
    Bridge {
        /// The remote robot whose host this bridge is on, if any.
        host: Option<usize>,
    },
    /// The ROS 2 side of the primary swarm's `--ros2` robots.
    Ros2,
    /// With `--record mcap`: the recorder of the primary swarm's states (`run.mcap`).
    Mcap,
    /// Remote robot `index` of the primary swarm, on its own host.
    RemoteRobot {
        /// The robot.
        index: usize,
    },
    /// Robot `index` of swarm `swarm`.
    Robot {
        /// Index into [`Plan::swarms`].
        swarm: usize,
        /// The robot.
        index: usize,
    },
}

/// What the launcher does when a member exits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Restart {
    /// Its exit ends the run (the primary sim: it tells everyone else).
    EndsTheRun,
    /// Left ended (an extra swarm's sim, or any member under `--restart off`).
    Never,
    /// Started again at once after a failure; a robot rejoins with the latest weights.
    OnFailure,
    /// Started again after a failure from the run's last checkpoint; three deaths in a row
    /// within seconds of their start stop the run instead.
    OnFailureResuming,
}

/// A validated run.
#[derive(Debug)]
pub struct Plan {
    /// train or eval.
    pub mode: Mode,
    /// Stop after this many episodes.
    pub episodes: Option<u64>,
    /// Stop after this many minutes.
    pub minutes: Option<f64>,
    /// Train: end the run after the critic's this many updates.
    pub updates: Option<u64>,
    /// Eval: the agents' weights; train: the critic's resume point.
    pub checkpoint: Option<PathBuf>,
    /// Where the recording goes.
    pub viewer: ViewerMode,
    /// Ticks paced at dt of wall-clock time.
    pub realtime: bool,
    /// The `--config` file, passed on to every member (with `--reality`: LAUNCH_CONFIG_FILE in
    /// the run directory).
    pub config_path: Option<PathBuf>,
    /// With `--reality`: the text of LAUNCH_CONFIG_FILE, written by [`Plan::write_launch_config`].
    pub launch_config: Option<String>,
    /// The `--shape` override, passed on to every member.
    pub shape: Option<FormationShape>,
    /// CPU placement of every member.
    pub placement: Placement,
    /// Whether failed members are restarted.
    pub restart: bool,
    /// The Zenoh endpoint the sim host's bridge listens on (with remote robots).
    pub bridge_endpoint: Option<String>,
    /// `--net-delay-ms` and `--net-loss` of the bridges.
    pub net_delay_ms: f64,
    /// Loss probability of the emulated network.
    pub net_loss: f64,
    /// With `--ros2`: the topics' namespace, the domain id and the Zenoh endpoint.
    pub ros2: Ros2Link,
    /// `--record mcap`: the primary swarm's run is written as `run.mcap`.
    pub record_mcap: bool,
    /// The configuration every member reads (defaults, the file, the shape).
    pub config: RunConfig,
    /// The primary swarm first, then the extra swarms.
    pub swarms: Vec<Swarm>,
}

impl Plan {
    /// Checks every flag and the configuration; nothing is created yet.
    pub fn new(args: LaunchArgs) -> Result<Self> {
        let sets = RobotSets::new(&args)?;
        let ros2_link = Ros2Link::new(&args)?;
        check_training_flags_and_files(&args)?;
        let learned = args.n - sets.scripted.len() - sets.oracle.len() - sets.external.len() - sets.ros2.len();
        let config = read_config(&args, learned)?;
        let checkpoint = checkpoint_to_load(&args, learned, &config)?;
        let run_dir = args.run_dir.clone().unwrap_or_else(default_run_dir);
        let (config_path, launch_config) = members_config(&args, &config, &run_dir);
        let run_id = new_run_id();
        let remote = remote_hosts(&sets.remote, &run_id, &run_dir)?;
        let bridge_endpoint = bridge_endpoint(&remote)?;
        let swarms = swarms(&args, sets, remote, &run_id, &run_dir)?;
        Ok(Self {
            mode: args.mode,
            episodes: args.episodes,
            minutes: args.minutes,
            updates: args.updates,
            checkpoint,
            viewer: args.viewer.unwrap_or_else(default_viewer),
            realtime: args.realtime,
            config_path,
            launch_config,
            shape: args.shape,
            placement: args.placement,
            restart: args.restart == Switch::On,
            bridge_endpoint,
            net_delay_ms: args.net_delay_ms,
            net_loss: args.net_loss,
            ros2: ros2_link,
            record_mcap: args.record == Some(crate::Record::Mcap),
            config,
            swarms,
        })
    }

    /// With `--reality`: writes the run's config where every member's `--config` points,
    /// creating the run directory. Before any member (or preflight check) starts.
    pub fn write_launch_config(&self) -> Result<()> {
        let (Some(text), Some(path)) = (&self.launch_config, &self.config_path) else {
            return Ok(());
        };
        let run_dir = &self.primary().run_dir;
        std::fs::create_dir_all(run_dir).with_context(|| format!("cannot create {}", run_dir.display()))?;
        let header = "# The run's config: --config with --reality's [reality] section (written by the launcher)\n";
        std::fs::write(path, format!("{header}{text}")).with_context(|| format!("cannot write {}", path.display()))
    }

    /// The primary swarm.
    pub fn primary(&self) -> &Swarm {
        &self.swarms[0]
    }

    /// The process set, in the order it starts: the MCAP recorder (if any: the launcher waits
    /// for its state subscriber, so it sees the first tick), the critic, the bridges and remote robots (if
    /// any), each extra swarm's robots and sim, then the primary swarm's robots and last its
    /// sim (which starts the first tick).
    pub fn members(&self) -> Vec<Member> {
        let mut members = Vec::new();
        if self.record_mcap {
            members.push(Member::Mcap);
        }
        members.push(Member::Critic);
        let remote = &self.primary().remote;
        if !remote.is_empty() {
            members.push(Member::Bridge { host: None });
            for host in remote {
                members.push(Member::Bridge { host: Some(host.robot) });
                members.push(Member::RemoteRobot { index: host.robot });
            }
        }
        if !self.primary().ros2.is_empty() {
            members.push(Member::Ros2);
        }
        let robots = |swarm: usize| {
            let s = &self.swarms[swarm];
            (0..s.n)
                .filter(move |index| {
                    !s.external.contains(index)
                        && !s.ros2.contains(index)
                        && !s.remote.iter().any(|h| h.robot == *index)
                })
                .map(move |index| Member::Robot { swarm, index })
        };
        for swarm in 1..self.swarms.len() {
            members.extend(robots(swarm));
            members.push(Member::Sim { swarm });
        }
        members.extend(robots(0));
        members.push(Member::Sim { swarm: 0 });
        members
    }

    /// The restart policy of every member, in one place.
    pub fn restart_policy(&self, member: Member) -> Restart {
        match member {
            Member::Sim { swarm: 0 } => Restart::EndsTheRun,
            // A restarted recorder would begin a new file without what was recorded.
            Member::Mcap => Restart::Never,
            _ if !self.restart => Restart::Never,
            Member::Sim { .. } => Restart::Never,
            Member::Robot { .. } | Member::RemoteRobot { .. } | Member::Bridge { .. } | Member::Ros2 => {
                Restart::OnFailure
            }
            Member::Critic => Restart::OnFailureResuming,
        }
    }

    /// The binary a member runs.
    pub fn program(member: Member) -> &'static str {
        match member {
            Member::Critic => "formation-critic",
            Member::Sim { .. } => "formation-sim",
            Member::Robot { .. } | Member::RemoteRobot { .. } => "formation-agent",
            Member::Bridge { .. } => "formation-bridge",
            Member::Ros2 => "formation-ros2",
            Member::Mcap => "formation-mcap",
        }
    }

    /// The member's log file.
    pub fn log_path(&self, member: Member) -> PathBuf {
        match member {
            Member::Critic => self.primary().run_dir.join("logs/critic.log"),
            Member::Sim { swarm } => self.swarms[swarm].run_dir.join("logs/sim.log"),
            Member::Robot { swarm, index } => self.swarms[swarm].run_dir.join(format!("logs/agent-{index}.log")),
            Member::Bridge { host: None } => self.primary().run_dir.join("logs/bridge.log"),
            Member::Bridge { host: Some(robot) } => self.host(robot).run_dir.join("logs/bridge.log"),
            Member::RemoteRobot { index } => self.host(index).run_dir.join(format!("logs/agent-{index}.log")),
            Member::Ros2 => self.primary().run_dir.join("logs/ros2.log"),
            Member::Mcap => self.primary().run_dir.join("logs/mcap.log"),
        }
    }

    /// A member's name in messages ("agent 2", "extra swarm 1: agent 0", "the critic").
    pub fn name(&self, member: Member) -> String {
        let swarm_name = |swarm: usize| match swarm {
            0 => String::new(),
            k => format!("extra swarm {k}: "),
        };
        match member {
            Member::Critic => "the critic".into(),
            Member::Sim { swarm } => format!("{}the sim", swarm_name(swarm)),
            Member::Robot { swarm, index } => format!("{}agent {index}", swarm_name(swarm)),
            Member::Bridge { host: None } => "the sim's bridge".into(),
            Member::Bridge { host: Some(robot) } => format!("robot {robot}'s bridge"),
            Member::RemoteRobot { index } => format!("agent {index} (remote)"),
            Member::Ros2 => "the ROS 2 side".into(),
            Member::Mcap => "the MCAP recorder".into(),
        }
    }

    /// The host of remote robot `robot`.
    pub fn host(&self, robot: usize) -> &RemoteHost {
        self.primary()
            .remote
            .iter()
            .find(|host| host.robot == robot)
            .unwrap_or_else(|| unreachable!("robot {robot} is a member only when remote"))
    }

    /// Every run identity this run creates: each swarm's and each remote host's.
    pub fn identities(&self) -> Vec<&RunIdentity> {
        let hosts = self.primary().remote.iter().map(|host| &host.identity);
        self.swarms.iter().map(|swarm| &swarm.identity).chain(hosts).collect()
    }

    /// Every run directory this run writes: each swarm's and each remote host's.
    pub fn run_dirs(&self) -> Vec<&Path> {
        let hosts = self.primary().remote.iter().map(|host| host.run_dir.as_path());
        self.swarms
            .iter()
            .map(|swarm| swarm.run_dir.as_path())
            .chain(hosts)
            .collect()
    }

    /// Whether robot `index` of swarm `swarm` runs the learned actor (if this launcher starts it).
    fn learned(&self, swarm: usize, index: usize) -> bool {
        let s = &self.swarms[swarm];
        !s.scripted.contains(&index) && !s.oracle.contains(&index)
    }

    /// Flags every member of swarm `swarm` takes.
    fn common_args(&self, swarm: usize) -> Vec<OsString> {
        let s = &self.swarms[swarm];
        self.common_args_on(s.n, &s.identity, &s.run_dir, s.seed)
    }

    /// Flags every member of the primary swarm on remote robot `robot`'s host takes.
    fn host_args(&self, robot: usize) -> Vec<OsString> {
        let (primary, host) = (self.primary(), self.host(robot));
        self.common_args_on(primary.n, &host.identity, &host.run_dir, primary.seed)
    }

    fn common_args_on(&self, n: usize, identity: &RunIdentity, run_dir: &Path, seed: u64) -> Vec<OsString> {
        let mut args: Vec<OsString> = vec![
            "--agents".into(),
            n.to_string().into(),
            "--run-id".into(),
            identity.run_id.clone().into(),
            "--run-dir".into(),
            run_dir.into(),
            "--seed".into(),
            seed.to_string().into(),
            "--mode".into(),
            self.mode.as_str().into(),
            "--placement".into(),
            value_name(self.placement).into(),
        ];
        if let Some(path) = &self.config_path {
            args.extend(["--config".into(), path.clone().into()]);
        }
        if let Some(shape) = self.shape {
            args.extend(["--shape".into(), shape.as_str().into()]);
        }
        args
    }

    /// The flags `member` starts with. The critic's depend on the start: `resume` is the
    /// checkpoint it resumes from (train), `minutes_left` the time its display counts down.
    pub fn args(&self, member: Member, resume: Option<&Path>, minutes_left: Option<f64>) -> Vec<OsString> {
        let opt = |flag: &str, value: Option<String>| value.map(|v| [OsString::from(flag), v.into()]);
        match member {
            Member::Critic => {
                let mut args = self.common_args(0);
                for extra in &self.swarms[1..] {
                    args.extend([
                        "--extra-swarm".into(),
                        format!("{}:{}", extra.identity.run_id, extra.n).into(),
                    ]);
                }
                args.extend(["--viewer".into(), self.viewer.as_arg().into()]);
                args.extend(
                    opt("--minutes", minutes_left.map(|m| format!("{:.3}", m.max(0.01))))
                        .into_iter()
                        .flatten(),
                );
                if let (Mode::Train, Some(path)) = (self.mode, resume) {
                    args.extend(["--checkpoint".into(), path.into()]);
                }
                if let Some(updates) = self.updates {
                    args.extend(["--updates".into(), updates.to_string().into()]);
                }
                args
            }
            Member::Bridge { host } => self.bridge_args(host),
            Member::Mcap => {
                let mut args = self.common_args(0);
                args.extend(["--namespace".into(), self.ros2.namespace.clone().into()]);
                args
            }
            Member::Ros2 => {
                let link = &self.ros2;
                let mut args = self.common_args(0);
                args.extend([
                    "--robots".into(),
                    robot_set_arg(&self.primary().ros2).into(),
                    "--namespace".into(),
                    link.namespace.clone().into(),
                    "--domain".into(),
                    link.domain.to_string().into(),
                ]);
                match &link.endpoint {
                    Ros2Endpoint::Listen(endpoint) => args.extend(["--listen".into(), endpoint.into()]),
                    Ros2Endpoint::Connect(endpoint) => args.extend(["--connect".into(), endpoint.into()]),
                }
                args
            }
            Member::RemoteRobot { index } => {
                let mut args = self.host_args(index);
                args.extend(["--agent".into(), index.to_string().into()]);
                args.extend(self.policy_args(0, index));
                args
            }
            Member::Robot { swarm, index } => {
                let mut args = self.common_args(swarm);
                args.extend(["--agent".into(), index.to_string().into()]);
                args.extend(self.policy_args(swarm, index));
                args
            }
            Member::Sim { swarm } => {
                let s = &self.swarms[swarm];
                let mut args = self.common_args(swarm);
                let viewer = if swarm == 0 { self.viewer.as_arg() } else { "off".into() };
                args.extend(["--viewer".into(), viewer.into()]);
                args.extend(
                    opt("--episodes", self.episodes.map(|e| e.to_string()))
                        .into_iter()
                        .flatten(),
                );
                args.extend(
                    opt("--minutes", self.minutes.map(|m| m.to_string()))
                        .into_iter()
                        .flatten(),
                );
                if self.updates.is_some() && self.minutes.is_none() && self.episodes.is_none() {
                    // The launcher ends it once the critic's updates are done.
                    args.push("--open-ended".into());
                }
                if self.realtime && swarm == 0 {
                    args.push("--realtime".into());
                }
                if self.record_mcap && swarm == 0 {
                    args.push("--expect-recorder".into());
                }
                if !s.external.is_empty() {
                    args.extend(["--external".into(), robot_set_arg(&s.external).into()]);
                }
                if !s.scripted.is_empty() {
                    args.extend(["--scripted".into(), robot_set_arg(&s.scripted).into()]);
                }
                args
            }
        }
    }

    /// A robot's controller flags.
    fn policy_args(&self, swarm: usize, index: usize) -> Vec<OsString> {
        let mut args: Vec<OsString> = Vec::new();
        if self.learned(swarm, index) {
            args.extend(["--policy".into(), "learned".into()]);
            if let (Mode::Eval, Some(path)) = (self.mode, &self.checkpoint) {
                args.extend(["--checkpoint".into(), path.into()]);
            }
        } else if self.swarms[swarm].oracle.contains(&index) {
            args.extend(["--policy".into(), "oracle".into()]);
        } else {
            args.extend(["--policy".into(), "scripted".into()]);
        }
        args
    }

    /// A bridge's flags: the sim host's listens, each robot host's dials it.
    fn bridge_args(&self, host: Option<usize>) -> Vec<OsString> {
        let endpoint = self.bridge_endpoint.clone().unwrap_or_default();
        let primary = self.primary();
        let mut args = match host {
            None => {
                let robots: Vec<usize> = primary.remote.iter().map(|h| h.robot).collect();
                let mut args = self.common_args(0);
                args.extend([
                    "--side".into(),
                    "sim".into(),
                    "--robots".into(),
                    robot_set_arg(&robots).into(),
                ]);
                args.extend(["--listen".into(), endpoint.into()]);
                args
            }
            Some(robot) => {
                let mut args = self.host_args(robot);
                args.extend([
                    "--side".into(),
                    "robot".into(),
                    "--robots".into(),
                    robot.to_string().into(),
                ]);
                args.extend(["--swarm".into(), primary.identity.run_id.clone().into()]);
                args.extend(["--connect".into(), endpoint.into()]);
                args
            }
        };
        if self.net_delay_ms > 0.0 {
            args.extend(["--net-delay-ms".into(), self.net_delay_ms.to_string().into()]);
        }
        if self.net_loss > 0.0 {
            args.extend(["--net-loss".into(), self.net_loss.to_string().into()]);
        }
        args
    }

    /// Checks that need a member's own code (a checkpoint against the config, the critic's
    /// settings for several swarms), as `(program, flags)`: each must exit 0 before anything
    /// starts.
    pub fn preflight(&self) -> Vec<(&'static str, Vec<OsString>)> {
        let mut checks = Vec::new();
        // Eval: one learned robot loads the checkpoint. The highest index, so that a checkpoint
        // of independent actors is refused when it holds fewer robots than the swarm.
        let primary = self.primary();
        let last_learned = (0..primary.n).rev().find(|&index| {
            self.learned(0, index) && !primary.external.contains(&index) && !primary.ros2.contains(&index)
        });
        if let (Mode::Eval, Some(index), Some(_)) = (self.mode, last_learned, &self.checkpoint) {
            let member = Member::Robot { swarm: 0, index };
            let mut args = self.args(member, None, None);
            args.push("--check".into());
            checks.push((Self::program(member), args));
        }
        if (self.mode == Mode::Train && self.checkpoint.is_some()) || self.swarms.len() > 1 {
            let mut args = self.args(Member::Critic, self.checkpoint.as_deref(), None);
            args.push("--check".into());
            checks.push((Self::program(Member::Critic), args));
        }
        checks
    }

    /// `run.json`: everything a client in another language needs to attach to the primary
    /// swarm, given its run directory.
    pub fn run_json(&self) -> serde_json::Value {
        let s = self.primary();
        let env = &self.config.env;
        let ticks = &self.config.ticks;
        serde_json::json!({
            "run_id": s.identity.run_id,
            "n_agents": s.n,
            "shm_prefix": s.identity.shm_prefix(),
            "root_path": format!("{}/", s.identity.root_path().display()),
            "iceoryx2_config": ICEORYX_CONFIG_FILE,
            "protocol_version": PROTOCOL_VERSION,
            "observation": env.observation.as_str(),
            "observation_dim": Layout::of(env.observation).dim(),
            "critic_window": ticks.critic_window,
            "startup_timeout_s": ticks.startup_timeout_s,
            "sim_silence_ms": ticks.sim_silence_ms,
            "command_timeout_ms": ticks.command_timeout_ms,
            "v_max": env.v_max,
            "w_max": env.w_max,
            "proximity_range_m": env.proximity_range_m,
            "mode": self.mode.as_str(),
            "external": s.external,
            "ros2": s.ros2,
            "extra_swarms": self.swarms[1..].iter().map(|x| serde_json::json!({
                "run_id": x.identity.run_id,
                "n_agents": x.n,
                "run_dir": x.run_dir,
            })).collect::<Vec<_>>(),
            "launcher_pid": std::process::id(),
        })
    }
}

/// Refuses `--updates` and `--extra-swarms` outside training, more than [`MAX_EXTRA_SWARMS`], and a `--config` or
/// `--checkpoint` that does not exist.
fn check_training_flags_and_files(args: &LaunchArgs) -> Result<()> {
    ensure!(
        args.updates.is_none() || args.mode == Mode::Train,
        "--updates is for training: an eval does no updates (give --episodes)"
    );
    if !args.extra_swarms.is_empty() {
        ensure!(
            args.mode == Mode::Train,
            "--extra-swarms is for training; evaluate each size on its own"
        );
        ensure!(
            args.extra_swarms.len() <= MAX_EXTRA_SWARMS,
            "--extra-swarms: at most {MAX_EXTRA_SWARMS} extra swarms"
        );
    }
    if let Some(path) = &args.config {
        ensure!(path.is_file(), "--config file {} does not exist", path.display());
    }
    if let Some(path) = &args.checkpoint {
        ensure!(path.exists(), "--checkpoint {} does not exist", path.display());
    }
    Ok(())
}

/// The configuration every member reads: `--config` (or the defaults) with `--reality`'s
/// `[reality]`, the `--shape` and the `--obstacles`; in training, checked for the seeds and the
/// critic. Among obstacles a swarm observes its range sensor (`slot_proximity_scan`) when the
/// config leaves the default model and no learned robot reads another: none is `learned`, or
/// they load the shipped obstacle model ([`shipped_model`]).
fn read_config(args: &LaunchArgs, learned: usize) -> Result<RunConfig> {
    let mut config = match &args.config {
        Some(path) => RunConfig::from_toml_file(path)?,
        None => RunConfig::default(),
    };
    if let Some(path) = &args.reality {
        config.reality = read_reality(path)?;
    }
    if let Some(shape) = args.shape {
        config.env.shape = shape;
    }
    if let Some(kind) = args.obstacles {
        config.env.obstacles.kind = kind;
    }
    if learned == 0 || loads_shipped_model(args, learned) {
        config.env.scan_among_obstacles();
    }
    if args.mode == Mode::Train {
        config.learn.check_training_seeds(args.seed, args.extra_swarms.len())?;
        config.check_training_critic()?;
        config.learn.check_imitation_start(args.checkpoint.is_some())?;
    }
    Ok(config)
}

/// Whether the `learned` robots load a shipped model: an eval without `--checkpoint`.
fn loads_shipped_model(args: &LaunchArgs, learned: usize) -> bool {
    learned > 0 && args.mode == Mode::Eval && args.checkpoint.is_none()
}

/// `--checkpoint`; without it, an eval with `learned` robots loads the shipped model of the
/// run's world.
fn checkpoint_to_load(args: &LaunchArgs, learned: usize, config: &RunConfig) -> Result<Option<PathBuf>> {
    Ok(match loads_shipped_model(args, learned) {
        true => Some(shipped_model(&config.env)?),
        false => args.checkpoint.clone(),
    })
}

/// The `--config` every member is given and, with `--reality` or `--obstacles`, the text to
/// write there first (LAUNCH_CONFIG_FILE in the run directory, by
/// [`Plan::write_launch_config`]).
fn members_config(args: &LaunchArgs, config: &RunConfig, run_dir: &Path) -> (Option<PathBuf>, Option<String>) {
    if args.reality.is_some() || args.obstacles.is_some() {
        (Some(run_dir.join(LAUNCH_CONFIG_FILE)), Some(config.to_toml()))
    } else {
        (args.config.clone(), None)
    }
}

/// The primary swarm's `--remote` robots, each on a host of its own (run id `<run_id>h<robot>`,
/// directory `host-<robot>`).
fn remote_hosts(remote: &[usize], run_id: &str, run_dir: &Path) -> Result<Vec<RemoteHost>> {
    remote
        .iter()
        .map(|&robot| {
            Ok(RemoteHost {
                robot,
                identity: RunIdentity::new(&format!("{run_id}h{robot}"))?,
                run_dir: run_dir.join(format!("host-{robot}")),
            })
        })
        .collect()
}

/// With remote robots: the endpoint the sim host's bridge listens on, a free local port.
fn bridge_endpoint(remote: &[RemoteHost]) -> Result<Option<String>> {
    if remote.is_empty() {
        Ok(None)
    } else {
        Ok(Some(format!("tcp/127.0.0.1:{}", free_local_port()?)))
    }
}

/// The primary swarm (every robot set, run id `run_id`, the run directory, `--seed`), then one
/// learned swarm per `--extra-swarms` size (run id `<run_id>x<k>`, directory `swarm-<k>-n<size>`,
/// its own seed).
fn swarms(
    args: &LaunchArgs,
    sets: RobotSets,
    remote: Vec<RemoteHost>,
    run_id: &str,
    run_dir: &Path,
) -> Result<Vec<Swarm>> {
    let mut swarms = vec![Swarm {
        n: args.n,
        identity: RunIdentity::new(run_id)?,
        run_dir: run_dir.to_path_buf(),
        seed: args.seed,
        scripted: sets.scripted,
        oracle: sets.oracle,
        external: sets.external,
        remote,
        ros2: sets.ros2,
    }];
    for (k, &size) in (1..).zip(&args.extra_swarms) {
        swarms.push(Swarm {
            n: size,
            identity: RunIdentity::new(&format!("{run_id}x{k}"))?,
            run_dir: run_dir.join(format!("swarm-{k}-n{size}")),
            seed: extra_swarm_seed(args.seed, k),
            scripted: Vec::new(),
            oracle: Vec::new(),
            external: Vec::new(),
            remote: Vec::new(),
            ros2: Vec::new(),
        });
    }
    Ok(swarms)
}

/// The `[reality]` section of `path`, validated; the file's other sections are not read.
/// Refusals name the file and the field.
fn read_reality(path: &Path) -> Result<RealityConfig> {
    /// Only the `[reality]` table of the file.
    #[derive(serde::Deserialize)]
    struct Section {
        reality: Option<RealityConfig>,
    }
    let text = std::fs::read_to_string(path).with_context(|| format!("--reality: cannot read {}", path.display()))?;
    let section: Section =
        toml::from_str(&text).map_err(|err| anyhow!("--reality file {} does not parse: {err}", path.display()))?;
    let reality = section
        .reality
        .with_context(|| format!("--reality file {} has no [reality] section", path.display()))?;
    reality
        .validate()
        .map_err(|err| anyhow!("--reality file {}: {err}", path.display()))?;
    Ok(reality)
}

/// Where the ROS 2 side meets ROS 2 nodes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Ros2Endpoint {
    /// Listen as a Zenoh peer (where rmw_zenoh nodes look for their router).
    Listen(String),
    /// Dial a Zenoh router.
    Connect(String),
}

/// `--ros2-namespace`, `--ros2-domain` and `--ros2-endpoint`.
#[derive(Debug, Clone)]
pub struct Ros2Link {
    /// The topics' namespace.
    pub namespace: String,
    /// ROS_DOMAIN_ID.
    pub domain: u32,
    /// Listen or dial.
    pub endpoint: Ros2Endpoint,
}

impl Ros2Link {
    fn new(args: &LaunchArgs) -> Result<Self> {
        let endpoint = match args.ros2_endpoint.strip_prefix("connect=") {
            Some(endpoint) => Ros2Endpoint::Connect(endpoint.to_string()),
            None => Ros2Endpoint::Listen(args.ros2_endpoint.clone()),
        };
        let locator = match &endpoint {
            Ros2Endpoint::Listen(locator) | Ros2Endpoint::Connect(locator) => locator,
        };
        ensure!(
            locator
                .split_once('/')
                .is_some_and(|(proto, addr)| !proto.is_empty() && !addr.is_empty()),
            "--ros2-endpoint takes a Zenoh endpoint like tcp/127.0.0.1:7447 or connect=tcp/10.0.0.2:7447, got {:?}",
            args.ros2_endpoint
        );
        ensure!(
            args.ros2_domain <= 232,
            "--ros2-domain must be a ROS_DOMAIN_ID, 0 to 232, got {}",
            args.ros2_domain
        );
        Ok(Self {
            namespace: args.ros2_namespace.clone(),
            domain: args.ros2_domain,
            endpoint,
        })
    }
}

/// Which robots are scripted, oracle, external, remote and ROS 2, checked against each other.
struct RobotSets {
    scripted: Vec<usize>,
    oracle: Vec<usize>,
    external: Vec<usize>,
    remote: Vec<usize>,
    ros2: Vec<usize>,
}

impl RobotSets {
    fn new(args: &LaunchArgs) -> Result<Self> {
        let n = args.n;
        let external_flag = args.external.as_deref().unwrap_or("");
        let external = parse_robot_set("--external", external_flag, n)?;
        ensure!(
            external_flag.trim().is_empty() || !external.is_empty(),
            "--external takes 'all' or indices like 0,2; got {external_flag:?}"
        );
        let ros2 = parse_robot_set("--ros2", args.ros2.as_deref().unwrap_or(""), n)?;
        let scripted_flag = args.scripted.as_deref().unwrap_or("");
        let mut scripted = parse_robot_set("--scripted", scripted_flag, n)?;
        if scripted_flag.trim() == "all" {
            // `--scripted all --external 2`: every robot this launcher starts is scripted.
            scripted.retain(|robot| !external.contains(robot) && !ros2.contains(robot));
        } else if let Some(both) = scripted.iter().find(|robot| external.contains(robot)) {
            bail!("robot {both} cannot be both --scripted and --external");
        } else if let Some(both) = scripted.iter().find(|robot| ros2.contains(robot)) {
            bail!("robot {both} cannot be both --scripted and --ros2");
        }
        if let Some(both) = ros2.iter().find(|robot| external.contains(robot)) {
            bail!("robot {both} cannot be both --ros2 and --external");
        }
        let oracle_flag = args.oracle.as_deref().unwrap_or("");
        let mut oracle = parse_robot_set("--oracle", oracle_flag, n)?;
        let remote_robots = parse_robot_set("--remote", args.remote.as_deref().unwrap_or(""), n)?;
        if oracle_flag.trim() == "all" {
            // `--oracle all --scripted 1`: the planner drives every other robot this launcher starts.
            ensure!(
                scripted_flag.trim() != "all",
                "--oracle all and --scripted all name the same robots"
            );
            oracle.retain(|robot| {
                !external.contains(robot)
                    && !ros2.contains(robot)
                    && !scripted.contains(robot)
                    && !remote_robots.contains(robot)
            });
        } else {
            for (flag, set) in [
                ("--external", &external),
                ("--ros2", &ros2),
                ("--remote", &remote_robots),
            ] {
                if let Some(both) = oracle.iter().find(|robot| set.contains(robot)) {
                    bail!(
                        "robot {both} cannot be both --oracle and {flag} (the planner reads the sim's true state on the sim's host)"
                    );
                }
            }
            if scripted_flag.trim() == "all" {
                scripted.retain(|robot| !oracle.contains(robot));
            } else if let Some(both) = oracle.iter().find(|robot| scripted.contains(robot)) {
                bail!("robot {both} cannot be both --oracle and --scripted");
            }
        }
        let remote_flag = args.remote.as_deref().unwrap_or("");
        let remote = parse_robot_set("--remote", remote_flag, n)?;
        if let Some(both) = remote.iter().find(|robot| external.contains(robot)) {
            bail!("robot {both} cannot be both --remote and --external");
        }
        if let Some(both) = remote.iter().find(|robot| ros2.contains(robot)) {
            bail!("robot {both} cannot be both --remote and --ros2");
        }
        ensure!(
            remote.is_empty() || args.extra_swarms.is_empty(),
            "--remote is for the primary swarm only; leave out --extra-swarms"
        );
        ensure!(
            !remote.is_empty() || (args.net_delay_ms == 0.0 && args.net_loss == 0.0),
            "--net-delay-ms and --net-loss emulate the link of --remote robots; name them with --remote"
        );
        Ok(Self {
            scripted,
            oracle,
            external,
            remote,
            ros2,
        })
    }
}

/// A clap value's spelling on the command line.
fn value_name(value: impl ValueEnum) -> String {
    value
        .to_possible_value()
        .map(|v| v.get_name().to_string())
        .unwrap_or_default()
}

/// A TCP port on 127.0.0.1 that is free now (the OS picks it; the bridge binds it a moment later).
fn free_local_port() -> Result<u16> {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").context("cannot find a free local port")?;
    Ok(listener.local_addr()?.port())
}

/// The model shipped with the repository for the run's world, any N and any `[reality]`
/// ([`EnvConfig::shipped_model_file`]): in the open arena `models/formation.safetensors`
/// (trained under randomised reality; it does not see obstacles), among obstacles a model that
/// reads the range sensor: `models/formation-obstacles-passage.safetensors` in the passage,
/// `models/formation-obstacles.safetensors` (trained in mixed episodes) otherwise (models/README.md).
fn shipped_model(env: &EnvConfig) -> Result<PathBuf> {
    let name = env.shipped_model_file();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models").join(name);
    ensure!(
        path.is_file(),
        "eval with learned robots needs --checkpoint (no shipped model at {})",
        path.display()
    );
    path.canonicalize().context("cannot resolve the shipped model's path")
}

/// A run id unique on this machine: the clock's last six digits of seconds and this pid.
fn new_run_id() -> String {
    let seconds = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
    format!("r{:06}p{}", seconds % 1_000_000, std::process::id())
}

/// `runs/<local date-time>`.
fn default_run_dir() -> PathBuf {
    let now = SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let time = now as libc::time_t;
    // SAFETY: localtime_r writes only into `tm`, which lives on this stack frame.
    let mut tm: libc::tm = unsafe { std::mem::zeroed() };
    let stamp = if unsafe { libc::localtime_r(&time, &mut tm) }.is_null() {
        now.to_string()
    } else {
        format!(
            "{:04}{:02}{:02}-{:02}{:02}{:02}",
            tm.tm_year + 1900,
            tm.tm_mon + 1,
            tm.tm_mday,
            tm.tm_hour,
            tm.tm_min,
            tm.tm_sec
        )
    };
    PathBuf::from("runs").join(stamp)
}

/// spawn when a `rerun` viewer is on PATH and a display is present, else save.
fn default_viewer() -> ViewerMode {
    let display = ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|name| std::env::var_os(name).is_some_and(|v| !v.is_empty()));
    let rerun_on_path = std::env::var_os("PATH")
        .is_some_and(|path| std::env::split_paths(&path).any(|dir| dir.join("rerun").is_file()));
    let mode = if display && rerun_on_path {
        ViewerMode::Spawn
    } else {
        ViewerMode::Save
    };
    println!(
        "viewer: {} (choose with --viewer spawn|save|off|connect=URL)",
        mode.as_arg()
    );
    mode
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    fn plan(args: &[&str]) -> Result<Plan> {
        let args = LaunchArgs::try_parse_from(std::iter::once("formation").chain(args.iter().copied()))?;
        Plan::new(args)
    }

    /// A file of the repository, as a path argument.
    fn repo_path(relative: &str) -> String {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .join(relative)
            .to_string_lossy()
            .into_owned()
    }

    #[test]
    fn every_started_robot_and_one_sim_per_swarm_are_members_and_the_primary_sim_starts_last() {
        let plan = plan(&["4", "--external", "1", "--extra-swarms", "3", "--viewer", "off"]).expect("plan");
        let members = plan.members();
        assert_eq!(members.first(), Some(&Member::Critic));
        assert_eq!(members.last(), Some(&Member::Sim { swarm: 0 }));
        let primary_robots: Vec<usize> = members
            .iter()
            .filter_map(|m| match m {
                Member::Robot { swarm: 0, index } => Some(*index),
                _ => None,
            })
            .collect();
        assert_eq!(primary_robots, vec![0, 2, 3], "the external robot is not started");
        assert_eq!(
            members
                .iter()
                .filter(|m| matches!(m, Member::Robot { swarm: 1, .. }))
                .count(),
            3
        );
        assert_eq!(plan.restart_policy(Member::Sim { swarm: 0 }), Restart::EndsTheRun);
        assert_eq!(plan.restart_policy(Member::Critic), Restart::OnFailureResuming);
        assert_eq!(
            plan.restart_policy(Member::Robot { swarm: 1, index: 0 }),
            Restart::OnFailure
        );
        assert_eq!(plan.restart_policy(Member::Sim { swarm: 1 }), Restart::Never);
    }

    #[test]
    fn restart_off_leaves_every_member_but_the_primary_sim_ended() {
        let plan = plan(&["3", "--restart", "off", "--viewer", "off"]).expect("plan");
        for member in plan.members() {
            let expected = if member == (Member::Sim { swarm: 0 }) {
                Restart::EndsTheRun
            } else {
                Restart::Never
            };
            assert_eq!(plan.restart_policy(member), expected, "{member:?}");
        }
    }

    #[test]
    fn scripted_all_with_an_external_robot_scripts_the_others_and_the_sim_is_told_both() {
        let plan = plan(&[
            "3",
            "--mode",
            "eval",
            "--scripted",
            "all",
            "--external",
            "2",
            "--viewer",
            "off",
        ])
        .expect("plan");
        assert_eq!(plan.primary().scripted, vec![0, 1]);
        let sim: Vec<String> = plan
            .args(Member::Sim { swarm: 0 }, None, None)
            .iter()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        let after = |flag: &str| sim.iter().position(|a| a == flag).map(|i| sim[i + 1].clone());
        assert_eq!(after("--scripted").as_deref(), Some("0,1"));
        assert_eq!(after("--external").as_deref(), Some("2"));
        assert!(plan.checkpoint.is_none(), "no learned robot: no model needed");
        assert!(plan.preflight().is_empty());
    }

    #[test]
    fn training_an_mlp_critic_on_changing_formations_is_refused_naming_both_fields() {
        let dir = std::env::temp_dir().join(format!("formation-plan-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let changing = dir.join("changing.toml");
        std::fs::write(&changing, "[env]\nshape_changes = 2\n").expect("config");
        let config = changing.to_string_lossy().into_owned();
        let err = plan(&["6", "--config", &config, "--viewer", "off"]).expect_err("mlp with changes");
        let message = format!("{err:#}");
        assert!(
            message.contains("learn.critic") && message.contains("env.shape_changes"),
            "{message}"
        );
        // An evaluation trains no critic; a pooled critic learns changing formations.
        assert!(
            plan(&[
                "6",
                "--mode",
                "eval",
                "--scripted",
                "all",
                "--config",
                &config,
                "--viewer",
                "off"
            ])
            .is_ok()
        );
        let pooled = dir.join("pooled.toml");
        std::fs::write(&pooled, "[env]\nshape_changes = 2\n\n[learn]\ncritic = \"pooled\"\n").expect("config");
        let pooled = pooled.to_string_lossy().into_owned();
        assert!(plan(&["6", "--config", &pooled, "--viewer", "off"]).is_ok());
        std::fs::remove_dir_all(&dir).expect("clean up");
    }

    /// The flags `member` of `plan` starts with, as text.
    fn text_of(plan: &Plan, member: Member) -> Vec<String> {
        plan.args(member, None, None)
            .iter()
            .map(|a| a.to_string_lossy().into_owned())
            .collect()
    }

    #[test]
    fn record_mcap_starts_the_recorder_first_never_restarted_with_the_ros2_namespace() {
        let plain = plan(&["3", "--mode", "eval", "--scripted", "all", "--viewer", "off"]).expect("plan");
        assert!(!plain.members().contains(&Member::Mcap));
        let recorded = plan(&[
            "3",
            "--mode",
            "eval",
            "--scripted",
            "all",
            "--viewer",
            "off",
            "--record",
            "mcap",
            "--ros2-namespace",
            "lab",
        ])
        .expect("plan");
        let members = recorded.members();
        assert_eq!(members[0], Member::Mcap, "started before anything else");
        assert_eq!(members.iter().filter(|&&m| m == Member::Mcap).count(), 1);
        assert_eq!(Plan::program(Member::Mcap), "formation-mcap");
        assert_eq!(recorded.restart_policy(Member::Mcap), Restart::Never);
        let args = text_of(&recorded, Member::Mcap);
        assert!(args.windows(2).any(|w| w == ["--namespace", "lab"]), "{args:?}");
        assert!(args.windows(2).any(|w| w == ["--mode", "eval"]), "{args:?}");
        // The sim waits for the recorder as for the critic, so the file loses no state.
        assert!(text_of(&recorded, Member::Sim { swarm: 0 }).contains(&"--expect-recorder".to_string()));
        assert!(!text_of(&plain, Member::Sim { swarm: 0 }).contains(&"--expect-recorder".to_string()));
        assert!(plan(&["3", "--record", "bag"]).is_err());
    }

    #[test]
    fn ros2_robots_are_carried_by_one_ros2_member_need_no_checkpoint_and_conflict_with_other_roles() {
        let carried = plan(&[
            "4",
            "--mode",
            "eval",
            "--scripted",
            "all",
            "--ros2",
            "1,3",
            "--viewer",
            "off",
        ])
        .expect("plan");
        assert_eq!(
            carried.primary().scripted,
            vec![0, 2],
            "scripted all leaves the ROS 2 robots"
        );
        assert_eq!(carried.primary().ros2, vec![1, 3]);
        let members = carried.members();
        assert!(members.contains(&Member::Ros2));
        assert!(!members.contains(&Member::Robot { swarm: 0, index: 1 }));
        assert!(!members.contains(&Member::Robot { swarm: 0, index: 3 }));
        assert!(carried.checkpoint.is_none(), "no learned robot: no model needed");
        assert!(carried.preflight().is_empty());
        assert_eq!(Plan::program(Member::Ros2), "formation-ros2");
        assert_eq!(carried.restart_policy(Member::Ros2), Restart::OnFailure);
        let args = text_of(&carried, Member::Ros2);
        for pair in [
            ["--robots", "1,3"],
            ["--namespace", "formation"],
            ["--domain", "0"],
            ["--listen", "tcp/127.0.0.1:7447"],
        ] {
            assert!(args.windows(2).any(|w| w == pair), "{pair:?} in {args:?}");
        }
        assert_eq!(carried.run_json()["ros2"], serde_json::json!([1, 3]));

        let dialled = plan(&[
            "3",
            "--mode",
            "eval",
            "--scripted",
            "0,1",
            "--ros2",
            "2",
            "--ros2-namespace",
            "lab",
            "--ros2-domain",
            "7",
            "--ros2-endpoint",
            "connect=tcp/10.0.0.2:7447",
            "--viewer",
            "off",
        ])
        .expect("plan");
        let args = text_of(&dialled, Member::Ros2);
        for pair in [
            ["--connect", "tcp/10.0.0.2:7447"],
            ["--namespace", "lab"],
            ["--domain", "7"],
        ] {
            assert!(args.windows(2).any(|w| w == pair), "{pair:?} in {args:?}");
        }
        assert!(dialled.checkpoint.is_none());

        for (args, needle) in [
            (
                vec!["3", "--scripted", "1,2", "--ros2", "2"],
                "robot 2 cannot be both --scripted and --ros2",
            ),
            (
                vec!["3", "--external", "2", "--ros2", "2"],
                "robot 2 cannot be both --ros2 and --external",
            ),
            (
                vec!["3", "--remote", "0,2", "--ros2", "2"],
                "robot 2 cannot be both --remote and --ros2",
            ),
            (vec!["3", "--ros2", "3"], "--ros2: robot 3 does not exist"),
            (
                vec!["3", "--ros2", "2", "--ros2-endpoint", "7447"],
                "--ros2-endpoint takes a Zenoh endpoint",
            ),
            (
                vec!["3", "--ros2", "2", "--ros2-domain", "300"],
                "--ros2-domain must be",
            ),
        ] {
            let refusal = plan(&args).expect_err(needle);
            assert!(format!("{refusal:#}").contains(needle), "{args:?}: {refusal:#}");
        }
    }

    #[test]
    fn eval_with_learned_robots_defaults_to_the_shipped_model_and_checks_it_once() {
        let ideal = plan(&["5", "--mode", "eval", "--viewer", "off"]).expect("plan");
        let model = ideal.checkpoint.clone().expect("shipped model");
        assert!(model.ends_with("models/formation.safetensors"));
        // Under a reality, the same model: it was trained under randomised reality.
        let field = repo_path("configs/reality-field.toml");
        let real = plan(&["5", "--mode", "eval", "--viewer", "off", "--reality", &field]).expect("plan");
        let model = real.checkpoint.clone().expect("shipped model");
        assert!(model.ends_with("models/formation.safetensors"), "{model:?}");
        // A checkpoint given is used in any world.
        let given = repo_path("models/formation.safetensors");
        let chosen = plan(&[
            "5",
            "--mode",
            "eval",
            "--viewer",
            "off",
            "--reality",
            &field,
            "--checkpoint",
            &given,
        ])
        .expect("plan");
        assert_eq!(chosen.checkpoint.as_deref(), Some(Path::new(&given)));
        let checks = ideal.preflight();
        assert_eq!(checks.len(), 1);
        let (program, args) = &checks[0];
        assert_eq!(*program, "formation-agent");
        let text: Vec<String> = args.iter().map(|a| a.to_string_lossy().into_owned()).collect();
        assert!(text.windows(2).any(|w| w == ["--agent", "4"]), "{text:?}");
        assert!(text.contains(&"--check".to_string()));
    }

    #[test]
    fn among_obstacles_an_eval_loads_the_obstacle_policy_and_observes_its_range_sensor() {
        use formation_core::config::ObservationModel;
        for kind in ["forest", "passage", "trap", "mixed"] {
            let plan = plan(&["4", "--mode", "eval", "--viewer", "off", "--obstacles", kind]).expect("plan");
            let model = plan.checkpoint.clone().expect("a shipped model");
            let shipped = match kind {
                "passage" => "models/formation-obstacles-passage.safetensors",
                _ => "models/formation-obstacles.safetensors",
            };
            assert!(model.ends_with(shipped), "{kind}: {model:?}");
            assert_eq!(
                plan.config.env.observation,
                ObservationModel::SlotProximityScan,
                "{kind}"
            );
        }
        // A checkpoint given keeps the config's model (the run refuses a mismatch at start).
        let given = repo_path("models/formation.safetensors");
        let chosen = plan(&[
            "4",
            "--mode",
            "eval",
            "--viewer",
            "off",
            "--obstacles",
            "forest",
            "--checkpoint",
            &given,
        ])
        .expect("plan");
        assert_eq!(chosen.checkpoint.as_deref(), Some(Path::new(&given)));
        assert_eq!(chosen.config.env.observation, ObservationModel::default());
    }

    #[test]
    fn updates_go_to_the_critic_and_leave_the_sims_without_a_time_limit() {
        let strings =
            |args: Vec<OsString>| -> Vec<String> { args.iter().map(|a| a.to_string_lossy().into_owned()).collect() };
        let open_ended = plan(&["3", "--updates", "5000", "--viewer", "off"]).expect("plan");
        let critic = strings(open_ended.args(Member::Critic, None, None));
        assert!(critic.windows(2).any(|w| w == ["--updates", "5000"]), "{critic:?}");
        let sim = strings(open_ended.args(Member::Sim { swarm: 0 }, None, None));
        assert!(sim.contains(&"--open-ended".to_string()), "{sim:?}");
        assert!(!sim.contains(&"--minutes".to_string()), "{sim:?}");
        // With --minutes too, whichever comes first ends the run.
        let capped = plan(&["3", "--updates", "5000", "--minutes", "10", "--viewer", "off"]).expect("plan");
        let sim = strings(capped.args(Member::Sim { swarm: 0 }, None, None));
        assert!(sim.windows(2).any(|w| w == ["--minutes", "10"]), "{sim:?}");
        assert!(!sim.contains(&"--open-ended".to_string()), "{sim:?}");
        let err = plan(&["3", "--updates", "5000", "--mode", "eval"]).expect_err("eval does no updates");
        assert!(format!("{err:#}").contains("--updates is for training"), "{err:#}");
    }

    #[test]
    fn a_restarted_critic_resumes_and_counts_down_what_is_left() {
        let plan = plan(&["3", "--viewer", "off"]).expect("plan");
        let args: Vec<String> = plan
            .args(
                Member::Critic,
                Some(Path::new("runs/x/checkpoint.safetensors")),
                Some(2.5),
            )
            .iter()
            .map(|a| a.to_string_lossy().into_owned())
            .collect();
        assert!(
            args.windows(2)
                .any(|w| w == ["--checkpoint", "runs/x/checkpoint.safetensors"])
        );
        assert!(args.windows(2).any(|w| w == ["--minutes", "2.500"]));
    }

    #[test]
    fn conflicting_or_impossible_flags_are_refused_by_name() {
        // Training towards the actor it starts from needs one to start from.
        let anchored = repo_path("configs/obstacles-mixed-anchored.toml");
        let start = repo_path("models/formation-obstacles.safetensors");
        plan(&["3", "--config", &anchored, "--checkpoint", &start]).expect("a start given");
        for (args, needle) in [
            (
                vec!["3", "--scripted", "0,2", "--external", "2"],
                "cannot be both --scripted and --external",
            ),
            (vec!["3", "--external", "3"], "robot 3 does not exist (robots are 0..2)"),
            (vec!["3", "--extra-swarms", "4", "--mode", "eval"], "for training"),
            (vec!["3", "--config", "/nonexistent.toml"], "does not exist"),
            (vec!["3", "--viewer", "window"], "--viewer must be"),
            (vec!["2"], "between 3 and 64"),
            (vec!["3", "--extra-swarms", "4,2"], "sizes 3 to 64"),
            (vec!["3", "--minutes", "0"], "--minutes must be a positive number"),
            (
                vec!["3", "--seed", "1000"],
                "the run (--seed 1000) would train on seed 1000",
            ),
            (vec!["3", "--seed", "6168263"], "learn.selection_seed"),
            (vec!["3", "--config", &anchored], "learn.imitation_teacher = \"start\""),
            (
                vec!["3", "--seed", "6160344", "--extra-swarms", "4,5"],
                "extra swarm 1 (--seed 6160344 + 7919 x 1) would train on seed 6168263",
            ),
        ] {
            let refusal = plan(&args).expect_err(needle);
            assert!(format!("{refusal:#}").contains(needle), "{args:?}: {refusal:#}");
        }
    }

    #[test]
    fn run_json_carries_the_contract_of_the_configured_observation() {
        let plan = plan(&["6", "--viewer", "off"]).expect("plan");
        let json = plan.run_json();
        assert_eq!(json["n_agents"], 6);
        assert_eq!(json["protocol_version"], PROTOCOL_VERSION);
        assert_eq!(json["observation_dim"], Layout::of(plan.config.env.observation).dim());
        let root = json["root_path"].as_str().expect("root path");
        assert!(root.ends_with(&format!("/formation-iox2/{}/", plan.primary().identity.run_id)));
    }

    /// A directory of this test's own under the system's temp dir, removed when dropped.
    struct Scratch(PathBuf);

    impl Scratch {
        fn new(name: &str) -> Self {
            let dir = std::env::temp_dir().join(format!("formation-launcher-{name}-{}", std::process::id()));
            std::fs::create_dir_all(&dir).expect("scratch dir");
            Self(dir)
        }

        fn file(&self, name: &str, text: &str) -> String {
            let path = self.0.join(name);
            std::fs::write(&path, text).expect("scratch file");
            path.to_string_lossy().into_owned()
        }
    }

    impl Drop for Scratch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    #[test]
    fn a_reality_file_replaces_the_configs_reality_and_every_member_reads_the_result() {
        use formation_core::reality::Spread;

        let scratch = Scratch::new("reality");
        let config = scratch.file("config.toml", "[env]\nmax_steps = 90\n[reality]\ncommand_loss = 0.2\n");
        let reality = scratch.file(
            "reality.toml",
            "# a preset\n[reality]\nposition_noise_m = [0.05, 0.1]\nactuation_delay_ticks = 2\n[env]\nmax_steps = 5\n",
        );
        let run_dir = scratch.0.join("run");
        let run_dir_arg = run_dir.to_string_lossy().into_owned();
        let plan = plan(&[
            "3",
            "--mode",
            "eval",
            "--scripted",
            "all",
            "--viewer",
            "off",
            "--config",
            &config,
            "--reality",
            &reality,
            "--run-dir",
            &run_dir_arg,
        ])
        .expect("plan");
        let given = &plan.config.reality;
        assert_eq!(given.position_noise_m, Spread::range(0.05, 0.1));
        assert_eq!(given.actuation_delay_ticks, Spread::fixed(2.0));
        assert!(
            given.command_loss.is_off(),
            "the whole [reality] of --config is replaced"
        );
        assert_eq!(plan.config.env.max_steps, 90, "only the file's [reality] is read");

        let launch_config = run_dir.join(LAUNCH_CONFIG_FILE);
        for member in plan.members() {
            let args: Vec<String> = plan
                .args(member, None, None)
                .iter()
                .map(|a| a.to_string_lossy().into_owned())
                .collect();
            let given_config = args.windows(2).find(|w| w[0] == "--config").map(|w| w[1].clone());
            assert_eq!(given_config.as_deref(), launch_config.to_str(), "{member:?}");
        }
        assert!(!launch_config.exists(), "the plan creates nothing");
        plan.write_launch_config().expect("written");
        assert_eq!(RunConfig::from_toml_file(&launch_config).expect("loads"), plan.config);
    }

    #[test]
    fn bad_reality_files_are_refused_naming_the_file_and_the_field() {
        let scratch = Scratch::new("bad-reality");
        for (text, needle) in [
            (
                "[reality]\ncommand_loss = 1.5\n",
                "reality.command_loss = 1.5 is invalid",
            ),
            (
                "[reality]\nactuation_delay_ticks = [3, 1]\n",
                "reality.actuation_delay_ticks",
            ),
            ("[reality]\nposition_noise_m = -0.1\n", "reality.position_noise_m"),
            ("[reality]\ncomand_loss = 0.1\n", "unknown field `comand_loss`"),
            ("[reality]\ndead_robot = \"brake\"\n", "dead_robot"),
            ("[env]\nmax_steps = 90\n", "has no [reality] section"),
        ] {
            let path = scratch.file("reality.toml", text);
            let refusal = plan(&["3", "--viewer", "off", "--reality", &path]).expect_err(needle);
            let message = format!("{refusal:#}");
            assert!(message.contains(needle), "{text:?}: {message}");
            assert!(message.contains(&path), "{text:?} names the file: {message}");
        }
        let missing = scratch.0.join("missing.toml").to_string_lossy().into_owned();
        let refusal = plan(&["3", "--viewer", "off", "--reality", &missing]).expect_err("missing");
        assert!(format!("{refusal:#}").contains(&format!("--reality: cannot read {missing}")));
    }
}
