//! The rules of one tick, written once: what each robot is told, which commands act, how the
//! motors turn them into motion, the step, the judgement, and the mission's changes after it.
//!
//! An [`EpisodeStepper`] owns one episode's [`World`], [`Mission`] and [`Reality`] and applies
//! them in this order, every tick:
//!
//! 1. [`EpisodeStepper::tell`]: each robot's observation of the world, through its sensor noise
//!    ([`Reality::tell`]), and whether the message is lost ([`Reality::observation_lost`]; never
//!    on the episode's last tick, which asks for no command);
//! 2. the driver collects the answers: the sim over its transport (on time, late, missed), an
//!    in-process player from its controllers; each command read passes the radio
//!    ([`EpisodeStepper::command_arrives`]);
//! 3. [`EpisodeStepper::step`] with the commands in use: a robot out of the formation is
//!    commanded to stand still, each robot's recovery behaviour may take over its command
//!    ([`crate::recovery`], off by default), its collision monitor caps its forward speed, the
//!    motors act through [`Reality::actuate`], the world integrates,
//!    the [`Mission`] judges the step (its time limit, success only after the last change) and
//!    changes the formation on schedule;
//! 4. [`EpisodeStepper::call_the_roll`]: a controller that failed at this tick leaves the
//!    formation, and the [`Attendance`] sends a robot silent for 10 ticks out and brings one back.
//!
//! The sim's lockstep and real-time loops (`formation-sim`) drive it around iceoryx2; model
//! selection and distillation (`formation-critic`) drive it with in-process controllers. So a
//! new effect of the world (an obstacle, a sensor, a collision kind) lands here once.

use formation_protocol::MAX_OBS_DIM;
use serde::Serialize;

use crate::config::EnvConfig;
use crate::formation::EpisodeInit;
use crate::mission::{Attendance, Away, Call, Heard, Mission, NO_SLOT, team_seed};
use crate::observation::{Layout, ObservationView};
use crate::obstacles::robot_radius_m;
use crate::range_sensor::braking_speed;
use crate::reality::{Command, Reality, RealityConfig};
use crate::recovery::{Recovery, Sensed};
use crate::task::{Conditions, Outcome, StepResult};
use crate::world::World;

/// How far beyond its radius either side of a robot's line a hit counts as in its way for the
/// collision monitor, metres: the surface between two sparse rays (a forest disc of 0.15 m read
/// by the ray beside its nearest point), and narrow enough that a robot inside the passage's
/// narrowest gap (0.35 m) is not stopped by the gap's sides.
const MONITOR_SLACK_M: f64 = 0.05;

/// One episode, stepped by the rules of a tick.
#[derive(Debug, Clone)]
pub struct EpisodeStepper {
    world: World,
    mission: Mission,
    reality: Reality,
    layout: Layout,
    /// What each robot is told this tick.
    told: Vec<[f32; MAX_OBS_DIM]>,
    /// Robots whose observation of this tick is lost.
    lost: Vec<bool>,
    /// Each robot's command in use for the last transition, clamped (the replay's action).
    applied: Vec<Command>,
    /// The velocities acting on the physics in the last transition.
    acting: Vec<Command>,
    /// The last step's result (running, zero reward before the first).
    last: StepResult,
    episode_return: f64,
    formation_ticks: u32,
    lost_observations: u64,
    lost_commands: u64,
    /// Each robot's recovery memory (`[obstacles] recovery_ticks`).
    recoveries: Vec<Recovery>,
}

/// What a driver's transport adds to an episode's record: counts the stepper cannot see.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TransportCounts {
    /// Robot-ticks missed (nothing new arrived: the command in use stayed).
    pub missed_ticks: u64,
    /// Robot-ticks that took up a late answer to an earlier tick.
    pub late_commands: u64,
    /// Wall-clock seconds since the run started, at the episode's end.
    pub wall_s: f64,
}

/// A change of the team that [`EpisodeStepper::call_the_roll`] made.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TeamChange {
    /// The robot.
    pub robot: usize,
    /// Why: `Leave` (failed or silent) or `Return`.
    pub call: Call,
    /// Why it is away (`None` once back).
    pub away: Option<Away>,
}

impl EpisodeStepper {
    /// Episode `episode` of a run seeded `seed`: its world at `init`, its mission (the shape
    /// changes `init` carries, team draws seeded by [`team_seed`]) and its reality drawn from
    /// `reality` (validated). The robots' first observations are not told yet.
    pub fn new(env: &EnvConfig, reality: &RealityConfig, seed: u64, episode: u32, mut init: EpisodeInit) -> Self {
        let n = init.poses.len();
        let changes = std::mem::take(&mut init.changes);
        let mission = Mission::new(changes, &init.slots, init.spec, team_seed(seed, episode));
        let world = World::new(env, init);
        let reality = Reality::new(reality, env, seed, u64::from(episode), n);
        let last = StepResult {
            reward: 0.0,
            outcome: Outcome::Running,
            conditions: world.conditions(),
        };
        Self {
            layout: Layout::of(env.observation),
            told: vec![[0.0; MAX_OBS_DIM]; n],
            lost: vec![false; n],
            applied: vec![(0.0, 0.0); n],
            acting: vec![(0.0, 0.0); n],
            last,
            episode_return: 0.0,
            formation_ticks: 0,
            lost_observations: 0,
            lost_commands: 0,
            recoveries: vec![Recovery::default(); n],
            world,
            mission,
            reality,
        }
    }

    /// At the episode's start: robots the `attendance` keeps away (silent in an earlier
    /// episode) stay out, the others take the same formation for them; when fewer than three
    /// would stay, everyone is in again.
    pub fn start_team(&mut self, attendance: &mut Attendance) {
        attendance.new_episode();
        let n = self.world.n_agents();
        let present: Vec<bool> = (0..n).map(|r| attendance.away(r).is_none()).collect();
        if present.iter().filter(|&&p| p).count() < formation_protocol::MIN_AGENTS {
            (0..n).for_each(|r| attendance.set_away(r, None));
            return;
        }
        self.mission.start_with(&mut self.world, &present);
        self.last.conditions = self.world.conditions();
    }

    /// Tells every robot the world of this tick (rule 1). While the episode runs, each
    /// message may be lost; on its last tick none is.
    pub fn tell(&mut self) {
        self.tell_asking(self.running());
    }

    /// Tells every robot the world as the last tick of an episode cut short (by a signal):
    /// nothing is lost, no command is asked.
    pub fn tell_last(&mut self) {
        self.tell_asking(false);
    }

    fn tell_asking(&mut self, asks: bool) {
        for (agent, (told, lost)) in self.told.iter_mut().zip(&mut self.lost).enumerate() {
            *told = self.world.observation(agent);
            self.reality.tell(agent, self.layout, told);
            *lost = asks && self.reality.observation_lost(agent);
            self.lost_observations += u64::from(*lost);
        }
    }

    /// Whether a command robot `agent` sent arrives (rule 2: one draw of the radio per
    /// message read).
    pub fn command_arrives(&mut self, agent: usize) -> bool {
        let lost = self.reality.command_lost(agent);
        self.lost_commands += u64::from(lost);
        !lost
    }

    /// Steps the world with each robot's command in use (rule 3); `present(i)` is false for a
    /// robot whose controller the driver finds gone (it acts as `dead_robot` says). Returns
    /// the step's judgement.
    pub fn step(&mut self, in_use: &[Command], present: impl Fn(usize) -> bool) -> StepResult {
        debug_assert_eq!(in_use.len(), self.world.n_agents());
        let tick = self.world.steps;
        for (agent, &command) in in_use.iter().enumerate() {
            // A robot out of the formation is commanded to stand still (a dead or silent one
            // does what `dead_robot` says).
            let command = if self.world.slot_of[agent] == NO_SLOT {
                (0.0, 0.0)
            } else {
                command
            };
            // While a robot recovers, its recovery's command is the one in use (and the replay's
            // action: what the motors were asked for).
            let command = self.recovered(agent, command);
            self.applied[agent] = self.world.env.clamp_command(command.0, command.1);
            let speed_cap = self.monitored_speed(agent);
            self.acting[agent] = self
                .reality
                .actuate_within(agent, tick, command, present(agent), speed_cap);
        }
        let result = self
            .mission
            .judge(self.world.step(&self.acting), self.world.steps, &self.world.env);
        self.last = result;
        self.episode_return += result.reward;
        self.formation_ticks += u32::from(result.conditions.in_formation);
        // A shape change due at this tick reaches its observations, told next.
        self.mission.after_step(
            &mut self.world,
            result.conditions.in_formation,
            result.outcome == Outcome::Running,
        );
        result
    }

    /// The command robot `agent`'s motors take after its recovery behaviour (`[obstacles]
    /// recovery_ticks`, [`crate::recovery`]), from what it was told this tick: `command`
    /// unless it recovers; always `command` when recovery is off or the robot observes no scan
    /// or slot.
    fn recovered(&mut self, agent: usize, command: Command) -> Command {
        let env = &self.world.env;
        let ticks = env.obstacles.recovery_ticks;
        if ticks == 0 {
            return command;
        }
        let driven = self.acting[agent].0.abs() * env.dt_s;
        match Sensed::told(self.layout, &self.told[agent], env, driven) {
            Some(sensed) => self.recoveries[agent].command(&sensed, ticks, command),
            None => command,
        }
    }

    /// The forward speed robot `agent`'s collision monitor allows this tick (`[obstacles]
    /// collision_monitor_m`): a brake over the monitor's range on its told scan
    /// ([`braking_speed`]); unbounded when the monitor is off or the robot observes no scan.
    fn monitored_speed(&self, agent: usize) -> f64 {
        let env = &self.world.env;
        let range = env.obstacles.collision_monitor_m;
        if range <= 0.0 {
            return f64::INFINITY;
        }
        ObservationView::new(self.layout, &self.told[agent])
            .scan()
            .map_or(f64::INFINITY, |scan| {
                braking_speed(
                    scan,
                    env.scan_range_m,
                    robot_radius_m(env),
                    MONITOR_SLACK_M,
                    range,
                    env.v_max,
                )
            })
    }

    /// After the step of a running episode (rule 4): a controller that failed at this tick
    /// leaves the formation; each robot's `heard` goes to the `attendance`, which sends a robot
    /// silent for 10 ticks out and brings one away for silence back after 5 answers. A
    /// departure that would leave fewer than 3 robots in is not made (it is asked again next
    /// tick). Returns the changes made.
    pub fn call_the_roll(&mut self, attendance: &mut Attendance, heard: impl Fn(usize) -> Heard) -> Vec<TeamChange> {
        let mut changes = Vec::new();
        if !self.running() {
            return changes;
        }
        let tick = self.world.steps - 1;
        if let Some(failure) = self.reality.failure().filter(|f| f.tick == tick)
            && attendance.away(failure.agent).is_none()
            && self.mission.leave(&mut self.world, failure.agent).is_ok()
        {
            attendance.set_away(failure.agent, Some(Away::Failed));
            changes.push(TeamChange {
                robot: failure.agent,
                call: Call::Leave,
                away: Some(Away::Failed),
            });
        }
        for agent in 0..self.world.n_agents() {
            let change = match attendance.record(agent, heard(agent)) {
                Some(Call::Leave) if self.mission.leave(&mut self.world, agent).is_ok() => Some(Away::Silent),
                Some(Call::Return) if self.mission.rejoin(&mut self.world, agent).is_ok() => None,
                _ => continue,
            };
            attendance.set_away(agent, change);
            changes.push(TeamChange {
                robot: agent,
                call: if change.is_some() { Call::Leave } else { Call::Return },
                away: change,
            });
        }
        changes
    }

    /// Whether the episode goes on.
    pub fn running(&self) -> bool {
        self.last.outcome == Outcome::Running
    }

    /// The last step's judgement (reward, outcome, C1-C3); before the first step: running, no
    /// reward, the start's conditions.
    pub fn last(&self) -> &StepResult {
        &self.last
    }

    /// What each robot was told this tick.
    pub fn told(&self) -> &[[f32; MAX_OBS_DIM]] {
        &self.told
    }

    /// Which robots' observations of this tick were lost.
    pub fn lost(&self) -> &[bool] {
        &self.lost
    }

    /// Each robot's command in use for the last transition, clamped.
    pub fn applied(&self) -> &[Command] {
        &self.applied
    }

    /// The velocities that acted on the physics in the last transition.
    pub fn acting(&self) -> &[Command] {
        &self.acting
    }

    /// Whether robot `agent`'s command in the last transition was its recovery behaviour's
    /// (`[obstacles] recovery_ticks`), not its controller's.
    pub fn recovering(&self, agent: usize) -> bool {
        self.recoveries[agent].took_over()
    }

    /// The true state.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// The mission planner.
    pub fn mission(&self) -> &Mission {
        &self.mission
    }

    /// The episode's reality.
    pub fn reality(&self) -> &Reality {
        &self.reality
    }

    /// The world and the mission, for the live changes a user asks for between ticks (a new
    /// goal, a new formation, a robot removed or restored).
    pub fn live(&mut self) -> (&mut World, &mut Mission) {
        (&mut self.world, &mut self.mission)
    }

    /// The episode's `episodes.csv` row (`episode` is its number; the transport's counts
    /// from the driver).
    pub fn record(&self, episode: u32, transport: TransportCounts) -> EpisodeRecord {
        let mission = &self.mission;
        let reform_ticks = mission.reform_ticks();
        let reform_ticks_sum: u64 = reform_ticks.iter().map(|&t| u64::from(t)).sum();
        let steps = self.world.steps;
        let last: &Conditions = &self.last.conditions;
        EpisodeRecord {
            episode,
            outcome: self.last.outcome,
            steps,
            episode_return: self.episode_return,
            final_edge_error_m: last.mean_edge_error,
            final_goal_distance_m: last.goal_distance,
            formation_hold_rate: f64::from(self.formation_ticks) / f64::from(steps.max(1)),
            missed_ticks: transport.missed_ticks,
            late_commands: transport.late_commands,
            lost_commands: self.lost_commands,
            lost_observations: self.lost_observations,
            reconfigurations: mission.reconfigurations(),
            reforms: reform_ticks.len() as u32,
            mean_reform_ticks: (!reform_ticks.is_empty()).then(|| reform_ticks_sum as f64 / reform_ticks.len() as f64),
            reform_ticks_sum,
            departures: mission.departures(),
            returns: mission.returns(),
            wall_s: transport.wall_s,
            obstacle_collisions: u32::from(last.obstacle_collision),
        }
    }
}

/// One row of `episodes.csv`.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct EpisodeRecord {
    /// Episode counter.
    pub episode: u32,
    /// How it ended: `success`, `collision`, `timeout` or `aborted` in the file.
    #[serde(serialize_with = "outcome_name")]
    pub outcome: Outcome,
    /// Steps taken.
    pub steps: u32,
    /// Undiscounted sum of rewards.
    pub episode_return: f64,
    /// Mean edge error at the last tick, metres.
    pub final_edge_error_m: f64,
    /// Centroid-to-goal distance at the last tick, metres.
    pub final_goal_distance_m: f64,
    /// Fraction of ticks on which C1 held.
    pub formation_hold_rate: f64,
    /// Robot-ticks missed (nothing new arrived: the command in use stayed).
    pub missed_ticks: u64,
    /// Robot-ticks that took up a late answer to an earlier tick.
    pub late_commands: u64,
    /// Commands lost on the way (`[reality]`'s `command_loss`).
    pub lost_commands: u64,
    /// Observations not delivered (`[reality]`'s `observation_loss`).
    pub lost_observations: u64,
    /// The mission planner's slot reassignments in the episode: shape changes, goal moves and
    /// team changes.
    pub reconfigurations: u32,
    /// Changes after which the swarm re-formed (every observed edge within eps_form for 5
    /// consecutive ticks, or held to a success).
    pub reforms: u32,
    /// Mean ticks from a change to re-forming, over the changes that re-formed (empty if none).
    pub mean_reform_ticks: Option<f64>,
    /// Sum of those ticks (not written: the run's mean weighs every change alike).
    #[serde(skip)]
    pub reform_ticks_sum: u64,
    /// Robots that left the formation in the episode.
    pub departures: u32,
    /// Robots that came back into the formation in the episode.
    pub returns: u32,
    /// Wall-clock seconds since the run started, at the episode's end.
    pub wall_s: f64,
    /// 1 when the episode ended because a robot touched an obstacle (its outcome is then
    /// `collision`), else 0.
    pub obstacle_collisions: u32,
}

/// Writes an outcome by its name.
fn outcome_name<S: serde::Serializer>(outcome: &Outcome, serializer: S) -> Result<S::Ok, S::Error> {
    serializer.serialize_str(outcome.as_str())
}
