//! Training in the critic process: the replay, the learner, updates at the configured
//! update-to-data ratio, the weights stream and the checkpoints.

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use formation_model::checkpoint::{BEST_FILE_NAME, FILE_NAME};
use formation_protocol::config::Algorithm;
use formation_protocol::services::Sizing;
use formation_replay::buffer::ReplayBuffer;
use formation_replay::sample::Sampler;
use iceoryx2::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::collector::FinishedEpisode;
use crate::learner::{Learner, Losses};
use crate::progress::{Rolling, TrainingStatus};
use crate::run::CriticOptions;
use crate::weights::WeightsPublisher;

/// Longest run of updates between two drains of the streams: the critic keeps telling the sim
/// it is alive (and acknowledging) while updates are slow, e.g. a big swarm on a busy machine.
const UPDATES_BETWEEN_DRAINS: Duration = Duration::from_millis(40);

/// The learning half of the critic process (absent in eval mode).
pub struct Trainer<S: Service> {
    learner: Learner,
    weights: WeightsPublisher<S>,
    replay: ReplayBuffer,
    sampler: Sampler,
    rng: StdRng,
    losses: Losses,
    best_eval: f64,
    last_checkpoint: Instant,
    checkpoint_every: Duration,
    warmup_transitions: usize,
    updates_per_transition: f64,
    batch_size: usize,
    publish_every_updates: u64,
    run_dir: PathBuf,
    seed: u64,
    algorithm: Algorithm,
}

impl<S: Service> Trainer<S> {
    /// A fresh learner, or one resumed from `options.resume` (whose weights are streamed at
    /// once so that the agents act with them from the first tick).
    pub fn new(node: &Node<S>, sizing: &Sizing, options: &CriticOptions) -> Result<Self> {
        let config = &options.config;
        let learn = &config.learn;
        let mut learner = Learner::new(options.n_agents, &config.env, learn, options.seed)?;
        if let Some(path) = &options.resume {
            learner.load(path)?;
            eprintln!(
                "critic: resumed from {} ({} updates)",
                path.display(),
                learner.updates()
            );
        }
        let mut weights = WeightsPublisher::new(node, sizing, &learner)?;
        if options.resume.is_some() {
            weights.publish(&learner)?;
        }
        Ok(Self {
            learner,
            weights,
            replay: ReplayBuffer::new(learn.replay_capacity),
            sampler: Sampler {
                history: config.env.history,
                her_probability: learn.her_probability,
                env: config.env.clone(),
            },
            rng: StdRng::seed_from_u64(options.seed ^ 0x5eed_c817),
            losses: Losses::default(),
            best_eval: -1.0,
            last_checkpoint: Instant::now(),
            checkpoint_every: Duration::from_secs(learn.checkpoint_every_s),
            warmup_transitions: learn.warmup_transitions,
            updates_per_transition: learn.updates_per_transition,
            batch_size: learn.batch_size,
            publish_every_updates: learn.publish_every_updates,
            run_dir: options.run_dir.clone(),
            seed: options.seed,
            algorithm: learn.algorithm,
        })
    }

    /// Stores a finished episode; a noise-free one that lifts the rolling evaluation success
    /// to a new best saves `best.safetensors`.
    pub fn keep(&mut self, finished: FinishedEpisode, rolling: &Rolling) -> Result<()> {
        if let (true, Some(eval)) = (finished.eval, rolling.eval_success_rate())
            && eval > self.best_eval
        {
            self.best_eval = eval;
            self.learner
                .save(&self.run_dir.join(BEST_FILE_NAME), self.meta(rolling, Some(eval)))?;
        }
        self.replay.push(finished.episode);
        Ok(())
    }

    /// Updates still due for `ticks` received.
    pub fn updates_owed(&self, ticks: u64) -> u64 {
        updates_owed(
            ticks,
            self.warmup_transitions,
            self.updates_per_transition,
            self.learner.updates(),
        )
    }

    /// Connects agents that appeared since (they get the latest weights).
    pub fn update_connections(&self) -> Result<()> {
        self.weights.update_connections()
    }

    /// Does the updates owed for `ticks` received, for at most 40 ms (at least one), streams weights every
    /// `publish_every_updates`, checkpoints every `checkpoint_every_s`; returns the ticks the
    /// updates have paid for (what the critic may acknowledge to the sim).
    pub fn train(&mut self, ticks: u64, rolling: &Rolling) -> Result<u64> {
        let started = Instant::now();
        for _ in 0..self.updates_owed(ticks) {
            if started.elapsed() >= UPDATES_BETWEEN_DRAINS {
                break;
            }
            let Some(batch) = self.sampler.sample(&self.replay, self.batch_size, &mut self.rng) else {
                break;
            };
            let step = self.learner.update(&batch)?;
            self.losses.critic = step.critic;
            if step.actor.is_some() {
                self.losses.actor = step.actor;
                self.losses.action_magnitude = step.action_magnitude;
            }
            if self.learner.updates().is_multiple_of(self.publish_every_updates) || self.weights.version == 0 {
                self.weights.publish(&self.learner)?;
            }
            if !self.losses.critic.is_finite() {
                bail!(
                    "critic: the critic loss diverged to {} after {} updates",
                    self.losses.critic,
                    self.learner.updates()
                );
            }
        }
        if self.last_checkpoint.elapsed() >= self.checkpoint_every {
            self.save_checkpoint(rolling)?;
            self.last_checkpoint = Instant::now();
        }
        if self.replay.transitions() == 0 {
            // Nothing to learn from yet: let the sim run on.
            return Ok(u64::MAX);
        }
        Ok(self.warmup_transitions as u64 + (self.learner.updates() as f64 / self.updates_per_transition) as u64)
    }

    /// Saves the current networks as `checkpoint.safetensors`.
    pub fn save_checkpoint(&self, rolling: &Rolling) -> Result<()> {
        self.learner
            .save(&self.run_dir.join(FILE_NAME), self.meta(rolling, None))
    }

    /// Figures for the progress display and `training.csv`.
    pub fn status(&self) -> TrainingStatus {
        TrainingStatus {
            updates: self.learner.updates(),
            losses: self.losses,
            weights_version: self.weights.version,
            replay_transitions: self.replay.transitions(),
        }
    }

    fn meta(&self, rolling: &Rolling, eval: Option<f64>) -> HashMap<String, String> {
        let mut extra = HashMap::new();
        extra.insert("updates".into(), self.learner.updates().to_string());
        extra.insert("episodes".into(), rolling.episodes.to_string());
        extra.insert("seed".into(), self.seed.to_string());
        extra.insert("algorithm".into(), format!("{:?}", self.algorithm).to_lowercase());
        extra.insert("success_rate_100".into(), format!("{:.3}", rolling.success_rate()));
        if let Some(eval) = eval {
            extra.insert("eval_success_rate_20".into(), format!("{eval:.3}"));
        }
        extra
    }
}

/// Updates still due at `ratio` updates per tick after `warmup` ticks.
fn updates_owed(ticks: u64, warmup: usize, ratio: f64, done: u64) -> u64 {
    if ticks < warmup as u64 {
        return 0;
    }
    let due = ((ticks - warmup as u64) as f64 * ratio) as u64;
    due.saturating_sub(done)
}
