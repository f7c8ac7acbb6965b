//! The run's one Rerun recording: every process that logs (the sim's world view, the critic's
//! curves) opens its stream here with the same application and recording id, so a viewer shows
//! them as one recording.

use std::path::Path;

use anyhow::{Context, Result};
use formation_ipc::cli::ViewerMode;
use rerun::{RecordingStream, RecordingStreamBuilder};

/// Application id shared by every process of a run, so sim and critic land in one recording.
pub const APPLICATION_ID: &str = "formation-control";

/// Opens the recording stream of `mode` (`None` when off). `spawn_viewer` is false for the
/// processes that only join a viewer the sim spawned.
pub fn open_recording(
    mode: &ViewerMode,
    run_id: &str,
    run_dir: &Path,
    stem: &str,
    spawn_viewer: bool,
) -> Result<Option<RecordingStream>> {
    let builder = RecordingStreamBuilder::new(APPLICATION_ID).recording_id(run_id.to_string());
    let stream = match mode {
        ViewerMode::Off => return Ok(None),
        ViewerMode::Save => builder.save(run_dir.join(format!("{stem}.rrd")))?,
        ViewerMode::Connect(url) => builder.connect_grpc_opts(url.clone())?,
        ViewerMode::Spawn if spawn_viewer => builder
            .spawn()
            .context("cannot start the `rerun` viewer (pip install rerun-sdk==0.36.3)")?,
        ViewerMode::Spawn => builder.connect_grpc()?,
    };
    Ok(Some(stream))
}
