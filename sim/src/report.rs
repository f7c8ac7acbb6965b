//! Per-episode records, `episodes.csv` and the sim's part of `summary.json`.

use std::path::Path;

use anyhow::{Context, Result};
use formation_ipc::summary::Summary;
use serde::Serialize;

use formation_core::task::Outcome;

/// One row of `episodes.csv`.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EpisodeRecord {
    /// Episode counter.
    pub episode: u32,
    /// How it ended: `success`, `collision`, `timeout` or `aborted` in the file.
    #[serde(serialize_with = "outcome_name")]
    pub outcome: Outcome,
    /// Steps taken.
    pub steps: u32,
    /// Undiscounted sum of rewards.
    pub episode_return: f64,
    /// Mean edge error at the last tick, metres.
    pub final_edge_error_m: f64,
    /// Centroid-to-goal distance at the last tick, metres.
    pub final_goal_distance_m: f64,
    /// Fraction of ticks on which C1 held.
    pub formation_hold_rate: f64,
    /// Robot-ticks missed (nothing new arrived: the command in use stayed).
    pub missed_ticks: u64,
    /// Robot-ticks that took up a late answer to an earlier tick.
    pub late_commands: u64,
    /// Commands lost on the way (`[reality]`'s `command_loss`).
    pub lost_commands: u64,
    /// Observations not delivered (`[reality]`'s `observation_loss`).
    pub lost_observations: u64,
    /// The mission planner's slot reassignments in the episode: shape changes, goal moves and
    /// team changes.
    pub reconfigurations: u32,
    /// Changes after which the swarm re-formed (every observed edge within eps_form for 5
    /// consecutive ticks, or held to a success).
    pub reforms: u32,
    /// Mean ticks from a change to re-forming, over the changes that re-formed (empty if none).
    pub mean_reform_ticks: Option<f64>,
    /// Sum of those ticks (not written: the run's mean weighs every change alike).
    #[serde(skip)]
    pub reform_ticks_sum: u64,
    /// Robots that left the formation in the episode.
    pub departures: u32,
    /// Robots that came back into the formation in the episode.
    pub returns: u32,
    /// Wall-clock seconds since the run started, at the episode's end.
    pub wall_s: f64,
}

/// Writes an outcome by its name.
fn outcome_name<S: serde::Serializer>(outcome: &Outcome, serializer: S) -> Result<S::Ok, S::Error> {
    serializer.serialize_str(outcome.as_str())
}

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
