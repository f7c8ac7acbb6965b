//! Flags every process of a run shares (one spelling everywhere).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::{Args, ValueEnum};

use crate::config::{FormationShape, RunConfig, validate_agent_count};
use crate::placement::{self, Placement, Role};
use crate::services::RunIdentity;

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

/// Creates the run directory and writes the configuration as run into it.
pub fn prepare_run_dir(run_dir: &Path, config: &RunConfig) -> Result<()> {
    std::fs::create_dir_all(run_dir).with_context(|| format!("cannot create run directory {}", run_dir.display()))?;
    let path = run_dir.join("config.toml");
    std::fs::write(&path, config.to_toml()).with_context(|| format!("cannot write {}", path.display()))
}

/// Writes `contents` to `path` atomically (write a temporary file, then rename).
pub fn write_atomically(path: &Path, contents: &[u8]) -> Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, contents).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot rename {} to {}", tmp.display(), path.display()))
}
