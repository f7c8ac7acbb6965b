//! Flags every process of a run shares (one spelling everywhere).

use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::{Args, ValueEnum};

use crate::placement::{self, Placement, Role};
use crate::services::RunIdentity;
use formation_core::config::{FormationShape, RunConfig, validate_agent_count};

/// What a training critic given `--updates` prints, on a line of its own, once it has done them:
/// the launcher, reading the critic's output, then asks every sim to end the run.
pub const UPDATE_BUDGET_SPENT: &str = "formation-critic: the update budget is spent; ending the run";

/// Train (explore, learn, checkpoint) or evaluate (no noise, no learning).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Agents explore, the critic learns and streams weights back.
    Train,
    /// Agents act without noise; the critic only records.
    Eval,
}

impl Mode {
    /// Lower-case name as written in files.
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Train => "train",
            Mode::Eval => "eval",
        }
    }
}

/// Where the run's Rerun recording goes (`--viewer` of the sim, the critic and the launcher).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ViewerMode {
    /// Start the `rerun` viewer from PATH and stream to it.
    Spawn,
    /// Write `<stem>.rrd` into the run directory.
    Save,
    /// No recording.
    Off,
    /// Stream to a running viewer at this URL.
    Connect(String),
}

impl ViewerMode {
    /// Parses `spawn`, `save`, `off` or `connect=URL`.
    pub fn parse(text: &str) -> Result<Self> {
        Ok(match text {
            "spawn" => Self::Spawn,
            "save" => Self::Save,
            "off" => Self::Off,
            other => match other.strip_prefix("connect=") {
                Some(url) if !url.is_empty() => Self::Connect(url.to_string()),
                _ => bail!("--viewer must be spawn, save, off or connect=URL, got {other:?}"),
            },
        })
    }

    /// The flag's spelling, as [`ViewerMode::parse`] reads it.
    pub fn as_arg(&self) -> String {
        match self {
            Self::Spawn => "spawn".into(),
            Self::Save => "save".into(),
            Self::Off => "off".into(),
            Self::Connect(url) => format!("connect={url}"),
        }
    }
}

/// Robots named by a flag such as `--scripted` or `--external`: empty or `none`, `all`, or
/// indices like `0,2`. Returns them sorted; `flag` names the flag in errors.
pub fn parse_robot_set(flag: &str, text: &str, n_agents: usize) -> Result<Vec<usize>> {
    let robots: Vec<usize> = match text.trim() {
        "" | "none" => return Ok(Vec::new()),
        "all" => return Ok((0..n_agents).collect()),
        list => list
            .split(',')
            .map(|part| {
                part.trim()
                    .parse()
                    .map_err(|_| anyhow::anyhow!("{flag} takes 'all' or indices like 0,2; got {text:?}"))
            })
            .collect::<Result<_>>()?,
    };
    let mut sorted = Vec::with_capacity(robots.len());
    for robot in robots {
        if robot >= n_agents {
            bail!("{flag}: robot {robot} does not exist (robots are 0..{})", n_agents - 1);
        }
        if sorted.contains(&robot) {
            bail!("{flag}: robot {robot} is named twice");
        }
        sorted.push(robot);
    }
    sorted.sort_unstable();
    Ok(sorted)
}

/// The spelling of a robot set for a flag: `0,2` (empty for none).
pub fn robot_set_arg(robots: &[usize]) -> String {
    robots.iter().map(usize::to_string).collect::<Vec<_>>().join(",")
}

/// Flags shared by sim, agent and critic.
#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// Robots in the swarm (3 to 64).
    #[arg(long, default_value_t = 3)]
    pub agents: usize,
    /// train: explore and learn; eval: act without noise and only record.
    #[arg(long, value_enum, default_value_t = Mode::Train)]
    pub mode: Mode,
    /// Run id: every process of one run must use the same; it names the run's iceoryx2
    /// shared memory (`/dev/shm/fc_<id>_*`) so runs never collide.
    #[arg(long, default_value = "default")]
    pub run_id: String,
    /// Run directory for results; created if missing.
    #[arg(long, default_value = "runs/manual")]
    pub run_dir: PathBuf,
    /// TOML file of overrides of the defaults (see `config.toml` in any run directory).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Seed for episodes, noise and network initialisation.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// CPU placement: auto keeps the sim's tick thread and the robots on one CPU and the
    /// critic on the others (a tick is a chain of wake-ups, cheapest on one CPU; swarms of 24
    /// or more split their robots into groups of at least 12 per CPU); off leaves placement to
    /// the operating system.
    #[arg(long, value_enum, default_value_t = Placement::Auto)]
    pub placement: Placement,
    /// Formation shape of every episode (overrides `env.shape` of the config): random rigid
    /// shapes, or a named one drawn at a random size and orientation.
    #[arg(long, value_enum)]
    pub shape: Option<FormationShape>,
}

impl RunArgs {
    /// Validates the flags and loads the configuration.
    pub fn load(&self) -> Result<(RunIdentity, RunConfig)> {
        validate_agent_count(self.agents)?;
        let identity = RunIdentity::new(&self.run_id)?;
        let mut config = match &self.config {
            Some(path) => RunConfig::from_toml_file(path)?,
            None => RunConfig::default(),
        };
        if let Some(shape) = self.shape {
            config.env.shape = shape;
        }
        Ok((identity, config))
    }

    /// Moves the calling thread (and the threads it starts later) to the CPUs `--placement`
    /// gives `role`; returns them, if any.
    pub fn place(&self, role: Role) -> Result<Option<Vec<usize>>> {
        placement::apply(self.placement, role)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robot_sets_read_all_none_and_lists_and_refuse_strangers() {
        assert_eq!(
            parse_robot_set("--scripted", "", 3).expect("empty"),
            Vec::<usize>::new()
        );
        assert_eq!(parse_robot_set("--scripted", "all", 3).expect("all"), vec![0, 1, 2]);
        assert_eq!(parse_robot_set("--scripted", "2, 0", 3).expect("list"), vec![0, 2]);
        let stranger = parse_robot_set("--external", "0,3", 3).expect_err("robot 3");
        assert!(
            stranger
                .to_string()
                .contains("robot 3 does not exist (robots are 0..2)"),
            "{stranger}"
        );
        let twice = parse_robot_set("--external", "1,1", 3).expect_err("twice");
        assert!(twice.to_string().contains("named twice"), "{twice}");
        let word = parse_robot_set("--external", "x", 3).expect_err("word");
        assert!(word.to_string().contains("--external takes 'all' or indices"), "{word}");
        assert_eq!(robot_set_arg(&[0, 2]), "0,2");
    }

    #[test]
    fn viewer_modes_round_trip_through_their_flag() {
        for text in ["spawn", "save", "off", "connect=rerun+http://127.0.0.1:9876/proxy"] {
            assert_eq!(ViewerMode::parse(text).expect(text).as_arg(), text);
        }
        assert!(ViewerMode::parse("connect=").is_err());
        assert!(ViewerMode::parse("window").is_err());
    }
}
