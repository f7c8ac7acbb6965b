//! Model selection: a checkpoint's score is measured on a fixed set of noise-free episodes,
//! played in-process with exactly the weights that are saved.
//!
//! The episodes are the first `learn.selection_episodes` of `learn.selection_seed` for each
//! swarm size the critic trains on: the ones a sim started with that `--seed` plays, from the
//! same [`Episodes`]. Each robot keeps its window as an agent does ([`ObservationHistory`]) and
//! acts through the agents' own [`FrozenActor`]; actions become commands as in an agent (scaled
//! to the limits, sent as f32) and the world steps as in the sim. So the score is what a swarm
//! run with that seed measures, episode for episode.
//!
//! Not a batched candle forward pass over every window of a tick: that measured two to three
//! times cheaper, but its sums round differently (up to 1e-5 per action), and that alone
//! changed the outcome of 6 of 200 episodes of the 3-robot paper model.

use anyhow::{Context, Result, ensure};
use formation_core::config::{EnvConfig, LearnConfig};
use formation_core::formation::Episodes;
use formation_core::observation::Layout;
use formation_core::task::Outcome;
use formation_core::world::World;
use formation_model::actor::{ActorShape, FrozenActor};
use formation_model::checkpoint::{SelectionScore, SizeScore};
use formation_model::history::ObservationHistory;

/// The fixed episodes a run's checkpoints are scored on.
#[derive(Debug, Clone)]
pub struct Selector {
    env: EnvConfig,
    seed: u64,
    episodes: usize,
    sizes: Vec<usize>,
}

impl Selector {
    /// The run's selection episodes (`learn.selection_*`) for each of the swarm sizes `sizes`.
    pub fn new(env: &EnvConfig, learn: &LearnConfig, sizes: &[usize]) -> Self {
        Self {
            env: env.clone(),
            seed: learn.selection_seed,
            episodes: learn.selection_episodes,
            sizes: sizes.to_vec(),
        }
    }

    /// Whether `score` was measured on these episodes (seed, count and swarm sizes).
    pub fn measured(&self, score: &SelectionScore) -> bool {
        let sizes: Vec<usize> = score.sizes.iter().map(|s| s.n_agents).collect();
        score.seed == self.seed && score.episodes == self.episodes && sizes == self.sizes
    }

    /// Scores actors given as flat weights (one shared, or one per robot) on every size.
    pub fn score(&self, actors: &[Vec<f32>], shape: &ActorShape) -> Result<SelectionScore> {
        let mut actors = actors
            .iter()
            .map(|flat| FrozenActor::from_flat(flat, shape))
            .collect::<Result<Vec<_>>>()
            .context("selection: actor weights")?;
        let sizes = self
            .sizes
            .iter()
            .map(|&n| play(&self.env, n, self.seed, self.episodes, &mut actors, shape, None))
            .collect::<Result<_>>()?;
        Ok(SelectionScore {
            seed: self.seed,
            episodes: self.episodes,
            sizes,
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

/// One selection episode: its world, each robot's window and what it has added up.
struct Game {
    world: World,
    windows: Vec<ObservationHistory>,
    outcome: Outcome,
    formation_ticks: u32,
}

impl Game {
    /// Every robot's window starts padded with its first observation, as an agent's does.
    fn new(world: World, history: usize, dim: usize) -> Self {
        let windows = (0..world.n_agents())
            .map(|agent| {
                let mut window = ObservationHistory::new(history, dim);
                window.reset(&world.observation(agent));
                window
            })
            .collect();
        Self {
            world,
            windows,
            outcome: Outcome::Running,
            formation_ticks: 0,
        }
    }

    /// One tick: each robot's action from its window (its own actor, or the shared one) scaled
    /// to (v, w) as an agent does and rounded to the f32 of the wire, but for a robot in a
    /// sudden turn; the world clamps and integrates as in the sim.
    fn step(
        &mut self,
        actors: &mut [FrozenActor],
        turn: Option<SuddenTurn>,
        commands: &mut Vec<(f64, f64)>,
    ) -> Result<()> {
        commands.clear();
        let step = self.world.steps;
        for (agent, window) in self.windows.iter().enumerate() {
            let actor = &mut actors[agent % actors.len()];
            let (v, w) = self.world.env.command_from_action(actor.act(window.as_flat())?);
            let imposed = turn.and_then(|turn| turn.command(&self.world.env, agent, step));
            commands.push(imposed.unwrap_or((f64::from(v as f32), f64::from(w as f32))));
        }
        let result = self.world.step(commands);
        self.outcome = result.outcome;
        self.formation_ticks += u32::from(result.conditions.in_formation);
        if self.outcome == Outcome::Running {
            for (agent, window) in self.windows.iter_mut().enumerate() {
                window.push(&self.world.observation(agent));
            }
        }
        Ok(())
    }
}

/// Plays the first `episodes` episodes of `n` robots that `seed` starts, noise-free, with
/// `actors` (one shared, or one per robot) and, if given, a robot's sudden turn in each; scores
/// them.
pub fn play(
    env: &EnvConfig,
    n: usize,
    seed: u64,
    episodes: usize,
    actors: &mut [FrozenActor],
    shape: &ActorShape,
    turn: Option<SuddenTurn>,
) -> Result<SizeScore> {
    let dim = Layout::of(env.observation).dim();
    ensure!(
        shape.obs_dim == dim && shape.history == env.history,
        "selection: an actor of shape {shape:?} cannot read windows of {} observations of {dim} floats",
        env.history
    );
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
    let mut games: Vec<Game> = Episodes::new(n, env, seed)
        .take(episodes)
        .map(|init| Game::new(World::new(env, init), env.history, dim))
        .collect();
    let mut commands = Vec::with_capacity(n);
    for game in &mut games {
        while game.outcome == Outcome::Running {
            game.step(actors, turn, &mut commands)?;
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
