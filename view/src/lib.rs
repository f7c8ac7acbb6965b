//! The run's one Rerun recording: every process that logs (the sim's world view, the critic's
//! curves) opens its stream here with the same application and recording id, so a viewer shows
//! them as one recording.

use std::path::Path;

use anyhow::{Context, Result, bail};
use rerun::{RecordingStream, RecordingStreamBuilder};

/// Application id shared by every process of a run, so sim and critic land in one recording.
pub const APPLICATION_ID: &str = "formation-control";

/// Where the recording goes.
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

    /// Opens a recording stream for this mode (`None` when off). `spawn_viewer` is false for
    /// the processes that only join a viewer the sim spawned.
    pub fn open(
        &self,
        run_id: &str,
        run_dir: &Path,
        stem: &str,
        spawn_viewer: bool,
    ) -> Result<Option<RecordingStream>> {
        let builder = RecordingStreamBuilder::new(APPLICATION_ID).recording_id(run_id.to_string());
        let stream = match self {
            Self::Off => return Ok(None),
            Self::Save => builder.save(run_dir.join(format!("{stem}.rrd")))?,
            Self::Connect(url) => builder.connect_grpc_opts(url.clone())?,
            Self::Spawn if spawn_viewer => builder
                .spawn()
                .context("cannot start the `rerun` viewer (pip install rerun-sdk==0.36.3)")?,
            Self::Spawn => builder.connect_grpc()?,
        };
        Ok(Some(stream))
    }
}
