//! The critic's loop: drain the streams into the replay, acknowledge progress (the sim's flow
//! control), train at the configured update-to-data ratio, report; at the end, score and save
//! the checkpoint and add the learner's figures to `summary.json`. One critic may serve several
//! swarms (sizes) at once, each its own sim and robots under its own run id: one link each.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use formation_core::config::RunConfig;
use formation_core::observation::Layout;
use formation_core::run_dir::write_atomically;
use formation_ipc::cli::ViewerMode;
use formation_ipc::cli::{Mode, UPDATE_BUDGET_SPENT};
use formation_ipc::services::{self, FileDescriptorBased, ProgressPublisher, RunIdentity, Sizing, StreamReader};
use formation_ipc::summary::Summary;
use formation_model::checkpoint::FILE_NAME;
use iceoryx2::port::listener::Listener;
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
    /// How long the run lasts (`--minutes`), for the time left on the progress display.
    pub minutes: Option<f64>,
    /// Gradient updates this run does at most (`--updates`); then it only records.
    pub updates: Option<u64>,
    /// Other swarms (run id, robots) whose sims and robots this critic also trains on.
    pub extra_swarms: Vec<(RunIdentity, usize)>,
}

/// One swarm the critic serves: its sim's streams and the flow control towards it.
struct SwarmLink<S: Service> {
    identity: RunIdentity,
    sizing: Sizing,
    collector: Collector<S>,
    progress: ProgressPublisher<S>,
    sim_watch: services::SimWatch,
    paid_ticks: u64,
    /// Episodes its sim has finished in this run.
    episodes: u64,
    last_acknowledged: u64,
    last_progress: Instant,
    /// Last: the ports above live in it.
    node: Node<S>,
}

impl<S: Service> SwarmLink<S>
where
    Listener<S>: FileDescriptorBased,
{
    fn open(identity: &RunIdentity, n_agents: usize, config: &RunConfig) -> Result<Self> {
        let node = services::create_node::<S>(identity, "critic")?;
        let sizing = Sizing::new(
            n_agents,
            config.ticks.critic_window,
            Layout::of(config.env.observation).dim(),
        );
        Ok(Self {
            identity: identity.clone(),
            collector: Collector::new(&node, &sizing, &config.env)?,
            progress: ProgressPublisher::open(&node, &sizing, StreamReader::Critic)?,
            sim_watch: services::SimWatch::new(
                Duration::from_millis(config.ticks.sim_silence_ms),
                Duration::from_secs(config.ticks.startup_timeout_s),
            ),
            sizing,
            paid_ticks: u64::MAX,
            episodes: 0,
            last_acknowledged: 0,
            last_progress: Instant::now(),
            node,
        })
    }

    fn ended(&self) -> bool {
        self.collector.stats.run_ended
    }

    /// Acknowledges only the ticks the updates have paid for: the sim stays at most
    /// `critic_window` ticks ahead, which holds the update-to-data ratio. Progress also goes
    /// out as a heartbeat: the sim takes a critic silent for a while as gone and runs on
    /// without flow control. Before the first tick this repeats the greeting until the sim
    /// has connected.
    fn acknowledge(&mut self, training: Option<TrainingStatus>) -> Result<()> {
        let acknowledged = self.collector.stats.acknowledgeable(self.paid_ticks);
        if acknowledged != self.last_acknowledged
            || self.collector.stats.ticks_received == 0
            || self.last_progress.elapsed() >= HEARTBEAT_EVERY
        {
            self.last_acknowledged = acknowledged;
            self.last_progress = Instant::now();
            self.publish_progress(acknowledged, training)?;
        }
        Ok(())
    }

    /// Sends the sim `acknowledged` with the training's weights version and updates.
    fn publish_progress(&self, acknowledged: u64, training: Option<TrainingStatus>) -> Result<()> {
        self.progress.publish(
            acknowledged,
            training.map_or(0, |t| t.weights_version),
            training.map_or(0, |t| t.updates),
        )
    }
}

/// Runs until every sim it serves ends its run (or one falls silent); extends `summary.json`.
pub fn run<S: Service>(identity: &RunIdentity, options: &CriticOptions) -> Result<Summary>
where
    Listener<S>: FileDescriptorBased,
{
    let config = &options.config;
    let mut links = vec![SwarmLink::<S>::open(identity, options.n_agents, config)?];
    for (other, n_agents) in &options.extra_swarms {
        links.push(SwarmLink::open(other, *n_agents, config)?);
    }
    let mut trainer = match options.mode {
        Mode::Train => {
            let ports: Vec<_> = links.iter().map(|l| (&l.node, l.sizing)).collect();
            Some(Trainer::new(&ports, options)?)
        }
        Mode::Eval => None,
    };
    let mut progress = Progress::open(options)?;
    let mut budget_announced = false;
    for link in &links {
        link.publish_progress(0, trainer.as_ref().map(Trainer::status))?;
    }

    loop {
        let ticks: Vec<u64> = links.iter().map(|l| l.collector.stats.ticks_received).collect();
        let owed: u64 = trainer
            .as_ref()
            .map_or(0, |t| (0..links.len()).map(|k| t.updates_owed(k, ticks[k])).sum());
        if owed == 0 {
            let listeners: Vec<_> = links.iter().map(|l| l.collector.wake_listener()).collect();
            services::wait_for_any_event(&listeners, Duration::from_millis(100))?;
        }
        for (k, link) in links.iter_mut().enumerate() {
            let before = link.collector.stats.ticks_received;
            for finished in link.collector.drain()? {
                link.episodes += 1;
                progress.episode(&finished)?;
                // Eval mode only records figures: keeping episodes would grow memory for nothing.
                if let Some(trainer) = &mut trainer {
                    trainer.keep(k, finished);
                }
            }
            if link.collector.stats.ticks_received > before {
                link.sim_watch.heard();
            }
        }
        if let Some(trainer) = &trainer {
            trainer.update_connections()?;
        }
        if links.iter().all(SwarmLink::ended) {
            break;
        }
        // A sim silent for `silence` is given up on once its process is gone (at once when it
        // was killed); a live one that stalls (a loaded machine) is waited for up to the
        // start-up limit, since a critic restart loses the replay.
        for link in links.iter_mut().filter(|l| !l.ended()) {
            if let Some(quiet) = link.sim_watch.gone::<S>(&link.identity, "critic")? {
                if let Some(trainer) = &mut trainer {
                    trainer.save_checkpoint(&progress.rolling)?;
                }
                bail!(
                    "critic: no state from the sim of run {} for {:.1} s; is it alive? (checkpoint saved)",
                    link.identity.run_id,
                    quiet.as_secs_f64()
                );
            }
        }
        if let Some(trainer) = &mut trainer {
            let ticks: Vec<u64> = links.iter().map(|l| l.collector.stats.ticks_received).collect();
            for (link, paid) in links.iter_mut().zip(trainer.train(&ticks, &progress.rolling)?) {
                link.paid_ticks = paid;
            }
            // The run ends once every swarm has also fed the replay an episode: a size whose
            // sim was still starting is not left out of the run unnoticed.
            if trainer.budget_spent() && !budget_announced && links.iter().all(|l| l.episodes > 0) {
                budget_announced = true;
                println!("{UPDATE_BUDGET_SPENT}");
            }
        }
        let status = trainer.as_ref().map(Trainer::status);
        for link in links.iter_mut().filter(|l| !l.ended()) {
            link.acknowledge(status)?;
        }
        let received = links.iter().map(|l| l.collector.stats.ticks_received).sum();
        progress.report(received, status)?;
    }

    let elapsed = progress.elapsed_s();
    if let Some(trainer) = &mut trainer {
        trainer.save_checkpoint(&progress.rolling)?;
    }
    let status = trainer.as_ref().map(Trainer::status);
    progress.finish();
    merge_summary(options, &links[0].collector.stats, status, elapsed)
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
        summary.updates_per_s = Some(status.run_updates as f64 / elapsed_s.max(1e-9));
        summary.critic_loss = Some(status.losses.critic);
        summary.actor_loss = status.losses.actor;
        summary.weights_version = Some(status.weights_version);
        summary.checkpoint = Some(FILE_NAME.to_string());
    }
    write_atomically(&summary_path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    Ok(summary)
}
