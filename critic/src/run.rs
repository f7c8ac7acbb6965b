//! The critic's loop: drain the streams into the replay, acknowledge progress (the sim's flow
//! control), train at the configured update-to-data ratio, stream weights, checkpoint.

use std::collections::{HashMap, VecDeque};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_model::checkpoint::{BEST_FILE_NAME, FILE_NAME};
use formation_protocol::cli::{Mode, write_atomically};
use formation_protocol::config::RunConfig;
use formation_protocol::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_protocol::summary::Summary;
use formation_protocol::wire::*;
use formation_replay::buffer::ReplayBuffer;
use formation_replay::sample::Sampler;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;
use indicatif::{ProgressBar, ProgressStyle};
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::Serialize;

use crate::collector::{Collector, FinishedEpisode};
use crate::learner::{Learner, Losses};
use crate::view::CurveView;
use formation_core::task::Outcome;
use formation_view::ViewerMode;

/// Updates done between two drains of the streams (keeps flow control responsive).
const UPDATES_PER_DRAIN: u64 = 8;
/// Episodes in the rolling success rate.
const ROLLING_EPISODES: usize = 100;
/// Noise-free evaluation episodes in the rolling evaluation success rate.
const ROLLING_EVAL_EPISODES: usize = 20;
/// Seconds between rows of `training.csv` (and plain progress lines when not on a terminal).
const REPORT_EVERY: Duration = Duration::from_secs(10);

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

/// One row of `training.csv`.
#[derive(Debug, Clone, Default, Serialize)]
struct TrainingRow {
    wall_s: f64,
    episodes: u64,
    env_steps: u64,
    updates: u64,
    success_rate_100: f64,
    eval_success_rate_20: Option<f64>,
    mean_return_100: f64,
    critic_loss: f64,
    actor_loss: Option<f64>,
    action_magnitude: Option<f64>,
    weights_version: u32,
    replay_transitions: usize,
}

struct Rolling {
    outcomes: VecDeque<(bool, f64)>,
    eval: VecDeque<bool>,
    episodes: u64,
}

impl Rolling {
    fn push(&mut self, finished: &FinishedEpisode) {
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

    fn success_rate(&self) -> f64 {
        let n = self.outcomes.len().max(1) as f64;
        self.outcomes.iter().filter(|(s, _)| *s).count() as f64 / n
    }

    fn mean_return(&self) -> f64 {
        let n = self.outcomes.len().max(1) as f64;
        self.outcomes.iter().map(|(_, r)| r).sum::<f64>() / n
    }

    fn eval_success_rate(&self) -> Option<f64> {
        (self.eval.len() == ROLLING_EVAL_EPISODES)
            .then(|| self.eval.iter().filter(|&&s| s).count() as f64 / self.eval.len() as f64)
    }
}

struct WeightsPublisher<S: Service> {
    publishers: Vec<Publisher<S, [f32], WeightsHeader>>,
    version: u32,
}

impl<S: Service> WeightsPublisher<S> {
    fn new(node: &Node<S>, sizing: &Sizing, learner: &Learner) -> Result<Self> {
        let len = learner.actor_shape().parameter_count();
        let publishers = (0..learner.n_actors())
            .map(|index| {
                services::weights_stream(node, sizing, index)?
                    .publisher_builder()
                    .initial_max_slice_len(len)
                    .create()
                    .with_context(|| format!("critic: weights publisher {index}"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { publishers, version: 0 })
    }

    /// Connects subscribers that appeared since the last publication (they get the history).
    fn update_connections(&self) -> Result<()> {
        for publisher in &self.publishers {
            publisher.update_connections().context("critic: weights connections")?;
        }
        Ok(())
    }

    /// Publishes every actor's current weights; the version is the update count, so it keeps
    /// growing across a resume from a checkpoint.
    fn publish(&mut self, learner: &Learner) -> Result<()> {
        self.version = u32::try_from(learner.updates().max(1)).unwrap_or(u32::MAX);
        for (index, publisher) in self.publishers.iter().enumerate() {
            let flat = learner.actor_weights(index)?;
            let mut sample = publisher
                .loan_slice_uninit(flat.len())
                .context("critic: loan weights")?;
            *sample.user_header_mut() = WeightsHeader {
                protocol_version: PROTOCOL_VERSION,
                actor_index: index as u32,
                version: self.version,
                len: flat.len() as u32,
            };
            let sample = sample.write_from_slice(&flat);
            sample.send().context("critic: send weights")?;
        }
        Ok(())
    }
}

/// `training.csv`: a resumed critic (one restarted mid-run) appends to its predecessor's rows.
fn open_training_log(path: &std::path::Path, resumed: bool) -> Result<csv::Writer<std::fs::File>> {
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

/// Runs until the sim ends the run (or falls silent); extends `summary.json`.
pub fn run<S: Service>(identity: &RunIdentity, options: &CriticOptions) -> Result<Summary>
where
    Listener<S>: FileDescriptorBased,
{
    let config = &options.config;
    let learn = &config.learn;
    let node = services::create_node::<S>(identity, "critic")?;
    let sizing = Sizing::new(options.n_agents, config.ticks.critic_window);
    let mut collector = Collector::new(&node, &sizing, &config.env)?;
    let progress_publisher = services::critic_progress_stream(&node, &sizing)?
        .publisher_builder()
        .create()
        .context("critic: progress publisher")?;
    let progress_ready = services::critic_progress_event(&node, &sizing)?
        .notifier_builder()
        .create()
        .context("critic: progress notifier")?;

    let training = options.mode == Mode::Train;
    let mut learner = if training {
        let mut learner = Learner::new(options.n_agents, &config.env, learn, options.seed)?;
        if let Some(path) = &options.resume {
            learner.load(path)?;
            eprintln!(
                "critic: resumed from {} ({} updates)",
                path.display(),
                learner.updates()
            );
        }
        Some(learner)
    } else {
        None
    };
    let mut weights = match &learner {
        Some(learner) => Some(WeightsPublisher::new(&node, &sizing, learner)?),
        None => None,
    };
    if let (Some(weights), Some(learner), Some(_)) = (&mut weights, &learner, &options.resume) {
        weights.publish(learner)?;
    }

    let mut replay = ReplayBuffer::new(learn.replay_capacity);
    let sampler = Sampler {
        history: config.env.history,
        her_probability: learn.her_probability,
        env: config.env.clone(),
    };
    let mut rng = StdRng::seed_from_u64(options.seed ^ 0x5eed_c817);
    let mut rolling = Rolling {
        outcomes: VecDeque::new(),
        eval: VecDeque::new(),
        episodes: 0,
    };
    let mut losses = Losses::default();
    let mut best_eval = -1.0;
    let mut training_log = open_training_log(&options.run_dir.join("training.csv"), options.resume.is_some())?;
    let bar = progress_bar(options.progress);
    let curves = CurveView::open(&options.viewer, &options.run_id, &options.run_dir)?;

    let started = Instant::now();
    let mut last_checkpoint = Instant::now();
    let mut last_report = Instant::now();
    let mut last_bar = Instant::now();
    let mut sim_watch = services::SimWatch::new(
        Duration::from_millis(config.ticks.sim_silence_ms),
        Duration::from_secs(config.ticks.startup_timeout_s),
    );
    // Not from the seeded generator: a restarted critic must differ from the one it replaces.
    let session = rand::random_range(1..u64::MAX);
    let mut paid_ticks = u64::MAX;
    let mut last_acknowledged = 0;
    publish_progress(&progress_publisher, &progress_ready, session, 0, &learner, &weights)?;

    loop {
        let owed = learner.as_ref().map_or(0, |l| {
            updates_owed(
                collector.stats.ticks_received,
                learn.warmup_transitions,
                learn.updates_per_transition,
                l.updates(),
            )
        });
        if owed == 0 {
            collector.wait(Duration::from_millis(100))?;
        }
        let before = collector.stats.ticks_received;
        for finished in collector.drain()? {
            rolling.push(&finished);
            if let Some(curves) = &curves {
                curves.episode(
                    rolling.episodes,
                    finished.episode_return,
                    rolling.success_rate(),
                    rolling.eval_success_rate(),
                )?;
            }
            if let (true, Some(eval), Some(learner)) = (finished.eval, rolling.eval_success_rate(), &learner)
                && eval > best_eval
            {
                best_eval = eval;
                learner.save(
                    &options.run_dir.join(BEST_FILE_NAME),
                    checkpoint_meta(learner, &rolling, options, Some(eval)),
                )?;
            }
            if training {
                // Eval mode only records figures: keeping episodes would grow memory for nothing.
                replay.push(finished.episode);
            }
        }
        if collector.stats.ticks_received > before {
            sim_watch.heard();
        }
        if let Some(weights) = &weights {
            // Hands the latest weights (history 1) to agents that connected since.
            weights.update_connections()?;
        }
        if collector.stats.run_ended {
            break;
        }
        // A sim silent for `silence` is given up on once its process is gone (at once when it
        // was killed); a live one that stalls (a loaded machine) is waited for up to the
        // start-up limit, since a critic restart loses the replay.
        if let Some(quiet) = sim_watch.gone::<S>(identity, "critic")? {
            if let Some(learner) = &learner {
                learner.save(
                    &options.run_dir.join(FILE_NAME),
                    checkpoint_meta(learner, &rolling, options, None),
                )?;
            }
            bail!(
                "critic: no state from the sim for {:.1} s; is it alive? (checkpoint saved)",
                quiet.as_secs_f64()
            );
        }

        if let (Some(learner), Some(weights)) = (&mut learner, &mut weights) {
            let owed = updates_owed(
                collector.stats.ticks_received,
                learn.warmup_transitions,
                learn.updates_per_transition,
                learner.updates(),
            );
            for _ in 0..owed.min(UPDATES_PER_DRAIN) {
                let Some(batch) = sampler.sample(&replay, learn.batch_size, &mut rng) else {
                    break;
                };
                let step = learner.update(&batch)?;
                losses.critic = step.critic;
                if step.actor.is_some() {
                    losses.actor = step.actor;
                    losses.action_magnitude = step.action_magnitude;
                }
                if learner.updates() % learn.publish_every_updates == 0 || weights.version == 0 {
                    weights.publish(learner)?;
                }
                if !losses.critic.is_finite() {
                    bail!(
                        "critic: the critic loss diverged to {} after {} updates",
                        losses.critic,
                        learner.updates()
                    );
                }
            }
            if replay.transitions() == 0 {
                // Nothing to learn from yet: let the sim run on.
                paid_ticks = u64::MAX;
            } else {
                paid_ticks =
                    learn.warmup_transitions as u64 + (learner.updates() as f64 / learn.updates_per_transition) as u64;
            }
            if last_checkpoint.elapsed() >= Duration::from_secs(learn.checkpoint_every_s) {
                learner.save(
                    &options.run_dir.join(FILE_NAME),
                    checkpoint_meta(learner, &rolling, options, None),
                )?;
                last_checkpoint = Instant::now();
            }
        }

        // Acknowledge only the ticks the updates have paid for: the sim stays at most
        // `critic_window` ticks ahead, which holds the update-to-data ratio.
        let acknowledged = collector.acknowledgeable(paid_ticks);
        if acknowledged != last_acknowledged || collector.stats.ticks_received == 0 {
            // Before the first tick this repeats the greeting until the sim has connected.
            last_acknowledged = acknowledged;
            publish_progress(
                &progress_publisher,
                &progress_ready,
                session,
                acknowledged,
                &learner,
                &weights,
            )?;
        }

        if last_bar.elapsed() >= Duration::from_millis(500) {
            last_bar = Instant::now();
            let line = progress_line(&rolling, &collector, &learner, &losses, &weights, started);
            match &bar {
                Some(bar) => bar.set_message(line),
                None if last_report.elapsed() >= REPORT_EVERY => eprintln!("critic: {line}"),
                None => {}
            }
        }
        if last_report.elapsed() >= REPORT_EVERY {
            last_report = Instant::now();
            if let (Some(curves), true) = (&curves, learner.is_some()) {
                curves.losses(rolling.episodes, losses.critic, losses.actor)?;
            }
            training_log.serialize(TrainingRow {
                wall_s: started.elapsed().as_secs_f64(),
                episodes: rolling.episodes,
                env_steps: collector.stats.ticks_received,
                updates: learner.as_ref().map_or(0, Learner::updates),
                success_rate_100: rolling.success_rate(),
                eval_success_rate_20: rolling.eval_success_rate(),
                mean_return_100: rolling.mean_return(),
                critic_loss: losses.critic,
                actor_loss: losses.actor,
                action_magnitude: losses.action_magnitude,
                weights_version: weights.as_ref().map_or(0, |w| w.version),
                replay_transitions: replay.transitions(),
            })?;
            training_log.flush()?;
        }
    }
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    if let Some(curves) = curves {
        curves.close();
    }

    let checkpoint = match &learner {
        Some(learner) => {
            learner.save(
                &options.run_dir.join(FILE_NAME),
                checkpoint_meta(learner, &rolling, options, None),
            )?;
            Some(FILE_NAME.to_string())
        }
        None => None,
    };
    let summary_path = options.run_dir.join("summary.json");
    let mut summary: Summary = std::fs::read_to_string(&summary_path)
        .ok()
        .and_then(|text| serde_json::from_str(&text).ok())
        .unwrap_or_else(|| Summary {
            mode: options.mode.as_str().into(),
            n_agents: options.n_agents,
            ..Summary::default()
        });
    let elapsed = started.elapsed().as_secs_f64();
    summary.transitions_received = Some(collector.stats.ticks_received);
    summary.lost_transitions = Some(collector.stats.lost_transitions);
    if let Some(learner) = &learner {
        summary.updates = Some(learner.updates());
        summary.updates_per_s = Some(learner.updates() as f64 / elapsed.max(1e-9));
        summary.critic_loss = Some(losses.critic);
        summary.actor_loss = losses.actor;
        summary.weights_version = weights.as_ref().map(|w| w.version);
        summary.checkpoint = checkpoint;
    }
    write_atomically(&summary_path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    Ok(summary)
}

/// Updates still due at `ratio` updates per tick after `warmup` ticks.
fn updates_owed(ticks: u64, warmup: usize, ratio: f64, done: u64) -> u64 {
    if ticks < warmup as u64 {
        return 0;
    }
    let due = ((ticks - warmup as u64) as f64 * ratio) as u64;
    due.saturating_sub(done)
}

fn checkpoint_meta(
    learner: &Learner,
    rolling: &Rolling,
    options: &CriticOptions,
    eval: Option<f64>,
) -> HashMap<String, String> {
    let mut extra = HashMap::new();
    extra.insert("updates".into(), learner.updates().to_string());
    extra.insert("episodes".into(), rolling.episodes.to_string());
    extra.insert("seed".into(), options.seed.to_string());
    extra.insert(
        "algorithm".into(),
        format!("{:?}", options.config.learn.algorithm).to_lowercase(),
    );
    extra.insert("success_rate_100".into(), format!("{:.3}", rolling.success_rate()));
    if let Some(eval) = eval {
        extra.insert("eval_success_rate_20".into(), format!("{eval:.3}"));
    }
    extra
}

fn publish_progress<S: Service>(
    publisher: &Publisher<S, CriticProgressMsg, ()>,
    ready: &iceoryx2::port::notifier::Notifier<S>,
    session: u64,
    acknowledged_sequence: u64,
    learner: &Option<Learner>,
    weights: &Option<WeightsPublisher<S>>,
) -> Result<()> {
    publisher
        .send_copy(CriticProgressMsg {
            protocol_version: PROTOCOL_VERSION,
            weights_version: weights.as_ref().map_or(0, |w| w.version),
            acknowledged_sequence,
            updates: learner.as_ref().map_or(0, Learner::updates),
            session,
        })
        .context("critic: progress")?;
    ready.notify().context("critic: progress notify")?;
    Ok(())
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

fn progress_line<S: Service>(
    rolling: &Rolling,
    collector: &Collector<S>,
    learner: &Option<Learner>,
    losses: &Losses,
    weights: &Option<WeightsPublisher<S>>,
    started: Instant,
) -> String {
    let secs = started.elapsed().as_secs_f64().max(1e-9);
    let mut line = format!(
        "episodes {} | success(100) {:.2} | eval(20) {} | {:.0} steps/s",
        rolling.episodes,
        rolling.success_rate(),
        rolling.eval_success_rate().map_or("-".into(), |e| format!("{e:.2}")),
        collector.stats.ticks_received as f64 / secs,
    );
    if let Some(learner) = learner {
        line += &format!(
            " | {:.0} updates/s | critic {:.3} | actor {} | weights v{}",
            learner.updates() as f64 / secs,
            losses.critic,
            losses.actor.map_or("-".into(), |a| format!("{a:.2}")),
            weights.as_ref().map_or(0, |w| w.version),
        );
    }
    line
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
