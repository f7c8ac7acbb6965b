//! Central training: actor(s) and critic(s) in candle, DDPG (the paper) or TD3.
//!
//! * critic target y = r + gamma (1 - terminal) min_j Q'_j(s', [u_{t-H+2..t}, pi'(o')]); a
//!   time-limit truncation is not terminal; with n-step returns r is the discounted sum of k <= n
//!   rewards, s' the state k ticks on and gamma is gamma^k (the batch carries both);
//! * actor step on -Q_1(s, [u_{t-H+1..t-1}, pi(o_t)]): each robot's last action replaced by its
//!   current policy's output, earlier actions as executed;
//! * target networks follow by polyak averaging with tau.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{Context, Result, bail};
use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{AdamW, Linear, Optimizer, ParamsAdamW, VarBuilder, VarMap};
use formation_core::baseline::{BaselineGains, ScriptedBaseline};
use formation_core::config::{
    ActorUpdate, Algorithm, Credit, CriticArchitecture, EnvConfig, ImitationTeacher, LearnConfig, ObservationModel,
    QGradientActions,
};
use formation_core::features::CriticFeatures;
use formation_core::observation::{Layout, SCAN_RAYS};
use formation_ipc::placement;
use formation_model::actor::{Actor, ActorHead, ActorShape, dense, var_map_actor_weights};
use formation_model::checkpoint::{self, CheckpointMeta, actor_prefix};
use formation_protocol::ACTION_DIM;
use formation_replay::sample::Batch;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};

/// Losses of one update.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Losses {
    /// Mean squared TD error, summed over the critics.
    pub critic: f64,
    /// -Q of the current policy (only on updates that step the actor).
    pub actor: Option<f64>,
    /// Mean |action| of the current policy, a saturation gauge (1 = every output at a limit).
    pub action_magnitude: Option<f64>,
    /// Rms of the actor loss's gradient over the actor's weights: the scale that
    /// `learn.actor_adam_eps` is set against.
    pub actor_gradient_rms: Option<f64>,
}

/// What one actor step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ActorStep {
    /// The actor loss before the step.
    pub loss: f64,
    /// Mean |action| of the current policy over the robots in the formation.
    pub action_magnitude: f64,
    /// Rms of the loss's gradient over the actor's weights.
    pub gradient_rms: f64,
}

/// What the batches of one swarm (one replay) have driven. The actor's schedule is kept per
/// swarm: the actor steps on every `policy_delay`-th update of each swarm's own, so that with
/// the swarms taken in turn every swarm's batches get their share of actor (and teacher)
/// steps. One count over every update would give them all to the same swarms (with two
/// swarms and a delay of 2, all to the second).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SwarmSteps {
    /// Critic updates on the swarm's batches.
    pub updates: u64,
    /// Actor steps on them.
    pub actor: u64,
    /// Actor steps on them that also pulled towards the teacher.
    pub teacher: u64,
}

/// Linear layers with ReLU between them (and after the last with `relu_last`).
#[derive(Debug, Clone)]
pub struct Mlp {
    layers: Vec<Linear>,
    relu_last: bool,
}

impl Mlp {
    fn new(vb: VarBuilder, input: usize, widths: &[usize], relu_last: bool) -> candle_core::Result<Self> {
        let mut layers = Vec::with_capacity(widths.len());
        let mut width = input;
        for (i, &w) in widths.iter().enumerate() {
            layers.push(candle_nn::linear(width, w, vb.pp(format!("layer{i}")))?);
            width = w;
        }
        Ok(Self { layers, relu_last })
    }

    fn forward(&self, input: &Tensor) -> candle_core::Result<Tensor> {
        let mut x = input.clone();
        for (i, layer) in self.layers.iter().enumerate() {
            x = dense(layer, &x)?;
            if self.relu_last || i + 1 < self.layers.len() {
                x = x.relu()?;
            }
        }
        Ok(x)
    }
}

/// Which robots of a batch's samples are in the formation, as the pooled critic's mean and the
/// actor's per-robot terms read it ([`Batch::present`]).
#[derive(Debug, Clone)]
pub struct Members {
    /// [B, N, 1]: 1 for a robot in the formation, 0 for one out.
    robots: Tensor,
    /// [B, 1]: 1 / the robots in the formation of each sample (at least one).
    per_sample: Tensor,
    /// [B, N * 2]: the robots' mask repeated for each of their action's components.
    actions: Tensor,
    /// Action components in the formation over the batch (at least one).
    action_count: usize,
    /// Robots in the formation over the batch (at least one).
    robot_count: usize,
}

impl Members {
    /// The members of a [B, N] mask, or `None` for an empty one (every robot present: the
    /// plain means, as before presence was recorded).
    pub fn of(mask: &[f32], batch_size: usize, n_agents: usize) -> Result<Option<Self>> {
        if mask.is_empty() {
            return Ok(None);
        }
        let device = Device::Cpu;
        // 1 / m as an affine's f64 factor narrows to f32: the same float as a plain mean's.
        let per_sample: Vec<f32> = mask
            .chunks_exact(n_agents)
            .map(|robots| (1.0 / f64::from(robots.iter().sum::<f32>().max(1.0))) as f32)
            .collect();
        let actions: Vec<f32> = mask.iter().flat_map(|&m| [m; ACTION_DIM]).collect();
        let action_count = (actions.iter().sum::<f32>() as usize).max(1);
        let robot_count = (mask.iter().sum::<f32>() as usize).max(1);
        Ok(Some(Self {
            robots: Tensor::from_slice(mask, (batch_size, n_agents, 1), &device)?,
            per_sample: Tensor::from_vec(per_sample, (batch_size, 1), &device)?,
            actions: Tensor::from_vec(actions, (batch_size, n_agents * ACTION_DIM), &device)?,
            action_count,
            robot_count,
        }))
    }
}

/// The mean of a per-robot-action term `values` [B, N * 2] over the robots in the formation
/// (over every entry without `members`, candle's `mean_all`: with every robot in, the same
/// floats).
fn member_mean(values: &Tensor, members: Option<&Members>) -> Result<Tensor> {
    Ok(match members {
        None => values.mean_all()?,
        Some(m) => (values * &m.actions)?
            .sum_all()?
            .affine(1.0 / m.action_count as f64, 0.0)?,
    })
}

/// Joint actions [B, N * 2] with the same values, whose gradient reaches only the turn rates:
/// each robot's forward speed (component 0) is detached.
fn turn_only_gradient(actions: &Tensor) -> Result<Tensor> {
    let (b, joint) = actions.dims2()?;
    let robots = joint / ACTION_DIM;
    let per_robot = actions.reshape((b, robots, ACTION_DIM))?;
    let speed = per_robot.narrow(2, 0, 1)?.detach();
    let turn = per_robot.narrow(2, 1, ACTION_DIM - 1)?;
    Ok(Tensor::cat(&[speed, turn], 2)?.reshape((b, joint))?)
}

/// The mean of values [B, 1] (the team's) or [B, N] (each robot's, `learn.credit = "robot"`)
/// over the robots in the formation, as a scalar tensor.
fn value_mean(values: &Tensor, members: Option<&Members>) -> Result<Tensor> {
    Ok(match members {
        Some(m) if values.dim(1)? > 1 => (values * m.robots.squeeze(2)?)?
            .sum_all()?
            .affine(1.0 / m.robot_count as f64, 0.0)?,
        _ => values.mean_all()?,
    })
}

/// The critics' squared TD error: of the team's value [B, 1], or of each robot's [B, N]
/// averaged over the robots in the formation at t.
fn td_loss(q: &Tensor, target: &Tensor, members: Option<&Members>) -> Result<Tensor> {
    value_mean(&(q - target)?.sqr()?, members)
}

/// Q(s, u) of the whole team, shape [B, 1], or of each robot, [B, N] (`learn.credit = "robot"`).
#[derive(Debug, Clone)]
pub enum CriticNet {
    /// An MLP over the flat state and joint-action windows, [B, H (state_dim + 2N)]. It reads
    /// robots by index and cannot leave one out: refused for training runs whose robots leave
    /// the formation (`RunConfig::check_training_critic`).
    Mlp(Mlp),
    /// Deep sets over robot tokens [B, N, H (token_dim + 2)]: `head(mean_i encoder(token_i))`,
    /// the mean over the robots in the formation only ([`Members`]).
    ///
    /// A robot out of the formation is left out, not entered as an obstacle token: its token's
    /// fields (slot, desired edges, observed neighbours) are a member's and mean nothing for
    /// it, an obstacle token would need a field of its own (another token width: no shipped
    /// critic would carry over) and, with every robot in, the value would no longer be the
    /// same floats. What it costs: the critic does not see a stopped robot, so a collision
    /// with it is a surprise to the value (the actors still sense it through their proximity
    /// observation); the team's value is that of the robots in the formation, whose success
    /// the sim judges.
    ///
    /// With `learn.credit = "robot"` the head reads each robot's encoding beside the mean,
    /// `head([encoder(token_i), mean_j encoder(token_j)])`: one value per robot, for its own
    /// reward ([`formation_replay::sample::Batch::robot_rewards`]).
    Pooled {
        /// Applied to each robot's token alone.
        encoder: Mlp,
        /// Applied to the mean of the encodings (beside each robot's own, per robot).
        head: Mlp,
        /// Whose value the head gives.
        credit: Credit,
    },
}

impl CriticNet {
    fn new(vb: VarBuilder, config: &LearnConfig, input: usize) -> candle_core::Result<Self> {
        let head_widths: Vec<usize> = config.critic_hidden.iter().copied().chain([1]).collect();
        Ok(match config.critic {
            CriticArchitecture::Mlp => Self::Mlp(Mlp::new(vb, input, &head_widths, false)?),
            CriticArchitecture::Pooled => {
                let encoded = *config.critic_encoder.last().expect("validated: not empty");
                let head_input = match config.credit {
                    Credit::Team => encoded,
                    Credit::Robot => 2 * encoded,
                };
                Self::Pooled {
                    encoder: Mlp::new(vb.pp("encoder"), input, &config.critic_encoder, true)?,
                    head: Mlp::new(vb.pp("head"), head_input, &head_widths, false)?,
                    credit: config.credit,
                }
            }
        })
    }

    /// Q values, shape [B, 1] (or [B, N] per robot), the pooled critic's mean over the robots
    /// of `members` (over every robot without; the `mlp` critic reads every robot).
    pub fn forward(&self, input: &Tensor, members: Option<&Members>) -> candle_core::Result<Tensor> {
        match self {
            Self::Mlp(mlp) => mlp.forward(input),
            Self::Pooled { encoder, head, credit } => {
                let (batch, robots, width) = input.dims3()?;
                let encoded = encoder.forward(&input.reshape((batch * robots, width))?)?;
                let encoded = encoded.reshape((batch, robots, encoded.dim(1)?))?;
                let pooled = match members {
                    None => encoded.mean(1)?,
                    // With every robot in: the same floats as `mean` (x * 1, the same sum,
                    // times the same 1 / N).
                    Some(m) => encoded.broadcast_mul(&m.robots)?.sum(1)?.broadcast_mul(&m.per_sample)?,
                };
                match credit {
                    Credit::Team => head.forward(&pooled),
                    Credit::Robot => {
                        let width = pooled.dim(1)?;
                        let beside = pooled.unsqueeze(1)?.broadcast_as((batch, robots, width))?;
                        let own = Tensor::cat(&[&encoded, &beside], 2)?.reshape((batch * robots, 2 * width))?;
                        head.forward(&own)?.reshape((batch, robots))
                    }
                }
            }
        }
    }

    /// For each robot i of each sample, shape [B, N]: Q with every robot's token from `played`
    /// minus Q with robot i's token from `swapped` instead, the others as played. `pooled`
    /// only: a swap moves the mean of the encodings by robot i's change alone, so all N swaps
    /// cost one more encoder pass and a head pass over [B * N].
    pub fn swap_advantages(&self, played: &Tensor, swapped: &Tensor, members: Option<&Members>) -> Result<Tensor> {
        let Self::Pooled {
            encoder,
            head,
            credit: Credit::Team,
        } = self
        else {
            bail!("learn.actor_update = \"advantage_filtered\" needs the pooled critic of the team's value");
        };
        let (batch, robots, width) = played.dims3()?;
        let encode = |input: &Tensor| -> candle_core::Result<Tensor> {
            let encoded = encoder.forward(&input.reshape((batch * robots, width))?)?;
            encoded.reshape((batch, robots, encoded.dim(1)?))
        };
        let (played, swapped) = (encode(played)?, encode(swapped)?);
        let (pooled, weights) = match members {
            None => (
                played.mean(1)?,
                Tensor::full(1.0 / robots as f32, (batch, robots, 1), &Device::Cpu)?,
            ),
            Some(m) => (
                played.broadcast_mul(&m.robots)?.sum(1)?.broadcast_mul(&m.per_sample)?,
                m.robots.broadcast_mul(&m.per_sample.unsqueeze(2)?)?,
            ),
        };
        // A robot out of the formation is not in the mean: its swap changes nothing.
        let shifted = (swapped - &played)?
            .broadcast_mul(&weights)?
            .broadcast_add(&pooled.unsqueeze(1)?)?;
        let width = pooled.dim(1)?;
        let q_swapped = head
            .forward(&shifted.reshape((batch * robots, width))?)?
            .reshape((batch, robots))?;
        Ok(head.forward(&pooled)?.broadcast_sub(&q_swapped)?)
    }
}

/// Every network of a [`Learner`] at one moment ([`Learner::snapshot`]).
pub struct LearnerSnapshot {
    tensors: Vec<(String, Tensor)>,
    meta: CheckpointMeta,
}

impl LearnerSnapshot {
    /// Writes the networks to a checkpoint with the training figures `extra`.
    pub fn save(&self, path: &Path, extra: HashMap<String, String>) -> Result<()> {
        let meta = CheckpointMeta {
            extra,
            ..self.meta.clone()
        };
        checkpoint::save(path, &self.tensors, &meta)
    }
}

/// Every network, its target and its optimiser.
pub struct Learner {
    config: LearnConfig,
    n_agents: usize,
    observation: ObservationModel,
    history: usize,
    /// Where each observation's range-sensor rays start and how many there are, when the model
    /// has a range sensor: the critics read every robot's rays beside its state (the state
    /// holds no obstacle, so without them no value could foresee a collision with one).
    scan: Option<(usize, usize)>,
    actor_shape: ActorShape,
    actor_vars: VarMap,
    actor_target_vars: VarMap,
    actors: Vec<Actor>,
    actor_targets: Vec<Actor>,
    critic_vars: VarMap,
    critic_target_vars: VarMap,
    critics: Vec<CriticNet>,
    critic_targets: Vec<CriticNet>,
    actor_optimizer: AdamW,
    /// One per critic (Adam is per parameter: the same steps as one over all of them), so that
    /// each critic can step on its own thread.
    critic_optimizers: Vec<AdamW>,
    updates: u64,
    /// Updates of this run (not restored from a checkpoint): `critic_warmup_updates` counts these.
    run_updates: u64,
    /// Indexed by swarm; grown as swarms appear.
    swarm_steps: Vec<SwarmSteps>,
    rng: StdRng,
    /// Whom the imitation term pulls towards, when `imitation_alpha` > 0.
    teacher: Option<Teacher>,
}

/// The imitation term's teacher.
enum Teacher {
    /// The scripted baseline and the environment it commands.
    Baseline(Box<(ScriptedBaseline, EnvConfig)>),
    /// The actors as the run started, frozen (copies, never stepped).
    Start(Vec<Actor>),
    /// `learn.imitation_teacher = "start"` until [`Learner::freeze_start`] is called.
    StartPending,
}

/// `n` actors of `shape` built in `vars` (`actor0`, `actor1`, ...), on the CPU.
fn actors_in(vars: &VarMap, n: usize, shape: &ActorShape) -> Result<Vec<Actor>> {
    let vb = VarBuilder::from_varmap(vars, DType::F32, &Device::Cpu);
    (0..n)
        .map(|k| Ok(Actor::new(vb.pp(format!("actor{k}")), shape)?))
        .collect()
}

/// Re-draws every variable from `rng`, U(-1/sqrt(fan_in), 1/sqrt(fan_in)) (PyTorch's default
/// for linear layers), because candle's CPU generator cannot be seeded.
pub(crate) fn reinitialise(vars: &VarMap, rng: &mut StdRng) -> Result<()> {
    let data = vars
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    let mut names: Vec<&String> = data.keys().collect();
    names.sort();
    // Fan-in of a layer is the width of its weight's second dimension.
    let fan_in = |name: &str| -> Option<usize> {
        let weight = name
            .strip_suffix(".bias")
            .map_or_else(|| name.to_string(), |stem| format!("{stem}.weight"));
        data.get(&weight).and_then(|w| w.as_tensor().dims().get(1).copied())
    };
    for name in names {
        let var = &data[name];
        let bound = 1.0 / (fan_in(name).unwrap_or(1) as f32).sqrt();
        let count = var.as_tensor().elem_count();
        let values: Vec<f32> = (0..count).map(|_| rng.random_range(-bound..bound)).collect();
        var.set(&Tensor::from_vec(values, var.as_tensor().shape(), &Device::Cpu)?)?;
    }
    Ok(())
}

fn copy_vars(from: &VarMap, to: &VarMap) -> Result<()> {
    let source = from
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    let target = to.data().lock().map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    for (name, var) in target.iter() {
        let src = source
            .get(name)
            .ok_or_else(|| anyhow::anyhow!("no variable {name} to copy"))?;
        var.set(src.as_tensor())?;
    }
    Ok(())
}

/// target <- tau * online + (1 - tau) * target, for every variable.
pub fn soft_update(online: &VarMap, target: &VarMap, tau: f64) -> Result<()> {
    let source = online
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    let dest = target
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    for (name, var) in dest.iter() {
        let src = source
            .get(name)
            .ok_or_else(|| anyhow::anyhow!("no variable {name} for the soft update"))?;
        let blended = ((src.as_tensor() * tau)? + (var.as_tensor() * (1.0 - tau))?)?;
        var.set(&blended)?;
    }
    Ok(())
}

/// The variable-name prefix of critic `index`.
fn critic_prefix(index: usize) -> String {
    format!("critic{index}")
}

/// The variables of `vars` named under `prefix` (`prefix.`...).
fn vars_under(vars: &VarMap, prefix: &str) -> Result<Vec<Var>> {
    let data = vars
        .data()
        .lock()
        .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
    let stem = format!("{prefix}.");
    let mut named: Vec<(&String, &Var)> = data.iter().filter(|(name, _)| name.starts_with(&stem)).collect();
    named.sort_by_key(|(name, _)| *name);
    Ok(named.into_iter().map(|(_, var)| var.clone()).collect())
}

/// The actor variables its optimizer steps: every one, or with `output_layer_only` each
/// actor's output layer alone (`learn.actor_output_layer_only`).
fn trained_actor_vars(vars: &VarMap, n_actors: usize, shape: &ActorShape, output_layer_only: bool) -> Result<Vec<Var>> {
    if !output_layer_only {
        return Ok(vars.all_vars());
    }
    let last = shape.hidden.len();
    let mut trained = Vec::new();
    for actor in 0..n_actors {
        trained.extend(vars_under(vars, &format!("actor{actor}.layer{last}"))?);
    }
    Ok(trained)
}

/// `work` on each item, in order: on its own thread per item when `parallel` (the later
/// threads free to use any CPU, [`placement::widen`]), else one after the other.
fn per_critic<I: Send, T: Send>(parallel: bool, items: Vec<I>, work: impl Fn(I) -> Result<T> + Sync) -> Result<Vec<T>> {
    if !parallel || items.len() < 2 {
        return items.into_iter().map(work).collect();
    }
    let work = &work;
    std::thread::scope(|scope| {
        let mut items = items.into_iter();
        let first = items.next().expect("at least two items");
        let others: Vec<_> = items
            .map(|item| {
                scope.spawn(move || {
                    placement::widen();
                    work(item)
                })
            })
            .collect();
        let mut results = vec![work(first)];
        for handle in others {
            results.push(
                handle
                    .join()
                    .map_err(|_| anyhow::anyhow!("a critic's thread panicked"))?,
            );
        }
        results.into_iter().collect()
    })
}

fn adam(vars: Vec<Var>, lr: f64, eps: f64) -> Result<AdamW> {
    // The paper's Adam: candle's AdamW defaults weight_decay to 0.01.
    Ok(AdamW::new(
        vars,
        ParamsAdamW {
            lr,
            eps,
            weight_decay: 0.0,
            ..ParamsAdamW::default()
        },
    )?)
}

impl Learner {
    /// Fresh networks for `n_agents` robots (seeded through candle's CPU generator).
    pub fn new(n_agents: usize, env: &EnvConfig, config: &LearnConfig, seed: u64) -> Result<Self> {
        let device = Device::Cpu;
        let mut rng = StdRng::seed_from_u64(seed);
        let history = env.history;
        let actor_shape = ActorShape {
            obs_dim: Layout::of(env.observation).dim(),
            history,
            hidden: config.actor_hidden.clone(),
            head: ActorHead::Command,
        };
        let n_actors = if config.shared_actor { 1 } else { n_agents };
        let n_critics = match config.algorithm {
            Algorithm::Ddpg => 1,
            Algorithm::Td3 => 2,
        };
        let features =
            CriticFeatures::new(n_agents, env.observation, config.critic).with_map_points(config.critic_map_points);
        let scan = Layout::of(env.observation).scan().map(|offset| (offset, SCAN_RAYS));
        let rays = scan.map_or(0, |(_, rays)| rays);
        let critic_input = match config.critic {
            CriticArchitecture::Mlp => history * (features.dim() + n_agents * (ACTION_DIM + rays)),
            CriticArchitecture::Pooled => history * (features.token_dim() + ACTION_DIM + rays),
        };
        let build_actors = |vars: &VarMap| actors_in(vars, n_actors, &actor_shape);
        let build_critics = |vars: &VarMap| -> Result<Vec<CriticNet>> {
            let vb = VarBuilder::from_varmap(vars, DType::F32, &device);
            (0..n_critics)
                .map(|j| Ok(CriticNet::new(vb.pp(critic_prefix(j)), config, critic_input)?))
                .collect()
        };
        let actor_vars = VarMap::new();
        let actors = build_actors(&actor_vars)?;
        reinitialise(&actor_vars, &mut rng)?;
        let actor_target_vars = VarMap::new();
        let actor_targets = build_actors(&actor_target_vars)?;
        copy_vars(&actor_vars, &actor_target_vars)?;
        let critic_vars = VarMap::new();
        let critics = build_critics(&critic_vars)?;
        reinitialise(&critic_vars, &mut rng)?;
        let critic_target_vars = VarMap::new();
        let critic_targets = build_critics(&critic_target_vars)?;
        copy_vars(&critic_vars, &critic_target_vars)?;
        Ok(Self {
            actor_optimizer: adam(
                trained_actor_vars(&actor_vars, n_actors, &actor_shape, config.actor_output_layer_only)?,
                config.actor_lr,
                config.actor_adam_eps,
            )?,
            critic_optimizers: (0..n_critics)
                .map(|j| {
                    adam(
                        vars_under(&critic_vars, &critic_prefix(j))?,
                        config.critic_lr,
                        ParamsAdamW::default().eps,
                    )
                })
                .collect::<Result<_>>()?,
            config: config.clone(),
            n_agents,
            observation: env.observation,
            history,
            scan,
            actor_shape,
            actor_vars,
            actor_target_vars,
            actors,
            actor_targets,
            critic_vars,
            critic_target_vars,
            critics,
            critic_targets,
            updates: 0,
            run_updates: 0,
            swarm_steps: Vec::new(),
            rng,
            teacher: (config.imitation_alpha > 0.0).then(|| match config.imitation_teacher {
                ImitationTeacher::Baseline => Teacher::Baseline(Box::new((
                    ScriptedBaseline::new(env, BaselineGains::default()),
                    env.clone(),
                ))),
                ImitationTeacher::Start => Teacher::StartPending,
            }),
        })
    }

    /// With `learn.imitation_teacher = "start"`: freezes a copy of the actors as they are now
    /// (after [`Learner::load`]) as the teacher. Without the start teacher, nothing.
    pub fn freeze_start(&mut self) -> Result<()> {
        if matches!(self.teacher, Some(Teacher::StartPending)) {
            let vars = VarMap::new();
            let actors = actors_in(&vars, self.n_actors(), &self.actor_shape)?;
            copy_vars(&self.actor_vars, &vars)?;
            self.teacher = Some(Teacher::Start(actors));
        }
        Ok(())
    }

    /// The teacher (with `imitation_alpha` > 0) commands with these gains: the run's
    /// `[baseline]` section. Without this, the default gains.
    pub fn with_teacher_gains(mut self, gains: BaselineGains) -> Self {
        if let Some(Teacher::Baseline(teacher)) = &mut self.teacher {
            teacher.0 = ScriptedBaseline::new(&teacher.1, gains);
        }
        self
    }

    /// Gradient updates done (with those of the checkpoint it resumed from).
    pub fn updates(&self) -> u64 {
        self.updates
    }

    /// Gradient updates done by this learner since it was made.
    pub fn run_updates(&self) -> u64 {
        self.run_updates
    }

    /// Number of actors (1 when shared).
    pub fn n_actors(&self) -> usize {
        self.actors.len()
    }

    /// The actors' shape.
    pub fn actor_shape(&self) -> &ActorShape {
        &self.actor_shape
    }

    /// Joint actions [B, N * 2] of `actors` for observation windows [B, N, H * obs_dim].
    fn joint_actions(actors: &[Actor], observations: &Tensor) -> Result<Tensor> {
        let (batch, n, width) = observations.dims3()?;
        if actors.len() == 1 {
            let flat = observations.reshape((batch * n, width))?;
            return Ok(actors[0].forward(&flat)?.reshape((batch, n * ACTION_DIM))?);
        }
        let per_agent = (0..n)
            .map(|agent| actors[agent].forward(&observations.narrow(1, agent, 1)?.squeeze(1)?))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Tensor::cat(&per_agent, 1)?)
    }

    /// The teacher's normalised actions [B, N * 2] on each robot's newest observation of the
    /// batch, or `None` without a teacher.
    fn teacher_actions(&self, batch: &Batch) -> Result<Option<Tensor>> {
        let (baseline, env) = match &self.teacher {
            None => return Ok(None),
            Some(Teacher::StartPending) => bail!("the start teacher was never frozen (Learner::freeze_start)"),
            Some(Teacher::Start(actors)) => {
                let obs = Tensor::from_slice(
                    &batch.observations,
                    (batch.batch_size, batch.n_agents, batch.window_dim()),
                    &Device::Cpu,
                )?;
                return Ok(Some(Self::joint_actions(actors, &obs)?.detach()));
            }
            Some(Teacher::Baseline(teacher)) => (&teacher.0, &teacher.1),
        };
        let window = batch.window_dim();
        let actions: Vec<f32> = batch
            .observations
            .chunks_exact(window)
            .flat_map(|robot_window| {
                let (v, w) = baseline.command_in(robot_window);
                env.action_from_command(v, w)
            })
            .collect();
        let shape = (batch.batch_size, batch.n_agents * ACTION_DIM);
        Ok(Some(Tensor::from_vec(actions, shape, &Device::Cpu)?))
    }

    /// Mean squared distance between the actors' and the teacher's normalised actions on a
    /// batch, or `None` without a teacher.
    pub fn imitation_error(&self, batch: &Batch) -> Result<Option<f64>> {
        let Some(teacher) = self.teacher_actions(batch)? else {
            return Ok(None);
        };
        let obs = Tensor::from_slice(
            &batch.observations,
            (batch.batch_size, batch.n_agents, batch.window_dim()),
            &Device::Cpu,
        )?;
        let current = Self::joint_actions(&self.actors, &obs)?;
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let error = member_mean(&(current - teacher)?.sqr()?, members.as_ref())?.to_scalar::<f32>()?;
        Ok(Some(f64::from(error)))
    }

    /// What the critics read, from a state window [B, H * state_dim], a joint-action window
    /// [B, H * N * 2] (both tick-major) and the robots' observation windows [B, N, H * od]: the
    /// three side by side for the `mlp` critic, one token per robot [B, N, H * (token_dim + 2) +
    /// H * rays] (its own ticks' features and actions, then its range sensor's rays over the
    /// window) for `pooled`. Of the observations only the rays are read, when the model has them.
    fn critic_input(&self, batch: &Batch, states: Tensor, actions: Tensor, observations: &Tensor) -> Result<Tensor> {
        let (b, h, n) = (batch.batch_size, batch.history, batch.n_agents);
        let scans = match self.scan {
            Some((offset, rays)) => Some(
                observations
                    .reshape((b, n, h, batch.obs_dim))?
                    .narrow(3, offset, rays)?
                    .reshape((b, n, h * rays))?,
            ),
            None => None,
        };
        if self.config.critic == CriticArchitecture::Mlp {
            let mut parts = vec![states, actions];
            parts.extend(scans.map(|s| s.reshape((b, ()))).transpose()?);
            return Ok(Tensor::cat(&parts, 1)?);
        }
        let token = batch.state_dim / n;
        let states = states.reshape((b, h, n, token))?.transpose(1, 2)?;
        let actions = actions.reshape((b, h, n, ACTION_DIM))?.transpose(1, 2)?;
        let tokens = Tensor::cat(&[states, actions], 3)?.reshape((b, n, h * (token + ACTION_DIM)))?;
        Ok(match scans {
            Some(scans) => Tensor::cat(&[tokens, scans], 2)?,
            None => tokens,
        })
    }

    /// The TD target y for a batch (no gradient flows through it).
    pub fn td_target(&mut self, batch: &Batch) -> Result<Tensor> {
        let device = Device::Cpu;
        let b = batch.batch_size;
        let n = batch.n_agents;
        let h = self.history;
        let next_obs = Tensor::from_slice(&batch.next_observations, (b, n, batch.window_dim()), &device)?;
        let next_states = Tensor::from_slice(&batch.next_states, (b, batch.state_window_dim()), &device)?;
        let played = Tensor::from_slice(&batch.bootstrap_actions, (b, batch.action_window_dim()), &device)?;
        let rewards = match self.config.credit {
            Credit::Robot if !batch.robot_rewards.is_empty() => {
                Tensor::from_slice(&batch.robot_rewards, (b, n), &device)?
            }
            _ => Tensor::from_slice(&batch.rewards, (b, 1), &device)?,
        };
        let rewards = (rewards * self.config.reward_scale)?;
        let discounts = Tensor::from_slice(&batch.discounts, (b, 1), &device)?;
        let terminals = Tensor::from_slice(&batch.terminals, (b, 1), &device)?;
        let mut next_actions = Self::joint_actions(&self.actor_targets, &next_obs)?;
        if self.config.algorithm == Algorithm::Td3 && self.config.target_noise > 0.0 {
            let normal = Normal::new(0.0f32, self.config.target_noise as f32)?;
            let clip = self.config.target_noise_clip as f32;
            let values: Vec<f32> = (0..next_actions.elem_count())
                .map(|_| normal.sample(&mut self.rng).clamp(-clip, clip))
                .collect();
            let noise = Tensor::from_vec(values, next_actions.shape(), &device)?;
            next_actions = (next_actions + noise)?.clamp(-1f32, 1f32)?;
        }
        let joint = n * ACTION_DIM;
        let next_window = Tensor::cat(&[played.narrow(1, joint, (h - 1) * joint)?, next_actions], 1)?;
        let next_input = self.critic_input(batch, next_states, next_window, &next_obs)?;
        let members = Members::of(&batch.next_present, b, n)?;
        let q_targets = per_critic(
            self.config.parallel_critics,
            self.critic_targets.iter().collect(),
            |target| Ok(target.forward(&next_input, members.as_ref())?),
        )?;
        let mut q_next = q_targets[0].clone();
        for q in &q_targets[1..] {
            q_next = q_next.minimum(q)?;
        }
        let not_done = terminals.affine(-1.0, 1.0)?;
        // [B, 1] for the team; [B, N] per robot (a team reward broadcast to every robot).
        let future = q_next.broadcast_mul(&not_done)?.broadcast_mul(&discounts)?;
        let y = rewards.broadcast_add(&future)?;
        Ok(y.detach())
    }

    /// A batch's robots' observation windows [B, N, H * od], state windows [B, H * state_dim]
    /// and joint-action windows as played [B, H * N * 2].
    fn played_tensors(batch: &Batch) -> Result<(Tensor, Tensor, Tensor)> {
        let device = Device::Cpu;
        let b = batch.batch_size;
        Ok((
            Tensor::from_slice(&batch.observations, (b, batch.n_agents, batch.window_dim()), &device)?,
            Tensor::from_slice(&batch.states, (b, batch.state_window_dim()), &device)?,
            Tensor::from_slice(&batch.actions, (b, batch.action_window_dim()), &device)?,
        ))
    }

    /// A joint-action window as played with the actions at t replaced by `at_t` [B, N * 2].
    fn with_actions_at_t(&self, played: &Tensor, at_t: Tensor) -> Result<Tensor> {
        let joint = at_t.dim(1)?;
        Ok(Tensor::cat(
            &[played.narrow(1, 0, (self.history - 1) * joint)?, at_t],
            1,
        )?)
    }

    /// The critics' input for the batch's states and actions as played.
    fn played_input(&self, batch: &Batch) -> Result<Tensor> {
        let (obs, states, actions) = Self::played_tensors(batch)?;
        self.critic_input(batch, states, actions, &obs)
    }

    /// The critic loss on a batch against a given target, summed over the critics (used by
    /// tests on a fixed batch).
    pub fn critic_loss(&self, batch: &Batch, target: &Tensor) -> Result<Tensor> {
        let input = self.played_input(batch)?;
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let mut loss: Option<Tensor> = None;
        for critic in &self.critics {
            let l = td_loss(&critic.forward(&input, members.as_ref())?, target, members.as_ref())?;
            loss = Some(match loss {
                Some(acc) => (acc + l)?,
                None => l,
            });
        }
        loss.context("no critic")
    }

    /// One gradient step of every critic towards `target`; returns the summed loss.
    fn critic_steps(&mut self, batch: &Batch, target: &Tensor) -> Result<f64> {
        let input = self.played_input(batch)?;
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let losses = per_critic(
            self.config.parallel_critics,
            self.critics.iter().zip(self.critic_optimizers.iter_mut()).collect(),
            |(critic, optimizer)| {
                let loss = td_loss(&critic.forward(&input, members.as_ref())?, target, members.as_ref())?;
                optimizer.backward_step(&loss)?;
                Ok(f64::from(loss.to_scalar::<f32>()?))
            },
        )?;
        Ok(losses.iter().sum())
    }

    /// Q_1 of the current policy on a batch (each robot's action at t replaced by its actor's
    /// output, the earlier actions of the window as played), those actions, and the robots in
    /// the formation at t (a robot out of it adds nothing to Q, so no gradient reaches its
    /// action).
    fn policy_q(&self, batch: &Batch) -> Result<(Tensor, Tensor, Option<Members>)> {
        let (obs, states, actions) = Self::played_tensors(batch)?;
        let current = Self::joint_actions(&self.actors, &obs)?;
        let into_q = match self.config.q_gradient_actions {
            QGradientActions::Both => current.clone(),
            QGradientActions::Turn => turn_only_gradient(&current)?,
        };
        let window = self.with_actions_at_t(&actions, into_q)?;
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let q = self.critics[0].forward(&self.critic_input(batch, states, window, &obs)?, members.as_ref())?;
        Ok((q, current, members))
    }

    /// The actors' normalised actions [B, N * 2] on a batch's observation windows.
    pub fn policy_actions(&self, batch: &Batch) -> Result<Vec<f32>> {
        let obs = Tensor::from_slice(
            &batch.observations,
            (batch.batch_size, batch.n_agents, batch.window_dim()),
            &Device::Cpu,
        )?;
        Ok(Self::joint_actions(&self.actors, &obs)?.flatten_all()?.to_vec1()?)
    }

    /// Q_1 of each sample [B] with the actions as played.
    pub fn played_value(&self, batch: &Batch) -> Result<Vec<f32>> {
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let q = self.critics[0].forward(&self.played_input(batch)?, members.as_ref())?;
        Ok(q.flatten_all()?.to_vec1()?)
    }

    /// For each robot of each sample [B, N], Q_1 with the actions as played minus Q_1 with the
    /// robot's action at t replaced by its actor's (the others' as played), given the actors'
    /// actions `current` [B, N * 2].
    fn advantages_over(&self, batch: &Batch, current: &Tensor) -> Result<Tensor> {
        let (obs, states, actions) = Self::played_tensors(batch)?;
        let swapped = self.with_actions_at_t(&actions, current.detach())?;
        let members = Members::of(&batch.present, batch.batch_size, batch.n_agents)?;
        let played_input = self.critic_input(batch, states.clone(), actions, &obs)?;
        let swapped_input = self.critic_input(batch, states, swapped, &obs)?;
        Ok(self.critics[0]
            .swap_advantages(&played_input, &swapped_input, members.as_ref())?
            .detach())
    }

    /// [`Learner::advantages_over`] the actors' current actions, as plain numbers [B * N].
    pub fn advantages(&self, batch: &Batch) -> Result<Vec<f32>> {
        let current = Tensor::from_vec(
            self.policy_actions(batch)?,
            (batch.batch_size, batch.n_agents * ACTION_DIM),
            &Device::Cpu,
        )?;
        Ok(self.advantages_over(batch, &current)?.flatten_all()?.to_vec1()?)
    }

    /// The advantage-filtered copy ([`ActorUpdate::AdvantageFiltered`]): the squared distance
    /// from each robot's actor action to its action as played at t, where the first critic
    /// rates the played one higher, averaged over the robots in the formation at t. Returns
    /// it, the actors' actions and those robots.
    fn filtered_copy(&self, batch: &Batch) -> Result<(Tensor, Tensor, Option<Members>)> {
        let (b, joint) = (batch.batch_size, batch.n_agents * ACTION_DIM);
        let (obs, _, actions) = Self::played_tensors(batch)?;
        let current = Self::joint_actions(&self.actors, &obs)?;
        let better = self.advantages_over(batch, &current)?.gt(0f32)?.to_dtype(DType::F32)?;
        let better = Tensor::cat(&vec![better.unsqueeze(2)?; ACTION_DIM], 2)?.reshape((b, joint))?;
        let played = actions.narrow(1, (self.history - 1) * joint, joint)?;
        let members = Members::of(&batch.present, b, batch.n_agents)?;
        let copy = member_mean(&((&current - played)?.sqr()? * better)?, members.as_ref())?;
        Ok((copy, current, members))
    }

    /// Mean Q_1 of the current policy on a batch: what an actor step raises.
    pub fn policy_value(&self, batch: &Batch) -> Result<f64> {
        let (q, _, _) = self.policy_q(batch)?;
        Ok(f64::from(q.mean_all()?.to_scalar::<f32>()?))
    }

    /// One gradient step of the actor(s) up the first critic (and towards the teacher, if any);
    /// the critics are left alone. Returns the actor loss, the mean |action| and the rms of the
    /// loss's gradient over the actor's weights. The teacher's pull, the action penalty and the
    /// mean |action| are over the robots in the formation at t: a robot out of it is not
    /// trained on.
    pub fn actor_step(&mut self, batch: &Batch) -> Result<ActorStep> {
        // The critic's term, and Q itself for the Q gradient (its scale against the teacher's).
        let (mut actor_loss, q, current, members) = match self.config.actor_update {
            ActorUpdate::QGradient => {
                let (q, current, members) = self.policy_q(batch)?;
                (value_mean(&q, members.as_ref())?.neg()?, Some(q), current, members)
            }
            ActorUpdate::AdvantageFiltered => {
                let (copy, current, members) = self.filtered_copy(batch)?;
                (copy, None, current, members)
            }
        };
        let members = members.as_ref();
        if let Some(teacher) = self.teacher_actions(batch)? {
            // TD3+BC: Q normalised by its mean magnitude (no gradient through the scale), at
            // least 1 so that a fresh critic (Q near 0, e.g. after a change of N) cannot blow
            // its random gradients up over the teacher's. The filtered copy is a squared
            // distance like the teacher's pull: no scale between them.
            let scale = match &q {
                Some(q) => f64::from(q.abs()?.mean_all()?.to_scalar::<f32>()?).max(1.0),
                None => 1.0,
            };
            let imitation = member_mean(&(&current - teacher)?.sqr()?, members)?;
            actor_loss = (actor_loss.affine(self.config.imitation_alpha / scale, 0.0)? + imitation)?;
        }
        if self.config.action_l2 > 0.0 {
            actor_loss = (actor_loss + member_mean(&current.sqr()?, members)?.affine(self.config.action_l2, 0.0)?)?;
        }
        let gradients = actor_loss.backward()?;
        let (mut square_sum, mut weights) = (0.0, 0);
        for var in self.actor_vars.all_vars() {
            if let Some(gradient) = gradients.get(&var) {
                square_sum += f64::from(gradient.sqr()?.sum_all()?.to_scalar::<f32>()?);
                weights += gradient.elem_count();
            }
        }
        self.actor_optimizer.step(&gradients)?;
        Ok(ActorStep {
            loss: f64::from(actor_loss.to_scalar::<f32>()?),
            action_magnitude: f64::from(member_mean(&current.abs()?, members)?.to_scalar::<f32>()?),
            gradient_rms: (square_sum / weights.max(1) as f64).sqrt(),
        })
    }

    /// Whether the actor has stepped in this run: past the critic's warm-up and the policy
    /// delay, its weights are no longer those the run started from.
    pub fn actor_has_stepped(&self) -> bool {
        self.swarm_steps.iter().any(|steps| steps.actor > 0)
    }

    /// What swarm `swarm`'s batches have driven so far.
    pub fn swarm_steps(&self, swarm: usize) -> SwarmSteps {
        self.swarm_steps.get(swarm).copied().unwrap_or_default()
    }

    /// One gradient update of the critic(s) on a batch of swarm `swarm` (0 for a run of one
    /// swarm), and of the actor(s) and targets when that swarm's schedule has them due.
    pub fn update(&mut self, batch: &Batch, swarm: usize) -> Result<Losses> {
        let sized_by_n = self.config.critic == CriticArchitecture::Mlp;
        if (sized_by_n && batch.n_agents != self.n_agents) || batch.history != self.history {
            bail!(
                "batch for {} robots and H = {} given to a learner for {} robots and H = {}",
                batch.n_agents,
                batch.history,
                self.n_agents,
                self.history
            );
        }
        let target = self.td_target(batch)?;
        let mut losses = Losses {
            critic: self.critic_steps(batch, &target)?,
            ..Losses::default()
        };
        self.updates += 1;
        self.run_updates += 1;
        if self.run_updates <= self.config.critic_warmup_updates {
            soft_update(&self.critic_vars, &self.critic_target_vars, self.config.tau)?;
            return Ok(losses);
        }
        let delay = match self.config.algorithm {
            Algorithm::Ddpg => 1,
            Algorithm::Td3 => u64::from(self.config.policy_delay),
        };
        if self.swarm_steps.len() <= swarm {
            self.swarm_steps.resize(swarm + 1, SwarmSteps::default());
        }
        let steps = &mut self.swarm_steps[swarm];
        steps.updates += 1;
        if steps.updates.is_multiple_of(delay) {
            steps.actor += 1;
            steps.teacher += u64::from(self.teacher.is_some());
            let step = self.actor_step(batch)?;
            losses.actor = Some(step.loss);
            losses.action_magnitude = Some(step.action_magnitude);
            losses.actor_gradient_rms = Some(step.gradient_rms);
            soft_update(&self.actor_vars, &self.actor_target_vars, self.config.tau)?;
            soft_update(&self.critic_vars, &self.critic_target_vars, self.config.tau)?;
        }
        Ok(losses)
    }

    /// Flat weights of actor `index`, in the order agents rebuild them.
    pub fn actor_weights(&self, index: usize) -> Result<Vec<f32>> {
        var_map_actor_weights(&self.actor_vars, &actor_prefix(index), &self.actor_shape)
    }

    fn all_tensors(&self) -> Result<Vec<(String, Tensor)>> {
        let mut out = Vec::new();
        for (prefix, vars) in [
            ("", &self.actor_vars),
            ("target.", &self.actor_target_vars),
            ("", &self.critic_vars),
            ("target.", &self.critic_target_vars),
        ] {
            let data = vars
                .data()
                .lock()
                .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
            let mut names: Vec<&String> = data.keys().collect();
            names.sort();
            for name in names {
                out.push((format!("{prefix}{name}"), data[name].as_tensor().clone()));
            }
        }
        Ok(out)
    }

    /// Whether `tensors` hold this learner's critics, every variable at its shape.
    fn critic_matches(&self, tensors: &HashMap<String, Tensor>) -> Result<bool> {
        let data = self
            .critic_vars
            .data()
            .lock()
            .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
        Ok(data
            .iter()
            .all(|(name, var)| tensors.get(name).is_some_and(|t| t.dims() == var.as_tensor().dims())))
    }

    /// Whether the checkpoint at `path` holds critics of this learner's shape (a training
    /// run's full checkpoint; an actor-only file does not).
    pub fn holds_critic(&self, path: &Path) -> Result<bool> {
        self.critic_matches(&checkpoint::load(path)?.tensors)
    }

    /// Writes every network (online and target) to a checkpoint.
    pub fn save(&self, path: &Path, extra: HashMap<String, String>) -> Result<()> {
        self.snapshot()?.save(path, extra)
    }

    /// A copy of every network (online and target) as they are now, to save later while
    /// training goes on.
    pub fn snapshot(&self) -> Result<LearnerSnapshot> {
        let tensors = self
            .all_tensors()?
            .into_iter()
            .map(|(name, tensor)| Ok((name, tensor.copy()?)))
            .collect::<Result<Vec<_>>>()?;
        Ok(LearnerSnapshot {
            tensors,
            meta: CheckpointMeta {
                n_agents: self.n_agents,
                observation: self.observation,
                n_actors: self.n_actors(),
                actor: self.actor_shape.clone(),
                extra: HashMap::new(),
            },
        })
    }

    /// Resumes from a checkpoint written by [`Learner::save`]. A shared actor trained with
    /// another critic (an `mlp` critic for another N, or another architecture or width) is
    /// carried over alone and the critic starts fresh: that is how training moves on to other
    /// swarm sizes. A `pooled` critic carries over to any N.
    pub fn load(&mut self, path: &Path) -> Result<()> {
        let loaded = checkpoint::load(path)?;
        loaded
            .meta
            .check_observation(path, self.observation, self.actor_shape.obs_dim)?;
        let same_critic = self.critic_matches(&loaded.tensors)?;
        let actor_only = !same_critic && loaded.meta.n_actors == 1 && self.n_actors() == 1;
        if (!same_critic && !actor_only)
            || loaded.meta.n_actors != self.n_actors()
            || loaded.meta.actor != self.actor_shape
        {
            bail!(
                "checkpoint {} is for {} robots, {} actors of shape {:?}{}; this run trains {} robots, {} actors of shape {:?}",
                path.display(),
                loaded.meta.n_agents,
                loaded.meta.n_actors,
                loaded.meta.actor,
                if same_critic { "" } else { " and another critic" },
                self.n_agents,
                self.n_actors(),
                self.actor_shape
            );
        }
        let mut parts = vec![("", &self.actor_vars), ("target.", &self.actor_target_vars)];
        if !actor_only {
            parts.extend([("", &self.critic_vars), ("target.", &self.critic_target_vars)]);
        }
        for (prefix, vars) in parts {
            let data = vars
                .data()
                .lock()
                .map_err(|_| anyhow::anyhow!("var map lock poisoned"))?;
            for (name, var) in data.iter() {
                let full = format!("{prefix}{name}");
                let tensor = loaded
                    .tensors
                    .get(&full)
                    .ok_or_else(|| anyhow::anyhow!("checkpoint {} has no tensor {full}", path.display()))?;
                if tensor.dims() != var.as_tensor().dims() {
                    bail!(
                        "checkpoint {}: {full} has shape {:?}, this run needs {:?} (critic widths or algorithm differ)",
                        path.display(),
                        tensor.dims(),
                        var.as_tensor().dims()
                    );
                }
                var.set(tensor)?;
            }
        }
        if actor_only {
            eprintln!(
                "critic: {} was trained with another critic ({} robots); its shared actor carries over, the critic starts fresh",
                path.display(),
                loaded.meta.n_agents,
            );
        } else if let Some(updates) = loaded.meta.extra.get("updates").and_then(|u| u.parse().ok()) {
            self.updates = updates;
        }
        Ok(())
    }
}
