//! The critic's curves in the run's Rerun recording (paper Fig. 4 and the losses), on the
//! `episode` timeline, beside the sim's world view.

use std::path::Path;

use anyhow::Result;
use formation_ipc::cli::ViewerMode;
use rerun::RecordingStream;

/// Training curves of one run.
pub struct CurveView {
    stream: RecordingStream,
}

impl CurveView {
    /// Joins the run's recording (`training.rrd` in save mode); `None` when the viewer is off.
    pub fn open(mode: &ViewerMode, run_id: &str, run_dir: &Path) -> Result<Option<Self>> {
        let Some(stream) = formation_view::open_recording(mode, run_id, run_dir, "training", false)? else {
            return Ok(None);
        };
        for (path, name, colour) in [
            ("plots/training/episode_reward", "episode reward", [0, 90, 200]),
            ("plots/training/success_rate", "success rate (last 100)", [40, 160, 40]),
            (
                "plots/training/eval_success_rate",
                "noise-free success (last 20)",
                [200, 120, 0],
            ),
            ("plots/training/critic_loss", "critic loss", [150, 0, 150]),
            ("plots/training/actor_loss", "actor loss", [120, 120, 120]),
        ] {
            stream.log_static(
                path,
                &rerun::SeriesLines::new().with_names([name]).with_colors([colour]),
            )?;
        }
        Ok(Some(Self { stream }))
    }

    /// Logs one finished episode's figures.
    pub fn episode(&self, episode: u64, reward: f64, success_rate: f64, eval_success: Option<f64>) -> Result<()> {
        self.stream.set_time_sequence("episode", episode as i64);
        self.stream
            .log("plots/training/episode_reward", &rerun::Scalars::single(reward))?;
        self.stream
            .log("plots/training/success_rate", &rerun::Scalars::single(success_rate))?;
        if let Some(eval) = eval_success {
            self.stream
                .log("plots/training/eval_success_rate", &rerun::Scalars::single(eval))?;
        }
        Ok(())
    }

    /// Logs the latest losses.
    pub fn losses(&self, episode: u64, critic: f64, actor: Option<f64>) -> Result<()> {
        self.stream.set_time_sequence("episode", episode as i64);
        self.stream
            .log("plots/training/critic_loss", &rerun::Scalars::single(critic))?;
        if let Some(actor) = actor {
            self.stream
                .log("plots/training/actor_loss", &rerun::Scalars::single(actor))?;
        }
        Ok(())
    }

    /// Flushes and closes the recording.
    pub fn close(self) {
        let _ = self.stream.flush_blocking();
        self.stream.disconnect();
    }
}
