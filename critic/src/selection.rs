//! Model selection: a checkpoint's score is measured on a fixed set of episodes, played
//! in-process with exactly the weights that are saved, under the run's `[reality]` (the
//! training reality distribution; the ideal world when it is off). Under a reality the ideal
//! world is played too and reported beside the score.
//!
//! The episodes are the first `learn.selection_episodes` of `learn.selection_seed` for each
//! swarm size the critic trains on: the ones a sim started with that `--seed` plays, from the
//! same [`Episodes`]. Each robot keeps its window as an agent does ([`ObservationHistory`]) and
//! acts through the agents' own [`FrozenActor`]; actions become commands as in an agent (scaled
//! to the limits, sent as f32) and the world steps as in the sim, through the sim's
//! [`Reality`] as a lockstep sim applies it (what a robot is told, lost observations and
//! commands, the motors), and with the sim's [`Mission`]: the episode's shape changes at their
//! ticks, its time limit ([`EnvConfig::episode_steps`], the world's), success only once the last
//! change has come ([`Mission::judge`]), and a robot whose controller fails leaving the
//! formation (the others re-form without it; it is commanded to stand still). So the score is what a lockstep swarm run with
//! that seed measures, episode for episode.
//!
//! Not a batched candle forward pass over every window of a tick: that measured two to three
//! times cheaper, but its sums round differently (up to 1e-5 per action), and that alone
//! changed the outcome of 6 of 200 episodes of the 3-robot paper model.

use anyhow::{Context, Result, ensure};
use formation_core::config::{EnvConfig, LearnConfig};
use formation_core::formation::Episodes;
use formation_core::mission::{Mission, NO_SLOT, team_seed};
use formation_core::observation::Layout;
use formation_core::reality::{Command, Reality, RealityConfig};
use formation_core::task::Outcome;
use formation_core::world::World;
use formation_model::actor::{ActorShape, FrozenActor};
use formation_model::checkpoint::{SelectionScore, SizeScore};
use formation_model::history::ObservationHistory;

/// The fixed episodes a run's checkpoints are scored on.
#[derive(Debug, Clone)]
pub struct Selector {
    env: EnvConfig,
    reality: RealityConfig,
    seed: u64,
    episodes: usize,
    sizes: Vec<usize>,
}

impl Selector {
    /// The run's selection episodes (`learn.selection_*`) for each of the swarm sizes `sizes`,
    /// played under `reality`.
    pub fn new(env: &EnvConfig, learn: &LearnConfig, reality: &RealityConfig, sizes: &[usize]) -> Self {
        Self {
            env: env.clone(),
            reality: reality.clone(),
            seed: learn.selection_seed,
            episodes: learn.selection_episodes,
            sizes: sizes.to_vec(),
        }
    }

    /// Whether `score` was measured on these episodes (seed, count, swarm sizes and reality).
    pub fn measured(&self, score: &SelectionScore) -> bool {
        let sizes: Vec<usize> = score.sizes.iter().map(|s| s.n_agents).collect();
        score.seed == self.seed
            && score.episodes == self.episodes
            && sizes == self.sizes
            && score.reality == self.reality_name()
    }

    /// The reality the score is played under as the checkpoint records it (`None`: ideal).
    fn reality_name(&self) -> Option<String> {
        (!self.reality.is_ideal()).then(|| self.reality.one_line())
    }

    /// Scores actors given as flat weights (one shared, or one per robot) on every size.
    pub fn score(&self, actors: &[Vec<f32>], shape: &ActorShape) -> Result<SelectionScore> {
        let mut actors = actors
            .iter()
            .map(|flat| FrozenActor::from_flat(flat, shape))
            .collect::<Result<Vec<_>>>()
            .context("selection: actor weights")?;
        let mut play_all = |reality: &RealityConfig| {
            self.sizes
                .iter()
                .map(|&n| {
                    let episodes = Played {
                        seed: self.seed,
                        count: self.episodes,
                        reality,
                    };
                    play(&self.env, n, &episodes, &mut actors, shape, None)
                })
                .collect::<Result<Vec<_>>>()
        };
        let sizes = play_all(&self.reality)?;
        let ideal = match self.reality.is_ideal() {
            true => None,
            false => Some(play_all(&RealityConfig::default())?),
        };
        Ok(SelectionScore {
            seed: self.seed,
            episodes: self.episodes,
            sizes,
            reality: self.reality_name(),
            ideal,
        })
    }
}

/// A neighbour's sudden turn, to measure robustness: robot `robot` ignores its actor for
/// `ticks` ticks from step `at_step` and drives at full speed on a full-rate turn instead
/// (v and w at their limits), as a robot that swerves would.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SuddenTurn {
    /// The robot that turns.
    pub robot: usize,
    /// The step (0 = the episode's first) it starts turning.
    pub at_step: u32,
    /// How many ticks it turns.
    pub ticks: u32,
}

impl SuddenTurn {
    /// The command it imposes on `agent` at step `step`, if any.
    fn command(&self, env: &EnvConfig, agent: usize, step: u32) -> Option<(f64, f64)> {
        (agent == self.robot && (self.at_step..self.at_step.saturating_add(self.ticks)).contains(&step))
            .then_some((env.v_max, env.w_max))
    }
}

/// What a robot that was told this tick is asked to answer: the controller sees its window.
pub(crate) struct Asked<'a> {
    /// The robot.
    pub agent: usize,
    /// The episode's step (0 = its first).
    pub step: u32,
    /// Whether the robot is in the formation (a robot out of it is commanded to stand still
    /// whatever it answers).
    pub present: bool,
    /// Its observation window.
    pub window: &'a ObservationHistory,
}

/// One episode played in-process as a lockstep sim plays it: its world, mission and reality,
/// each robot's window, the commands in use and what it has added up. Model selection and
/// distillation (`crate::distill`) play these.
pub(crate) struct Game {
    world: World,
    mission: Mission,
    reality: Reality,
    layout: Layout,
    windows: Vec<ObservationHistory>,
    /// Whether each robot has been told anything yet this episode (its window starts then).
    heard: Vec<bool>,
    /// Whether each robot was told this tick (a robot whose observation was lost is not asked).
    asked: Vec<bool>,
    in_use: Vec<Command>,
    pub(crate) outcome: Outcome,
    formation_ticks: u32,
}

impl Game {
    /// The episode's reality (what a privileged teacher may read).
    pub(crate) fn reality(&self) -> &Reality {
        &self.reality
    }

    fn new(world: World, mission: Mission, reality: Reality, history: usize, layout: Layout) -> Self {
        let n = world.n_agents();
        let mut game = Self {
            world,
            mission,
            reality,
            layout,
            windows: (0..n).map(|_| ObservationHistory::new(history, layout.dim())).collect(),
            heard: vec![false; n],
            asked: vec![false; n],
            in_use: vec![(0.0, 0.0); n],
            outcome: Outcome::Running,
            formation_ticks: 0,
        };
        game.tell();
        game
    }

    /// What each robot is told of the world this tick, as the sim tells it: through the
    /// sensor noise, unless the message is lost. A robot's window starts padded with the first
    /// observation it is told in the episode, as an agent's does.
    fn tell(&mut self) {
        for (agent, window) in self.windows.iter_mut().enumerate() {
            let mut told = self.world.observation(agent);
            self.reality.tell(agent, self.layout, &mut told);
            self.asked[agent] = !self.reality.observation_lost(agent);
            if !self.asked[agent] {
                continue;
            }
            if self.heard[agent] {
                window.push(&told);
            } else {
                window.reset(&told);
                self.heard[agent] = true;
            }
        }
    }

    /// One tick: each robot that was told answers through `answer` with its (v, w) command,
    /// rounded to the f32 of the wire as the sim receives it (a lost answer leaves the command
    /// in use); the motors act through the reality and the
    /// world clamps and integrates as in the sim; the mission judges the step, changes the
    /// formation on schedule and takes a robot whose controller failed at this tick out of the
    /// formation, as in the sim.
    pub(crate) fn step(
        &mut self,
        mut answer: impl FnMut(Asked) -> Result<Command>,
        acting: &mut Vec<(f64, f64)>,
    ) -> Result<()> {
        acting.clear();
        let step = self.world.steps;
        for (agent, window) in self.windows.iter().enumerate() {
            let present = self.world.slot_of[agent] != NO_SLOT;
            if self.asked[agent] {
                let (v, w) = answer(Asked {
                    agent,
                    step,
                    present,
                    window,
                })?;
                if !self.reality.command_lost(agent) {
                    self.in_use[agent] = (f64::from(v as f32), f64::from(w as f32));
                }
            }
            // A robot out of the formation is commanded to stand still, as the sim commands it.
            let command = if present { self.in_use[agent] } else { (0.0, 0.0) };
            acting.push(self.reality.actuate(agent, step, command, true));
        }
        let result = self
            .mission
            .judge(self.world.step(acting), self.world.steps, &self.world.env);
        self.outcome = result.outcome;
        self.formation_ticks += u32::from(result.conditions.in_formation);
        // A change due at this tick reaches the observations told next.
        self.mission.after_step(
            &mut self.world,
            result.conditions.in_formation,
            self.outcome == Outcome::Running,
        );
        if self.outcome == Outcome::Running {
            // So does the team's change: a controller that failed at this tick leaves (not when
            // fewer than three robots would stay, as in the sim).
            if let Some(failure) = self.reality.failure().filter(|f| f.tick == step) {
                let _refused_below_three = self.mission.leave(&mut self.world, failure.agent);
            }
            self.tell();
        }
        Ok(())
    }
}

/// The episodes [`play`] plays: the first `count` that `seed` starts, under `reality`.
#[derive(Debug, Clone, Copy)]
pub struct Played<'a> {
    /// The sim's `--seed`.
    pub seed: u64,
    /// How many, from the run's first.
    pub count: usize,
    /// The `[reality]` they are played under (the default: the ideal world).
    pub reality: &'a RealityConfig,
}

impl Played<'_> {
    /// A game for each of these episodes of `n` robots: the episodes, shape changes, team
    /// changes and reality a lockstep sim started with this seed plays.
    pub(crate) fn games(&self, env: &EnvConfig, n: usize) -> Vec<Game> {
        let layout = Layout::of(env.observation);
        Episodes::new(n, env, self.seed)
            .take(self.count)
            .enumerate()
            .map(|(episode, mut init)| {
                let reality = Reality::new(self.reality, env, self.seed, episode as u64, n);
                let changes = std::mem::take(&mut init.changes);
                let team_seed = team_seed(self.seed, episode as u32);
                let mission = Mission::new(changes, &init.slots, init.spec, team_seed);
                Game::new(World::new(env, init), mission, reality, env.history, layout)
            })
            .collect()
    }
}

/// Plays `episodes` of `n` robots with `actors` (one shared, or one per robot) and, if given, a
/// robot's sudden turn in each; scores them.
pub fn play(
    env: &EnvConfig,
    n: usize,
    episodes: &Played,
    actors: &mut [FrozenActor],
    shape: &ActorShape,
    turn: Option<SuddenTurn>,
) -> Result<SizeScore> {
    let layout = Layout::of(env.observation);
    let dim = layout.dim();
    ensure!(
        shape.obs_dim == dim,
        "selection: an actor of shape {shape:?} cannot read observations of {dim} floats"
    );
    // The robots keep the window the actor reads, as an agent evaluating a checkpoint does.
    let env = &EnvConfig {
        history: shape.history,
        ..env.clone()
    };
    ensure!(
        actors.len() == 1 || actors.len() == n,
        "selection: {} independent actors cannot drive {n} robots",
        actors.len()
    );
    ensure!(
        turn.is_none_or(|turn| turn.robot < n),
        "a sudden turn of robot {} in a swarm of {n}",
        turn.map_or(0, |turn| turn.robot)
    );
    let mut games = episodes.games(env, n);
    let mut acting = Vec::with_capacity(n);
    for game in &mut games {
        while game.outcome == Outcome::Running {
            game.step(
                |asked| {
                    let actor = &mut actors[asked.agent % actors.len()];
                    let imposed = turn.and_then(|turn| turn.command(env, asked.agent, asked.step));
                    match imposed {
                        Some(command) => Ok(command),
                        None => actor.command(asked.window.as_flat(), env),
                    }
                },
                &mut acting,
            )?;
        }
    }
    let count = games.len().max(1) as f64;
    let successes = games.iter().filter(|g| g.outcome == Outcome::Success).count();
    Ok(SizeScore {
        n_agents: n,
        success: successes as f64 / count,
        formation_held: games
            .iter()
            .map(|g| f64::from(g.formation_ticks) / f64::from(g.world.steps.max(1)))
            .sum::<f64>()
            / count,
        mean_steps: games.iter().map(|g| f64::from(g.world.steps)).sum::<f64>() / count,
    })
}
