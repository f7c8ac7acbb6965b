//! Distillation: the shared actor taught its teacher's command for every observation the robots
//! are told, by DAgger (Ross, Gordon and Bagnell 2011, "A Reduction of Imitation Learning and
//! Structured Prediction to No-Regret Online Learning"), in-process and offline.
//!
//! The teacher is the scripted baseline with the run's `[baseline]` gains (or, among obstacles,
//! a planner that knows the map, the team's or each robot's own,
//! `DistillOptions::planner_teacher`), answering from what
//! the robot was told (the noisy observation under a `[reality]`), as a scripted agent does.
//! A student with a command head is taught the teacher's command; one with a gains head (a gain
//! schedule, [`ActorHead::Gains`]) is taught the teacher's gains, and runs the baseline's law
//! with the gains it outputs.
//! Each round plays episodes of every swarm size as a lockstep sim plays them (the games of
//! model selection, [`crate::selection`]), labels every answer a robot gives with the teacher's
//! command for the same window, and adds the pairs to a buffer; then the actor takes gradient
//! steps on the mean squared error to those labels. The first round the teacher drives; later
//! rounds the student drives most episodes, so the buffer holds the states the student reaches
//! (DAgger's point: a copy that drifts is taught the way back).
//!
//! Why beside TD3+BC: the imitation term of an RL update is a few hundred samples of one batch
//! among the critic's updates, a dozen a second with a swarm of 44 robots on two CPUs; here
//! the actor takes hundreds of pure regression steps a second, and a student copies its
//! teacher to within a millimetre of formation precision where TD3+BC left ten (docs/RESULTS.md,
//! "Distillation").

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, ensure};
use candle_core::{DType, Device, Tensor};
use candle_nn::{AdamW, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use formation_core::baseline::{BaselineGains, ScriptedBaseline};
use formation_core::config::{EnvConfig, RunConfig};
use formation_core::observation::Layout;
use formation_core::task::Outcome;
use formation_model::actor::{Actor, ActorHead, ActorShape, FrozenActor, var_map_actor_weights};
use formation_model::checkpoint::{self, CheckpointMeta, actor_prefix};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::learner::reinitialise;
use crate::selection::{PlannerKind, Played, TruthPlanner};

/// How a distillation runs.
#[derive(Debug, Clone)]
pub struct DistillOptions {
    /// Swarm sizes played every round.
    pub sizes: Vec<usize>,
    /// Robots per size and round: each size plays ceil(this / N) episodes a round.
    pub robots_per_round: usize,
    /// Gradient steps after each round's episodes.
    pub updates_per_round: usize,
    /// Samples per gradient step.
    pub batch: usize,
    /// Share of the episodes after the first round that the teacher drives (the first round it
    /// drives them all; the student drives the rest).
    pub teacher_share: f64,
    /// Learning rate of the first round; it decays exponentially to `lr_end` at `rounds`.
    pub lr_start: f64,
    /// Learning rate of the last round.
    pub lr_end: f64,
    /// Rounds the learning rate decays over.
    pub rounds: usize,
    /// Labelled samples kept (the oldest are overwritten).
    pub capacity: usize,
    /// Seeds the episodes, the sampling and a fresh actor's weights.
    pub seed: u64,
    /// A privileged teacher: the gains for a robot whose drawn position noise is at most
    /// `quiet_below_m` (the run's `[baseline]` gains apply from `noise_scale_m` up, blended
    /// linearly between). `None`: the `[baseline]` gains for every robot.
    pub quiet_teacher: Option<BaselineGains>,
    /// The position noise (standard deviation, metres) up to which the quiet teacher applies in
    /// full: a whole band of windows with one answer, which a student learns flat.
    pub quiet_below_m: f64,
    /// The position noise (standard deviation, metres) from which the `[baseline]` gains apply
    /// in full.
    pub noise_scale_m: f64,
    /// With a quiet teacher: the actuation delay (ticks) from which the `[baseline]` gains apply
    /// in full whatever the noise. `None`: the noise alone chooses.
    pub soft_from_delay_ticks: Option<u32>,
    /// What the student outputs (a student carried on from a checkpoint has the checkpoint's).
    pub head: ActorHead,
    /// A planner that knows the map teaches instead of the scripted baseline (command heads
    /// only): every robot's label is the planner's command for it at that tick, planned from
    /// the true state as the sim's truth stream carries it. `None`: the baseline teaches.
    pub planner_teacher: Option<PlannerKind>,
    /// How the student's distance to its labels is measured.
    pub loss: ImitationLoss,
    /// A teacher with memory: every robot's recovery behaviour ([`formation_core::recovery`])
    /// runs in the episodes with this longest recovery (ticks), and where it takes over a
    /// robot's motors its command is the label (command heads only). `None`: the config's
    /// `[obstacles] recovery_ticks` plays, and only the teacher's command is taught.
    pub teach_recovery_ticks: Option<u32>,
    /// A learned teacher: this checkpoint's shared actor answers every window instead of the
    /// scripted baseline (command heads only, a window of the student's width). With
    /// `teach_recovery_ticks` the recovery answers where it takes over: a student learns its
    /// teacher and the recovery together (expert iteration). `None`: the baseline teaches.
    pub actor_teacher: Option<PathBuf>,
}

/// The student's error to its labels, per output.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum ImitationLoss {
    /// The squared error: the student learns the teacher's mean answer for what it sees.
    #[default]
    Squared,
    /// The absolute error: the student learns the teacher's median answer, so where the teacher
    /// answers one of two ways (stop or go, left or right) it takes the more frequent one
    /// instead of a mean between them.
    Absolute,
}

impl ImitationLoss {
    /// The mean error of a batch's `outputs` to its `labels` (rows are samples), one per output.
    pub fn per_output(self, outputs: &Tensor, labels: &Tensor) -> candle_core::Result<Tensor> {
        let error = (outputs - labels)?;
        match self {
            Self::Squared => error.sqr()?,
            Self::Absolute => error.abs()?,
        }
        .mean(0)
    }
}

impl Default for DistillOptions {
    fn default() -> Self {
        Self {
            sizes: vec![3, 12, 32],
            robots_per_round: 96,
            updates_per_round: 400,
            batch: 1024,
            teacher_share: 0.2,
            lr_start: 1e-3,
            lr_end: 3e-5,
            rounds: 400,
            capacity: 2_000_000,
            seed: 1,
            quiet_teacher: None,
            quiet_below_m: 0.0,
            noise_scale_m: 0.05,
            soft_from_delay_ticks: None,
            head: ActorHead::Command,
            planner_teacher: None,
            actor_teacher: None,
            loss: ImitationLoss::Squared,
            teach_recovery_ticks: None,
        }
    }
}

/// Labelled windows: each robot window the actor reads and the teacher's outputs for it.
#[derive(Debug, Clone)]
pub struct Samples {
    windows: Vec<f32>,
    labels: Vec<f32>,
    width: usize,
    label_width: usize,
    capacity: usize,
    next: usize,
    len: usize,
}

impl Samples {
    /// An empty buffer of `capacity` windows of `width` floats, labelled with `label_width`.
    pub fn new(width: usize, label_width: usize, capacity: usize) -> Self {
        Self {
            windows: vec![0.0; width * capacity],
            labels: vec![0.0; label_width * capacity],
            width,
            label_width,
            capacity,
            next: 0,
            len: 0,
        }
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether none are held.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Adds one, overwriting the oldest when full; returns where it is stored (for
    /// [`Samples::relabel`], until `capacity` more are pushed).
    pub fn push(&mut self, window: &[f32], label: &[f32]) -> usize {
        let (i, l) = (self.next, self.label_width);
        self.windows[i * self.width..(i + 1) * self.width].copy_from_slice(window);
        self.labels[l * i..l * (i + 1)].copy_from_slice(label);
        self.next = (self.next + 1) % self.capacity;
        self.len = (self.len + 1).min(self.capacity);
        i
    }

    /// Replaces the label of the sample stored at `stored` (what [`Samples::push`] returned).
    pub fn relabel(&mut self, stored: usize, label: &[f32]) {
        let l = self.label_width;
        self.labels[l * stored..l * (stored + 1)].copy_from_slice(label);
    }

    /// Sample `i` (0 = the oldest still held).
    pub fn get(&self, i: usize) -> (&[f32], &[f32]) {
        let slot = (self.next + self.capacity - self.len + i) % self.capacity;
        let l = self.label_width;
        let window = &self.windows[slot * self.width..(slot + 1) * self.width];
        (window, &self.labels[l * slot..l * (slot + 1)])
    }

    /// Windows and labels of `rows` as two tensors.
    fn batch(&self, rows: impl Iterator<Item = usize>, device: &Device) -> Result<(Tensor, Tensor)> {
        let mut windows = Vec::new();
        let mut labels = Vec::new();
        for i in rows {
            let (window, label) = self.get(i);
            windows.extend_from_slice(window);
            labels.extend_from_slice(label);
        }
        let rows = labels.len() / self.label_width;
        Ok((
            Tensor::from_vec(windows, (rows, self.width), device)?,
            Tensor::from_vec(labels, (rows, self.label_width), device)?,
        ))
    }
}

/// What one swarm size did in a round, driven by the student.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StudentScore {
    /// Robots.
    pub n_agents: usize,
    /// Successful share of the episodes the student drove (`None`: the teacher drove them all).
    pub success: Option<f64>,
}

/// One round's figures.
#[derive(Debug, Clone, PartialEq)]
pub struct RoundReport {
    /// Rounds done, this one included.
    pub round: usize,
    /// Samples in the buffer.
    pub samples: usize,
    /// Mean error ([`DistillOptions::loss`]) of the round's gradient steps (outputs in [-1, 1]).
    pub loss: f64,
    /// The same error for each output alone (the command head: v, then w; the gains head: its five gains).
    pub loss_per_output: Vec<f64>,
    /// The learning rate of the round.
    pub lr: f64,
    /// Each size's episodes the student drove.
    pub student: Vec<StudentScore>,
}

/// A distillation in progress: the teacher, the student actor and its optimiser, the buffer.
pub struct Distiller {
    config: RunConfig,
    /// The world the rounds play: the config's, with the recovery behaviour a teacher with
    /// memory needs ([`DistillOptions::teach_recovery_ticks`]).
    play_env: EnvConfig,
    options: DistillOptions,
    shape: ActorShape,
    vars: VarMap,
    actor: Actor,
    optimiser: AdamW,
    samples: Samples,
    rng: StdRng,
    round: usize,
    device: Device,
    /// [`DistillOptions::actor_teacher`], loaded.
    actor_teacher: Option<FrozenActor>,
}

impl Distiller {
    /// A student of the shape `config` asks for (`env.history`, `learn.actor_hidden`) with the
    /// options' head, fresh or carried over from the shared actor of `start`.
    pub fn new(config: &RunConfig, options: DistillOptions, start: Option<&Path>) -> Result<Self> {
        config.validate()?;
        ensure!(!options.sizes.is_empty(), "distillation needs at least one swarm size");
        for &n in &options.sizes {
            formation_core::config::validate_agent_count(n)?;
        }
        ensure!(
            options.batch > 0
                && options.capacity >= options.batch
                && options.rounds > 0
                && options.robots_per_round > 0,
            "batch, rounds and robots per round must be > 0 and the buffer at least a batch"
        );
        ensure!(
            options.noise_scale_m.is_finite() && options.noise_scale_m > 0.0,
            "the noise scale must be > 0 metres, not {}",
            options.noise_scale_m
        );
        ensure!(
            (0.0..options.noise_scale_m).contains(&options.quiet_below_m),
            "the quiet band must lie in [0, {}) metres (the noise scale), not {}",
            options.noise_scale_m,
            options.quiet_below_m
        );
        if let Some(quiet) = &options.quiet_teacher {
            quiet.validate()?;
        }
        ensure!(
            options.planner_teacher.is_none()
                || (options.head == ActorHead::Command && options.quiet_teacher.is_none()),
            "the planner teaches commands only, and alone (no quiet teacher, no gains head)"
        );
        if options.head == ActorHead::Gains {
            for (teacher, gains) in [
                ("[baseline]", Some(config.baseline)),
                ("the quiet teacher", options.quiet_teacher),
            ] {
                if let Some(gains) = gains {
                    gains
                        .check_schedulable()
                        .map_err(|why| anyhow::anyhow!("{teacher}: {why}; a gains head cannot be taught it"))?;
                }
            }
        }
        ensure!(
            (0.0..=1.0).contains(&options.teacher_share),
            "the teacher's share of episodes must lie in [0, 1], not {}",
            options.teacher_share
        );
        let layout = Layout::of(config.env.observation);
        let mut play_env = config.env.clone();
        if let Some(ticks) = options.teach_recovery_ticks {
            ensure!(
                ticks > 0 && options.head == ActorHead::Command && layout.scan().is_some(),
                "the recovery teaches commands only, to a student that reads a scan (env.observation = \"slot_proximity_scan\"), for at least one tick"
            );
            play_env.obstacles.recovery_ticks = ticks;
        }
        let shape = ActorShape {
            obs_dim: layout.dim(),
            history: config.env.history,
            hidden: config.learn.actor_hidden.clone(),
            head: options.head,
        };
        let actor_teacher = options
            .actor_teacher
            .as_deref()
            .map(|path| load_actor_teacher(path, &shape, config))
            .transpose()?;
        ensure!(
            actor_teacher.is_none() || (options.planner_teacher.is_none() && options.quiet_teacher.is_none()),
            "a learned teacher teaches alone (no planner, no quiet teacher)"
        );
        let device = Device::Cpu;
        let vars = VarMap::new();
        let actor = Actor::new(
            VarBuilder::from_varmap(&vars, DType::F32, &device).pp(actor_prefix(0).trim_end_matches('.')),
            &shape,
        )?;
        let mut rng = StdRng::seed_from_u64(options.seed);
        match start {
            Some(path) => load_shared_actor(&vars, path, &shape, config)?,
            None => reinitialise(&vars, &mut rng)?,
        }
        let optimiser = AdamW::new(
            vars.all_vars(),
            ParamsAdamW {
                lr: options.lr_start,
                weight_decay: 0.0,
                ..Default::default()
            },
        )?;
        Ok(Self {
            samples: Samples::new(shape.input_dim(), shape.head.outputs(), options.capacity),
            config: config.clone(),
            play_env,
            options,
            shape,
            vars,
            actor,
            optimiser,
            rng,
            round: 0,
            device,
            actor_teacher,
        })
    }

    /// The teacher's gains for a robot whose drawn position noise is `sigma` metres and actuation
    /// delay `delay` ticks: the `[baseline]` gains, or with a quiet teacher the quiet gains up to
    /// `quiet_below_m`, the `[baseline]` gains from `noise_scale_m` (or from
    /// `soft_from_delay_ticks` of delay), blended linearly between.
    pub fn teacher_gains(&self, sigma: f64, delay: u32) -> BaselineGains {
        let noisy = self.config.baseline;
        match self.options.quiet_teacher {
            None => noisy,
            Some(quiet) => {
                let (below, scale) = (self.options.quiet_below_m, self.options.noise_scale_m);
                let delayed = self.options.soft_from_delay_ticks.is_some_and(|from| delay >= from);
                let t = if delayed {
                    1.0
                } else {
                    ((sigma - below) / (scale - below)).clamp(0.0, 1.0)
                };
                let (quiet, noisy) = (quiet.values(), noisy.values());
                BaselineGains::from_values(std::array::from_fn(|i| quiet[i] + t * (noisy[i] - quiet[i])))
            }
        }
    }

    /// The student's shape.
    pub fn shape(&self) -> &ActorShape {
        &self.shape
    }

    /// The student's weights, flat as agents load them.
    pub fn actor_weights(&self) -> Result<Vec<f32>> {
        var_map_actor_weights(&self.vars, &actor_prefix(0), &self.shape)
    }

    /// One round: every size's episodes (the teacher driving in the first round, then a
    /// `teacher_share` of them), every answer labelled; then the gradient steps.
    pub fn round(&mut self) -> Result<RoundReport> {
        let first = self.round == 0;
        let mut student = FrozenActor::from_flat(&self.actor_weights()?, &self.shape)?;
        let mut scores = Vec::with_capacity(self.options.sizes.len());
        for &n in &self.options.sizes.clone() {
            let played = Played {
                seed: episode_seed(self.options.seed, self.round, n),
                count: self.options.robots_per_round.div_ceil(n),
                reality: &self.config.reality,
            };
            let (mut student_episodes, mut student_successes) = (0usize, 0usize);
            for mut game in played.games(&self.play_env, n) {
                let teacher_drives = first || self.rng.random::<f64>() < self.options.teacher_share;
                let teachers: Vec<(ScriptedBaseline, [f32; 5])> = (0..n)
                    .map(|agent| {
                        let reality = game.reality();
                        let gains = self.teacher_gains(reality.position_noise_m(agent), reality.delay(agent));
                        (ScriptedBaseline::new(&self.config.env, gains), gains.to_unit())
                    })
                    .collect();
                let mut planner = self
                    .options
                    .planner_teacher
                    .map(|kind| TruthPlanner::new(kind, &self.config.env));
                while game.running() {
                    let planned = match &mut planner {
                        Some(planner) => planner.commands(game.world(), &self.config.env, self.config.baseline),
                        None => Vec::new(),
                    };
                    let (env, samples, head) = (&self.config.env, &mut self.samples, self.shape.head);
                    let teaches_recovery = self.options.teach_recovery_ticks.is_some();
                    let mut stored = vec![None; if teaches_recovery { n } else { 0 }];
                    let mut actor_teacher = self.actor_teacher.as_mut();
                    game.step(|asked| {
                        let (teacher, unit_gains) = &teachers[asked.agent];
                        let (v, w) = match (planned.get(asked.agent), actor_teacher.as_mut()) {
                            (Some(&command), _) => command,
                            (None, Some(actor)) => actor.command(asked.window.as_flat(), env)?,
                            (None, None) => teacher.command_in(asked.window.as_flat()),
                        };
                        let action = env.action_from_command(v, w);
                        if asked.present {
                            let label: &[f32] = match head {
                                ActorHead::Command => &action,
                                ActorHead::Gains => unit_gains,
                            };
                            let at = samples.push(asked.window.as_flat(), label);
                            if let Some(stored) = stored.get_mut(asked.agent) {
                                *stored = Some(at);
                            }
                        }
                        if teacher_drives {
                            // The command the label stands for.
                            Ok(env.command_from_action(action))
                        } else {
                            student.command(asked.window.as_flat(), env)
                        }
                    })?;
                    // Where a robot's recovery took its motors over, the teacher with memory
                    // answered with the recovery's command.
                    for (agent, stored) in stored.into_iter().enumerate() {
                        if let (Some(stored), Some((v, w))) = (stored, game.recovery_command(agent)) {
                            samples.relabel(stored, &env.action_from_command(v, w));
                        }
                    }
                }
                if !teacher_drives {
                    student_episodes += 1;
                    student_successes += usize::from(game.outcome() == Outcome::Success);
                }
            }
            scores.push(StudentScore {
                n_agents: n,
                success: (student_episodes > 0).then(|| student_successes as f64 / student_episodes as f64),
            });
        }
        let lr = self.learning_rate();
        self.optimiser.set_learning_rate(lr);
        let updates = self.options.updates_per_round.max(1) as f64;
        let mut loss_sum = vec![0.0; self.shape.head.outputs()];
        for _ in 0..self.options.updates_per_round {
            let len = self.samples.len();
            let rows: Vec<usize> = (0..self.options.batch).map(|_| self.rng.random_range(0..len)).collect();
            let (windows, labels) = self.samples.batch(rows.into_iter(), &self.device)?;
            let per_output = self.options.loss.per_output(&self.actor.forward(&windows)?, &labels)?;
            self.optimiser.backward_step(&per_output.mean_all()?)?;
            for (sum, loss) in loss_sum.iter_mut().zip(per_output.to_vec1::<f32>()?) {
                *sum += f64::from(loss);
            }
        }
        self.round += 1;
        let loss_per_output: Vec<f64> = loss_sum.iter().map(|sum| sum / updates).collect();
        Ok(RoundReport {
            round: self.round,
            samples: self.samples.len(),
            loss: loss_per_output.iter().sum::<f64>() / loss_per_output.len() as f64,
            loss_per_output,
            lr,
            student: scores,
        })
    }

    /// This round's learning rate: `lr_start` decaying exponentially to `lr_end` over `rounds`.
    fn learning_rate(&self) -> f64 {
        let o = &self.options;
        let progress = self.round as f64 / (o.rounds.max(2) - 1) as f64;
        o.lr_start * (o.lr_end / o.lr_start).powf(progress.min(1.0))
    }

    /// The student's mean squared error to the labels of `samples` (outputs in [-1, 1]).
    pub fn mean_squared_error(&self, samples: &Samples) -> Result<f64> {
        ensure!(!samples.is_empty(), "no samples to measure the student on");
        let (windows, labels) = samples.batch(0..samples.len(), &self.device)?;
        let error = (self.actor.forward(&windows)? - labels)?.sqr()?.mean_all()?;
        Ok(f64::from(error.to_scalar::<f32>()?))
    }

    /// Writes the student as a checkpoint of one shared actor (its target copy too, so training
    /// can carry it on with a fresh critic), with `extra` and the teacher's gains as metadata.
    pub fn save(&self, path: &Path, mut extra: HashMap<String, String>) -> Result<()> {
        let gains = gains_text(&self.config.baseline);
        let teacher = match self.options.planner_teacher {
            Some(PlannerKind::Team) => format!("planner (tracking with {gains})"),
            Some(PlannerKind::Solo) => format!("solo planner (tracking with {gains})"),
            Some(PlannerKind::SoloLocal) => {
                format!(
                    "solo planner seeing {} m (tracking with {gains})",
                    self.config.env.scan_range_m
                )
            }
            None => match &self.options.actor_teacher {
                Some(path) => format!("actor {}", path.display()),
                None => gains,
            },
        };
        extra.insert("distilled_from".into(), teacher);
        if let Some(quiet) = self.options.quiet_teacher {
            extra.insert(
                "distilled_from_quiet".into(),
                format!(
                    "{} up to {} m of position noise, blended up to {} m",
                    gains_text(&quiet),
                    self.options.quiet_below_m,
                    self.options.noise_scale_m
                ) + &self.options.soft_from_delay_ticks.map_or(String::new(), |ticks| {
                    format!(", the config's from {ticks} ticks of delay")
                }),
            );
        }
        extra.insert("distill_rounds".into(), self.round.to_string());
        extra.insert("distill_seed".into(), self.options.seed.to_string());
        let data = self
            .vars
            .data()
            .lock()
            .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
        let mut names: Vec<&String> = data.keys().collect();
        names.sort();
        let mut tensors = Vec::with_capacity(2 * names.len());
        for prefix in ["", "target."] {
            for name in &names {
                tensors.push((format!("{prefix}{name}"), data[*name].as_tensor().clone()));
            }
        }
        let meta = CheckpointMeta {
            n_agents: *self.options.sizes.iter().max().expect("sizes checked non-empty"),
            observation: self.config.env.observation,
            n_actors: 1,
            actor: self.shape.clone(),
            extra,
        };
        checkpoint::save(path, &tensors, &meta)
    }
}

/// Gains as the checkpoint's metadata names a teacher: "baseline k_form 0.45 k_goal ...".
fn gains_text(gains: &BaselineGains) -> String {
    let pairs: Vec<String> = BaselineGains::NAMES
        .iter()
        .zip(gains.values())
        .map(|(name, value)| format!("{name} {value}"))
        .collect();
    format!("baseline {}", pairs.join(" "))
}

/// The teacher's labelled windows of `count` episodes of `n` robots from `seed`, the teacher
/// driving: a fixed yardstick for the student's error.
pub fn teacher_samples(config: &RunConfig, n: usize, seed: u64, count: usize) -> Result<Samples> {
    let teacher = ScriptedBaseline::new(&config.env, config.baseline);
    let width = Layout::of(config.env.observation).dim() * config.env.history;
    let mut samples = Samples::new(
        width,
        ActorHead::Command.outputs(),
        count * n * config.env.episode_steps(n) as usize,
    );
    let played = Played {
        seed,
        count,
        reality: &config.reality,
    };
    let env = &config.env;
    for mut game in played.games(env, n) {
        while game.running() {
            game.step(|asked| {
                let (v, w) = teacher.command_in(asked.window.as_flat());
                if asked.present {
                    samples.push(asked.window.as_flat(), &env.action_from_command(v, w));
                }
                Ok((v, w))
            })?;
        }
    }
    Ok(samples)
}

/// The mean and standard deviation of each gain a gain schedule ([`ActorHead::Gains`]) answers
/// over every window of `count` episodes of `n` robots from `seed` under `reality`, in the order
/// of [`BaselineGains::values`]: what it learned to pick where.
pub fn gain_profile(
    env: &formation_core::config::EnvConfig,
    reality: &formation_core::reality::RealityConfig,
    shape: &ActorShape,
    weights: &[f32],
    (n, seed, count): (usize, u64, usize),
) -> Result<[(f64, f64); 5]> {
    ensure!(shape.head == ActorHead::Gains, "only a gains head has a gain profile");
    let mut actor = FrozenActor::from_flat(weights, shape)?;
    let (mut sum, mut sum_sq, mut answers) = ([0.0f64; 5], [0.0f64; 5], 0usize);
    let played = Played { seed, count, reality };
    for mut game in played.games(env, n) {
        while game.running() {
            game.step(|asked| {
                let window = asked.window.as_flat();
                let gains = BaselineGains::from_unit(actor.act(window)?);
                for (i, value) in gains.values().into_iter().enumerate() {
                    sum[i] += value;
                    sum_sq[i] += value * value;
                }
                answers += 1;
                actor.command(window, env)
            })?;
        }
    }
    ensure!(answers > 0, "no robot answered");
    Ok(std::array::from_fn(|i| {
        let mean = sum[i] / answers as f64;
        (mean, (sum_sq[i] / answers as f64 - mean * mean).max(0.0).sqrt())
    }))
}

/// The episode seed of size `n` in round `round`: far above the held-out seeds (1000 and up),
/// the gain searches' (2000) and model selection's, and distinct for every round and size.
fn episode_seed(seed: u64, round: usize, n: usize) -> u64 {
    (1 << 40) + seed.wrapping_mul(0x9E37_79B9) + ((round as u64) << 8) + n as u64
}

/// The shared actor of `path` as a teacher: a command head reading the student's window.
fn load_actor_teacher(path: &Path, student: &ActorShape, config: &RunConfig) -> Result<FrozenActor> {
    let loaded = load_observing(path, student, config)?;
    let shape = &loaded.meta.actor;
    ensure!(
        loaded.meta.n_actors == 1
            && shape.head == ActorHead::Command
            && shape.history == student.history
            && student.head == ActorHead::Command,
        "the teacher {} must be one shared actor with a command head reading the student's window, H = {} (it has {} actor(s), head {:?}, H = {})",
        loaded.path.display(),
        student.history,
        loaded.meta.n_actors,
        shape.head,
        shape.history
    );
    FrozenActor::from_flat(&loaded.actor_weights(0)?, shape)
}

/// The checkpoint at `path`, refused unless it observes as the config's student of `shape`.
fn load_observing(path: &Path, shape: &ActorShape, config: &RunConfig) -> Result<checkpoint::Checkpoint> {
    let loaded = checkpoint::load(&checkpoint::resolve(path)?)?;
    loaded
        .meta
        .check_observation(&loaded.path, config.env.observation, shape.obs_dim)?;
    Ok(loaded)
}

/// Loads the shared actor of `path` into `vars`.
fn load_shared_actor(vars: &VarMap, path: &Path, shape: &ActorShape, config: &RunConfig) -> Result<()> {
    let loaded = load_observing(path, shape, config)?;
    ensure!(
        loaded.meta.n_actors == 1 && &loaded.meta.actor == shape,
        "checkpoint {} holds {} actor(s) of shape {:?}; distillation trains one shared actor of shape {:?} (env.history, learn.actor_hidden)",
        loaded.path.display(),
        loaded.meta.n_actors,
        loaded.meta.actor,
        shape
    );
    let data = vars
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    for (name, var) in data.iter() {
        let tensor = loaded
            .tensors
            .get(name)
            .with_context(|| format!("checkpoint {} has no tensor {name}", loaded.path.display()))?;
        var.set(tensor)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_core::config::ObservationModel;
    use formation_core::obstacles::ObstacleKind;

    #[test]
    fn the_absolute_error_takes_the_more_frequent_of_two_answers_where_the_squared_takes_their_mean() {
        // One window, answered +1 three times and -1 once (as a teacher that stops or goes on
        // windows a student cannot tell apart); a constant student fitted by plain descent.
        let labels = Tensor::new(&[[1.0_f32], [1.0], [1.0], [-1.0]], &Device::Cpu).expect("labels");
        let fit = |loss: ImitationLoss| {
            let student = candle_core::Var::zeros((1, 1), DType::F32, &Device::Cpu).expect("a student");
            let mut descent = candle_nn::SGD::new(vec![student.clone()], 0.01).expect("descent");
            for _ in 0..500 {
                let outputs = student.as_tensor().broadcast_as((4, 1)).expect("outputs");
                let error = loss
                    .per_output(&outputs, &labels)
                    .expect("error")
                    .mean_all()
                    .expect("mean");
                descent.backward_step(&error).expect("a step");
            }
            student
                .as_tensor()
                .flatten_all()
                .expect("flat")
                .to_vec1::<f32>()
                .expect("value")[0]
        };
        let (mean, median) = (fit(ImitationLoss::Squared), fit(ImitationLoss::Absolute));
        assert!((mean - 0.5).abs() < 0.02, "squared: {mean}");
        assert!(median > 0.95, "absolute: {median}");
    }

    #[test]
    fn the_buffer_overwrites_the_oldest_and_reads_them_in_order() {
        let mut samples = Samples::new(1, 2, 3);
        for i in 0..5 {
            samples.push(&[i as f32], &[i as f32, 0.0]);
        }
        assert_eq!(samples.len(), 3);
        let held: Vec<f32> = (0..3).map(|i| samples.get(i).0[0]).collect();
        assert_eq!(held, vec![2.0, 3.0, 4.0]);
        assert_eq!(samples.get(2).1, &[4.0, 0.0]);
    }

    #[test]
    fn a_quiet_teacher_teaches_the_robots_without_noise_and_blends_into_the_config_s_gains() {
        let config = RunConfig::default();
        let quiet = BaselineGains {
            k_form: 2.0,
            k_goal: 0.2,
            ..BaselineGains::default()
        };
        let options = DistillOptions {
            sizes: vec![3],
            capacity: 2048,
            quiet_teacher: Some(quiet),
            noise_scale_m: 0.04,
            ..DistillOptions::default()
        };
        let distiller = Distiller::new(&config, options, None).expect("a distiller");
        // An observation of two neighbours and a goal, in the robot's frame.
        let mut obs = [0.0_f32; formation_protocol::MAX_OBS_DIM];
        obs[..12].copy_from_slice(&[1.2, 0.3, 1.0, 0.0, 1.0, -0.2, 1.1, 1.0, 0.0, 1.0, 2.0, 1.0]);
        let gains_noisy = config.baseline;
        let half = BaselineGains {
            k_form: (quiet.k_form + gains_noisy.k_form) / 2.0,
            k_goal: (quiet.k_goal + gains_noisy.k_goal) / 2.0,
            ..gains_noisy
        };
        let of = |gains| ScriptedBaseline::new(&config.env, gains).command(&obs);
        assert_eq!(of(distiller.teacher_gains(0.0, 0)), of(quiet));
        assert_eq!(of(distiller.teacher_gains(0.04, 0)), of(gains_noisy));
        assert_eq!(of(distiller.teacher_gains(0.5, 0)), of(gains_noisy));
        let (v, w) = of(distiller.teacher_gains(0.02, 0));
        let (hv, hw) = of(half);
        assert!((v - hv).abs() < 1e-12 && (w - hw).abs() < 1e-12);
        assert_ne!(of(quiet), of(gains_noisy), "the two teachers answer alike");
        // A quiet band: the quiet gains in full up to 1 cm, the blend's middle at 2.5 cm.
        let banded = DistillOptions {
            sizes: vec![3],
            capacity: 2048,
            quiet_teacher: Some(quiet),
            quiet_below_m: 0.01,
            noise_scale_m: 0.04,
            ..DistillOptions::default()
        };
        let distiller = Distiller::new(&config, banded, None).expect("a distiller");
        assert_eq!(of(distiller.teacher_gains(0.01, 0)), of(quiet));
        let (v, w) = of(distiller.teacher_gains(0.025, 0));
        assert!((v - hv).abs() < 1e-12 && (w - hw).abs() < 1e-12);
        let outside = DistillOptions {
            quiet_below_m: 0.05,
            ..DistillOptions::default()
        };
        let refused = Distiller::new(&config, outside, None).err().expect("refused");
        assert!(refused.to_string().contains("quiet band"), "{refused}");
        // A delay from 2 ticks: the config's gains whatever the noise; below it the noise chooses.
        let by_delay = DistillOptions {
            sizes: vec![3],
            capacity: 2048,
            quiet_teacher: Some(quiet),
            soft_from_delay_ticks: Some(2),
            ..DistillOptions::default()
        };
        let distiller = Distiller::new(&config, by_delay, None).expect("a distiller");
        assert_eq!(of(distiller.teacher_gains(0.0, 2)), of(gains_noisy));
        assert_eq!(of(distiller.teacher_gains(0.0, 1)), of(quiet));
    }

    #[test]
    fn a_planner_teacher_labels_each_robot_with_its_command_from_the_truth() {
        let mut config = RunConfig::default();
        config.env.observation = ObservationModel::SlotProximityScan;
        config.env.obstacles.kind = ObstacleKind::Forest;
        let n = 4;
        for kind in [PlannerKind::Team, PlannerKind::Solo, PlannerKind::SoloLocal] {
            let options = DistillOptions {
                sizes: vec![n],
                robots_per_round: n,
                updates_per_round: 1,
                batch: 8,
                capacity: 4096,
                planner_teacher: Some(kind),
                ..DistillOptions::default()
            };
            let mut distiller = Distiller::new(&config, options, None).expect("a distiller");
            distiller.round().expect("a round the teacher drives");
            // The first tick of the round's one episode, as the teacher saw it.
            let played = Played {
                seed: episode_seed(1, 0, n),
                count: 1,
                reality: &config.reality,
            };
            let game = played.games(&config.env, n).remove(0);
            let commands = TruthPlanner::new(kind, &config.env).commands(game.world(), &config.env, config.baseline);
            for (agent, (v, w)) in commands.into_iter().enumerate() {
                assert_eq!(
                    distiller.samples.get(agent).1,
                    &config.env.action_from_command(v, w)[..],
                    "{kind:?}: robot {agent}'s first label"
                );
            }
            assert!(
                distiller.samples.len() > 10 * n,
                "{kind:?}: {} labels",
                distiller.samples.len()
            );
        }
    }

    #[test]
    fn a_teacher_with_memory_labels_the_ticks_its_recovery_takes_over_with_the_recovery_s_command() {
        let mut config = RunConfig::default();
        config.env.observation = ObservationModel::SlotProximityScan;
        config.env.obstacles.kind = ObstacleKind::Forest;
        let (n, episodes, ticks) = (4, 6, 30);
        let options = DistillOptions {
            sizes: vec![n],
            robots_per_round: n * episodes,
            updates_per_round: 1,
            batch: 8,
            capacity: 1 << 17,
            teach_recovery_ticks: Some(ticks),
            ..DistillOptions::default()
        };
        let gains_head = DistillOptions {
            head: ActorHead::Gains,
            ..options.clone()
        };
        let refused = Distiller::new(&config, gains_head, None).err().expect("refused");
        assert!(refused.to_string().contains("commands only"), "{refused}");
        let mut distiller = Distiller::new(&config, options, None).expect("a distiller");
        distiller.round().expect("a round the teacher drives");
        // The same episodes replayed: the teacher drives, every robot's recovery on.
        let mut env = config.env.clone();
        env.obstacles.recovery_ticks = ticks;
        let played = Played {
            seed: episode_seed(1, 0, n),
            count: episodes,
            reality: &config.reality,
        };
        let teacher = ScriptedBaseline::new(&config.env, config.baseline);
        let (mut expected, mut recovered) = (Vec::new(), 0);
        for mut game in played.games(&env, n) {
            while game.running() {
                let mut answered = Vec::new();
                game.step(|asked| {
                    let (v, w) = teacher.command_in(asked.window.as_flat());
                    let action = env.action_from_command(v, w);
                    if asked.present {
                        answered.push((asked.agent, action));
                    }
                    Ok(env.command_from_action(action))
                })
                .expect("a tick");
                for (agent, action) in answered {
                    expected.push(match game.recovery_command(agent) {
                        Some((v, w)) => {
                            recovered += 1;
                            env.action_from_command(v, w)
                        }
                        None => action,
                    });
                }
            }
        }
        assert!(
            recovered > 0,
            "the field stalls at a disc somewhere in {episodes} forest episodes"
        );
        assert_eq!(distiller.samples.len(), expected.len());
        for (i, label) in expected.iter().enumerate() {
            assert_eq!(distiller.samples.get(i).1, &label[..], "label {i}");
        }
    }

    #[test]
    fn a_learned_teacher_labels_every_window_with_its_actor_s_command() {
        let mut config = RunConfig::default();
        config.env.observation = ObservationModel::SlotProximityScan;
        config.env.obstacles.kind = ObstacleKind::Forest;
        config.env.history = 2;
        config.learn.actor_hidden = vec![16];
        let n = 3;
        let options = DistillOptions {
            sizes: vec![n],
            robots_per_round: 2 * n,
            updates_per_round: 1,
            batch: 8,
            capacity: 1 << 16,
            seed: 5,
            ..DistillOptions::default()
        };
        // The teacher: a fresh student of another seed, saved.
        let dir = std::env::temp_dir().join(format!("formation-distill-teacher-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("teacher.safetensors");
        let teacher = Distiller::new(&config, options.clone(), None).expect("a teacher");
        teacher.save(&path, HashMap::new()).expect("saved");
        let mut frozen =
            FrozenActor::from_flat(&teacher.actor_weights().expect("weights"), teacher.shape()).expect("actor");
        let learned = DistillOptions {
            actor_teacher: Some(path.clone()),
            seed: 6,
            ..options.clone()
        };
        let mut distiller = Distiller::new(&config, learned.clone(), None).expect("a distiller");
        distiller.round().expect("a round the teacher drives");
        assert!(!distiller.samples.is_empty());
        let baseline = ScriptedBaseline::new(&config.env, config.baseline);
        let mut unlike_the_baseline = 0;
        for i in 0..distiller.samples.len() {
            let (window, label) = distiller.samples.get(i);
            let (v, w) = frozen.command(window, &config.env).expect("command");
            assert_eq!(label, &config.env.action_from_command(v, w)[..], "label {i}");
            let (v, w) = baseline.command_in(window);
            unlike_the_baseline += usize::from(label != &config.env.action_from_command(v, w)[..]);
        }
        assert!(unlike_the_baseline > 0, "the baseline taught");
        // A teacher must read the student's window.
        let mut longer = config.clone();
        longer.env.history = 3;
        let refused = Distiller::new(&longer, learned, None).err().expect("refused");
        assert!(refused.to_string().contains("window, H = 3"), "{refused}");
        std::fs::remove_dir_all(&dir).expect("cleaned");
    }

    #[test]
    fn the_learning_rate_decays_from_start_to_end_over_the_rounds() {
        let config = RunConfig::default();
        let options = DistillOptions {
            sizes: vec![3],
            rounds: 5,
            capacity: 2048,
            ..DistillOptions::default()
        };
        let mut distiller = Distiller::new(&config, options, None).expect("a distiller");
        assert!((distiller.learning_rate() - 1e-3).abs() < 1e-12);
        distiller.round = 4;
        assert!((distiller.learning_rate() - 3e-5).abs() < 1e-12);
        distiller.round = 9;
        assert!((distiller.learning_rate() - 3e-5).abs() < 1e-12);
    }
}
