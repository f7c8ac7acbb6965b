//! Training in the critic process: the learner, one replay and weights stream per swarm it
//! serves, updates at the configured update-to-data ratio on each swarm's data, and the
//! checkpoints.

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

/// What the trainer keeps of one swarm: its episodes, the stream of weights to its robots, and
/// the updates its data has paid for (which its sim's flow control counts).
struct SwarmData<S: Service> {
    n_agents: usize,
    replay: ReplayBuffer,
    weights: WeightsPublisher<S>,
    updates: u64,
}

/// The learning half of the critic process (absent in eval mode).
pub struct Trainer<S: Service> {
    learner: Learner,
    swarms: Vec<SwarmData<S>>,
    sampler: Sampler,
    rng: StdRng,
    losses: Losses,
    best_eval: f64,
    last_checkpoint: Instant,
    checkpoint_every: Duration,
    warmup_transitions: usize,
    updates_per_transition: f64,
    /// Ticks a sim may run ahead of the critic's acknowledgements.
    critic_window: u64,
    /// The swarm whose data the last update used.
    last_served: usize,
    batch_size: usize,
    publish_every_updates: u64,
    run_dir: PathBuf,
    seed: u64,
    algorithm: Algorithm,
}

impl<S: Service> Trainer<S> {
    /// A fresh learner, or one resumed from `options.resume` (whose weights are streamed at
    /// once so that the agents act with them from the first tick), for the swarms reached
    /// through `nodes` (one node and sizing per swarm, the run's own first).
    pub fn new(swarms: &[(&Node<S>, Sizing)], options: &CriticOptions) -> Result<Self> {
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
        let mut data = Vec::with_capacity(swarms.len());
        for (node, sizing) in swarms {
            let mut weights = WeightsPublisher::new(node, sizing, &learner)?;
            if options.resume.is_some() {
                weights.publish(&learner)?;
            }
            data.push(SwarmData {
                n_agents: sizing.n_agents,
                replay: ReplayBuffer::new(learn.replay_capacity / swarms.len()),
                weights,
                updates: 0,
            });
        }
        Ok(Self {
            learner,
            swarms: data,
            sampler: Sampler {
                history: config.env.history,
                her_probability: learn.her_probability,
                env: config.env.clone(),
                critic: learn.critic,
            },
            rng: StdRng::seed_from_u64(options.seed ^ 0x5eed_c817),
            losses: Losses::default(),
            best_eval: -1.0,
            last_checkpoint: Instant::now(),
            checkpoint_every: Duration::from_secs(learn.checkpoint_every_s),
            warmup_transitions: learn.warmup_transitions,
            critic_window: u64::from(config.ticks.critic_window),
            last_served: 0,
            updates_per_transition: learn.updates_per_transition,
            batch_size: learn.batch_size,
            publish_every_updates: learn.publish_every_updates,
            run_dir: options.run_dir.clone(),
            seed: options.seed,
            algorithm: learn.algorithm,
        })
    }

    /// Stores a finished episode of swarm `swarm`; a noise-free one that lifts the rolling
    /// evaluation success to a new best saves `best.safetensors`.
    pub fn keep(&mut self, swarm: usize, finished: FinishedEpisode, rolling: &Rolling) -> Result<()> {
        if let (true, Some(eval)) = (finished.eval, rolling.eval_success_rate())
            && eval > self.best_eval
        {
            self.best_eval = eval;
            self.learner
                .save(&self.run_dir.join(BEST_FILE_NAME), self.meta(rolling, Some(eval)))?;
        }
        self.swarms[swarm].replay.push(finished.episode);
        Ok(())
    }

    /// Updates still due on swarm `swarm`'s data for its `ticks` received.
    pub fn updates_owed(&self, swarm: usize, ticks: u64) -> u64 {
        updates_owed(
            ticks,
            self.warmup_transitions,
            self.updates_per_transition,
            self.swarms[swarm].updates,
        )
    }

    /// Connects agents that appeared since (they get the latest weights).
    pub fn update_connections(&self) -> Result<()> {
        self.swarms.iter().try_for_each(|s| s.weights.update_connections())
    }

    /// Does the updates owed for each swarm's `ticks` received (in turn), for at most 40 ms (at least one), streams weights
    /// every `publish_every_updates`, checkpoints every `checkpoint_every_s`; returns for each
    /// swarm the ticks its updates have paid for (what the critic may acknowledge to its sim).
    pub fn train(&mut self, ticks: &[u64], rolling: &Rolling) -> Result<Vec<u64>> {
        let started = Instant::now();
        while started.elapsed() < UPDATES_BETWEEN_DRAINS {
            // Round robin over the swarms owed updates: every size gets the same share, and
            // a swarm whose updates are slow (a large N) cannot starve the others.
            let count = self.swarms.len();
            let Some(swarm) = (1..=count)
                .map(|step| (self.last_served + step) % count)
                .find(|&k| self.updates_owed(k, ticks[k]) > 0)
            else {
                break;
            };
            self.last_served = swarm;
            let data = &mut self.swarms[swarm];
            let Some(batch) = self.sampler.sample(&data.replay, self.batch_size, &mut self.rng) else {
                break;
            };
            let step = self.learner.update(&batch)?;
            data.updates += 1;
            self.losses.critic = step.critic;
            if step.actor.is_some() {
                self.losses.actor = step.actor;
                self.losses.action_magnitude = step.action_magnitude;
            }
            if self.learner.updates().is_multiple_of(self.publish_every_updates) || self.weights_version() == 0 {
                for data in &mut self.swarms {
                    data.weights.publish(&self.learner)?;
                }
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
        let mut paid = Vec::with_capacity(self.swarms.len());
        for (k, data) in self.swarms.iter_mut().enumerate() {
            if data.replay.transitions() == 0 {
                // Nothing to learn from yet: let the sim run on.
                paid.push(u64::MAX);
                continue;
            }
            let paid_ticks =
                |updates: u64| self.warmup_transitions as u64 + (updates as f64 / self.updates_per_transition) as u64;
            // A sim that ran on without flow control (it took the critic for gone) is owed
            // for more ticks than its window: paying that debt would hold it for minutes, so
            // everything beyond the window is forgiven.
            let unpaid = ticks[k].saturating_sub(paid_ticks(data.updates));
            if unpaid > 2 * self.critic_window {
                let forgiven = ((unpaid - self.critic_window) as f64 * self.updates_per_transition) as u64;
                data.updates += forgiven;
                eprintln!(
                    "critic: swarm {k} ran {unpaid} ticks ahead while the critic was away; {forgiven} updates forgiven"
                );
            }
            paid.push(paid_ticks(data.updates));
        }
        Ok(paid)
    }

    fn weights_version(&self) -> u32 {
        self.swarms[0].weights.version
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
            weights_version: self.weights_version(),
            replay_transitions: self.swarms.iter().map(|s| s.replay.transitions()).sum(),
            best_eval: (self.best_eval >= 0.0).then_some(self.best_eval),
        }
    }

    fn meta(&self, rolling: &Rolling, eval: Option<f64>) -> HashMap<String, String> {
        let mut extra = HashMap::new();
        extra.insert("updates".into(), self.learner.updates().to_string());
        extra.insert("episodes".into(), rolling.episodes.to_string());
        extra.insert("seed".into(), self.seed.to_string());
        let sizes: Vec<String> = self.swarms.iter().map(|s| s.n_agents.to_string()).collect();
        extra.insert("swarm_sizes".into(), sizes.join(","));
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
