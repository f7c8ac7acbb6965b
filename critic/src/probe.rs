//! The critic probe (`formation-critic-probe`): does a trained critic know how one robot's
//! action changes the team's value?
//!
//! The actor steps up the first critic's action gradient, so every RL stage is only as good as
//! that gradient. In the ideal world the episodes are deterministic, so the true effect of an
//! action can be measured exactly: the probe plays an episode with an actor and, every few
//! ticks, branches a copy of the game in which one robot's normalised action of that tick is
//! moved by `±delta` (its speed, then its turn rate); the rest of the branch is played by the
//! same actor. The discounted return of the branch minus that of the episode over the same
//! `horizon` is the true change; the first critic's Q with that robot's action moved by the
//! same amount minus its Q with the action as played, on the same transition as the replay
//! would sample it (no relabelling, one-step), is the critic's.
//!
//! With exploration noise (`noise_std`) each robot's draw is a function of the seed, episode,
//! tick and robot, so the episode and its branches stay comparable; a move may be held for
//! several ticks (`hold`), the critic's change staying that of the first. Where the true
//! change of one point is dominated by chaos (docs/RESULTS.md, "What the critic knows of an
//! action"), only means over many points can grade a critic.

use std::collections::{BTreeMap, BTreeSet};

use anyhow::{Context, Result, ensure};
use formation_core::config::{EnvConfig, LearnConfig};
use formation_core::formation::Episodes;
use formation_core::mission::NO_SLOT;
use formation_core::observation::Layout;
use formation_core::reality::{Command, RealityConfig};
use formation_core::stepper::EpisodeStepper;
use formation_model::actor::FrozenActor;
use formation_protocol::ACTION_DIM;
use formation_replay::buffer::{Episode, Formation, Tick};
use formation_replay::record;
use formation_replay::sample::{Batch, Sampler};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde::Serialize;

use crate::learner::Learner;
use crate::selection::Game;

/// What the probe plays and how it perturbs.
#[derive(Debug, Clone)]
pub struct ProbeOptions {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Episodes of `seed`, from the first.
    pub episodes: usize,
    /// The episodes' seed (as a lockstep eval's `--seed`).
    pub seed: u64,
    /// A probe every this many ticks, from this tick on.
    pub every: u32,
    /// The move of one normalised action component (actions lie in [-1, 1]).
    pub delta: f32,
    /// Ticks the move is held, from the branch point (1: that tick alone; the critic's change
    /// is always that of the first tick's action).
    pub hold: u32,
    /// Ticks over which a branch's and the episode's discounted returns are summed (fewer at
    /// the episode's end).
    pub horizon: u32,
    /// Std of Gaussian noise on every robot's normalised action at every tick (0: the actor
    /// alone), as an exploring robot's; the same draws in the episode and its branches.
    pub noise_std: f64,
}

/// The action components a probe moves, as the actor's output orders them.
pub const COMPONENTS: [&str; ACTION_DIM] = ["speed", "turn"];

/// One perturbation of one robot's action at one tick.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ProbeRow {
    /// Episode (from 0).
    pub episode: usize,
    /// The tick whose action is moved.
    pub tick: u32,
    /// The robot whose action is moved.
    pub robot: usize,
    /// `speed` or `turn`.
    pub component: &'static str,
    /// The move of the normalised component, after clamping to [-1, 1].
    pub change: f32,
    /// The first critic's Q (the mean over an ensemble's) with the moved action minus with the
    /// action as played, in reward units (divided by `learn.reward_scale`).
    pub critic_change: f64,
    /// The branch's discounted return minus the episode's, over the same ticks.
    pub true_change: f64,
    /// The change of the moved tick's own reward alone (the part of `true_change` that the
    /// move decides without the world's later course).
    pub reward_change: f64,
    /// The first critic's Q of the transition as played, in reward units.
    pub critic_value: f64,
    /// The episode's discounted return from the tick over the horizon.
    pub true_value: f64,
}

/// A tick where the episode branches: a copy of the game before its step, and whom it moves.
struct BranchPoint {
    game: Game,
    tick: u32,
    robot: usize,
}

/// Plays `options.episodes` episodes with `actors` (one shared, or one per robot) in the ideal
/// world and probes the first critic of `critics` (their mean, for several: an ensemble of
/// trained critics) at every branch point (module docs).
pub fn probe(
    env: &EnvConfig,
    learn: &LearnConfig,
    critics: &[Learner],
    actors: &mut [FrozenActor],
    options: &ProbeOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<ProbeRow>> {
    ensure!(!critics.is_empty(), "a probe needs a critic");
    ensure!(options.every > 0, "probe every 0 ticks");
    ensure!(options.horizon > 0, "a probe horizon of 0 ticks");
    ensure!(
        (1..=options.horizon).contains(&options.hold),
        "a move held for {} ticks (1 to the horizon, {})",
        options.hold,
        options.horizon
    );
    ensure!(
        options.noise_std >= 0.0 && options.noise_std.is_finite(),
        "a probe's noise std {} is not a finite number >= 0",
        options.noise_std
    );
    ensure!(
        options.delta > 0.0 && options.delta <= 2.0,
        "a probe's move {} outside (0, 2]",
        options.delta
    );
    let n = options.n_agents;
    let layout = Layout::of(env.observation);
    let ideal = RealityConfig::default();
    let sampler = Sampler {
        history: env.history,
        her_probability: 0.0,
        n_step: 1,
        gamma: learn.gamma,
        env: env.clone(),
        critic: learn.critic,
        critic_map_points: learn.critic_map_points,
    };
    let mut rng = StdRng::seed_from_u64(options.seed ^ 0x9e0b_e000);
    let mut rows = Vec::new();
    for (episode, init) in Episodes::new(n, env, options.seed).take(options.episodes).enumerate() {
        let stepper = EpisodeStepper::new(env, &ideal, options.seed, episode as u32, init);
        let game = Game::new(stepper, env.history, layout.dim());
        let (recorder, points, game) = play_branching(game, actors, env, options, episode, &mut rng)?;
        let recorded = recorder.finish(&game);
        let values = critic_values(&sampler, critics, learn, &recorded, &points, env, &mut rng)?;
        for (point, value) in points.into_iter().zip(values) {
            let true_value = discounted(&recorder.rewards, point.tick, options.horizon, learn.gamma);
            for (component, &name) in COMPONENTS.iter().enumerate() {
                for sign in [1.0f32, -1.0] {
                    let (branch, first_reward, change) = branch_return(
                        point.game.clone(),
                        actors,
                        env,
                        Move {
                            robot: point.robot,
                            component,
                            delta: sign * options.delta,
                            hold: options.hold,
                        },
                        |tick, robot| exploration(options, episode, tick, robot),
                        (options.horizon, learn.gamma),
                    )?;
                    if change.abs() < 1e-6 {
                        continue; // at a limit already: no move to measure
                    }
                    let critic_change = value.moved(critics, point.robot, component, change, learn)?;
                    rows.push(ProbeRow {
                        episode,
                        tick: point.tick,
                        robot: point.robot,
                        component: name,
                        change,
                        critic_change,
                        true_change: branch - true_value,
                        reward_change: first_reward - recorder.rewards[point.tick as usize],
                        critic_value: value.played,
                        true_value,
                    });
                }
            }
        }
        progress(episode + 1, options.episodes);
    }
    Ok(rows)
}

/// Plays episode `episode` from `game` to its end with the actors (and the options' noise),
/// recording it; every `options.every` ticks it keeps a copy of the game before the tick's step
/// and picks one robot in the formation (not recovering) to move there. Returns the record,
/// the branch points and the finished game.
fn play_branching(
    mut game: Game,
    actors: &mut [FrozenActor],
    env: &EnvConfig,
    options: &ProbeOptions,
    episode: usize,
    rng: &mut StdRng,
) -> Result<(Recorder, Vec<BranchPoint>, Game)> {
    let n = game.world().n_agents();
    let mut recorder = Recorder::new(episode as u32, &game);
    let mut points = Vec::new();
    while game.running() {
        let tick = game.world().steps;
        if tick >= options.every && tick.is_multiple_of(options.every) {
            let members: Vec<usize> = (0..n)
                .filter(|&r| game.world().slot_of[r] != NO_SLOT && !game.recovering(r))
                .collect();
            if !members.is_empty() {
                let robot = members[rng.random_range(0..members.len())];
                points.push(BranchPoint {
                    game: game.clone(),
                    tick,
                    robot,
                });
            }
        }
        game.step(|asked| {
            let draw = exploration(options, episode, asked.step, asked.agent);
            act(
                &mut actors[asked.agent % actors.len()],
                asked.window.as_flat(),
                env,
                draw,
            )
        })?;
        recorder.record(&game);
    }
    Ok((recorder, points, game))
}

/// The discounted sum of `rewards[from..from + horizon]` (`rewards[t]` is the reward of the
/// transition t -> t + 1), summed in the order a branch sums its rewards.
fn discounted(rewards: &[f64], from: u32, horizon: u32, gamma: f64) -> f64 {
    let from = from as usize;
    let to = (from + horizon as usize).min(rewards.len());
    let (mut total, mut discount) = (0.0, 1.0);
    for reward in &rewards[from.min(to)..to] {
        total += discount * reward;
        discount *= gamma;
    }
    total
}

/// Robot `robot`'s exploration draw at `tick` of `episode` (zero without noise): a function of
/// the seed, episode, tick and robot alone, so the episode and each of its branches draw the
/// same noise (common random numbers) and differ by the move alone.
fn exploration(options: &ProbeOptions, episode: usize, tick: u32, robot: usize) -> [f32; ACTION_DIM] {
    if options.noise_std == 0.0 {
        return [0.0; ACTION_DIM];
    }
    let key = [options.seed, episode as u64, u64::from(tick), robot as u64]
        .iter()
        .fold(0x6a09_e667_f3bc_c908u64, |key, &part| {
            (key ^ part).wrapping_mul(0x9e37_79b9_7f4a_7c15).rotate_left(29)
        });
    let mut rng = StdRng::seed_from_u64(key);
    let normal = Normal::new(0.0, options.noise_std).expect("validated: finite, >= 0");
    [normal.sample(&mut rng) as f32, normal.sample(&mut rng) as f32]
}

/// The actor's command on `window` with `offset` added to its normalised action (clamped).
fn act(actor: &mut FrozenActor, window: &[f32], env: &EnvConfig, offset: [f32; ACTION_DIM]) -> Result<Command> {
    let (v, w) = actor.command(window, env)?;
    if offset == [0.0; ACTION_DIM] {
        return Ok((v, w));
    }
    let action = env.action_from_command(v, w);
    Ok(env.command_from_action([
        (action[0] + offset[0]).clamp(-1.0, 1.0),
        (action[1] + offset[1]).clamp(-1.0, 1.0),
    ]))
}

/// One robot's action component moved from a branch point on.
#[derive(Debug, Clone, Copy)]
struct Move {
    robot: usize,
    component: usize,
    delta: f32,
    /// Ticks it is held.
    hold: u32,
}

/// Plays a branch from its copy of the game: the move's robot's normalised action component
/// moved by its delta for its first `hold` ticks (after the exploration draw), the actor with
/// each robot's `draw(tick, robot)` everywhere, for at most `horizon` ticks. Returns the
/// branch's discounted return (by `gamma`), the reward of its first tick and the first tick's
/// move after clamping.
fn branch_return(
    mut game: Game,
    actors: &mut [FrozenActor],
    env: &EnvConfig,
    moved: Move,
    draw: impl Fn(u32, usize) -> [f32; ACTION_DIM],
    (horizon, gamma): (u32, f64),
) -> Result<(f64, f64, f32)> {
    let start = game.world().steps;
    let (mut total, mut discount, mut change) = (0.0, 1.0, 0.0f32);
    let mut first_reward = 0.0;
    while game.running() && game.world().steps < start + horizon {
        let first = game.world().steps == start;
        let held = game.world().steps < start + moved.hold;
        game.step(|asked| {
            let command = act(
                &mut actors[asked.agent % actors.len()],
                asked.window.as_flat(),
                env,
                draw(asked.step, asked.agent),
            )?;
            if !(held && asked.agent == moved.robot) {
                return Ok(command);
            }
            let mut action = env.action_from_command(command.0, command.1);
            let before = action[moved.component];
            action[moved.component] = (before + moved.delta).clamp(-1.0, 1.0);
            if first {
                change = action[moved.component] - before;
            }
            Ok(env.command_from_action(action))
        })?;
        if first {
            first_reward = game.last_reward();
        }
        total += discount * game.last_reward();
        discount *= gamma;
    }
    Ok((total, first_reward, change))
}

/// The first critic's view of one branch point: the transition as the replay samples it.
struct CriticValue {
    batch: Batch,
    played: f64,
}

impl CriticValue {
    /// Q with `robot`'s action component `component` at t moved by `change`, minus Q as
    /// played, in reward units.
    fn moved(
        &self,
        critics: &[Learner],
        robot: usize,
        component: usize,
        change: f32,
        learn: &LearnConfig,
    ) -> Result<f64> {
        let mut batch = self.batch.clone();
        let (h, n) = (batch.history, batch.n_agents);
        let offset = ((h - 1) * n + robot) * ACTION_DIM + component;
        batch.actions[offset] = (batch.actions[offset] + change).clamp(-1.0, 1.0);
        Ok(mean_value(critics, &batch, learn)? - self.played)
    }
}

/// The mean over `critics` of their first critic's Q of a one-sample batch, in reward units.
fn mean_value(critics: &[Learner], batch: &Batch, learn: &LearnConfig) -> Result<f64> {
    let mut sum = 0.0;
    for critic in critics {
        sum += f64::from(critic.played_value(batch)?[0]);
    }
    Ok(sum / critics.len() as f64 / learn.reward_scale)
}

/// Each branch point's transition of `episode` as a one-sample batch, and its Q as played.
fn critic_values(
    sampler: &Sampler,
    critics: &[Learner],
    learn: &LearnConfig,
    episode: &Episode,
    points: &[BranchPoint],
    env: &EnvConfig,
    rng: &mut StdRng,
) -> Result<Vec<CriticValue>> {
    let n = episode.n_agents();
    let env = EnvConfig {
        max_steps: episode.time_limit,
        ..env.clone()
    };
    points
        .iter()
        .map(|point| {
            let mut batch = Batch::zeroed(
                1,
                n,
                sampler.history,
                sampler.observer().dim(),
                sampler.features(n).dim(),
            );
            sampler.fill(&mut batch, 0, episode, point.tick as usize, &env, rng);
            let played = mean_value(critics, &batch, learn)?;
            Ok(CriticValue { batch, played })
        })
        .collect()
}

/// An in-process episode as the critic's collector assembles it from the streams: each
/// tick's poses and observations as sent (f32), the commands in use (the replay's actions)
/// and the reward, a new formation from each tick whose formation differs.
struct Recorder {
    number: u32,
    ticks: Vec<Tick>,
    formations: Vec<Formation>,
    rewards: Vec<f64>,
}

impl Recorder {
    fn new(number: u32, game: &Game) -> Self {
        let mut recorder = Self {
            number,
            ticks: Vec::new(),
            formations: Vec::new(),
            rewards: Vec::new(),
        };
        recorder.snapshot(game);
        recorder
    }

    /// After a step: the tick it reached and its reward.
    fn record(&mut self, game: &Game) {
        self.rewards.push(game.last_reward());
        self.snapshot(game);
    }

    fn snapshot(&mut self, game: &Game) {
        let wire = |v: f64| f64::from(v as f32);
        let world = game.world();
        let tick = self.ticks.len();
        let formation = record::formation(world, tick);
        if self.formations.last().is_none_or(|last| !last.same_as(&formation)) {
            self.formations.push(formation);
        }
        let commands: Vec<Command> = match tick {
            0 => vec![(0.0, 0.0); world.n_agents()],
            _ => game.applied().iter().map(|&(v, w)| (wire(v), wire(w))).collect(),
        };
        self.ticks.push(Tick {
            poses: record::wire_poses(world),
            commands,
            observations: game.told().to_vec(),
            reward: self.rewards.last().map_or(0.0, |&r| r as f32),
        });
    }

    fn finish(&self, game: &Game) -> Episode {
        let world = game.world();
        Episode {
            number: self.number,
            goal: world.goal.map(|v| f64::from(v as f32)),
            formations: self.formations.clone(),
            ticks: self.ticks.clone(),
            terminal: game.outcome().is_terminal(),
            obstacles: world.obstacles.clone(),
            arena_m: world.arena_m,
            time_limit: world.env.max_steps,
        }
    }
}

/// What a set of probe rows says for one action component. A slope is a branch point's
/// central difference per unit of normalised action, (change up - change down) / (move up -
/// move down), where both moves were measured.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ComponentSummary {
    /// `speed` or `turn`.
    pub component: &'static str,
    /// Branch points with both moves measured.
    pub points: usize,
    /// Of those whose true slope is not zero: the fraction where the critic's has its sign.
    pub sign_agreement: Option<f64>,
    /// Pearson correlation of the critic's and the true slopes.
    pub correlation: Option<f64>,
    /// Of those whose own-tick reward slope is not zero: the fraction where the critic's slope
    /// has its sign.
    pub reward_sign_agreement: Option<f64>,
    /// Mean slope of the critic's Q.
    pub critic_slope: Option<f64>,
    /// Mean true slope of the discounted return.
    pub true_slope: Option<f64>,
    /// The standard error of `true_slope`.
    pub true_slope_error: Option<f64>,
    /// Mean slope of the moved tick's own reward.
    pub reward_slope: Option<f64>,
}

/// One branch point's slopes: the critic's, the true return's and the own-tick reward's.
#[derive(Debug, Clone, Copy)]
struct Slopes {
    critic: f64,
    truth: f64,
    reward: f64,
}

/// The summary of `rows` for each component.
pub fn summarise(rows: &[ProbeRow]) -> Vec<ComponentSummary> {
    COMPONENTS
        .iter()
        .map(|&component| {
            let of = rows.iter().filter(|r| r.component == component);
            let downs: BTreeMap<(usize, u32, usize), &ProbeRow> = of
                .clone()
                .filter(|d| d.change < 0.0)
                .map(|d| ((d.episode, d.tick, d.robot), d))
                .collect();
            let slopes: Vec<Slopes> = of
                .filter(|u| u.change > 0.0)
                .filter_map(|u| {
                    let d = downs.get(&(u.episode, u.tick, u.robot))?;
                    let span = f64::from(u.change - d.change);
                    Some(Slopes {
                        critic: (u.critic_change - d.critic_change) / span,
                        truth: (u.true_change - d.true_change) / span,
                        reward: (u.reward_change - d.reward_change) / span,
                    })
                })
                .collect();
            let agreement = |reference: fn(&Slopes) -> f64| {
                let signed: Vec<&Slopes> = slopes.iter().filter(|s| reference(s) != 0.0).collect();
                let agree = signed
                    .iter()
                    .filter(|s| s.critic.signum() == reference(s).signum())
                    .count();
                (!signed.is_empty()).then(|| agree as f64 / signed.len() as f64)
            };
            let count = slopes.len() as f64;
            let mean = |f: fn(&Slopes) -> f64| (!slopes.is_empty()).then(|| slopes.iter().map(f).sum::<f64>() / count);
            let true_slope = mean(|s| s.truth);
            let true_slope_error = true_slope.filter(|_| slopes.len() > 1).map(|m| {
                let variance = slopes.iter().map(|s| (s.truth - m).powi(2)).sum::<f64>() / (count - 1.0);
                (variance / count).sqrt()
            });
            let pairs: Vec<(f64, f64)> = slopes.iter().map(|s| (s.critic, s.truth)).collect();
            ComponentSummary {
                component,
                points: slopes.len(),
                sign_agreement: agreement(|s| s.truth),
                correlation: correlation(&pairs),
                reward_sign_agreement: agreement(|s| s.reward),
                critic_slope: mean(|s| s.critic),
                true_slope,
                true_slope_error,
                reward_slope: mean(|s| s.reward),
            }
        })
        .collect()
}

/// The Pearson correlation of the pairs (`None` for fewer than 2 or no spread).
pub fn correlation(pairs: &[(f64, f64)]) -> Option<f64> {
    let count = pairs.len() as f64;
    if pairs.len() < 2 {
        return None;
    }
    let (mx, my) = pairs
        .iter()
        .fold((0.0, 0.0), |(x, y), (a, b)| (x + a / count, y + b / count));
    let (sxy, sxx, syy) = pairs.iter().fold((0.0, 0.0, 0.0), |(xy, xx, yy), (a, b)| {
        (xy + (a - mx) * (b - my), xx + (a - mx).powi(2), yy + (b - my).powi(2))
    });
    (sxx > 0.0 && syy > 0.0).then(|| sxy / (sxx * syy).sqrt())
}

/// The correlation of the critic's values with the true returns over the rows' branch points
/// (each point once), and the two means.
pub fn value_calibration(rows: &[ProbeRow]) -> (Option<f64>, f64, f64) {
    let mut seen = BTreeSet::new();
    let pairs: Vec<(f64, f64)> = rows
        .iter()
        .filter(|row| seen.insert((row.episode, row.tick)))
        .map(|row| (row.critic_value, row.true_value))
        .collect();
    let count = pairs.len().max(1) as f64;
    let critic = pairs.iter().map(|p| p.0).sum::<f64>() / count;
    let truth = pairs.iter().map(|p| p.1).sum::<f64>() / count;
    (correlation(&pairs), critic, truth)
}

/// Loads the learner (critics included) of a training checkpoint for `n` robots.
pub fn learner_with_critic(path: &std::path::Path, n: usize, env: &EnvConfig, learn: &LearnConfig) -> Result<Learner> {
    let mut learner = Learner::new(n, env, learn, 0)?;
    ensure!(
        learner.holds_critic(path)?,
        "{} holds no critic of this config's shape (a training run's best.safetensors, checkpoint.safetensors and checkpoints/ hold one, trained with that run's [learn]; a distilled student holds none)",
        path.display()
    );
    learner
        .load(path)
        .with_context(|| format!("loading {}", path.display()))?;
    Ok(learner)
}

#[cfg(test)]
mod tests {
    use super::*;
    use formation_core::config::{ObservationModel, RunConfig};
    use formation_core::obstacles::ObstacleKind;

    /// A forest world of 3 robots, a fresh learner's actor and a branch point every 25 ticks.
    fn forest_probe(noise_std: f64) -> (RunConfig, Learner, Vec<FrozenActor>, ProbeOptions) {
        let mut config = RunConfig::default();
        config.env.observation = ObservationModel::SlotProximityScan;
        config.env.obstacles.kind = ObstacleKind::Forest;
        config.env.max_steps = 150;
        let learner = Learner::new(3, &config.env, &config.learn, 5).expect("a learner");
        let actor = FrozenActor::from_flat(&learner.actor_weights(0).expect("weights"), learner.actor_shape())
            .expect("an actor");
        let options = ProbeOptions {
            n_agents: 3,
            episodes: 1,
            seed: 11,
            every: 25,
            delta: 0.2,
            hold: 1,
            horizon: 60,
            noise_std,
        };
        (config, learner, vec![actor], options)
    }

    #[test]
    fn a_branch_without_a_move_replays_the_episode_exactly_with_and_without_noise() {
        for noise_std in [0.0, 0.2] {
            let (config, _, mut actors, options) = forest_probe(noise_std);
            let env = &config.env;
            let init = Episodes::new(3, env, options.seed).next().expect("an episode");
            let stepper = EpisodeStepper::new(env, &RealityConfig::default(), options.seed, 0, init);
            let game = Game::new(stepper, env.history, Layout::of(env.observation).dim());
            let mut rng = StdRng::seed_from_u64(1);
            let (recorder, points, _) =
                play_branching(game, &mut actors, env, &options, 0, &mut rng).expect("an episode");
            assert!(!points.is_empty(), "noise {noise_std}: no branch point");
            for point in points {
                let (branch, first, change) = branch_return(
                    point.game,
                    &mut actors,
                    env,
                    Move {
                        robot: point.robot,
                        component: 0,
                        delta: 0.0,
                        hold: 5,
                    },
                    |tick, robot| exploration(&options, 0, tick, robot),
                    (options.horizon, 0.99),
                )
                .expect("a branch");
                assert_eq!(change, 0.0);
                assert_eq!(first, recorder.rewards[point.tick as usize], "noise {noise_std}");
                assert_eq!(
                    branch,
                    discounted(&recorder.rewards, point.tick, options.horizon, 0.99),
                    "noise {noise_std}, tick {}",
                    point.tick
                );
            }
        }
    }

    #[test]
    fn a_probe_moves_both_components_both_ways_and_the_critic_sees_the_move() {
        let (config, learner, mut actors, options) = forest_probe(0.0);
        let rows = probe(
            &config.env,
            &config.learn,
            std::slice::from_ref(&learner),
            &mut actors,
            &options,
            |_, _| {},
        )
        .expect("a probe");
        assert!(!rows.is_empty());
        for name in COMPONENTS {
            assert!(rows.iter().any(|r| r.component == name && r.change > 0.0), "{name} up");
            assert!(
                rows.iter().any(|r| r.component == name && r.change < 0.0),
                "{name} down"
            );
        }
        for row in &rows {
            assert!(row.change.abs() <= options.delta + 1e-6, "{row:?}");
            // A fresh critic is not flat: a move changes its Q.
            assert_ne!(row.critic_change, 0.0, "{row:?}");
        }
        assert_eq!(summarise(&rows).len(), COMPONENTS.len());
    }

    fn row(component: &'static str, tick: u32, change: f32, critic: f64, truth: f64) -> ProbeRow {
        let reward = f64::from(change) * 0.1;
        ProbeRow {
            episode: 0,
            tick,
            robot: 1,
            component,
            change,
            critic_change: critic,
            true_change: truth,
            reward_change: reward,
            critic_value: 1.0,
            true_value: 2.0,
        }
    }

    #[test]
    fn discounting_stops_at_the_horizon_and_the_episode_end() {
        let rewards = [1.0, 1.0, 1.0, 1.0];
        assert!((discounted(&rewards, 0, 2, 0.5) - 1.5).abs() < 1e-12);
        assert!((discounted(&rewards, 2, 10, 0.5) - 1.5).abs() < 1e-12);
        assert_eq!(discounted(&rewards, 4, 10, 0.5), 0.0);
    }

    #[test]
    fn the_summary_pairs_each_points_two_moves_and_scores_their_signs() {
        let rows = [
            // Tick 10: the critic and the truth both say faster is better.
            row("speed", 10, 0.2, 0.5, 1.0),
            row("speed", 10, -0.2, -0.5, -1.0),
            // Tick 20: the critic says slower, the truth faster.
            row("speed", 20, 0.2, -0.3, 0.4),
            row("speed", 20, -0.2, 0.3, -0.4),
            // A move at a limit: no pair.
            row("speed", 30, 0.2, 0.1, 0.1),
        ];
        let summary = summarise(&rows);
        let speed = &summary[0];
        assert_eq!(speed.points, 2);
        assert_eq!(speed.sign_agreement, Some(0.5));
        // Slopes: critic 2.5 and -1.5, truth 5 and 2, the own tick's reward 0.1 at both (to the
        // f32 of the moves).
        assert!((speed.critic_slope.expect("pairs") - 0.5).abs() < 1e-6);
        assert!((speed.true_slope.expect("pairs") - 3.5).abs() < 1e-6);
        assert!((speed.true_slope_error.expect("two pairs") - 1.5).abs() < 1e-6);
        assert!((speed.reward_slope.expect("pairs") - 0.1).abs() < 1e-6);
        assert_eq!(speed.reward_sign_agreement, Some(0.5));
        assert_eq!(summary[1].points, 0);
        assert_eq!(summary[1].sign_agreement, None);
    }

    #[test]
    fn correlation_of_a_line_is_one_and_of_its_mirror_minus_one() {
        let line: Vec<(f64, f64)> = (0..5).map(|i| (f64::from(i), 2.0 * f64::from(i) + 1.0)).collect();
        assert!((correlation(&line).expect("a line") - 1.0).abs() < 1e-12);
        let mirror: Vec<(f64, f64)> = line.iter().map(|&(x, y)| (x, -y)).collect();
        assert!((correlation(&mirror).expect("a line") + 1.0).abs() < 1e-12);
        assert_eq!(correlation(&line[..1]), None);
    }
}
