//! Training in the critic process: the learner, one replay and weights stream per swarm it
//! serves, updates at the configured update-to-data ratio on each swarm's data, and the
//! checkpoints, each scored by model selection before it is saved.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_core::config::Algorithm;
use formation_core::run_dir::write_atomically;
use formation_ipc::services::Sizing;
use formation_model::actor::ActorShape;
use formation_model::checkpoint::{self, BEST_FILE_NAME, FILE_NAME, SelectionScore};
use formation_replay::buffer::ReplayBuffer;
use formation_replay::sample::Sampler;
use iceoryx2::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::collector::FinishedEpisode;
use crate::learner::{Learner, LearnerSnapshot, Losses};
use crate::progress::{Rolling, TrainingStatus};
use crate::run::CriticOptions;
use crate::selection::Selector;
use crate::weights::WeightsPublisher;

/// Longest run of updates between two drains of the streams: the critic keeps telling the sim
/// it is alive (and acknowledging) while updates are slow, e.g. a big swarm on a busy machine.
const UPDATES_BETWEEN_DRAINS: Duration = Duration::from_millis(40);

/// Where a critic given `--updates` keeps its target, `RUN_ID TOTAL`: a critic restarted in the
/// same run resumes from the run's last checkpoint and must stop at the same total.
const UPDATE_TARGET_FILE: &str = "update-target.txt";

/// A selection running on its own thread: the score and how long it took.
type Selection = JoinHandle<Result<(SelectionScore, Duration)>>;

/// A checkpoint being scored: the selection's thread, and the networks it scores as they were
/// when it started, with their training figures then (saved once scored; updates go on).
struct PendingCheckpoint {
    selection: Selection,
    snapshot: LearnerSnapshot,
    meta: HashMap<String, String>,
    /// Each swarm's actor steps then, for the log.
    actor_steps: String,
}

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
    selector: Selector,
    /// The selection score of `best.safetensors`, once there is one.
    best: Option<SelectionScore>,
    /// The latest checkpoint's selection score.
    latest: Option<f64>,
    /// The checkpoint being scored, if any.
    selecting: Option<PendingCheckpoint>,
    last_checkpoint: Instant,
    checkpoint_every: Duration,
    /// `learn.keep_checkpoints`: every checkpoint also kept under `checkpoints/`.
    keep_checkpoints: bool,
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
    /// With `--updates`: the learner's total count (the checkpoint's included) at which
    /// training stops.
    stop_at_updates: Option<u64>,
}

impl<S: Service> Trainer<S> {
    /// A fresh learner, or one resumed from `options.resume` (whose weights are streamed at
    /// once so that the agents act with them from the first tick), for the swarms reached
    /// through `nodes` (one node and sizing per swarm, the run's own first).
    pub fn new(swarms: &[(&Node<S>, Sizing)], options: &CriticOptions) -> Result<Self> {
        let config = &options.config;
        let learn = &config.learn;
        let mut learner =
            Learner::new(options.n_agents, &config.env, learn, options.seed)?.with_teacher_gains(config.baseline);
        if let Some(path) = &options.resume {
            learner.load(path)?;
            eprintln!(
                "critic: resumed from {} ({} updates)",
                path.display(),
                learner.updates()
            );
        }
        learner.freeze_start()?;
        let stop_at_updates = options
            .updates
            .map(|updates| update_target(&options.run_dir, &options.run_id, learner.updates() + updates))
            .transpose()?;
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
        let sizes: Vec<usize> = swarms.iter().map(|(_, sizing)| sizing.n_agents).collect();
        let selector = Selector::new(&config.env, learn, &config.reality, &sizes);
        // A restarted critic (resuming in its run directory) keeps its predecessor's best.
        let best = match options.resume {
            Some(_) => previous_best(&options.run_dir, &selector),
            None => None,
        };
        Ok(Self {
            learner,
            swarms: data,
            sampler: Sampler {
                history: config.env.history,
                her_probability: learn.her_probability,
                n_step: learn.n_step,
                gamma: learn.gamma,
                env: config.env.clone(),
                critic: learn.critic,
                critic_map_points: learn.critic_map_points,
            },
            rng: StdRng::seed_from_u64(options.seed ^ 0x5eed_c817),
            losses: Losses::default(),
            selector,
            best,
            latest: None,
            selecting: None,
            last_checkpoint: Instant::now(),
            checkpoint_every: Duration::from_secs(learn.checkpoint_every_s),
            keep_checkpoints: learn.keep_checkpoints,
            warmup_transitions: learn.warmup_transitions,
            critic_window: u64::from(config.ticks.critic_window),
            last_served: 0,
            updates_per_transition: learn.updates_per_transition,
            batch_size: learn.batch_size,
            publish_every_updates: learn.publish_every_updates,
            run_dir: options.run_dir.clone(),
            seed: options.seed,
            algorithm: learn.algorithm,
            stop_at_updates,
        })
    }

    /// Stores a finished episode of swarm `swarm`.
    pub fn keep(&mut self, swarm: usize, finished: FinishedEpisode) {
        self.swarms[swarm].replay.push(finished.episode);
    }

    /// Whether `--updates` are done: no more updates, every tick acknowledged.
    pub fn budget_spent(&self) -> bool {
        self.stop_at_updates
            .is_some_and(|target| self.learner.updates() >= target)
    }

    /// Updates still due on swarm `swarm`'s data for its `ticks` received.
    pub fn updates_owed(&self, swarm: usize, ticks: u64) -> u64 {
        if self.budget_spent() {
            return 0;
        }
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

    /// Does the updates owed for each swarm's `ticks` received, streams weights every
    /// `publish_every_updates` and starts a checkpoint's selection every `checkpoint_every_s`
    /// (saving it once scored); returns for each swarm the ticks its updates have paid for
    /// (what the critic may acknowledge to its sim).
    pub fn train(&mut self, ticks: &[u64], rolling: &Rolling) -> Result<Vec<u64>> {
        if let Some(pending) = self.selecting.take_if(|p| p.selection.is_finished()) {
            self.save_scored(pending)?;
        }
        self.update(ticks)?;
        // Once the budget is spent the weights stay as they are: the end's checkpoint scores them.
        // Until the actor's first step (the critic's warm-up, then the policy delay) it is the
        // run's start: nothing to score.
        if !self.budget_spent()
            && self.learner.actor_has_stepped()
            && self.selecting.is_none()
            && self.last_checkpoint.elapsed() >= self.checkpoint_every
        {
            self.start_selection(rolling)?;
        }
        Ok(self.paid_ticks(ticks))
    }

    /// The updates owed, swarm by swarm in turn, for at most 40 ms (at least one).
    fn update(&mut self, ticks: &[u64]) -> Result<()> {
        let started = Instant::now();
        while started.elapsed() < UPDATES_BETWEEN_DRAINS {
            // Round robin over the swarms owed updates: every size gets the same share, and
            // a swarm whose updates are slow (a large N) cannot starve the others. The actor
            // steps on each swarm's own schedule, so it gets the same share too.
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
            let step = self.learner.update(&batch, swarm)?;
            data.updates += 1;
            self.losses.critic = step.critic;
            if step.actor.is_some() {
                self.losses.actor = step.actor;
                self.losses.action_magnitude = step.action_magnitude;
                self.losses.actor_gradient_rms = step.actor_gradient_rms;
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
        Ok(())
    }

    /// For each swarm, the ticks its updates have paid for.
    fn paid_ticks(&mut self, ticks: &[u64]) -> Vec<u64> {
        let spent = self.budget_spent();
        let mut paid = Vec::with_capacity(self.swarms.len());
        for (k, data) in self.swarms.iter_mut().enumerate() {
            if data.replay.transitions() == 0 || spent {
                // Nothing to learn from yet, or nothing more to learn: let the sim run on.
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
        paid
    }

    fn weights_version(&self) -> u32 {
        self.swarms[0].weights.version
    }

    /// The flat weights of every actor, as saved and as streamed.
    fn actor_weights(&self) -> Result<Vec<Vec<f32>>> {
        (0..self.learner.n_actors())
            .map(|k| self.learner.actor_weights(k))
            .collect()
    }

    /// Scores the current weights on a thread of its own while updates go on: the networks
    /// are copied as they are now, and saved with their score once it comes.
    fn start_selection(&mut self, rolling: &Rolling) -> Result<()> {
        let actors = self.actor_weights()?;
        let selector = self.selector.clone();
        let shape = self.learner.actor_shape().clone();
        let selection = std::thread::Builder::new()
            .name("selection".into())
            .spawn(move || {
                // The thread that drains the streams and acknowledges ticks comes first.
                formation_ipc::placement::run_in_the_background();
                timed_score(&selector, &actors, &shape)
            })
            .context("critic: cannot start the selection thread")?;
        self.selecting = Some(self.pending(selection, rolling)?);
        self.last_checkpoint = Instant::now();
        Ok(())
    }

    /// The checkpoint `selection` scores: the networks and their figures as they are now.
    fn pending(&self, selection: Selection, rolling: &Rolling) -> Result<PendingCheckpoint> {
        // Each swarm's batches step the actor on a schedule of their own (learner::SwarmSteps).
        let actor_steps: Vec<String> = (0..self.swarms.len())
            .map(|k| format!("N={} {}", self.swarms[k].n_agents, self.learner.swarm_steps(k).actor))
            .collect();
        Ok(PendingCheckpoint {
            selection,
            snapshot: self.learner.snapshot()?,
            meta: self.meta(rolling),
            actor_steps: actor_steps.join(", "),
        })
    }

    /// The checkpoint at the end of a run: the one being scored, if any, is finished and saved;
    /// then the current weights are scored and saved unless they are those.
    pub fn save_checkpoint(&mut self, rolling: &Rolling) -> Result<()> {
        let updates = self.learner.updates().to_string();
        if let Some(pending) = self.selecting.take() {
            let current = pending.meta["updates"] == updates;
            self.save_scored(pending)?;
            if current {
                return Ok(());
            }
        }
        let actors = self.actor_weights()?;
        let shape = self.learner.actor_shape().clone();
        let selector = self.selector.clone();
        let selection = std::thread::spawn(move || timed_score(&selector, &actors, &shape));
        let pending = self.pending(selection, rolling)?;
        self.save_scored(pending)
    }

    /// Saves a scored checkpoint as `checkpoint.safetensors` with its selection score, and as
    /// `best.safetensors` too when it beats the best so far.
    fn save_scored(&mut self, pending: PendingCheckpoint) -> Result<()> {
        let (score, took) = joined(pending.selection)?;
        let mut meta = pending.meta;
        score.to_metadata(&mut meta);
        pending.snapshot.save(&self.run_dir.join(FILE_NAME), meta.clone())?;
        if self.keep_checkpoints {
            let kept = self.run_dir.join("checkpoints");
            std::fs::create_dir_all(&kept).with_context(|| format!("cannot create {}", kept.display()))?;
            let updates: u64 = meta["updates"].parse().context("critic: updates of a checkpoint")?;
            let name = format!("updates-{updates:08}.safetensors");
            std::fs::copy(self.run_dir.join(FILE_NAME), kept.join(&name))
                .with_context(|| format!("cannot keep the checkpoint as {}", kept.join(&name).display()))?;
        }
        let better = score.beats(self.best.as_ref());
        if better {
            pending
                .snapshot
                .save(&self.run_dir.join(BEST_FILE_NAME), meta.clone())?;
        }
        let by_size: Vec<String> = score
            .sizes
            .iter()
            .map(|s| format!("N={} {:.2}", s.n_agents, s.success))
            .collect();
        // Under a reality the score is played under it; the ideal world is reported beside it.
        let ideal = score.ideal.as_ref().map_or(String::new(), |ideal| {
            let by_size: Vec<String> = ideal
                .iter()
                .map(|s| format!("N={} {:.2} in {:.1} steps", s.n_agents, s.success, s.mean_steps))
                .collect();
            format!("; ideal world {}", by_size.join(", "))
        });
        eprintln!(
            "critic: checkpoint at {} updates (actor steps {}): selection success {:.3} ({}){}, formation held {:.2}, {:.1} steps{ideal}; scored in {} ms{}",
            meta["updates"],
            pending.actor_steps,
            score.success(),
            by_size.join(", "),
            if score.reality.is_some() {
                " under the run's reality"
            } else {
                ""
            },
            score.mean(|s| s.formation_held),
            score.mean(|s| s.mean_steps),
            took.as_millis(),
            if better { "; new best" } else { "" }
        );
        self.latest = Some(score.success());
        if better {
            self.best = Some(score);
        }
        Ok(())
    }

    /// Figures for the progress display and `training.csv`.
    pub fn status(&self) -> TrainingStatus {
        TrainingStatus {
            updates: self.learner.updates(),
            run_updates: self.learner.run_updates(),
            losses: self.losses,
            weights_version: self.weights_version(),
            replay_transitions: self.swarms.iter().map(|s| s.replay.transitions()).sum(),
            selection: self.latest,
            best_selection: self.best.as_ref().map(SelectionScore::success),
            update_target: self.stop_at_updates,
        }
    }

    fn meta(&self, rolling: &Rolling) -> HashMap<String, String> {
        let mut extra = HashMap::new();
        extra.insert("updates".into(), self.learner.updates().to_string());
        extra.insert("episodes".into(), rolling.episodes.to_string());
        extra.insert("seed".into(), self.seed.to_string());
        let sizes: Vec<String> = self.swarms.iter().map(|s| s.n_agents.to_string()).collect();
        extra.insert("swarm_sizes".into(), sizes.join(","));
        extra.insert("algorithm".into(), format!("{:?}", self.algorithm).to_lowercase());
        // Actor steps of this run: 0 while the critic warms up (the actor is still the start's).
        let actor_steps: u64 = (0..self.swarms.len()).map(|k| self.learner.swarm_steps(k).actor).sum();
        extra.insert("run_actor_steps".into(), actor_steps.to_string());
        extra.insert("success_rate_100".into(), format!("{:.3}", rolling.success_rate()));
        extra
    }
}

/// The selection score of `actors` and how long it took.
fn timed_score(selector: &Selector, actors: &[Vec<f32>], shape: &ActorShape) -> Result<(SelectionScore, Duration)> {
    let started = Instant::now();
    Ok((selector.score(actors, shape)?, started.elapsed()))
}

/// The outcome of a finished (or finishing) selection thread.
fn joined(selection: Selection) -> Result<(SelectionScore, Duration)> {
    selection
        .join()
        .map_err(|_| anyhow::anyhow!("critic: the selection thread panicked"))?
}

/// The selection score of `best.safetensors` in `run_dir` if it was measured on `selector`'s
/// episodes; an unreadable file is reported and ignored (it will be replaced).
fn previous_best(run_dir: &Path, selector: &Selector) -> Option<SelectionScore> {
    let path = run_dir.join(BEST_FILE_NAME);
    if !path.is_file() {
        return None;
    }
    match checkpoint::load(&path).and_then(|loaded| loaded.meta.selection(&path)) {
        Ok(score) => score.filter(|score| selector.measured(score)),
        Err(err) => {
            eprintln!("critic: ignoring the best so far: {err:#}");
            None
        }
    }
}

/// The total update count at which a critic given `--updates` stops: `proposed` (its start's
/// count plus the budget), unless an earlier critic of the same run (`run_id`) wrote one into
/// `run_dir`, which a restarted critic keeps.
fn update_target(run_dir: &Path, run_id: &str, proposed: u64) -> Result<u64> {
    let path = run_dir.join(UPDATE_TARGET_FILE);
    let earlier = std::fs::read_to_string(&path).ok().and_then(|text| {
        let (id, total) = text.trim().split_once(' ')?;
        (id == run_id).then(|| total.parse().ok()).flatten()
    });
    if let Some(total) = earlier {
        return Ok(total);
    }
    write_atomically(&path, format!("{run_id} {proposed}\n").as_bytes())?;
    Ok(proposed)
}

/// Updates still due at `ratio` updates per tick after `warmup` ticks.
fn updates_owed(ticks: u64, warmup: usize, ratio: f64, done: u64) -> u64 {
    if ticks < warmup as u64 {
        return 0;
    }
    let due = ((ticks - warmup as u64) as f64 * ratio) as u64;
    due.saturating_sub(done)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_restarted_critic_keeps_its_run_s_update_target_and_a_new_run_sets_its_own() {
        let dir = std::env::temp_dir().join(format!("formation-update-target-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        // The first critic of run A: its start's count plus the budget.
        assert_eq!(update_target(&dir, "runA", 1_500).expect("target"), 1_500);
        // Restarted from the run's last checkpoint (say 900 updates in, asking 900 + 1_000).
        assert_eq!(update_target(&dir, "runA", 1_900).expect("target"), 1_500);
        // A new run in the same directory is not bound by the old one's.
        assert_eq!(update_target(&dir, "runB", 700).expect("target"), 700);
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
