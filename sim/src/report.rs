//! Per-episode records, `episodes.csv` and the sim's part of `summary.json`.

use std::path::Path;

use anyhow::{Context, Result};
pub use formation_core::stepper::EpisodeRecord;
use formation_core::task::Outcome;
use formation_ipc::summary::Summary;

/// Appends records to `episodes.csv` as episodes end, so a killed run keeps what it did.
pub struct EpisodeLog {
    writer: csv::Writer<std::fs::File>,
    records: Vec<EpisodeRecord>,
}

impl EpisodeLog {
    /// Creates `episodes.csv` in the run directory.
    pub fn create(run_dir: &Path) -> Result<Self> {
        let path = run_dir.join("episodes.csv");
        let writer = csv::Writer::from_path(&path).with_context(|| format!("cannot create {}", path.display()))?;
        Ok(Self {
            writer,
            records: Vec::new(),
        })
    }

    /// Adds one episode (written and flushed at once).
    pub fn push(&mut self, record: EpisodeRecord) -> Result<()> {
        self.writer.serialize(&record)?;
        self.writer.flush()?;
        self.records.push(record);
        Ok(())
    }

    /// Episodes so far.
    pub fn records(&self) -> &[EpisodeRecord] {
        &self.records
    }
}

/// Fills the episode figures of `summary` from the records (aborted episodes are left out of
/// the rates, since they did not run to an outcome).
pub fn fill_episode_figures(summary: &mut Summary, records: &[EpisodeRecord]) {
    let finished: Vec<&EpisodeRecord> = records.iter().filter(|r| r.outcome != Outcome::Aborted).collect();
    let count = finished.len() as f64;
    summary.episodes = finished.len() as u64;
    if finished.is_empty() {
        return;
    }
    let rate = |outcome: Outcome| finished.iter().filter(|r| r.outcome == outcome).count() as f64 / count;
    let mean = |f: &dyn Fn(&EpisodeRecord) -> f64| finished.iter().map(|r| f(r)).sum::<f64>() / count;
    summary.success_rate = rate(Outcome::Success);
    summary.collision_rate = rate(Outcome::Collision);
    summary.obstacle_collisions = finished.iter().map(|r| u64::from(r.obstacle_collisions)).sum();
    summary.timeout_rate = rate(Outcome::Timeout);
    summary.mean_final_edge_error_m = mean(&|r| r.final_edge_error_m);
    summary.mean_final_goal_distance_m = mean(&|r| r.final_goal_distance_m);
    summary.mean_return = mean(&|r| r.episode_return);
    let total_steps: f64 = finished.iter().map(|r| f64::from(r.steps)).sum();
    summary.formation_hold_rate = finished
        .iter()
        .map(|r| r.formation_hold_rate * f64::from(r.steps))
        .sum::<f64>()
        / total_steps.max(1.0);
    let successes: Vec<f64> = finished
        .iter()
        .filter(|r| r.outcome == Outcome::Success)
        .map(|r| f64::from(r.steps))
        .collect();
    summary.mean_steps_to_goal =
        (!successes.is_empty()).then(|| successes.iter().sum::<f64>() / successes.len() as f64);
    summary.reconfigurations = finished.iter().map(|r| u64::from(r.reconfigurations)).sum();
    summary.reforms = finished.iter().map(|r| u64::from(r.reforms)).sum();
    summary.departures = finished.iter().map(|r| u64::from(r.departures)).sum();
    summary.returns = finished.iter().map(|r| u64::from(r.returns)).sum();
    let reform_ticks: u64 = finished.iter().map(|r| r.reform_ticks_sum).sum();
    summary.mean_reform_ticks = (summary.reforms > 0).then(|| reform_ticks as f64 / summary.reforms as f64);
}
