//! What every process writes into the run directory: the configuration as run, and files
//! replaced atomically so a reader never sees half of one.

use std::path::Path;

use anyhow::{Context, Result};

use crate::config::RunConfig;

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
