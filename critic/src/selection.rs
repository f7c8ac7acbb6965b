//! Model selection: a checkpoint's score is measured on a fixed set of episodes, played
//! in-process with exactly the weights that are saved, under the run's `[reality]` (the
//! training reality distribution; the ideal world when it is off). Under a reality the ideal
//! world is played too and reported beside the score.
//!
//! The episodes are the first `learn.selection_episodes` of `learn.selection_seed` for each
//! swarm size the critic trains on: the ones a sim started with that `--seed` plays, from the
//! same [`Episodes`]. Each robot keeps its window as an agent does ([`ObservationHistory`]) and
//! acts through the agents' own [`FrozenActor`]; actions become commands as in an agent (scaled
//! to the limits, sent as f32), and each tick follows the sim's own rules, the core's
//! [`EpisodeStepper`]: what a robot is told through its [`Reality`], lost observations and
//! commands, the motors, the [`Mission`]'s shape changes at their ticks, its time limit, success
//! only once the last change has come, and a robot whose controller fails leaving the formation.
//! So the score is what a lockstep swarm run with that seed measures, episode for episode
//! ([`episode_records`] gives the very `episodes.csv` rows).
//!
//! Not a batched candle forward pass over every window of a tick: that measured two to three
//! times cheaper, but its sums round differently (up to 1e-5 per action), and that alone
//! changed the outcome of 6 of 200 episodes of the 3-robot paper model.

use anyhow::{Context, Result, ensure};
use formation_core::baseline::{BaselineGains, ScriptedBaseline};
use formation_core::config::{EnvConfig, LearnConfig};
use formation_core::formation::Episodes;
use formation_core::mission::{Attendance, Heard, NO_SLOT};
use formation_core::observation::Layout;
use formation_core::physics::Pose;
use formation_core::planner::Replanner;
use formation_core::reality::{Command, Reality, RealityConfig};
use formation_core::solo_planner::SoloPlanner;
use formation_core::stepper::{EpisodeRecord, EpisodeStepper, TransportCounts};
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

/// One episode played in-process by the rules a lockstep sim plays it with (the core's
/// [`EpisodeStepper`]): each robot's window and the commands in use, answered by in-process
/// controllers. Model selection, distillation (`crate::distill`) and the critic probe
/// (`crate::probe`, which branches copies of it) play these.
#[derive(Debug, Clone)]
pub(crate) struct Game {
    stepper: EpisodeStepper,
    /// No robot is ever silent here; the attendance still runs the rules of a team change.
    attendance: Attendance,
    windows: Vec<ObservationHistory>,
    /// Whether each robot has been told anything yet this episode (its window starts then).
    heard: Vec<bool>,
    in_use: Vec<Command>,
}

impl Game {
    pub(crate) fn new(stepper: EpisodeStepper, history: usize, dim: usize) -> Self {
        let n = stepper.world().n_agents();
        let mut game = Self {
            stepper,
            attendance: Attendance::new(n),
            windows: (0..n).map(|_| ObservationHistory::new(history, dim)).collect(),
            heard: vec![false; n],
            in_use: vec![(0.0, 0.0); n],
        };
        game.stepper.start_team(&mut game.attendance);
        game.listen();
        game
    }

    /// The episode's reality (what a privileged teacher may read).
    pub(crate) fn reality(&self) -> &Reality {
        self.stepper.reality()
    }

    /// The episode's true world (what a privileged planner reads).
    pub(crate) fn world(&self) -> &World {
        self.stepper.world()
    }

    /// Whether the episode goes on.
    pub(crate) fn running(&self) -> bool {
        self.stepper.running()
    }

    /// Robot `agent`'s recovery behaviour's command in the last transition, when it took the
    /// robot's motors over (`[obstacles] recovery_ticks`).
    pub(crate) fn recovery_command(&self, agent: usize) -> Option<Command> {
        self.stepper.recovering(agent).then(|| self.stepper.applied()[agent])
    }

    /// How it stands (ended: how it ended).
    pub(crate) fn outcome(&self) -> Outcome {
        self.stepper.last().outcome
    }

    /// The reward of the last transition (0 before the first).
    pub(crate) fn last_reward(&self) -> f64 {
        self.stepper.last().reward
    }

    /// Each robot's command in use for the last transition, clamped (the replay's action).
    pub(crate) fn applied(&self) -> &[Command] {
        self.stepper.applied()
    }

    /// What each robot was told at this tick.
    pub(crate) fn told(&self) -> &[[f32; formation_protocol::MAX_OBS_DIM]] {
        self.stepper.told()
    }

    /// Whether robot `agent`'s recovery behaviour drives it this tick.
    pub(crate) fn recovering(&self, agent: usize) -> bool {
        self.stepper.recovering(agent)
    }

    /// The stepper tells the robots this tick; each robot that heard it keeps it in its
    /// window, which starts padded with the first observation of the episode, as an agent's.
    fn listen(&mut self) {
        self.stepper.tell();
        for (agent, window) in self.windows.iter_mut().enumerate() {
            if self.stepper.lost()[agent] {
                continue;
            }
            let told = &self.stepper.told()[agent];
            if self.heard[agent] {
                window.push(told);
            } else {
                window.reset(told);
                self.heard[agent] = true;
            }
        }
    }

    /// One tick: each robot that was told answers through `answer` with its (v, w) command,
    /// rounded to the f32 of the wire as the sim receives it (a lost answer leaves the command
    /// in use); then the stepper steps, calls the roll and tells the next tick.
    pub(crate) fn step(&mut self, mut answer: impl FnMut(Asked) -> Result<Command>) -> Result<()> {
        let step = self.stepper.world().steps;
        for (agent, window) in self.windows.iter().enumerate() {
            if self.stepper.lost()[agent] {
                continue;
            }
            let (v, w) = answer(Asked {
                agent,
                step,
                present: self.stepper.world().slot_of[agent] != NO_SLOT,
                window,
            })?;
            if self.stepper.command_arrives(agent) {
                self.in_use[agent] = (f64::from(v as f32), f64::from(w as f32));
            }
        }
        self.stepper.step(&self.in_use, |_| true);
        if self.stepper.running() {
            let _always_answered = self.stepper.call_the_roll(&mut self.attendance, |_| Heard::Answered);
            self.listen();
        }
        Ok(())
    }

    /// The episode's `episodes.csv` row, as the sim writes it (no transport: nothing missed or
    /// late, no wall time).
    pub(crate) fn record(&self, episode: u32) -> EpisodeRecord {
        self.stepper.record(episode, TransportCounts::default())
    }
}

/// A planner that knows the map, on the truth as the sim's truth stream carries it.
pub(crate) enum TruthPlanner {
    /// The team's planner: planned at the episode's first tick and again when the formation
    /// changes, as each oracle agent plans.
    Team(Box<Replanner>),
    /// Each robot's own planner ([`SoloPlanner`]).
    Solo(SoloPlanner),
}

impl TruthPlanner {
    /// A fresh planner of this kind for an episode in the arena of `env`.
    pub(crate) fn new(kind: PlannerKind, env: &EnvConfig) -> Self {
        match kind {
            PlannerKind::Team => Self::Team(Box::default()),
            PlannerKind::Solo => Self::Solo(SoloPlanner::default()),
            PlannerKind::SoloLocal => Self::Solo(SoloPlanner::seeing(env.scan_range_m)),
        }
    }

    /// Every robot's command at the world's tick.
    pub(crate) fn commands(&mut self, world: &World, env: &EnvConfig, gains: BaselineGains) -> Vec<Command> {
        let wire = |v: f64| f64::from(v as f32);
        let poses: Vec<Pose> = world
            .poses
            .iter()
            .map(|p| Pose::from([p.x as f32, p.y as f32, p.theta as f32]))
            .collect();
        let slots: Vec<[f64; 2]> = world.slots.iter().map(|s| s.map(wire)).collect();
        let (goal, obstacles, tick) = (world.goal.map(wire), &world.obstacles, world.steps);
        match self {
            Self::Team(replanner) => replanner
                .commands(&poses, goal, &slots, obstacles, tick, env, gains)
                .to_vec(),
            Self::Solo(solo) => solo.commands(&poses, goal, &slots, obstacles, tick, env, gains),
        }
    }
}

/// Which planner that knows the map.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlannerKind {
    /// The team's ([`formation_core::planner`]): a formation or a file along one path.
    Team,
    /// Each robot's own ([`formation_core::solo_planner`]).
    Solo,
    /// Each robot's own over only the obstacles within its range sensor's reach
    /// (`env.scan_range_m`) of where it plans from.
    SoloLocal,
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
            .zip(0u32..)
            .map(|(init, episode)| {
                let stepper = EpisodeStepper::new(env, self.reality, self.seed, episode, init);
                Game::new(stepper, env.history, layout.dim())
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
    for game in &mut games {
        while game.running() {
            game.step(|asked| {
                let actor = &mut actors[asked.agent % actors.len()];
                let imposed = turn.and_then(|turn| turn.command(env, asked.agent, asked.step));
                match imposed {
                    Some(command) => Ok(command),
                    None => actor.command(asked.window.as_flat(), env),
                }
            })?;
        }
    }
    let count = games.len().max(1) as f64;
    let records: Vec<EpisodeRecord> = games.iter().map(|g| g.record(0)).collect();
    let successes = records.iter().filter(|r| r.outcome == Outcome::Success).count();
    Ok(SizeScore {
        n_agents: n,
        success: successes as f64 / count,
        formation_held: records.iter().map(|r| r.formation_hold_rate).sum::<f64>() / count,
        mean_steps: records.iter().map(|r| f64::from(r.steps)).sum::<f64>() / count,
    })
}

/// Who drives every robot of an in-process play.
pub enum Team<'a> {
    /// The scripted baseline with these gains, on the window (as a scripted agent: gap search
    /// reads an older observation, everything else the newest).
    Scripted(&'a BaselineGains),
    /// Actors (one shared, or one per robot) of `shape`, on the window they read.
    Actors(&'a mut [FrozenActor], &'a ActorShape),
    /// A planner that knows the map, tracking with these gains, on the true state as the sim's
    /// truth stream carries it (f32), as `formation-agent --policy oracle` reads it (the team's
    /// planner is the oracle).
    Planner(PlannerKind, &'a BaselineGains),
}

/// The `episodes.csv` rows of `episodes` of `n` robots driven by `team`, played in-process by
/// the sim's rules: the rows a lockstep eval with the same seed, config and team writes, but
/// for wall time and the transport's counts (nothing is missed or late in-process).
pub fn episode_records(env: &EnvConfig, n: usize, episodes: &Played, team: Team) -> Result<Vec<EpisodeRecord>> {
    episode_records_watched(env, n, episodes, team, |_, _| {})
}

/// [`episode_records`], calling `watch(episode, world)` at every tick of every episode (its
/// first included): what draws an episode's trajectories.
pub fn episode_records_watched(
    env: &EnvConfig,
    n: usize,
    episodes: &Played,
    team: Team,
    mut watch: impl FnMut(usize, &World),
) -> Result<Vec<EpisodeRecord>> {
    let env = &EnvConfig {
        history: match &team {
            Team::Scripted(_) | Team::Planner(..) => env.history,
            Team::Actors(_, shape) => shape.history,
        },
        ..env.clone()
    };
    if let Team::Actors(actors, shape) = &team {
        ensure!(
            actors.len() == 1 || actors.len() == n,
            "{} independent actors cannot drive {n} robots",
            actors.len()
        );
        ensure!(
            shape.obs_dim == Layout::of(env.observation).dim(),
            "an actor of shape {shape:?} reads another observation model"
        );
    }
    let baseline = match &team {
        Team::Scripted(gains) => Some(ScriptedBaseline::new(env, **gains)),
        _ => None,
    };
    let mut team = team;
    let mut games = episodes.games(env, n);
    for (episode, game) in games.iter_mut().enumerate() {
        let mut planner = match &team {
            Team::Planner(kind, _) => Some(TruthPlanner::new(*kind, env)),
            _ => None,
        };
        watch(episode, game.world());
        while game.running() {
            match &mut team {
                Team::Scripted(_) => {
                    let baseline = baseline.as_ref().expect("made for the scripted team");
                    game.step(|asked| Ok(baseline.command_in(asked.window.as_flat())))?;
                }
                Team::Actors(actors, _) => {
                    game.step(|asked| actors[asked.agent % actors.len()].command(asked.window.as_flat(), env))?;
                }
                Team::Planner(_, gains) => {
                    let planner = planner.as_mut().expect("made for the planner team");
                    let commands = planner.commands(game.world(), env, **gains);
                    game.step(|asked| Ok(commands[asked.agent]))?;
                }
            }
            watch(episode, game.world());
        }
    }
    Ok(games
        .iter()
        .zip(0u32..)
        .map(|(game, episode)| game.record(episode))
        .collect())
}
