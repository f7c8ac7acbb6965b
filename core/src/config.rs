//! The run configuration: one serde struct with the paper's defaults (docs/RESULTS.md says
//! where and why this project departs from them).
//!
//! Every process reads the same file (`config.toml` in the run directory), so the sim, the
//! agents and the critic can never disagree on dt, tolerances or network shapes.

use std::path::Path;

use serde::{Deserialize, Serialize};

use formation_protocol::{MAX_AGENTS, MIN_AGENTS};

use crate::baseline::BaselineGains;
use crate::obstacles::{ObstacleConfig, ObstacleKind, min_goal_distance_m};
use crate::reality::RealityConfig;

/// Everything a run is configured by. Unknown keys are rejected.
///
/// In a file the obstacles are a section of their own, `[obstacles]`; in memory they are
/// `env.obstacles`, since every function that draws or plays an episode reads them with the rest
/// of the task.
#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(from = "RunConfigFile", into = "RunConfigFile")]
pub struct RunConfig {
    /// Physics, task and reward.
    pub env: EnvConfig,
    /// Lockstep and real-time tick protocol.
    pub ticks: TickConfig,
    /// Central training.
    pub learn: LearnConfig,
    /// Live view and recordings.
    pub view: ViewConfig,
    /// The robots' own sensors, radio and motors between the truth and the robots (all off by
    /// default: the ideal world).
    pub reality: RealityConfig,
    /// Gains of the scripted baseline.
    pub baseline: BaselineGains,
}

/// [`RunConfig`] as a file spells it: `[obstacles]` beside `[env]`.
#[derive(Serialize, Deserialize, Clone, Debug, Default)]
#[serde(deny_unknown_fields, default)]
struct RunConfigFile {
    env: EnvConfig,
    obstacles: ObstacleConfig,
    ticks: TickConfig,
    learn: LearnConfig,
    view: ViewConfig,
    reality: RealityConfig,
    baseline: BaselineGains,
}

impl From<RunConfigFile> for RunConfig {
    fn from(file: RunConfigFile) -> Self {
        Self {
            env: EnvConfig {
                obstacles: file.obstacles,
                ..file.env
            },
            ticks: file.ticks,
            learn: file.learn,
            view: file.view,
            reality: file.reality,
            baseline: file.baseline,
        }
    }
}

impl From<RunConfig> for RunConfigFile {
    fn from(config: RunConfig) -> Self {
        Self {
            obstacles: config.env.obstacles.clone(),
            env: config.env,
            ticks: config.ticks,
            learn: config.learn,
            view: config.view,
            reality: config.reality,
            baseline: config.baseline,
        }
    }
}

/// The environment: unicycle robots, formation, goal and the paper's reward table (Table I).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct EnvConfig {
    /// Integration step, seconds.
    pub dt_s: f64,
    /// Episode time limit in steps (a truncation, not a terminal state).
    pub max_steps: u32,
    /// Largest forward speed, m/s (the smallest is 0).
    pub v_max: f64,
    /// Largest turn rate magnitude, rad/s.
    pub w_max: f64,
    /// Side of the square arena, metres (grown to fit large swarms, see `effective_arena_m`).
    pub arena_m: f64,
    /// Shortest desired edge, metres.
    pub edge_min_m: f64,
    /// Longest desired edge, metres.
    pub edge_max_m: f64,
    /// Nearest goal from the start centroid, metres.
    pub goal_min_m: f64,
    /// Farthest goal from the start centroid, metres.
    pub goal_max_m: f64,
    /// Largest deviation of a robot's start heading from the common heading, radians.
    pub heading_jitter_rad: f64,
    /// C1: largest edge error that still counts as "in formation", metres.
    pub eps_form_m: f64,
    /// C2: two robots closer than this have collided, metres.
    pub eps_coll_m: f64,
    /// C3: largest centroid-to-goal distance that counts as "at the goal", metres.
    pub eps_goal_m: f64,
    /// Reward when only C1 holds.
    pub r_edge: f64,
    /// Reward on collision (episode ends).
    pub r_collision: f64,
    /// Reward on success (episode ends).
    pub r_goal: f64,
    /// Reward otherwise.
    pub r_penalty: f64,
    /// Reward per metre the robots come closer to their slots at the goal in a tick (the mean
    /// over the robots in the formation of each one's approach, its speed times the cosine
    /// between its heading and its slot's bearing, times dt); 0 (the default) is the paper's
    /// table. Among obstacles it makes getting through worth more than waiting
    /// (docs/OBSTACLES.md, "The reward").
    pub r_progress: f64,
    /// Measure `r_progress`'s approach along each robot's way round the obstacles to its slot
    /// (the sim's map, [`crate::geodesic`]) instead of its slot's straight bearing: a detour
    /// round a disc is paid as progress. Needs `learn.her_probability = 0` and team credit (a
    /// relabelled goal has no way computed); false (the default): straight.
    pub geodesic_progress: bool,
    /// Reward per metre of the robots' mean distance from their slots at the goal, every tick
    /// (<= 0; 0, the default, is off): a cost of every tick not yet there, so waiting, in
    /// formation or stalled by a disc, costs what it keeps the robots from their slots.
    pub r_distance: f64,
    /// While a robot in the formation is within this distance of an obstacle's surface, the
    /// formation is excused from C1's reward: the tick earns `r_edge` in formation or not (a
    /// column through a gap is not punished); success still needs C1. Metres; 0 (the default):
    /// never excused.
    pub formation_excuse_m: f64,
    /// What each robot is told every tick (see `formation_core::observation`): `paper` (the
    /// paper's 12 floats: two neighbours and the goal), `slot` (also the robot's own place in
    /// the goal formation) or `slot_proximity` (also the nearest robot it does not track).
    pub observation: ObservationModel,
    /// Formation shapes of the episodes: `random` (rigid random shapes), `ring`, `line`,
    /// `wedge`, `grid`, or `mixed` (each episode one of those, drawn uniformly).
    pub shape: FormationShape,
    /// Range of the `slot_proximity` model's nearest-robot term, metres.
    pub proximity_range_m: f64,
    /// Ticks of history the actor and the critic see (H). The paper uses 15; the default, 1, is
    /// what learned fastest here (see docs/RESULTS.md); `configs/paper.toml` sets 15.
    pub history: usize,
    /// Shape changes per episode (0, the default: one formation for the whole episode). Each
    /// change gives the swarm a new formation (a shape of `change_shapes`, a random size and
    /// orientation) at a tick drawn in [20, max_steps - 50] from a random stream of its own, so
    /// starts, goals and first shapes are the same as without changes; the mission planner
    /// reassigns the slots (`formation_core::mission`) and the time limit grows
    /// ([`EnvConfig::episode_steps`]). Success means holding the last formation at the goal.
    pub shape_changes: u32,
    /// Shapes a change draws from, uniformly (not `mixed`).
    pub change_shapes: Vec<FormationShape>,
    /// How fast a formation morphs into a new one (`formation_core::mission::Morph`): the speed
    /// of its farthest-moving target relative to the swarm, as a fraction of `v_max` (> 0;
    /// default 0.35). Larger re-forms sooner with robots moving more at once; a very large value
    /// (1000) gives the step change of old: every target jumps in one tick.
    pub morph_speed: f64,
    /// Longest range of the `slot_proximity_scan` model's range sensor, metres (> 0; default
    /// 2): a ray that meets nothing nearer reads this.
    pub scan_range_m: f64,
    /// The episodes' obstacles: the `[obstacles]` section of a run's file (never written under
    /// `[env]`).
    #[serde(skip)]
    pub obstacles: ObstacleConfig,
}

impl Default for EnvConfig {
    fn default() -> Self {
        Self {
            dt_s: 0.1,
            max_steps: 120,
            v_max: 0.5,
            w_max: 1.0,
            arena_m: 10.0,
            edge_min_m: 0.8,
            edge_max_m: 2.0,
            goal_min_m: 1.0,
            goal_max_m: 2.5,
            heading_jitter_rad: 0.1,
            eps_form_m: 0.10,
            eps_coll_m: 0.20,
            eps_goal_m: 0.15,
            r_edge: 0.1,
            r_collision: -100.0,
            r_goal: 50.0,
            r_penalty: -0.5,
            r_progress: 0.0,
            geodesic_progress: false,
            r_distance: 0.0,
            formation_excuse_m: 0.0,
            observation: ObservationModel::default(),
            shape: FormationShape::Random,
            proximity_range_m: 1.0,
            history: 1,
            shape_changes: 0,
            change_shapes: FormationShape::KINDS.to_vec(),
            morph_speed: 0.35,
            scan_range_m: 2.0,
            obstacles: ObstacleConfig::default(),
        }
    }
}

/// What each robot observes (layouts in `formation_core::observation`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(any(test, feature = "clap"), derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
#[cfg_attr(any(test, feature = "clap"), value(rename_all = "snake_case"))]
pub enum ObservationModel {
    /// The paper's 12 floats: each neighbour's position, relative heading and desired distance,
    /// then the goal.
    Paper,
    /// The paper's floats and the robot's own slot: the goal plus its offset in the goal
    /// formation (14 floats).
    Slot,
    /// The slot model and the nearest robot that is not a neighbour (16 floats): the default,
    /// since it is what lets one policy drive any number of robots.
    #[default]
    SlotProximity,
    /// The `slot_proximity` floats and a range sensor's 16 rays (32 floats): what a robot needs
    /// among obstacles.
    SlotProximityScan,
}

impl ObservationModel {
    /// The name used in configs and checkpoints.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Slot => "slot",
            Self::SlotProximity => "slot_proximity",
            Self::SlotProximityScan => "slot_proximity_scan",
        }
    }

    /// Reads a name written by [`ObservationModel::as_str`].
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Paper, Self::Slot, Self::SlotProximity, Self::SlotProximityScan]
            .into_iter()
            .find(|model| model.as_str() == name)
    }
}

/// Formation shapes an episode may start in (every shape is drawn at a random size and
/// orientation, with every observed edge in [edge_min_m, edge_max_m]).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(any(test, feature = "clap"), derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
#[cfg_attr(any(test, feature = "clap"), value(rename_all = "snake_case"))]
pub enum FormationShape {
    /// A random rigid shape (a perturbed, relaxed ring).
    Random,
    /// Robots evenly on a circle (two interleaved circles for large swarms).
    Ring,
    /// Two files side by side, as a column marches.
    Line,
    /// A V of two files, pointing in the direction of travel at the start.
    Wedge,
    /// A rectangular block, robots on a lattice.
    Grid,
    /// Every episode one of the above, drawn uniformly (for training that sees every shape).
    Mixed,
}

impl FormationShape {
    /// Every kind a `mixed` run draws from.
    pub const KINDS: [FormationShape; 5] = [Self::Random, Self::Ring, Self::Line, Self::Wedge, Self::Grid];

    /// The name used in configs and reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Random => "random",
            Self::Ring => "ring",
            Self::Line => "line",
            Self::Wedge => "wedge",
            Self::Grid => "grid",
            Self::Mixed => "mixed",
        }
    }
}

impl EnvConfig {
    /// Maps a normalised action in [-1, 1]^2 (the actor's tanh output) to (v, w).
    pub fn command_from_action(&self, action: [f32; 2]) -> (f64, f64) {
        let a0 = f64::from(action[0]).clamp(-1.0, 1.0);
        let a1 = f64::from(action[1]).clamp(-1.0, 1.0);
        ((a0 + 1.0) * 0.5 * self.v_max, a1 * self.w_max)
    }

    /// Maps (v, w) back to the normalised action the actor would have produced.
    pub fn action_from_command(&self, v: f64, w: f64) -> [f32; 2] {
        let a0 = (2.0 * v / self.v_max - 1.0).clamp(-1.0, 1.0);
        let a1 = (w / self.w_max).clamp(-1.0, 1.0);
        [a0 as f32, a1 as f32]
    }

    /// Clamps a command to the robot's limits (what the sim applies).
    pub fn clamp_command(&self, v: f64, w: f64) -> (f64, f64) {
        (v.clamp(0.0, self.v_max), w.clamp(-self.w_max, self.w_max))
    }

    /// The arena side actually used for `n_agents`: large swarms need room for their closed
    /// strip of robots plus the goal distance, so the arena grows to fit them.
    pub fn effective_arena_m(&self, n_agents: usize) -> f64 {
        let needed = 2.0 * (self.formation_reach_m(n_agents) + self.goal_range_m(n_agents).1 + 1.0);
        self.arena_m.max(needed)
    }

    /// The nearest and farthest goal from the start centroid for `n_agents`, metres:
    /// [`goal_min_m`, `goal_max_m`], moved out to the obstacles' own minimum
    /// ([`min_goal_distance_m`]) when that is farther, keeping its width.
    ///
    /// [`goal_min_m`]: EnvConfig::goal_min_m
    /// [`goal_max_m`]: EnvConfig::goal_max_m
    pub fn goal_range_m(&self, n_agents: usize) -> (f64, f64) {
        let needed = min_goal_distance_m(&self.obstacles, self.obstacles.kind, n_agents, self);
        let shift = (needed - self.goal_min_m).max(0.0);
        (self.goal_min_m + shift, self.goal_max_m + shift)
    }

    /// Whether the episodes have obstacles.
    pub fn has_obstacles(&self) -> bool {
        self.obstacles.kind != ObstacleKind::None
    }

    /// The model under `models/` an eval's learned robots load without `--checkpoint`: in the
    /// open arena the open-arena model; among obstacles an obstacle policy (it reads the range
    /// sensor), the passage's own for `passage` (the one that gets formations through the gap),
    /// the forest-trained one for every other kind and for `mixed` (models/README.md).
    pub fn shipped_model_file(&self) -> &'static str {
        match self.obstacles.kind {
            ObstacleKind::None => "formation.safetensors",
            ObstacleKind::Passage => "formation-obstacles-passage.safetensors",
            _ => "formation-obstacles.safetensors",
        }
    }

    /// For robots that run no learned actor (scripted, the planner): among obstacles they
    /// observe their range sensor (`slot_proximity_scan`) unless another model than the default
    /// was asked for. A learned robot keeps its checkpoint's model.
    pub fn scan_among_obstacles(&mut self) {
        if self.has_obstacles() && self.observation == ObservationModel::default() {
            self.observation = ObservationModel::SlotProximityScan;
        }
    }

    /// The time limit of an episode of `n_agents`, steps: `max_steps`, plus for each shape
    /// change the ticks a robot needs to cross the widest formation of `change_shapes` at top
    /// speed (2 reach / (v_max dt)), so that a large swarm can re-form and still reach the goal
    /// (with every shape allowed, each change adds 161 ticks at N = 6, 198 at N = 16, 339 at N = 32).
    pub fn episode_steps(&self, n_agents: usize) -> u32 {
        if self.shape_changes == 0 {
            return self.max_steps;
        }
        let reach = self
            .change_shapes
            .iter()
            .map(|&shape| EnvConfig { shape, ..self.clone() }.formation_reach_m(n_agents))
            .fold(0.0, f64::max);
        let per_change = (2.0 * reach / (self.v_max * self.dt_s)).ceil() as u32;
        self.max_steps + self.shape_changes * per_change
    }

    /// The farthest a robot of a formation of `n_agents` (of the configured shape) can start
    /// from its centroid.
    pub fn formation_reach_m(&self, n_agents: usize) -> f64 {
        crate::shapes::reach_m(self.shape, n_agents, self)
    }
}

/// Episode seed of the held-out evaluations (`scripts/eval_grid.sh`, the tables in the docs):
/// model selection must not play these episodes.
pub const HELD_OUT_SEED: u64 = 1000;

/// Episode seed of extra swarm `k` (1, 2, ...) of a training run started with `--seed seed`:
/// 7919 (a prime) apart, so the swarms of a run play unrelated episodes.
pub fn extra_swarm_seed(seed: u64, k: usize) -> u64 {
    seed.wrapping_add(7919 * k as u64)
}

/// Most shape changes an episode may carry (`env.shape_changes`).
pub const MAX_SHAPE_CHANGES: u32 = 8;

/// Most map points a robot's token in the central critic may hold (`learn.critic_map_points`).
pub const MAX_CRITIC_MAP_POINTS: usize = 8;

/// From this many robots on, formations are compact rings (smaller swarms get freer shapes).
pub const LARGE_SWARM: usize = 8;

/// The tick protocol.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct TickConfig {
    /// Lockstep: how long the sim waits for every command of a tick before holding the
    /// missing robots' last commands, milliseconds.
    pub command_timeout_ms: u64,
    /// How long the sim waits for every agent (and the critic) to connect, seconds.
    pub startup_timeout_s: u64,
    /// Train mode: how many ticks the sim may run ahead of the critic's consumption.
    pub critic_window: u32,
    /// Silence from the sim after which agents give up, and the critic checks whether the sim
    /// still lives (a live one is waited for up to `startup_timeout_s`), milliseconds.
    pub sim_silence_ms: u64,
}

impl Default for TickConfig {
    fn default() -> Self {
        Self {
            command_timeout_ms: 200,
            startup_timeout_s: 60,
            critic_window: 64,
            sim_silence_ms: 2000,
        }
    }
}

/// Actor-critic variants. The paper uses DDPG; TD3 is the measured improvement.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Algorithm {
    /// One critic, actor step every update (the paper).
    Ddpg,
    /// Twin critics, target policy smoothing, delayed actor steps.
    Td3,
}

/// How the central critic reads the team.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum CriticArchitecture {
    /// An MLP over the whole team's state and joint action, flattened: sized by N.
    Mlp,
    /// Deep sets: one encoder applied to each robot's own features and actions, averaged over
    /// the robots in the formation, then an MLP head. The same weights serve any N.
    Pooled,
}

/// Whom TD3+BC's imitation term pulls the actor towards (`learn.imitation_teacher`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum ImitationTeacher {
    /// The scripted baseline with the run's `[baseline]` gains, on each replayed observation.
    #[default]
    Baseline,
    /// The actor the run started from (`--checkpoint`), frozen: the pull keeps the actor near
    /// its imitation start, whatever taught that (a planner that knows the map, whose command
    /// no replayed observation can recompute).
    Start,
}

/// How an actor step improves the actor on the critic (`learn.actor_update`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum ActorUpdate {
    /// Up the gradient of the first critic's Q (DDPG and TD3, the paper's).
    #[default]
    QGradient,
    /// Towards the replayed actions the critic rates above the actor's own, robot by robot
    /// (critic-regularised regression with a binary filter, Wang et al. 2020): a robot's played
    /// action is copied where Q with it beats Q with the actor's action in its place, the other
    /// robots' actions as played. The actor only moves towards actions that were tried, so a
    /// critic that is wrong cannot pull it off the replay; `pooled` critic only.
    AdvantageFiltered,
}

/// Which components of each robot's action the critic's Q gradient moves (`learn.q_gradient_actions`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "snake_case")]
pub enum QGradientActions {
    /// The forward speed and the turn rate (DDPG and TD3, the paper's).
    #[default]
    Both,
    /// The turn rate alone: the critic's Q reads the actor's speed with no gradient through it,
    /// so the speed learns only from the imitation term. The critic steers; the start sets the
    /// pace.
    Turn,
}

/// Whose value the central critic learns (`learn.credit`).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum Credit {
    /// One value of the team for the shared reward (the paper's).
    #[default]
    Team,
    /// One value per robot, for its own reward: the shared reward with the team's mean approach
    /// to the slots (`env.r_progress`) replaced by the robot's own. Each robot's value then
    /// answers for what its own action did, so one robot stalled among sixteen is not one
    /// sixteenth of the team's signal. `pooled` critic, `q_gradient` update only.
    Robot,
}

/// Central training hyper-parameters.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LearnConfig {
    /// DDPG (the paper) or TD3 (default, measured to be stable on this task).
    pub algorithm: Algorithm,
    /// One actor for every robot (default) or one per robot (the paper).
    pub shared_actor: bool,
    /// Concurrent sequences per gradient update (B).
    pub batch_size: usize,
    /// Discount factor.
    pub gamma: f64,
    /// Adam learning rate of the actor(s).
    pub actor_lr: f64,
    /// Adam's epsilon for the actor(s), added to each weight's gradient rms before it divides
    /// the step. At the default (1e-8, Adam's own) every weight moves by about `actor_lr` a
    /// step whatever the size of its gradient; at an epsilon near the gradients' size (see
    /// `actor_gradient_rms` in training.csv) a weight whose gradient is small moves in
    /// proportion to it, as under plain SGD with a rate of `actor_lr / actor_adam_eps`.
    pub actor_adam_eps: f64,
    /// Adam learning rate of the critic(s).
    pub critic_lr: f64,
    /// Polyak factor of the target networks.
    pub tau: f64,
    /// Probability that a sampled sequence gets its goal relabelled (HER).
    pub her_probability: f64,
    /// Steps of reward summed before the critic bootstraps (n-step returns, uncorrected; 1 =
    /// the paper's one-step target). The sum stops at a terminal tick and at the episode's end.
    pub n_step: usize,
    /// Exploration noise std (in normalised action units) at the start of training.
    pub noise_std: f64,
    /// Exploration noise std it decays to.
    pub noise_std_min: f64,
    /// Episodes over which the noise decays linearly.
    pub noise_decay_episodes: u32,
    /// Correlation time of the exploration noise, ticks: each robot's noise is an AR(1)
    /// process with this time constant and the std above (coloured noise, as Ornstein-Uhlenbeck
    /// exploration), so a robot held at an obstacle turns one way for a while instead of
    /// jittering in place. 0 (the default): white noise, drawn afresh every tick.
    pub noise_correlation_ticks: f64,
    /// Temporally extended exploration at stalls: when an exploring robot's own progress
    /// checker ([`crate::recovery::ProgressChecker`]) finds it stalled by a surface, an offset
    /// of this std (normalised action units, one draw per action) is added to its command and
    /// held for [`LearnConfig::stall_noise_ticks`], so the replay holds what turning away or
    /// pressing on does there. 0 (the default): off.
    pub stall_noise_std: f64,
    /// How long a stall's held offset lasts, ticks.
    pub stall_noise_ticks: u32,
    /// Gradient updates per team transition (update-to-data ratio).
    pub updates_per_transition: f64,
    /// Transitions collected with random actions before the first update.
    pub warmup_transitions: usize,
    /// Hidden layer widths of the actor.
    pub actor_hidden: Vec<usize>,
    /// The critic's architecture: `mlp` (sized by N, the paper's) or `pooled` (any N).
    pub critic: CriticArchitecture,
    /// Hidden layer widths of the critic (of its head, for `pooled`).
    pub critic_hidden: Vec<usize>,
    /// `pooled` only: widths of the per-robot encoder; the last is what is averaged.
    pub critic_encoder: Vec<usize>,
    /// `pooled` only: each robot's token also holds the nearest points of its this many nearest
    /// obstacles within [`crate::features::CRITIC_MAP_RANGE_M`], read from the episode's map:
    /// privileged information for the central critic, which no robot runs (0 = off).
    pub critic_map_points: usize,
    /// TD3: actor and target updates every this many critic updates.
    pub policy_delay: u32,
    /// TD3: std of the target policy smoothing noise.
    pub target_noise: f64,
    /// TD3: clip of the target policy smoothing noise.
    pub target_noise_clip: f64,
    /// Rewards are multiplied by this before training (1 = the paper's reward).
    pub reward_scale: f64,
    /// Weight of mean(a^2) added to the actor loss (keeps tanh out of saturation; 0 = off).
    pub action_l2: f64,
    /// The scripted baseline as a teacher (TD3+BC, Fujimoto & Gu 2021): the actor loss becomes
    /// -alpha Q / max(mean|Q|, 1) plus the squared distance between the actor's action and the
    /// baseline's on the same replayed observation. 0 = off (plain TD3 or DDPG, the paper);
    /// the default 2.5 is TD3+BC's own.
    pub imitation_alpha: f64,
    /// Whom the imitation term pulls towards: `baseline` (default) or `start` (the actor of
    /// `--checkpoint`, frozen; a run with it needs a checkpoint).
    pub imitation_teacher: ImitationTeacher,
    /// How the actor improves on the critic: `q_gradient` (default) or `advantage_filtered`
    /// (with a teacher, `imitation_alpha` weighs the filtered copy against the teacher's pull).
    pub actor_update: ActorUpdate,
    /// Which action components the Q gradient moves: `both` (default) or `turn` (the speed
    /// is left to the imitation term; `q_gradient` update only).
    pub q_gradient_actions: QGradientActions,
    /// The actor's steps move its output layer alone, its hidden layers held: a policy that can
    /// follow the mean of the critic's slopes over the states that share a feature, not each
    /// state's own (docs/RESULTS.md, "What the critic knows of an action"). Default false.
    pub actor_output_layer_only: bool,
    /// Whose value the critic learns: `team` (default, the shared reward) or `robot` (each
    /// robot's own reward and value, [`Credit::Robot`]).
    pub credit: Credit,
    /// Critic-only updates at the start of a run: the actor (and its target) is held while the
    /// critics learn its value, so that a run starting from an imitated actor does not climb a
    /// random critic first. 0 = off.
    pub critic_warmup_updates: u64,
    /// Replay capacity in ticks.
    pub replay_capacity: usize,
    /// New actor weights are published every this many updates.
    pub publish_every_updates: u64,
    /// A checkpoint is written at least this often, seconds.
    pub checkpoint_every_s: u64,
    /// Also keep every checkpoint, as `checkpoints/updates-<U>.safetensors` in the run directory,
    /// for learning curves computed afterwards (scripts/checkpoint_curves.py).
    pub keep_checkpoints: bool,
    /// Threads the critic's matrix products may use.
    pub threads: usize,
    /// TD3's twin critics take their gradient steps (and compute their target values) on two
    /// threads, the second free to run on any CPU: the same numbers as one after the other.
    /// Off by default: an update alone is 1.4x as fast, but on two CPUs a whole training run
    /// got 6 % fewer updates/s with it (docs/RESULTS.md); turn it on where CPUs are spare.
    pub parallel_critics: bool,
    /// In train mode, every this many episodes is played without noise to measure the policy.
    pub eval_every_episodes: u32,
    /// Seed of the model-selection episodes, scored at every checkpoint. Episode k of a run is
    /// the k-th draw of a generator seeded with the run's `--seed`, so only an equal seed plays
    /// the same episodes: the default (0x5E1EC7) is no training seed and not the held-out 1000.
    pub selection_seed: u64,
    /// Model-selection episodes per swarm size.
    pub selection_episodes: usize,
}

impl Default for LearnConfig {
    fn default() -> Self {
        Self {
            algorithm: Algorithm::Td3,
            shared_actor: true,
            batch_size: 256,
            gamma: 0.98,
            actor_lr: 3e-4,
            actor_adam_eps: 1e-8,
            critic_lr: 1e-3,
            tau: 5e-3,
            her_probability: 0.8,
            n_step: 1,
            noise_std: 0.2,
            noise_std_min: 0.2,
            noise_decay_episodes: 3000,
            noise_correlation_ticks: 0.0,
            stall_noise_std: 0.0,
            stall_noise_ticks: 30,
            updates_per_transition: 0.5,
            warmup_transitions: 5000,
            actor_hidden: vec![128, 128],
            critic: CriticArchitecture::Mlp,
            critic_hidden: vec![256, 256],
            critic_encoder: vec![64, 64],
            critic_map_points: 0,
            policy_delay: 2,
            target_noise: 0.2,
            target_noise_clip: 0.5,
            reward_scale: 1.0,
            action_l2: 0.0,
            imitation_alpha: 2.5,
            imitation_teacher: ImitationTeacher::Baseline,
            actor_update: ActorUpdate::QGradient,
            q_gradient_actions: QGradientActions::Both,
            actor_output_layer_only: false,
            credit: Credit::Team,
            critic_warmup_updates: 0,
            replay_capacity: 1_000_000,
            publish_every_updates: 50,
            checkpoint_every_s: 120,
            keep_checkpoints: false,
            threads: 1,
            parallel_critics: false,
            eval_every_episodes: 10,
            selection_seed: 0x5E1EC7,
            selection_episodes: 50,
        }
    }
}

/// What the live view logs.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ViewConfig {
    /// In train mode, log the world for one episode in this many (eval logs every episode).
    pub world_every_episodes: u32,
    /// Length of the robots' trails, ticks.
    pub trail_ticks: usize,
}

impl Default for ViewConfig {
    fn default() -> Self {
        Self {
            world_every_episodes: 20,
            trail_ticks: 40,
        }
    }
}

/// A configuration value that cannot work, with the field it is in.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config file {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        source: std::io::Error,
    },
    /// The file is not valid TOML for this struct (syntax, unknown key, wrong type).
    #[error("config file {path} does not parse: {message}")]
    Parse {
        /// The file.
        path: String,
        /// What toml said, with line and key.
        message: String,
    },
    /// A training swarm's episode seed draws episodes that training must never play.
    #[error("{swarm} would train on seed {seed}, which is {reserved}; pick another --seed")]
    ReservedSeed {
        /// Which swarm, with how its seed follows from `--seed`.
        swarm: String,
        /// Its episode seed.
        seed: u64,
        /// Whose seed it is and what its episodes are for.
        reserved: &'static str,
    },
    /// A value is out of its range.
    #[error("config value {field} = {value} is invalid: {reason}")]
    Invalid {
        /// Dotted name of the field, e.g. `env.dt_s`.
        field: &'static str,
        /// The value found.
        value: String,
        /// What it must be instead.
        reason: &'static str,
    },
}

fn check(ok: bool, field: &'static str, value: impl ToString, reason: &'static str) -> Result<(), ConfigError> {
    if ok {
        Ok(())
    } else {
        Err(ConfigError::Invalid {
            field,
            value: value.to_string(),
            reason,
        })
    }
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

impl RunConfig {
    /// Reads a TOML file of overrides on top of the defaults, then validates it.
    pub fn from_toml_file(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_toml_str(&text).map_err(|err| match err {
            ConfigError::Parse { message, .. } => ConfigError::Parse {
                path: path.display().to_string(),
                message,
            },
            other => other,
        })
    }

    /// Parses TOML overrides on top of the defaults, then validates.
    pub fn from_toml_str(text: &str) -> Result<Self, ConfigError> {
        let config: RunConfig = toml::from_str(text).map_err(|err| ConfigError::Parse {
            path: "<string>".into(),
            message: err.to_string(),
        })?;
        config.validate()?;
        Ok(config)
    }

    /// The configuration as TOML (what is written into the run directory).
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).unwrap_or_else(|err| format!("# cannot serialise config: {err}\n"))
    }

    /// Rejects values that make the task impossible or the numbers meaningless.
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.env.validate()?;
        self.ticks.validate()?;
        self.learn.validate()?;
        self.reality.validate()?;
        self.baseline.validate()?;
        check(
            self.view.world_every_episodes >= 1,
            "view.world_every_episodes",
            self.view.world_every_episodes,
            "must be >= 1",
        )?;
        check(
            !self.env.geodesic_progress || (self.learn.her_probability == 0.0 && self.learn.credit == Credit::Team),
            "env.geodesic_progress",
            true,
            "needs learn.her_probability = 0 and learn.credit = \"team\": the ways round the obstacles are \
             the sim's, to each episode's own goal, and a relabelled goal or a robot's own reward would be \
             scored straight",
        )?;
        Ok(())
    }

    /// Refuses a training run whose critic cannot learn its episodes: the `mlp` critic is sized
    /// by N and reads robots by index, so episodes whose formation changes
    /// (`env.shape_changes > 0`) or whose robots leave the formation
    /// (`reality.controller_failure > 0`: the `mlp` critic cannot mask a robot out) need the
    /// `pooled` critic. The critic and the launcher call this for train mode only (an
    /// evaluation trains no critic).
    pub fn check_training_critic(&self) -> Result<(), ConfigError> {
        check(
            self.learn.critic == CriticArchitecture::Pooled || self.env.shape_changes == 0,
            "learn.critic",
            "\"mlp\"",
            "must be \"pooled\" when env.shape_changes > 0: the mlp critic is sized by N and reads robots \
             by index, and a changing formation or team needs the pooled critic ([learn] critic = \"pooled\")",
        )?;
        check(
            self.learn.critic == CriticArchitecture::Pooled || self.reality.controller_failure.is_off(),
            "learn.critic",
            "\"mlp\"",
            "must be \"pooled\" when reality.controller_failure > 0: a robot whose controller fails leaves \
             the formation, and only the pooled critic can leave it out of the team's value \
             ([learn] critic = \"pooled\")",
        )
    }
}

impl EnvConfig {
    /// The task: robots, formations, observation and episode limits.
    fn validate(&self) -> Result<(), ConfigError> {
        let e = self;
        check(
            positive(e.dt_s) && e.dt_s <= 1.0,
            "env.dt_s",
            e.dt_s,
            "must be in (0, 1] seconds",
        )?;
        check(e.max_steps >= 1, "env.max_steps", e.max_steps, "must be at least 1")?;
        check(positive(e.v_max), "env.v_max", e.v_max, "must be > 0")?;
        check(positive(e.w_max), "env.w_max", e.w_max, "must be > 0")?;
        check(positive(e.arena_m), "env.arena_m", e.arena_m, "must be > 0")?;
        check(positive(e.eps_form_m), "env.eps_form_m", e.eps_form_m, "must be > 0")?;
        check(positive(e.eps_goal_m), "env.eps_goal_m", e.eps_goal_m, "must be > 0")?;
        check(
            e.eps_coll_m.is_finite() && e.eps_coll_m >= 0.0,
            "env.eps_coll_m",
            e.eps_coll_m,
            "must be >= 0",
        )?;
        check(
            positive(e.edge_min_m) && e.edge_min_m > e.eps_coll_m + e.eps_form_m,
            "env.edge_min_m",
            e.edge_min_m,
            "must exceed eps_coll_m + eps_form_m, or robots in formation would collide",
        )?;
        check(
            e.edge_max_m.is_finite() && e.edge_max_m >= e.edge_min_m,
            "env.edge_max_m",
            e.edge_max_m,
            "must be >= edge_min_m",
        )?;
        check(positive(e.goal_min_m), "env.goal_min_m", e.goal_min_m, "must be > 0")?;
        check(
            e.goal_max_m.is_finite() && e.goal_max_m >= e.goal_min_m,
            "env.goal_max_m",
            e.goal_max_m,
            "must be >= goal_min_m",
        )?;
        check(
            e.arena_m > 2.0 * (e.edge_max_m + e.goal_max_m),
            "env.arena_m",
            e.arena_m,
            "must exceed 2 * (edge_max_m + goal_max_m) so a formation and its goal fit",
        )?;
        check(
            e.heading_jitter_rad.is_finite() && e.heading_jitter_rad >= 0.0,
            "env.heading_jitter_rad",
            e.heading_jitter_rad,
            "must be >= 0",
        )?;
        check(
            positive(e.proximity_range_m),
            "env.proximity_range_m",
            e.proximity_range_m,
            "must be > 0",
        )?;
        for (field, value) in [
            ("env.r_edge", e.r_edge),
            ("env.r_collision", e.r_collision),
            ("env.r_goal", e.r_goal),
            ("env.r_penalty", e.r_penalty),
            ("env.r_progress", e.r_progress),
        ] {
            check(value.is_finite(), field, value, "must be finite")?;
        }
        check(
            e.r_distance.is_finite() && e.r_distance <= 0.0,
            "env.r_distance",
            e.r_distance,
            "must be <= 0 (a cost per metre from the slots)",
        )?;
        check(
            (1..=64).contains(&e.history),
            "env.history",
            e.history,
            "must be in 1..=64",
        )?;
        check(
            e.shape_changes <= MAX_SHAPE_CHANGES,
            "env.shape_changes",
            e.shape_changes,
            "must be in 0..=8",
        )?;
        check(
            e.shape_changes == 0 || e.max_steps >= 69 + e.shape_changes,
            "env.max_steps",
            e.max_steps,
            "must be >= 69 + shape_changes: changes start at distinct ticks in [20, max_steps - 50]",
        )?;
        check(
            !e.change_shapes.is_empty() && !e.change_shapes.contains(&FormationShape::Mixed),
            "env.change_shapes",
            format!("{:?}", e.change_shapes.iter().map(|s| s.as_str()).collect::<Vec<_>>()),
            "must name at least one shape, and not mixed",
        )?;
        check(
            e.morph_speed.is_finite() && e.morph_speed > 0.0,
            "env.morph_speed",
            e.morph_speed,
            "must be > 0 (a fraction of v_max)",
        )?;
        check(
            positive(e.scan_range_m),
            "env.scan_range_m",
            e.scan_range_m,
            "must be > 0",
        )?;
        e.obstacles.validate()
    }
}

impl TickConfig {
    /// Timing of the tick protocol.
    fn validate(&self) -> Result<(), ConfigError> {
        let t = self;
        check(
            t.command_timeout_ms >= 1,
            "ticks.command_timeout_ms",
            t.command_timeout_ms,
            "must be >= 1",
        )?;
        check(
            t.startup_timeout_s >= 1,
            "ticks.startup_timeout_s",
            t.startup_timeout_s,
            "must be >= 1",
        )?;
        check(
            (1..=4096).contains(&t.critic_window),
            "ticks.critic_window",
            t.critic_window,
            "must be in 1..=4096",
        )?;
        check(
            t.sim_silence_ms >= 100,
            "ticks.sim_silence_ms",
            t.sim_silence_ms,
            "must be >= 100",
        )?;
        Ok(())
    }
}

impl LearnConfig {
    /// The learner: algorithm, sizes and rates.
    fn validate(&self) -> Result<(), ConfigError> {
        let l = self;
        check(
            (1..=65536).contains(&l.batch_size),
            "learn.batch_size",
            l.batch_size,
            "must be in 1..=65536",
        )?;
        check(
            l.gamma.is_finite() && (0.0..1.0).contains(&l.gamma),
            "learn.gamma",
            l.gamma,
            "must be in [0, 1)",
        )?;
        check(positive(l.actor_lr), "learn.actor_lr", l.actor_lr, "must be > 0")?;
        check(
            positive(l.actor_adam_eps),
            "learn.actor_adam_eps",
            l.actor_adam_eps,
            "must be > 0",
        )?;
        check(positive(l.critic_lr), "learn.critic_lr", l.critic_lr, "must be > 0")?;
        check(positive(l.tau) && l.tau <= 1.0, "learn.tau", l.tau, "must be in (0, 1]")?;
        check(
            (0.0..=1.0).contains(&l.her_probability),
            "learn.her_probability",
            l.her_probability,
            "must be in [0, 1]",
        )?;
        check(
            (1..=64).contains(&l.n_step),
            "learn.n_step",
            l.n_step,
            "must be in 1..=64",
        )?;
        check(
            l.noise_std.is_finite() && l.noise_std >= 0.0,
            "learn.noise_std",
            l.noise_std,
            "must be >= 0",
        )?;
        check(
            l.noise_std_min.is_finite() && l.noise_std_min >= 0.0,
            "learn.noise_std_min",
            l.noise_std_min,
            "must be >= 0",
        )?;
        check(
            l.noise_correlation_ticks.is_finite() && l.noise_correlation_ticks >= 0.0,
            "learn.noise_correlation_ticks",
            l.noise_correlation_ticks,
            "must be >= 0",
        )?;
        check(
            l.stall_noise_std.is_finite() && l.stall_noise_std >= 0.0,
            "learn.stall_noise_std",
            l.stall_noise_std,
            "must be >= 0",
        )?;
        check(
            l.stall_noise_ticks >= 1,
            "learn.stall_noise_ticks",
            l.stall_noise_ticks,
            "must be >= 1",
        )?;
        check(
            positive(l.updates_per_transition) && l.updates_per_transition <= 64.0,
            "learn.updates_per_transition",
            l.updates_per_transition,
            "must be in (0, 64]",
        )?;
        check_widths(&l.actor_hidden, "learn.actor_hidden")?;
        check_widths(&l.critic_hidden, "learn.critic_hidden")?;
        check_widths(&l.critic_encoder, "learn.critic_encoder")?;
        check(
            l.critic_map_points <= MAX_CRITIC_MAP_POINTS
                && (l.critic_map_points == 0 || l.critic == CriticArchitecture::Pooled),
            "learn.critic_map_points",
            l.critic_map_points,
            "must be at most 8, and above 0 only with learn.critic = \"pooled\" (a robot's token holds its map points)",
        )?;
        check(
            l.actor_update == ActorUpdate::QGradient || l.critic == CriticArchitecture::Pooled,
            "learn.actor_update",
            "\"advantage_filtered\"",
            "needs learn.critic = \"pooled\": the filter rates each robot's action by swapping its token alone",
        )?;
        check(
            l.q_gradient_actions == QGradientActions::Both || l.actor_update == ActorUpdate::QGradient,
            "learn.q_gradient_actions",
            "\"turn\"",
            "needs learn.actor_update = \"q_gradient\": the filtered copy has no Q gradient to narrow",
        )?;
        check(
            l.credit == Credit::Team
                || (l.critic == CriticArchitecture::Pooled && l.actor_update == ActorUpdate::QGradient),
            "learn.credit",
            "\"robot\"",
            "needs learn.critic = \"pooled\" (a value per robot token) and learn.actor_update = \"q_gradient\"",
        )?;
        check(
            l.policy_delay >= 1,
            "learn.policy_delay",
            l.policy_delay,
            "must be >= 1",
        )?;
        check(
            positive(l.reward_scale),
            "learn.reward_scale",
            l.reward_scale,
            "must be > 0",
        )?;
        check(
            l.action_l2.is_finite() && l.action_l2 >= 0.0,
            "learn.action_l2",
            l.action_l2,
            "must be >= 0",
        )?;
        check(
            l.imitation_alpha.is_finite() && l.imitation_alpha >= 0.0,
            "learn.imitation_alpha",
            l.imitation_alpha,
            "must be >= 0 (0 = no teacher)",
        )?;
        self.validate_bookkeeping()
    }

    /// Refuses a training run whose swarms would play episodes training must never see: those
    /// of `learn.selection_seed` (model selection scores checkpoints on them) and those of
    /// [`HELD_OUT_SEED`] (the held-out evaluation). The run trains on `seed` and, with
    /// `extra_swarms` extra swarms, on [`extra_swarm_seed`]`(seed, k)` for k = 1..=extra_swarms.
    pub fn check_training_seeds(&self, seed: u64, extra_swarms: usize) -> Result<(), ConfigError> {
        for k in 0..=extra_swarms {
            let swarm_seed = extra_swarm_seed(seed, k);
            let reserved = if swarm_seed == self.selection_seed {
                "learn.selection_seed (the episodes its checkpoints are selected on)"
            } else if swarm_seed == HELD_OUT_SEED {
                "the held-out evaluation seed 1000 (the episodes results are measured on)"
            } else {
                continue;
            };
            let swarm = match k {
                0 => format!("the run (--seed {seed})"),
                k => format!("extra swarm {k} (--seed {seed} + 7919 x {k})"),
            };
            return Err(ConfigError::ReservedSeed {
                swarm,
                seed: swarm_seed,
                reserved,
            });
        }
        Ok(())
    }

    /// Refuses a training run whose imitation term pulls towards the actor it starts from
    /// (`imitation_teacher = "start"`) when it starts from none (`resuming`: a `--checkpoint`).
    pub fn check_imitation_start(&self, resuming: bool) -> Result<(), ConfigError> {
        let pulls_to_start = self.imitation_alpha > 0.0 && self.imitation_teacher == ImitationTeacher::Start;
        check(
            resuming || !pulls_to_start,
            "learn.imitation_teacher",
            "\"start\"",
            "it pulls the actor towards the one the run starts from: pass --checkpoint",
        )
    }

    /// Replay, weights streaming, threads, evaluation and model selection.
    fn validate_bookkeeping(&self) -> Result<(), ConfigError> {
        let l = self;
        check(
            l.replay_capacity >= 1000,
            "learn.replay_capacity",
            l.replay_capacity,
            "must be >= 1000 ticks",
        )?;
        check(
            l.publish_every_updates >= 1,
            "learn.publish_every_updates",
            l.publish_every_updates,
            "must be >= 1",
        )?;
        check(
            (1..=64).contains(&l.threads),
            "learn.threads",
            l.threads,
            "must be in 1..=64",
        )?;
        check(
            l.eval_every_episodes >= 1,
            "learn.eval_every_episodes",
            l.eval_every_episodes,
            "must be >= 1",
        )?;
        check(
            l.selection_seed != HELD_OUT_SEED,
            "learn.selection_seed",
            l.selection_seed,
            "must not be the held-out evaluation seed (selecting on the test episodes)",
        )?;
        check(
            (1..=10_000).contains(&l.selection_episodes),
            "learn.selection_episodes",
            l.selection_episodes,
            "must be in 1..=10000",
        )?;
        Ok(())
    }
}

/// Layer widths of a network: at least one, each in 1..=4096.
fn check_widths(widths: &[usize], field: &'static str) -> Result<(), ConfigError> {
    check(
        !widths.is_empty() && widths.iter().all(|&w| (1..=4096).contains(&w)),
        field,
        format!("{widths:?}"),
        "needs 1 or more widths in 1..=4096",
    )
}

/// Checks a swarm size against what the wire types support.
pub fn validate_agent_count(n_agents: usize) -> Result<(), ConfigError> {
    check(
        (MIN_AGENTS..=MAX_AGENTS).contains(&n_agents),
        "agents",
        n_agents,
        "the swarm needs 3 to 64 robots (each observes two distinct neighbours)",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_round_trip() {
        let config = RunConfig::default();
        config.validate().expect("defaults validate");
        let back = RunConfig::from_toml_str(&config.to_toml()).expect("round trip");
        assert_eq!(back, config);
    }

    #[test]
    fn every_shipped_config_loads_and_the_paper_teacher_differs_from_the_paper_only_in_its_teacher() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
        let mut loaded = 0;
        for entry in std::fs::read_dir(&dir).expect("configs/") {
            let path = entry.expect("entry").path();
            if path.extension().is_some_and(|e| e == "toml") {
                RunConfig::from_toml_file(&path).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
                loaded += 1;
            }
        }
        assert!(loaded >= 7, "only {loaded} configs in {}", dir.display());
        let paper = RunConfig::from_toml_file(&dir.join("paper.toml")).expect("paper");
        let mut taught = RunConfig::from_toml_file(&dir.join("paper-teacher.toml")).expect("paper-teacher");
        assert_eq!((paper.learn.imitation_alpha, taught.learn.imitation_alpha), (0.0, 2.5));
        taught.learn.imitation_alpha = 0.0;
        assert_eq!(taught, paper);
    }

    #[test]
    fn reality_is_off_and_the_baseline_default_unless_configured() {
        let config = RunConfig::default();
        assert_eq!(config.reality, RealityConfig::default());
        assert_eq!(config.baseline, BaselineGains::default());
        let tuned = RunConfig::from_toml_str(
            "[reality]\nactuation_delay_ticks = [1, 3]\ndead_robot = \"stop\"\n[baseline]\nk_form = 0.75\n",
        )
        .expect("parses");
        assert_eq!(
            tuned.reality.actuation_delay_ticks,
            crate::reality::Spread::range(1.0, 3.0)
        );
        assert_eq!(tuned.reality.dead_robot, crate::reality::DeadRobot::Stop);
        assert_eq!(tuned.baseline.k_form, 0.75);
        assert_eq!(tuned.baseline.k_goal, BaselineGains::default().k_goal);
        assert_eq!(RunConfig::from_toml_str(&tuned.to_toml()).expect("round trip"), tuned);
    }

    #[test]
    fn shape_changes_are_off_by_default_and_lengthen_the_episode_with_the_swarm() {
        let env = EnvConfig::default();
        assert_eq!(env.shape_changes, 0);
        assert_eq!(
            env.episode_steps(32),
            env.max_steps,
            "no changes: the limit is max_steps"
        );
        let config = RunConfig::from_toml_str("[env]\nshape_changes = 2\nchange_shapes = [\"line\", \"ring\"]\n")
            .expect("parses");
        assert_eq!(config.env.change_shapes, [FormationShape::Line, FormationShape::Ring]);
        assert_eq!(RunConfig::from_toml_str(&config.to_toml()).expect("round trip"), config);
        let changing = EnvConfig {
            shape_changes: 2,
            ..EnvConfig::default()
        };
        let limits = [6, 16, 32].map(|n| changing.episode_steps(n));
        assert_eq!(limits, [442, 516, 798], "the figures the README and RESULTS give");
    }

    #[test]
    fn progress_round_the_obstacles_needs_the_episodes_own_goals_and_the_team_s_credit() {
        let on = "[env]\ngeodesic_progress = true\n";
        let err = RunConfig::from_toml_str(on).expect_err("HER is on by default");
        assert!(err.to_string().contains("env.geodesic_progress"), "{err}");
        let robot = format!("{on}[learn]\nher_probability = 0.0\ncredit = \"robot\"\n");
        assert!(
            RunConfig::from_toml_str(&robot).is_err(),
            "a robot's own reward is scored straight"
        );
        let config = RunConfig::from_toml_str(&format!("{on}[learn]\nher_probability = 0.0\n")).expect("valid");
        assert!(config.env.geodesic_progress);
    }

    #[test]
    fn overrides_keep_other_defaults() {
        let config = RunConfig::from_toml_str("[env]\ndt_s = 0.05\n").expect("parses");
        assert_eq!(config.env.dt_s, 0.05);
        assert_eq!(config.env.max_steps, 120);
    }

    #[test]
    fn bad_values_name_their_field() {
        for (text, field) in [
            ("[env]\ndt_s = -0.1\n", "env.dt_s"),
            ("[env]\neps_goal_m = 0.0\n", "env.eps_goal_m"),
            ("[env]\nedge_min_m = 0.1\n", "env.edge_min_m"),
            ("[learn]\ngamma = 1.5\n", "learn.gamma"),
            ("[learn]\nn_step = 0\n", "learn.n_step"),
            ("[learn]\ncritic_encoder = []\n", "learn.critic_encoder"),
            ("[learn]\ncritic_map_points = 2\n", "learn.critic_map_points"),
            (
                "[learn]\ncritic = \"pooled\"\ncritic_map_points = 9\n",
                "learn.critic_map_points",
            ),
            ("[learn]\ncritic = \"attention\"\n", "critic"),
            ("[learn]\nselection_seed = 1000\n", "learn.selection_seed"),
            ("[learn]\nselection_episodes = 0\n", "learn.selection_episodes"),
            ("[reality]\ncommand_loss = 1.0\n", "reality.command_loss"),
            (
                "[reality]\nactuation_delay_ticks = [3, 2]\n",
                "reality.actuation_delay_ticks",
            ),
            ("[reality]\nposition_noise_m = -0.1\n", "reality.position_noise_m"),
            ("[baseline]\nk_turn = 0.0\n", "baseline.k_turn"),
            ("[env]\nshape_changes = 9\n", "env.shape_changes"),
            ("[env]\nshape_changes = 2\nmax_steps = 70\n", "env.max_steps"),
            ("[env]\nchange_shapes = []\n", "env.change_shapes"),
            ("[env]\nchange_shapes = [\"ring\", \"mixed\"]\n", "env.change_shapes"),
            ("[env]\nmorph_speed = 0.0\n", "env.morph_speed"),
        ] {
            let err = RunConfig::from_toml_str(text).expect_err(text);
            assert!(err.to_string().contains(field), "{err} should name {field}");
        }
    }

    #[test]
    fn the_turn_only_q_gradient_needs_the_q_gradient_update() {
        let turn = RunConfig::from_toml_str("[learn]\nq_gradient_actions = \"turn\"\n").expect("q gradient");
        assert_eq!(turn.learn.q_gradient_actions, QGradientActions::Turn);
        assert_eq!(RunConfig::default().learn.q_gradient_actions, QGradientActions::Both);
        let filtered = RunConfig::from_toml_str(
            "[learn]\nq_gradient_actions = \"turn\"\nactor_update = \"advantage_filtered\"\ncritic = \"pooled\"\n",
        )
        .expect_err("no Q gradient to narrow")
        .to_string();
        assert!(filtered.contains("learn.q_gradient_actions"), "{filtered}");
    }

    #[test]
    fn the_advantage_filtered_actor_update_needs_the_pooled_critic() {
        let mlp = RunConfig::from_toml_str("[learn]\nactor_update = \"advantage_filtered\"\n")
            .expect_err("mlp critic")
            .to_string();
        assert!(mlp.contains("learn.actor_update") && mlp.contains("pooled"), "{mlp}");
        let pooled = RunConfig::from_toml_str("[learn]\nactor_update = \"advantage_filtered\"\ncritic = \"pooled\"\n")
            .expect("pooled critic");
        assert_eq!(pooled.learn.actor_update, ActorUpdate::AdvantageFiltered);
        assert_eq!(RunConfig::default().learn.actor_update, ActorUpdate::QGradient);
    }

    #[test]
    fn per_robot_credit_needs_the_pooled_critic_and_the_q_gradient() {
        for text in [
            "[learn]\ncredit = \"robot\"\n",
            "[learn]\ncredit = \"robot\"\ncritic = \"pooled\"\nactor_update = \"advantage_filtered\"\n",
        ] {
            let err = RunConfig::from_toml_str(text).expect_err(text).to_string();
            assert!(err.contains("learn.credit") && err.contains("pooled"), "{err}");
        }
        let robot =
            RunConfig::from_toml_str("[learn]\ncredit = \"robot\"\ncritic = \"pooled\"\n").expect("pooled critic");
        assert_eq!(robot.learn.credit, Credit::Robot);
        assert_eq!(RunConfig::default().learn.credit, Credit::Team);
    }

    #[test]
    fn an_mlp_critic_is_refused_for_training_on_changing_formations_naming_both_fields() {
        let changing = RunConfig::from_toml_str("[env]\nshape_changes = 1\n").expect("parses");
        let err = changing.check_training_critic().expect_err("mlp with changes");
        let message = err.to_string();
        assert!(
            message.contains("learn.critic") && message.contains("env.shape_changes") && message.contains("mlp"),
            "{message}"
        );
        assert!(RunConfig::default().check_training_critic().is_ok());
        let pooled =
            RunConfig::from_toml_str("[env]\nshape_changes = 1\n\n[learn]\ncritic = \"pooled\"\n").expect("parses");
        assert!(pooled.check_training_critic().is_ok());
        // Robots leaving the formation: the mlp critic cannot mask them out.
        let failing = RunConfig::from_toml_str("[reality]\ncontroller_failure = 0.5\n").expect("parses");
        let message = failing
            .check_training_critic()
            .expect_err("mlp with failures")
            .to_string();
        assert!(
            message.contains("learn.critic")
                && message.contains("reality.controller_failure")
                && message.contains("mlp"),
            "{message}"
        );
        let pooled = RunConfig::from_toml_str("[reality]\ncontroller_failure = 1.0\n\n[learn]\ncritic = \"pooled\"\n")
            .expect("parses");
        assert!(pooled.check_training_critic().is_ok());
    }

    #[test]
    fn training_seeds_never_play_the_selection_or_held_out_episodes() {
        let learn = LearnConfig::default();
        assert!(learn.check_training_seeds(1, 4).is_ok());
        let selection = learn.selection_seed;
        for (seed, extra, needles) in [
            (
                selection,
                0,
                ["the run (--seed 6168263)", "seed 6168263", "learn.selection_seed"],
            ),
            (HELD_OUT_SEED, 2, ["the run (--seed 1000)", "seed 1000", "held-out"]),
            (
                selection - 2 * 7919,
                3,
                [
                    "extra swarm 2 (--seed 6152425 + 7919 x 2)",
                    "seed 6168263",
                    "learn.selection_seed",
                ],
            ),
            (
                HELD_OUT_SEED.wrapping_sub(7919),
                1,
                ["extra swarm 1 (--seed", "seed 1000,", "held-out"],
            ),
        ] {
            let text = learn
                .check_training_seeds(seed, extra)
                .expect_err("refused")
                .to_string();
            for needle in needles {
                assert!(text.contains(needle), "{text:?} should name {needle:?}");
            }
        }
        // Fewer extra swarms than it takes to reach a reserved seed: nothing to refuse.
        assert!(learn.check_training_seeds(selection - 2 * 7919, 1).is_ok());
    }

    #[test]
    fn unknown_keys_and_bad_syntax_are_rejected() {
        let err = RunConfig::from_toml_str("[env]\ndt = 0.1\n").expect_err("unknown key");
        assert!(err.to_string().contains("unknown field"), "{err}");
        assert!(RunConfig::from_toml_str("[env\n").is_err());
    }

    #[test]
    fn stall_exploration_is_refused_with_a_negative_std_or_no_ticks_naming_the_field() {
        for (text, field) in [
            ("[learn]\nstall_noise_std = -0.1\n", "learn.stall_noise_std"),
            (
                "[learn]\nstall_noise_std = 0.5\nstall_noise_ticks = 0\n",
                "learn.stall_noise_ticks",
            ),
        ] {
            let err = RunConfig::from_toml_str(text).expect_err(field).to_string();
            assert!(err.contains(field), "{err:?} should name {field}");
        }
        let config =
            RunConfig::from_toml_str("[learn]\nstall_noise_std = 0.6\nstall_noise_ticks = 20\n").expect("valid");
        assert_eq!(
            (config.learn.stall_noise_std, config.learn.stall_noise_ticks),
            (0.6, 20)
        );
    }

    #[test]
    fn agent_count_bounds() {
        assert!(validate_agent_count(2).is_err());
        assert!(validate_agent_count(3).is_ok());
        assert!(validate_agent_count(64).is_ok());
        assert!(validate_agent_count(65).is_err());
    }

    #[test]
    fn action_mapping_inverts() {
        let env = EnvConfig::default();
        for action in [[-1.0f32, 0.3], [0.0, -1.0], [1.0, 1.0]] {
            let (v, w) = env.command_from_action(action);
            let back = env.action_from_command(v, w);
            assert!((back[0] - action[0]).abs() < 1e-6 && (back[1] - action[1]).abs() < 1e-6);
        }
    }
}
