//! The critic's loop: drain the streams into the replay, acknowledge progress (the sim's flow
//! control), train at the configured update-to-data ratio, report; at the end, save the
//! checkpoint and add the learner's figures to `summary.json`.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_model::checkpoint::FILE_NAME;
use formation_protocol::cli::{Mode, write_atomically};
use formation_protocol::config::RunConfig;
use formation_protocol::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_protocol::summary::Summary;
use formation_protocol::wire::{CriticProgressMsg, PROTOCOL_VERSION};
use formation_view::ViewerMode;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;

use crate::collector::Collector;
use crate::progress::{Progress, TrainingStatus};
use crate::trainer::Trainer;

/// Longest silence towards the sim (it gives a critic up after a quarter of
/// `ticks.sim_silence_ms`, 500 ms by default).
const HEARTBEAT_EVERY: Duration = Duration::from_millis(100);

/// How the critic runs.
#[derive(Debug, Clone)]
pub struct CriticOptions {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Train (learn) or eval (record only).
    pub mode: Mode,
    /// Seed of the networks and the sampler.
    pub seed: u64,
    /// Run directory.
    pub run_dir: PathBuf,
    /// The configuration as run.
    pub config: RunConfig,
    /// Resume training from this checkpoint file.
    pub resume: Option<PathBuf>,
    /// Show the one-line progress display.
    pub progress: bool,
    /// Where the training curves go.
    pub viewer: ViewerMode,
    /// The run id (names the recording).
    pub run_id: String,
}

/// Runs until the sim ends the run (or falls silent); extends `summary.json`.
pub fn run<S: Service>(identity: &RunIdentity, options: &CriticOptions) -> Result<Summary>
where
    Listener<S>: FileDescriptorBased,
{
    let config = &options.config;
    let node = services::create_node::<S>(identity, "critic")?;
    let sizing = Sizing::new(options.n_agents, config.ticks.critic_window);
    let mut collector = Collector::new(&node, &sizing, &config.env)?;
    let progress_link = ProgressLink::new(&node, &sizing)?;
    let mut trainer = match options.mode {
        Mode::Train => Some(Trainer::new(&node, &sizing, options)?),
        Mode::Eval => None,
    };
    let mut progress = Progress::open(options)?;
    let mut sim_watch = services::SimWatch::new(
        Duration::from_millis(config.ticks.sim_silence_ms),
        Duration::from_secs(config.ticks.startup_timeout_s),
    );
    let mut paid_ticks = u64::MAX;
    let mut last_acknowledged = 0;
    let mut last_progress = Instant::now();
    progress_link.publish(0, trainer.as_ref().map(Trainer::status))?;

    loop {
        let owed = trainer
            .as_ref()
            .map_or(0, |t| t.updates_owed(collector.stats.ticks_received));
        if owed == 0 {
            collector.wait(Duration::from_millis(100))?;
        }
        let before = collector.stats.ticks_received;
        for finished in collector.drain()? {
            progress.episode(&finished)?;
            // Eval mode only records figures: keeping episodes would grow memory for nothing.
            if let Some(trainer) = &mut trainer {
                trainer.keep(finished, &progress.rolling)?;
            }
        }
        if collector.stats.ticks_received > before {
            sim_watch.heard();
        }
        if let Some(trainer) = &trainer {
            trainer.update_connections()?;
        }
        if collector.stats.run_ended {
            break;
        }
        // A sim silent for `silence` is given up on once its process is gone (at once when it
        // was killed); a live one that stalls (a loaded machine) is waited for up to the
        // start-up limit, since a critic restart loses the replay.
        if let Some(quiet) = sim_watch.gone::<S>(identity, "critic")? {
            if let Some(trainer) = &trainer {
                trainer.save_checkpoint(&progress.rolling)?;
            }
            bail!(
                "critic: no state from the sim for {:.1} s; is it alive? (checkpoint saved)",
                quiet.as_secs_f64()
            );
        }
        if let Some(trainer) = &mut trainer {
            paid_ticks = trainer.train(collector.stats.ticks_received, &progress.rolling)?;
        }

        // Acknowledge only the ticks the updates have paid for: the sim stays at most
        // `critic_window` ticks ahead, which holds the update-to-data ratio.
        // Progress also goes out as a heartbeat: the sim takes a critic silent for a while
        // as gone and runs on without flow control.
        let acknowledged = collector.stats.acknowledgeable(paid_ticks);
        if acknowledged != last_acknowledged
            || collector.stats.ticks_received == 0
            || last_progress.elapsed() >= HEARTBEAT_EVERY
        {
            // Before the first tick this repeats the greeting until the sim has connected.
            last_acknowledged = acknowledged;
            last_progress = Instant::now();
            progress_link.publish(acknowledged, trainer.as_ref().map(Trainer::status))?;
        }
        progress.report(collector.stats.ticks_received, trainer.as_ref().map(Trainer::status))?;
    }

    let elapsed = progress.elapsed_s();
    let status = trainer.as_ref().map(Trainer::status);
    if let Some(trainer) = &trainer {
        trainer.save_checkpoint(&progress.rolling)?;
    }
    progress.finish();
    merge_summary(options, &collector.stats, status, elapsed)
}

/// Adds the critic's figures to the sim's `summary.json` (or starts one if the sim wrote none).
fn merge_summary(
    options: &CriticOptions,
    stats: &crate::collector::CollectorStats,
    training: Option<TrainingStatus>,
    elapsed_s: f64,
) -> Result<Summary> {
    let summary_path = options.run_dir.join("summary.json");
    let mut summary: Summary = std::fs::read_to_string(&summary_path)
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or_else(|| Summary {
            mode: options.mode.as_str().into(),
            n_agents: options.n_agents,
            ..Summary::default()
        });
    summary.transitions_received = Some(stats.ticks_received);
    summary.lost_transitions = Some(stats.lost_transitions);
    if let Some(status) = training {
        summary.updates = Some(status.updates);
        summary.updates_per_s = Some(status.updates as f64 / elapsed_s.max(1e-9));
        summary.critic_loss = Some(status.losses.critic);
        summary.actor_loss = status.losses.actor;
        summary.weights_version = Some(status.weights_version);
        summary.checkpoint = Some(FILE_NAME.to_string());
    }
    write_atomically(&summary_path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    Ok(summary)
}

/// The critic's side of flow control: its progress (acknowledged ticks, updates, weights
/// version) and the event that wakes a sim waiting for it.
struct ProgressLink<S: Service> {
    publisher: Publisher<S, CriticProgressMsg, ()>,
    ready: Notifier<S>,
    /// Not from the seeded generator: a restarted critic must differ from the one it replaces.
    session: u64,
}

impl<S: Service> ProgressLink<S> {
    fn new(node: &Node<S>, sizing: &Sizing) -> Result<Self> {
        Ok(Self {
            publisher: services::critic_progress_stream(node, sizing)?
                .publisher_builder()
                .create()
                .context("critic: progress publisher")?,
            ready: services::critic_progress_event(node, sizing)?
                .notifier_builder()
                .create()
                .context("critic: progress notifier")?,
            session: rand::random_range(1..u64::MAX),
        })
    }

    fn publish(&self, acknowledged_sequence: u64, training: Option<TrainingStatus>) -> Result<()> {
        self.publisher
            .send_copy(CriticProgressMsg {
                protocol_version: PROTOCOL_VERSION,
                weights_version: training.map_or(0, |t| t.weights_version),
                acknowledged_sequence,
                updates: training.map_or(0, |t| t.updates),
                session: self.session,
            })
            .context("critic: progress")?;
        self.ready.notify().context("critic: progress notify")?;
        Ok(())
    }
}
