//! What the critic tells its user: rolling success rates, the one-line progress display,
//! `training.csv` every 10 s and the training curves in the run's recording.

use std::collections::VecDeque;
use std::io::IsTerminal;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use formation_core::task::Outcome;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::collector::FinishedEpisode;
use crate::learner::Losses;
use crate::run::CriticOptions;
use crate::view::CurveView;

/// Episodes in the rolling success rate.
const ROLLING_EPISODES: usize = 100;
/// Noise-free evaluation episodes in the rolling evaluation success rate.
const ROLLING_EVAL_EPISODES: usize = 20;
/// Seconds between rows of `training.csv` (and plain progress lines when not on a terminal).
const REPORT_EVERY: Duration = Duration::from_secs(10);
/// Refresh period of the progress display.
const BAR_EVERY: Duration = Duration::from_millis(500);

/// Success and return over the last episodes.
#[derive(Debug, Default)]
pub struct Rolling {
    outcomes: VecDeque<(bool, f64)>,
    eval: VecDeque<bool>,
    /// Episodes finished in this critic's lifetime.
    pub episodes: u64,
}

impl Rolling {
    /// Counts a finished episode.
    pub fn push(&mut self, finished: &FinishedEpisode) {
        let success = finished.outcome == Outcome::Success;
        self.episodes += 1;
        self.outcomes.push_back((success, finished.episode_return));
        if self.outcomes.len() > ROLLING_EPISODES {
            self.outcomes.pop_front();
        }
        if finished.eval {
            self.eval.push_back(success);
            if self.eval.len() > ROLLING_EVAL_EPISODES {
                self.eval.pop_front();
            }
        }
    }

    /// Success rate over the last 100 episodes (with exploration noise).
    pub fn success_rate(&self) -> f64 {
        let n = self.outcomes.len().max(1) as f64;
        self.outcomes.iter().filter(|(s, _)| *s).count() as f64 / n
    }

    /// Mean undiscounted return over the last 100 episodes.
    pub fn mean_return(&self) -> f64 {
        let n = self.outcomes.len().max(1) as f64;
        self.outcomes.iter().map(|(_, r)| r).sum::<f64>() / n
    }

    /// Success rate over the last 20 noise-free episodes, once there are 20.
    pub fn eval_success_rate(&self) -> Option<f64> {
        (self.eval.len() == ROLLING_EVAL_EPISODES)
            .then(|| self.eval.iter().filter(|&&s| s).count() as f64 / self.eval.len() as f64)
    }
}

/// The learner's side of a progress report.
#[derive(Debug, Clone, Copy)]
pub struct TrainingStatus {
    /// Gradient updates so far (with those of the checkpoint the run resumed from).
    pub updates: u64,
    /// Gradient updates of this process: what the rates count.
    pub run_updates: u64,
    /// The latest losses.
    pub losses: Losses,
    /// The weights version last streamed.
    pub weights_version: u32,
    /// Transitions held by the replay.
    pub replay_transitions: usize,
    /// The latest checkpoint's selection score, once one is saved.
    pub selection: Option<f64>,
    /// The selection score of `best.safetensors`, once there is one.
    pub best_selection: Option<f64>,
    /// With `--updates`: the total count at which training stops.
    pub update_target: Option<u64>,
}

/// One row of `training.csv`.
#[derive(Debug, Clone, Default, Serialize)]
struct TrainingRow {
    wall_s: f64,
    episodes: u64,
    env_steps: u64,
    updates: u64,
    success_rate_100: f64,
    eval_success_rate_20: Option<f64>,
    selection_success: Option<f64>,
    mean_return_100: f64,
    critic_loss: f64,
    actor_loss: Option<f64>,
    action_magnitude: Option<f64>,
    actor_gradient_rms: Option<f64>,
    weights_version: u32,
    replay_transitions: usize,
}

/// The critic's reporting: rolling rates, display, log and curves.
pub struct Progress {
    /// Success and return over the last episodes.
    pub rolling: Rolling,
    bar: Option<ProgressBar>,
    training_log: csv::Writer<std::fs::File>,
    curves: Option<CurveView>,
    started: Instant,
    /// When the run is due to end (`--minutes`), for the time left on the display.
    ends: Option<Instant>,
    last_bar: Instant,
    last_report: Instant,
}

impl Progress {
    /// Opens `training.csv` (appending when the critic resumes) and the curves.
    pub fn open(options: &CriticOptions) -> Result<Self> {
        let now = Instant::now();
        Ok(Self {
            rolling: Rolling::default(),
            bar: progress_bar(options.progress),
            training_log: open_training_log(&options.run_dir.join("training.csv"), options.resume.is_some())?,
            curves: CurveView::open(&options.viewer, &options.run_id, &options.run_dir)?,
            started: now,
            ends: options.minutes.map(|m| now + Duration::from_secs_f64(m * 60.0)),
            last_bar: now,
            last_report: now,
        })
    }

    /// Seconds since the critic started.
    pub fn elapsed_s(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// Counts a finished episode and draws it on the curves.
    pub fn episode(&mut self, finished: &FinishedEpisode) -> Result<()> {
        self.rolling.push(finished);
        if let Some(curves) = &self.curves {
            curves.episode(
                self.rolling.episodes,
                finished.episode_return,
                self.rolling.success_rate(),
                self.rolling.eval_success_rate(),
            )?;
        }
        Ok(())
    }

    /// Refreshes the display twice a second and writes a `training.csv` row every 10 s.
    pub fn report(&mut self, env_steps: u64, training: Option<TrainingStatus>) -> Result<()> {
        if let Some(bar) = &self.bar
            && self.last_bar.elapsed() >= BAR_EVERY
        {
            self.last_bar = Instant::now();
            bar.set_message(self.line(env_steps, training));
        }
        if self.last_report.elapsed() < REPORT_EVERY {
            return Ok(());
        }
        self.last_report = Instant::now();
        if self.bar.is_none() {
            // Not a terminal (a log file): a line every report instead of a live bar.
            eprintln!("critic: {}", self.line(env_steps, training));
        }
        let status = training.as_ref();
        let losses = status.map(|s| s.losses).unwrap_or_default();
        if let (Some(curves), Some(_)) = (&self.curves, status) {
            curves.losses(self.rolling.episodes, losses.critic, losses.actor)?;
        }
        self.training_log.serialize(TrainingRow {
            wall_s: self.elapsed_s(),
            episodes: self.rolling.episodes,
            env_steps,
            updates: status.map_or(0, |s| s.updates),
            success_rate_100: self.rolling.success_rate(),
            eval_success_rate_20: self.rolling.eval_success_rate(),
            selection_success: status.and_then(|s| s.selection),
            mean_return_100: self.rolling.mean_return(),
            critic_loss: losses.critic,
            actor_loss: losses.actor,
            action_magnitude: losses.action_magnitude,
            actor_gradient_rms: losses.actor_gradient_rms,
            weights_version: status.map_or(0, |s| s.weights_version),
            replay_transitions: status.map_or(0, |s| s.replay_transitions),
        })?;
        self.training_log.flush()?;
        Ok(())
    }

    /// Clears the display and closes the curves.
    pub fn finish(self) {
        if let Some(bar) = self.bar {
            bar.finish_and_clear();
        }
        if let Some(curves) = self.curves {
            curves.close();
        }
    }

    fn line(&self, env_steps: u64, training: Option<TrainingStatus>) -> String {
        let secs = self.elapsed_s().max(1e-9);
        let mut line = format!(
            "episodes {} | success(100) {:.2} | eval(20) {} | {:.0} steps/s",
            self.rolling.episodes,
            self.rolling.success_rate(),
            self.rolling
                .eval_success_rate()
                .map_or("-".into(), |e| format!("{e:.2}")),
            env_steps as f64 / secs,
        );
        if let Some(status) = training {
            line += &format!(
                " | {:.0} updates/s | critic {:.3} | actor {} | weights v{}",
                status.run_updates as f64 / secs,
                status.losses.critic,
                status.losses.actor.map_or("-".into(), |a| format!("{a:.2}")),
                status.weights_version,
            );
            if let Some(best) = status.best_selection {
                line += &format!(" | best {best:.2}");
            }
            if let Some(target) = status.update_target {
                line += &format!(" | {}/{target} updates", status.updates);
                if status.run_updates > 0 {
                    // At this run's rate so far.
                    let rate = status.run_updates as f64 / secs;
                    let left = (target.saturating_sub(status.updates) as f64 / rate) as u64;
                    line += &format!(", ~{}:{:02} left", left / 60, left % 60);
                }
            }
        }
        if let Some(ends) = self.ends {
            let left = ends.saturating_duration_since(Instant::now()).as_secs();
            line += &format!(" | {}:{:02} left", left / 60, left % 60);
        }
        line
    }
}

/// `training.csv`: a resumed critic (one restarted mid-run) appends to its predecessor's rows.
fn open_training_log(path: &Path, resumed: bool) -> Result<csv::Writer<std::fs::File>> {
    let continues = resumed && std::fs::metadata(path).is_ok_and(|m| m.len() > 0);
    let file = std::fs::OpenOptions::new()
        .create(true)
        .write(true)
        .append(continues)
        .truncate(!continues)
        .open(path)
        .with_context(|| format!("cannot create {}", path.display()))?;
    Ok(csv::WriterBuilder::new().has_headers(!continues).from_writer(file))
}

fn progress_bar(enabled: bool) -> Option<ProgressBar> {
    if !enabled || !std::io::stderr().is_terminal() {
        return None;
    }
    let bar = ProgressBar::new_spinner();
    bar.set_style(ProgressStyle::with_template("{spinner} {elapsed_precise} {msg}").ok()?);
    bar.enable_steady_tick(Duration::from_millis(200));
    Some(bar)
}
#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_resumed_critic_appends_to_training_csv_and_a_new_run_starts_it_afresh() {
        let dir = std::env::temp_dir().join(format!("critic-training-log-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("training.csv");
        let write = |resumed: bool, wall_s: f64| {
            let mut log = open_training_log(&path, resumed).expect("open");
            log.serialize(TrainingRow {
                wall_s,
                ..TrainingRow::default()
            })
            .expect("row");
            log.flush().expect("flush");
        };
        write(false, 1.0);
        write(true, 2.0);
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text.lines().filter(|l| l.starts_with("wall_s")).count(), 1, "{text}");
        assert_eq!(text.lines().count(), 3, "{text}");
        // A fresh critic (no resume) starts the file again.
        write(false, 3.0);
        let text = std::fs::read_to_string(&path).expect("read");
        assert_eq!(text.lines().count(), 2, "{text}");
        assert!(text.lines().nth(1).expect("row").starts_with('3'), "{text}");
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
