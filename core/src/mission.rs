//! The mission planner: an episode's shape changes, the robots' slots, and when the swarm has
//! re-formed.
//!
//! The sim's tick loop owns one [`Mission`] per episode and calls [`Mission::after_step`]
//! after every step. At a change's tick the planner assigns the robots to the new shape's
//! slots optimally ([`assign`]: Kuhn-Munkres, minimising the sum of squared distances from
//! each robot's position to its new target, goal + slot offset), and rewrites the world's
//! slot map, each robot's observed robots (the robots in the next two slots, mod N), desired
//! edges and slot offsets; the observations of that tick carry them. The robots' history
//! windows are not reset: a change is part of the episode, as a turn of the goal would be.
//!
//! A change is not a step: the formation *morphs* ([`Morph`]), whatever made it (the schedule,
//! the control service's new shape or goal, a robot leaving or coming back). At the change each
//! present robot r is assigned its slot as above, and its target offset from the goal moves in
//! a straight line, all robots in step, from where it stands in the swarm (its position
//! relative to the present robots' centroid) to its new slot's offset, over as many ticks as
//! the largest of those moves takes at `env.morph_speed` (0.35) of `v_max` (one tick, the step
//! change, when no robot must move relative to the others). Each tick the world's slot offsets
//! are the interpolated ones and the desired edges the distances between them, so the first
//! tick asks for the swarm's present geometry, no edge jumps, and each robot is led along its
//! straight line to its slot. Because the assignment minimises the sum of squared distances, no
//! two of those lines are traversed against each other: for robots i and j with relative
//! starts a and targets b, optimality gives (a_i - a_j)·(b_i - b_j) >= 0, so the interpolated
//! targets never come closer than min(|a_i - a_j|, |b_i - b_j|) / √2 (the argument of Turpin et
//! al.'s CAPT). A step change instead sent every robot at once at top speed towards slots
//! across the swarm, pulled by new neighbours metres away, and every collision under two
//! changes per episode happened so. While the formation morphs, a success does not end the
//! episode and ticks in formation do not count towards re-forming. A change during a morph
//! starts a new one from where the robots then stand.
//!
//! Success means holding the *last* formation at the goal: while a change is still to come,
//! C3 does not end the episode ([`Mission::judge`]: the transition scores as C1 alone would,
//! `r_edge`), and the swarm waits at the goal for its next formation.
//!
//! "Re-formed": every observed edge within C1's tolerance (`env.eps_form_m`) for
//! [`REFORM_HOLD_TICKS`] consecutive ticks; the ticks to re-form are counted from the change to
//! the first of them. An episode that ends in success before the run is complete (it holds the
//! formation at the goal) counts as re-formed at the first tick of its last run.
//!
//! The team changes too: a robot leaves the formation ([`Mission::leave`]) when its controller
//! fails, when the control service removes it, or after [`LEAVE_AFTER_SILENT_TICKS`] silent
//! ticks in a row ([`Attendance`]), and comes back ([`Mission::rejoin`]) after
//! [`RETURN_AFTER_ANSWERS`] answers in a row or when restored. At each the present robots are
//! assigned again, by the same Kuhn-Munkres assignment, to *the same formation for the robots
//! present* ([`Mission::formation_for`]): the formation in force at capacity (the launch N)
//! when every robot is in; otherwise its kind (ring, line, wedge, grid, random) drawn again for
//! M robots from the episode's own stream, with its orientation and scale. For `random` that is
//! a new random polygon of M: a polygon minus a vertex is generally not one (the edge across
//! the gap is the old second-neighbour edge and the new second-neighbour edge spans three old
//! steps, often past `edge_max`), and a redraw is valid by construction, the same for whichever
//! robot left. Where a robot out of the formation stands within `edge_min` of a slot, the
//! formation is turned about the goal until none does ([`clear_of_robots_out`]): a stopped
//! robot is an obstacle. A robot out holds no slot ([`NO_SLOT`]) and observes only itself;
//! neighbours are the robots in the next two slots modulo the robots present. A team change
//! counts as a reconfiguration, its re-forming is measured as a shape change's, and it extends
//! the episode's time limit as a shape change does.

use formation_protocol::{MIN_AGENTS, NEIGHBOURS};
use pathfinding::kuhn_munkres::kuhn_munkres_min;
use pathfinding::matrix::Matrix;

use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::config::{EnvConfig, FormationShape};
use crate::formation::{FormationSpec, ShapeChange};
use crate::shapes::{draw_shape, shape_is_valid};
use crate::task::{Outcome, StepResult, present_centroid};
use crate::world::World;

/// Consecutive ticks in formation that make a change re-formed.
pub const REFORM_HOLD_TICKS: u32 = 5;
/// The slot of a robot out of the formation.
pub const NO_SLOT: usize = usize::MAX;
/// Silent ticks in a row (no answer, losses of `[reality]` aside) after which a robot leaves
/// the formation: a lossy or slow robot that misses a few does not.
pub const LEAVE_AFTER_SILENT_TICKS: u32 = 10;
/// Answers in a row after which a robot that left for silence comes back.
pub const RETURN_AFTER_ANSWERS: u32 = 5;
/// Mixed into the run's seed for the formations redrawn at team changes.
const TEAM_STREAM: u64 = 0x7465_616D_5F63_6867;
/// Turns tried, either way, to keep a formation's slots clear of the robots out of it.
const CLEARANCE_STEP_RAD: f64 = std::f64::consts::PI / 18.0;
/// Draws of the same formation for M robots before its scale is given up.
const REDRAW_ATTEMPTS: usize = 16;
/// Integer costs for Kuhn-Munkres: squared distances in mm² (1 m² = 10^6). The largest arena
/// (64 robots) is under 40 m across, so a cost is under 2e9 and a sum of 64 under 2^63.
const COST_PER_M2: f64 = 1e6;

/// The slot each robot takes: the assignment of robots at `positions` to the slots whose targets
/// are `targets` (same length) minimising the sum of squared distances, squared metres rounded
/// to mm² ([`COST_PER_M2`]); ties go to Kuhn-Munkres' first optimum.
pub fn assign(positions: &[[f64; 2]], targets: &[[f64; 2]]) -> Vec<usize> {
    debug_assert_eq!(positions.len(), targets.len());
    if positions.is_empty() {
        return Vec::new();
    }
    let costs = Matrix::from_fn(positions.len(), targets.len(), |(robot, slot)| {
        let (dx, dy) = (
            positions[robot][0] - targets[slot][0],
            positions[robot][1] - targets[slot][1],
        );
        ((dx * dx + dy * dy) * COST_PER_M2).round() as i64
    });
    kuhn_munkres_min(&costs).1
}

/// Each robot's observed robots under `slot_of` (robot r holds slot `slot_of[r]`; a slot of N
/// or more, such as [`NO_SLOT`], is a robot out of the formation): the robots in slots s+1 and
/// s+2 mod M, M the robots present, who hold slots 0..M; a robot out observes itself.
pub fn observed_robots(slot_of: &[usize]) -> Vec<[usize; NEIGHBOURS]> {
    let n = slot_of.len();
    let m = slot_of.iter().filter(|&&s| s < n).count().max(1);
    let mut robot_in = vec![0; n];
    for (robot, &slot) in slot_of.iter().enumerate() {
        if slot < n {
            robot_in[slot] = robot;
        }
    }
    slot_of
        .iter()
        .enumerate()
        .map(|(robot, &s)| {
            if s < n {
                std::array::from_fn(|k| robot_in[(s + k + 1) % m])
            } else {
                [robot; NEIGHBOURS]
            }
        })
        .collect()
}

/// Gives `world` the formation `offsets` (slot s's offset from the goal, in tour order, one per
/// robot present) with robot r in slot `slot_of[r]` ([`NO_SLOT`] for a robot out): its slot
/// map, observed robots, desired edges and slot offsets (zero for a robot out).
pub fn set_formation(world: &mut World, offsets: &[[f64; 2]], slot_of: Vec<usize>) {
    let m = offsets.len();
    let distance = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    for (robot, &slot) in slot_of.iter().enumerate() {
        if slot < m {
            world.slots[robot] = offsets[slot];
            world.desired[robot] = std::array::from_fn(|k| distance(offsets[slot], offsets[(slot + k + 1) % m]));
        } else {
            world.slots[robot] = [0.0; 2];
            world.desired[robot] = [0.0; NEIGHBOURS];
        }
    }
    world.observed = observed_robots(&slot_of);
    world.slot_of = slot_of;
}

/// `shape`'s points turned and scaled as `spec` says.
fn placed(shape: &[[f64; 2]], spec: &FormationSpec) -> Vec<[f64; 2]> {
    let (s, c) = spec.orientation.sin_cos();
    shape
        .iter()
        .map(|p| [spec.scale * (c * p[0] - s * p[1]), spec.scale * (s * p[0] + c * p[1])])
        .collect()
}

/// A live formation's slot offsets: `kind` as [`draw_shape`] draws it for `world`'s robots from
/// a generator seeded with `seed`, times `scale`, turned by `orientation` radians. Refused, saying why, when `kind` is
/// `mixed`, `scale` is not a positive number, an observed edge leaves [edge_min, edge_max], two
/// robots would be closer than the start margin, or a slot around the goal leaves the arena.
pub fn live_formation(
    world: &World,
    kind: FormationShape,
    scale: f64,
    orientation: f64,
    seed: u64,
) -> Result<Vec<[f64; 2]>, String> {
    if kind == FormationShape::Mixed {
        return Err("mixed is not a shape (random, ring, line, wedge, grid)".into());
    }
    if !(scale.is_finite() && scale > 0.0) {
        return Err(format!("scale {scale} is not a positive number"));
    }
    if !orientation.is_finite() {
        return Err(format!("orientation {orientation} is not a number"));
    }
    let env = &world.env;
    let mut rng = StdRng::seed_from_u64(seed);
    let spec = FormationSpec {
        kind,
        orientation,
        scale,
    };
    let offsets = placed(&draw_shape(kind, world.n_agents(), env, &mut rng), &spec);
    if !shape_is_valid(&offsets, env) {
        return Err(format!(
            "scale {scale}: an edge leaves [{}, {}] m or two robots come too close",
            env.edge_min_m, env.edge_max_m
        ));
    }
    if !fits_arena(world, world.goal, &offsets) {
        return Err(format!("scale {scale}: the formation leaves the arena"));
    }
    Ok(offsets)
}

/// True when every slot `offsets` gives around `goal` lies in `world`'s arena.
pub fn fits_arena(world: &World, goal: [f64; 2], offsets: &[[f64; 2]]) -> bool {
    offsets.iter().all(|o| {
        [goal[0] + o[0], goal[1] + o[1]]
            .iter()
            .all(|v| (0.0..=world.arena_m).contains(v))
    })
}

/// The result of the `steps`-th step under the rule that success means holding the last
/// formation: while a change is still to come (`change_to_come`, the change of this very tick
/// included), a success (C3) is not the end of the episode; it scores `r_edge` (C1 holds) and
/// the episode goes on, or times out at the limit (`env.max_steps`, the episode's). The live
/// episode ([`Mission::judge`]) and HER's relabelled rewards both apply it.
pub fn success_after_last_change(
    mut result: StepResult,
    change_to_come: bool,
    steps: u32,
    env: &EnvConfig,
) -> StepResult {
    if result.outcome == Outcome::Success && change_to_come {
        // The progress term, if any, stays.
        result.reward = if env.r_progress == 0.0 {
            env.r_edge
        } else {
            env.r_edge + (result.reward - env.r_goal)
        };
        result.outcome = if steps >= env.max_steps {
            Outcome::Timeout
        } else {
            Outcome::Running
        };
    }
    result
}

/// Turns `offsets` about the goal, by the smallest multiple of [`CLEARANCE_STEP_RAD`] either
/// way, until no slot lies within `edge_min_m` of a robot out of the formation (one that
/// stopped is an obstacle: a robot sent to a slot beside it would be pushed off, or run into
/// it), the slots staying in the arena; when no turn clears every slot, the turn with the most
/// room. Unturned when nothing is in the way.
pub fn clear_of_robots_out(world: &World, present: &[bool], offsets: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    let out: Vec<[f64; 2]> = (0..world.n_agents())
        .filter(|&r| !present[r])
        .map(|r| [world.poses[r].x, world.poses[r].y])
        .collect();
    let room = |offsets: &[[f64; 2]]| {
        offsets
            .iter()
            .flat_map(|o| {
                out.iter()
                    .map(move |p| (world.goal[0] + o[0] - p[0]).hypot(world.goal[1] + o[1] - p[1]))
            })
            .fold(f64::INFINITY, f64::min)
    };
    let wanted = world.env.edge_min_m;
    if room(&offsets) >= wanted {
        return offsets;
    }
    let steps = (std::f64::consts::PI / CLEARANCE_STEP_RAD).round() as i32;
    let mut best = (room(&offsets), offsets.clone());
    for k in (1..=steps).flat_map(|k| [k, -k]) {
        let (s, c) = (f64::from(k) * CLEARANCE_STEP_RAD).sin_cos();
        let turned: Vec<[f64; 2]> = offsets
            .iter()
            .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1]])
            .collect();
        if !fits_arena(world, world.goal, &turned) {
            continue;
        }
        let r = room(&turned);
        if r >= wanted {
            return turned;
        }
        if r > best.0 {
            best = (r, turned);
        }
    }
    best.1
}

/// How a robot hears from the sim's command accounting at one tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Heard {
    /// It answered (on time, or late to an earlier tick).
    Answered,
    /// Nothing new from it.
    Silent,
    /// Its observation or its answer was lost on the way (`[reality]`): neither.
    Lost,
}

/// Why a robot is out of the formation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Away {
    /// Its controller failed (`[reality]` `controller_failure`): out for the episode.
    Failed,
    /// The control service removed it: out until restored, or the episode ends.
    Removed,
    /// Silent for [`LEAVE_AFTER_SILENT_TICKS`] ticks: out until it answers
    /// [`RETURN_AFTER_ANSWERS`] ticks in a row, across episodes.
    Silent,
}

/// What the attendance of one tick asks of the mission planner.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Call {
    /// The robot has been silent long enough to leave.
    Leave,
    /// The robot, away for silence, has answered long enough to come back.
    Return,
}

/// Who is in the formation and why not: runs of silent ticks and of answers per robot, kept
/// across episodes (a dead process stays dead); failures and removals last an episode.
#[derive(Debug, Clone)]
pub struct Attendance {
    silent: Vec<u32>,
    answers: Vec<u32>,
    away: Vec<Option<Away>>,
}

impl Attendance {
    /// Every one of `n` robots in.
    pub fn new(n: usize) -> Self {
        Self {
            silent: vec![0; n],
            answers: vec![0; n],
            away: vec![None; n],
        }
    }

    /// Why robot `agent` is out of the formation, if it is.
    pub fn away(&self, agent: usize) -> Option<Away> {
        self.away[agent]
    }

    /// A new episode: robots failed or removed in the last one are in again.
    pub fn new_episode(&mut self) {
        for away in &mut self.away {
            if *away != Some(Away::Silent) {
                *away = None;
            }
        }
    }

    /// Records what was heard from robot `agent` this tick; says when it should leave (in the
    /// formation, silent for [`LEAVE_AFTER_SILENT_TICKS`] ticks in a row, and every tick after
    /// while the mission planner keeps it) or come back (away for silence, answering for
    /// [`RETURN_AFTER_ANSWERS`] in a row). A loss counts neither way.
    pub fn record(&mut self, agent: usize, heard: Heard) -> Option<Call> {
        match heard {
            Heard::Answered => {
                self.silent[agent] = 0;
                self.answers[agent] = self.answers[agent].saturating_add(1);
            }
            Heard::Silent => {
                self.answers[agent] = 0;
                self.silent[agent] = self.silent[agent].saturating_add(1);
            }
            Heard::Lost => {}
        }
        match self.away[agent] {
            None if self.silent[agent] >= LEAVE_AFTER_SILENT_TICKS => Some(Call::Leave),
            Some(Away::Silent) if self.answers[agent] >= RETURN_AFTER_ANSWERS => Some(Call::Return),
            _ => None,
        }
    }

    /// Robot `agent` left the formation (`Some`) or came back (`None`).
    pub fn set_away(&mut self, agent: usize, away: Option<Away>) {
        self.away[agent] = away;
    }
}

/// A change under way: each present robot's target offset from the goal moving in a straight
/// line, all in step, from its place in the swarm at the change to its new slot's offset (see
/// the module's documentation).
#[derive(Debug, Clone)]
struct Morph {
    /// The new formation's slot map.
    slot_of: Vec<usize>,
    /// The offsets, by slot, at the change (the robots' positions relative to their centroid,
    /// moved onto the new formation's) and at the end (the new formation's).
    from: Vec<[f64; 2]>,
    to: Vec<[f64; 2]>,
    /// Ticks the morph lasts, and those applied so far.
    ticks: u32,
    done: u32,
}

impl Morph {
    /// The morph of `world`, whose present robots have just been assigned (its slot map) to
    /// the slots of `to`, from where they stand.
    fn new(world: &World, to: &[[f64; 2]]) -> Self {
        let slot_of = world.slot_of.clone();
        let centroid = present_centroid(&world.poses, &world.observed);
        let (sx, sy) = to.iter().fold((0.0, 0.0), |(sx, sy), o| (sx + o[0], sy + o[1]));
        let centre = [sx / to.len() as f64, sy / to.len() as f64];
        let mut from = to.to_vec();
        for r in (0..slot_of.len()).filter(|&r| slot_of[r] < to.len()) {
            from[slot_of[r]] = [
                world.poses[r].x - centroid[0] + centre[0],
                world.poses[r].y - centroid[1] + centre[1],
            ];
        }
        let longest = from
            .iter()
            .zip(to)
            .map(|(a, b)| (b[0] - a[0]).hypot(b[1] - a[1]))
            .fold(0.0, f64::max);
        let env = &world.env;
        let ticks = (longest / (env.morph_speed * env.v_max * env.dt_s)).ceil().max(1.0) as u32;
        Self {
            slot_of,
            from,
            to: to.to_vec(),
            ticks,
            done: 0,
        }
    }

    /// Gives `world` the next tick's formation; true when that was the last (the new
    /// formation itself).
    fn advance(&mut self, world: &mut World) -> bool {
        self.done += 1;
        let alpha = f64::from(self.done) / f64::from(self.ticks);
        let offsets: Vec<[f64; 2]> = if self.done >= self.ticks {
            self.to.clone()
        } else {
            self.from
                .iter()
                .zip(&self.to)
                .map(|(a, b)| [a[0] + alpha * (b[0] - a[0]), a[1] + alpha * (b[1] - a[1])])
                .collect()
        };
        set_formation(world, &offsets, self.slot_of.clone());
        self.done >= self.ticks
    }
}

/// One episode's mission: its schedule of shape changes, the team, and the re-form counts.
#[derive(Debug, Clone)]
pub struct Mission {
    changes: Vec<ShapeChange>,
    /// The formation in force at capacity (one slot per launched robot) and what it is.
    full: Vec<[f64; 2]>,
    spec: FormationSpec,
    /// The formation of the robots present (equal to `full` while every robot is in).
    current: Vec<[f64; 2]>,
    /// Seed of the formations redrawn for the robots present.
    seed: u64,
    /// Robots that left the formation, and that came back, this episode.
    departures: u32,
    returns: u32,
    /// Index of the next change to apply.
    next: usize,
    /// The latest change's tick while the swarm has not re-formed since.
    pending: Option<u32>,
    /// First tick of the current run of ticks in formation, and its length.
    run: Option<(u32, u32)>,
    /// Changes applied so far.
    reconfigurations: u32,
    /// Ticks to re-form after each change that re-formed.
    reform_ticks: Vec<u32>,
    /// The change under way, if any.
    morph: Option<Morph>,
}

/// The `seed` of [`Mission::new`] for episode `episode` of a run seeded with `run_seed`: the
/// sim's and the model selection's, so both redraw the same formations at a team change.
pub fn team_seed(run_seed: u64, episode: u32) -> u64 {
    run_seed ^ (u64::from(episode) << 32)
}

impl Mission {
    /// The mission of an episode that starts in formation `start` (what `spec` says, one slot
    /// per robot, robot i in slot i) with these shape changes (in tick order); `seed` (the
    /// run's and the episode's, [`team_seed`]) seeds the formations redrawn when the team
    /// changes.
    pub fn new(changes: Vec<ShapeChange>, start: &[[f64; 2]], spec: FormationSpec, seed: u64) -> Self {
        Self {
            changes,
            full: start.to_vec(),
            spec,
            current: start.to_vec(),
            seed: seed ^ TEAM_STREAM,
            departures: 0,
            returns: 0,
            next: 0,
            pending: None,
            run: None,
            reconfigurations: 0,
            reform_ticks: Vec::new(),
            morph: None,
        }
    }

    /// Called after the step into tick `world.steps` that C1 judged `in_formation` (under the
    /// formation in force) and that leaves the episode `running`: counts the re-form (ticks in
    /// a formation still morphing do not count), then applies the change scheduled for this
    /// tick, if any, or the next tick of a morph under way ([`Morph`]), so that the tick's
    /// observations carry it. Returns true when the formation changed.
    pub fn after_step(&mut self, world: &mut World, in_formation: bool, running: bool) -> bool {
        let tick = world.steps;
        let in_formation = in_formation && self.morph.is_none();
        self.run = match (in_formation, self.run) {
            (false, _) => None,
            (true, None) => Some((tick, 1)),
            (true, Some((first, len))) => Some((first, len + 1)),
        };
        if let (Some(changed), Some((first, len))) = (self.pending, self.run)
            && (len >= REFORM_HOLD_TICKS || !running)
        {
            self.reform_ticks.push(first - changed);
            self.pending = None;
        }
        if !running {
            return false;
        }
        if let Some(change) = self.changes.get(self.next).filter(|c| c.tick == tick) {
            let (offsets, spec) = (change.offsets.clone(), change.spec);
            self.next += 1;
            self.reform(world, &offsets, spec);
            return true;
        }
        let Some(morph) = &mut self.morph else {
            return false;
        };
        if morph.advance(world) {
            self.morph = None;
        }
        true
    }

    /// A live change (the control service): from the current tick on, the formation at
    /// capacity is `offsets` (slot s's offset from the goal, in tour order, one per launched
    /// robot; what `spec` says) around the world's goal, and the robots present are assigned
    /// to its slots (to the same formation for them, [`Mission::formation_for`], when some are
    /// out) as at a scheduled change. Counts as a reconfiguration. The schedule's later changes
    /// still come.
    pub fn reform(&mut self, world: &mut World, offsets: &[[f64; 2]], spec: FormationSpec) {
        self.full = offsets.to_vec();
        self.spec = spec;
        let present: Vec<bool> = (0..world.n_agents()).map(|r| world.slot_of[r] != NO_SLOT).collect();
        self.current = self.formation_for(world, &present);
        self.assign_present(world, &present);
        self.count_change(world);
    }

    /// A live move of the goal to `goal`: the formation in force around the new goal, the
    /// robots assigned to its slots again (a reconfiguration, as [`Mission::reform`]).
    pub fn move_goal(&mut self, world: &mut World, goal: [f64; 2]) {
        world.goal = goal;
        let present: Vec<bool> = (0..world.n_agents()).map(|r| world.slot_of[r] != NO_SLOT).collect();
        self.assign_present(world, &present);
        self.count_change(world);
    }

    /// Robot `robot` leaves the formation from the current tick on: the robots present re-form
    /// the same formation for one robot fewer. Refused, saying why, for an unknown robot, one
    /// already out, or when fewer than [`MIN_AGENTS`] would stay (every robot needs two
    /// neighbours). Counts as a departure and a reconfiguration.
    pub fn leave(&mut self, world: &mut World, robot: usize) -> Result<(), String> {
        let mut present = self.team(world, robot)?;
        if !present[robot] {
            return Err(format!("robot {robot} is already out of the formation"));
        }
        let m = present.iter().filter(|&&p| p).count();
        if m <= MIN_AGENTS {
            return Err(format!(
                "robot {robot}: fewer than {MIN_AGENTS} robots would stay in the formation"
            ));
        }
        present[robot] = false;
        self.regroup(world, &present);
        self.extend_time_limit(world);
        self.departures += 1;
        Ok(())
    }

    /// Robot `robot`, out of the formation, comes back from the current tick on: the robots
    /// present re-form the same formation for one robot more (the formation in force at
    /// capacity once every robot is in). Refused for an unknown robot or one already in.
    /// Counts as a return and a reconfiguration.
    pub fn rejoin(&mut self, world: &mut World, robot: usize) -> Result<(), String> {
        let mut present = self.team(world, robot)?;
        if present[robot] {
            return Err(format!("robot {robot} is already in the formation"));
        }
        present[robot] = true;
        self.regroup(world, &present);
        self.extend_time_limit(world);
        self.returns += 1;
        Ok(())
    }

    /// Starts the episode with only the `present` robots in the formation (the others are away
    /// from an earlier episode): they take the same formation for them. Not a reconfiguration;
    /// with fewer than [`MIN_AGENTS`] present, every robot stays in.
    pub fn start_with(&mut self, world: &mut World, present: &[bool]) {
        let m = present.iter().filter(|&&p| p).count();
        if m == present.len() || m < MIN_AGENTS {
            return;
        }
        self.current = self.formation_for(world, present);
        self.assign_present(world, present);
    }

    /// A team change mid-episode gives the swarm the time a shape change gets
    /// ([`EnvConfig::episode_steps`]): the ticks a robot needs to cross the formation in force
    /// (of its kind, at the launch N) at top speed, 2 reach / (v_max dt).
    fn extend_time_limit(&self, world: &mut World) {
        let env = &world.env;
        let reach = EnvConfig {
            shape: self.spec.kind,
            ..env.clone()
        }
        .formation_reach_m(world.n_agents());
        world.env.max_steps += (2.0 * reach / (env.v_max * env.dt_s)).ceil() as u32;
    }

    /// Who is in the formation now, after checking that `robot` is one of the swarm.
    fn team(&self, world: &World, robot: usize) -> Result<Vec<bool>, String> {
        let n = world.n_agents();
        if robot >= n {
            return Err(format!("no robot {robot} (robots 0 to {})", n - 1));
        }
        Ok((0..n).map(|r| world.slot_of[r] != NO_SLOT).collect())
    }

    /// The `present` robots take the same formation for them.
    fn regroup(&mut self, world: &mut World, present: &[bool]) {
        self.current = self.formation_for(world, present);
        self.assign_present(world, present);
        self.count_change(world);
    }

    /// Assigns the `present` robots to the slots of the current formation (Kuhn-Munkres, as at
    /// a shape change); the others hold [`NO_SLOT`].
    fn assign_present(&mut self, world: &mut World, present: &[bool]) {
        let robots: Vec<usize> = (0..world.n_agents()).filter(|&r| present[r]).collect();
        let positions: Vec<[f64; 2]> = robots.iter().map(|&r| [world.poses[r].x, world.poses[r].y]).collect();
        let targets: Vec<[f64; 2]> = self
            .current
            .iter()
            .map(|o| [world.goal[0] + o[0], world.goal[1] + o[1]])
            .collect();
        let mut slot_of = vec![NO_SLOT; world.n_agents()];
        for (&robot, slot) in robots.iter().zip(assign(&positions, &targets)) {
            slot_of[robot] = slot;
        }
        let offsets = self.current.clone();
        set_formation(world, &offsets, slot_of);
        // Not a step: the formation morphs from where the robots stand, its first tick now.
        let mut morph = Morph::new(world, &self.current);
        self.morph = (!morph.advance(world)).then_some(morph);
    }

    /// Counts a reconfiguration at the current tick, whose re-forming is then awaited.
    fn count_change(&mut self, world: &World) {
        self.reconfigurations += 1;
        self.pending = Some(world.steps);
        self.run = None;
    }

    /// The same formation for the `present` robots, M of them: the formation in force at
    /// capacity when M is the launch N; otherwise its kind drawn for M robots from the
    /// episode's team stream (seeded by the run, the episode and the departures and returns so
    /// far), turned and scaled as the formation in force; a draw whose scaled edges leave the
    /// allowed range or whose slots leave the arena is drawn again, and after
    /// [`REDRAW_ATTEMPTS`] the scale is given up. Then it keeps clear of the robots out
    /// ([`Mission::clear_of_robots_out`]).
    pub fn formation_for(&self, world: &World, present: &[bool]) -> Vec<[f64; 2]> {
        let m = present.iter().filter(|&&p| p).count();
        if m == self.full.len() {
            return self.full.clone();
        }
        let drawn = self.draw_for(world, m);
        clear_of_robots_out(world, present, drawn)
    }

    /// The formation's kind drawn for `m` robots (see [`Mission::formation_for`]).
    fn draw_for(&self, world: &World, m: usize) -> Vec<[f64; 2]> {
        let seed = self.seed ^ (u64::from(self.departures + self.returns) << 40) ^ m as u64;
        let mut rng = StdRng::seed_from_u64(seed);
        let env = &world.env;
        let unscaled = FormationSpec {
            scale: 1.0,
            ..self.spec
        };
        let mut last = Vec::new();
        for spec in [self.spec, unscaled] {
            for _ in 0..REDRAW_ATTEMPTS {
                last = placed(&draw_shape(self.spec.kind, m, env, &mut rng), &spec);
                if shape_is_valid(&last, env) && fits_arena(world, world.goal, &last) {
                    return last;
                }
            }
        }
        last
    }

    /// The step's result under the mission: a success (C3) before the last change, or while
    /// the formation still morphs, is not the end of the episode
    /// ([`success_after_last_change`]).
    pub fn judge(&self, result: StepResult, steps: u32, env: &EnvConfig) -> StepResult {
        let to_come = self.next < self.changes.len() || self.morph.is_some();
        success_after_last_change(result, to_come, steps, env)
    }

    /// Slot reassignments so far this episode: shape changes, goal moves and team changes.
    pub fn reconfigurations(&self) -> u32 {
        self.reconfigurations
    }

    /// Robots that left the formation this episode.
    pub fn departures(&self) -> u32 {
        self.departures
    }

    /// Robots that came back into the formation this episode.
    pub fn returns(&self) -> u32 {
        self.returns
    }

    /// Ticks from each change to the swarm's re-forming, for the changes that re-formed.
    pub fn reform_ticks(&self) -> &[u32] {
        &self.reform_ticks
    }
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::config::{EnvConfig, FormationShape};
    use crate::formation::{Episodes, random_episode};
    use crate::physics::Pose;
    use crate::shapes::draw_shape;

    fn cost(positions: &[[f64; 2]], targets: &[[f64; 2]], slot_of: &[usize]) -> f64 {
        slot_of
            .iter()
            .enumerate()
            .map(|(r, &s)| (positions[r][0] - targets[s][0]).powi(2) + (positions[r][1] - targets[s][1]).powi(2))
            .sum()
    }

    /// Every permutation of 0..n (Heap's algorithm).
    fn permutations(n: usize) -> Vec<Vec<usize>> {
        fn heap(k: usize, items: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
            if k <= 1 {
                out.push(items.clone());
                return;
            }
            for i in 0..k {
                heap(k - 1, items, out);
                let j = if k.is_multiple_of(2) { i } else { 0 };
                items.swap(j, k - 1);
            }
        }
        let mut out = Vec::new();
        heap(n, &mut (0..n).collect(), &mut out);
        out
    }

    #[test]
    fn the_assignment_is_optimal_on_small_cases_checked_by_brute_force() {
        let mut rng = StdRng::seed_from_u64(29);
        for n in 1..=7 {
            let all = permutations(n);
            for _ in 0..20 {
                let mut point = || [rng.random_range(0.0..10.0), rng.random_range(0.0..10.0)];
                let positions: Vec<[f64; 2]> = (0..n).map(|_| point()).collect();
                let targets: Vec<[f64; 2]> = (0..n).map(|_| point()).collect();
                let slot_of = assign(&positions, &targets);
                let mut sorted = slot_of.clone();
                sorted.sort_unstable();
                assert_eq!(sorted, (0..n).collect::<Vec<_>>(), "a permutation");
                let best = all
                    .iter()
                    .map(|p| cost(&positions, &targets, p))
                    .fold(f64::INFINITY, f64::min);
                // Within the rounding to mm² per robot.
                assert!(
                    cost(&positions, &targets, &slot_of) <= best + n as f64 * 1e-6,
                    "n = {n}: {} > {best}",
                    cost(&positions, &targets, &slot_of)
                );
            }
        }
    }

    fn spec(kind: FormationShape) -> FormationSpec {
        FormationSpec {
            kind,
            orientation: 0.0,
            scale: 1.0,
        }
    }

    /// A world of `n` robots standing on `points` (heading +x), goal at the origin, robot i in
    /// slot i of that formation.
    fn world_on(points: &[[f64; 2]]) -> World {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(1);
        let mut world = World::new(&env, random_episode(points.len(), &env, &mut rng));
        world.goal = [5.0, 5.0];
        for (pose, p) in world.poses.iter_mut().zip(points) {
            *pose = Pose {
                x: 5.0 + p[0],
                y: 5.0 + p[1],
                theta: 0.0,
            };
        }
        let slot_of = (0..points.len()).collect();
        set_formation(&mut world, points, slot_of);
        world
    }

    #[test]
    fn a_line_reversed_and_a_ring_turned_by_half_a_turn_get_the_better_assignment_than_index_order() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(5);
        for kind in [FormationShape::Line, FormationShape::Ring] {
            let n = 8;
            let shape = draw_shape(kind, n, &env, &mut rng);
            // Half a turn: every slot's offset negated.
            let turned: Vec<[f64; 2]> = shape.iter().map(|p| [-p[0], -p[1]]).collect();
            let mut world = world_on(&shape);
            let mut mission = Mission::new(
                vec![ShapeChange {
                    tick: 0,
                    offsets: turned.clone(),
                    spec: spec(kind),
                }],
                &shape,
                spec(kind),
                1,
            );
            assert!(mission.after_step(&mut world, true, true));
            let positions: Vec<[f64; 2]> = world.poses.iter().map(|p| [p.x - 5.0, p.y - 5.0]).collect();
            let index: Vec<usize> = (0..n).collect();
            let kept = cost(&positions, &turned, &index);
            let planned = cost(&positions, &turned, &world.slot_of);
            assert!(world.slot_of != index, "{kind:?}: the slot map changed");
            assert!(
                planned < 0.01 * kept,
                "{kind:?}: {planned} against index order's {kept}"
            );
            // Each robot's slot is the turned shape's point nearest to it: it barely moves.
            assert!(planned < 1e-9, "{kind:?}: the turned shape is the same set of points");
            // The world follows the slot map: slots, observed robots and desired edges.
            for robot in 0..n {
                let s = world.slot_of[robot];
                assert_eq!(world.slots[robot], turned[s]);
                let next = world.observed[robot][0];
                assert_eq!(world.slot_of[next], (s + 1) % n);
                let d = (turned[s][0] - turned[(s + 1) % n][0]).hypot(turned[s][1] - turned[(s + 1) % n][1]);
                assert!((world.desired[robot][0] - d).abs() < 1e-12);
            }
            // Standing still, the swarm is in the new formation at once.
            assert!(world.conditions().in_formation, "{kind:?}");
        }
    }

    #[test]
    fn a_live_formation_is_assigned_like_a_scheduled_one_and_bad_ones_are_refused() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(12);
        let ring = draw_shape(FormationShape::Ring, 6, &env, &mut rng);
        let mut world = world_on(&ring);
        let why = |r: Result<Vec<[f64; 2]>, String>| r.err().unwrap_or_default();
        assert!(why(live_formation(&world, FormationShape::Mixed, 1.0, 0.0, 1)).contains("mixed"));
        assert!(why(live_formation(&world, FormationShape::Line, 0.0, 0.0, 1)).contains("positive"));
        assert!(why(live_formation(&world, FormationShape::Line, 20.0, 0.0, 1)).contains("edge"));
        // The same seed draws the same formation; a half turn negates every offset.
        let line = live_formation(&world, FormationShape::Line, 1.0, 0.0, 7).unwrap_or_default();
        let turned = live_formation(&world, FormationShape::Line, 1.0, std::f64::consts::PI, 7).unwrap_or_default();
        assert_eq!(line.len(), 6);
        for (a, b) in line.iter().zip(&turned) {
            assert!((a[0] + b[0]).abs() < 1e-9 && (a[1] + b[1]).abs() < 1e-9);
        }
        let mut mission = Mission::new(Vec::new(), &ring, spec(FormationShape::Ring), 1);
        mission.reform(&mut world, &line, spec(FormationShape::Line));
        // It morphs as a scheduled change does: its first tick asks for about the ring the
        // robots stand in (a step change asked for edges metres off), and no success meanwhile.
        assert!(world.conditions().max_edge_error < env.eps_form_m, "no edge jumps");
        assert!(mission.judge(world.step(&[(0.0, 0.0); 6]), 1, &env).outcome != Outcome::Success);
        morph_to_the_end(&mut world, &mut mission);
        let positions: Vec<[f64; 2]> = world.poses.iter().map(|p| [p.x - 5.0, p.y - 5.0]).collect();
        assert_eq!(
            world.slot_of,
            assign(&positions, &line),
            "the mission planner's assignment"
        );
        for robot in 0..6 {
            assert_eq!(world.slots[robot], line[world.slot_of[robot]]);
        }
        assert_eq!(mission.reconfigurations(), 1);
        // A new goal keeps the formation, its slots reassigned around the goal.
        let offsets_before: Vec<[f64; 2]> = world.slots.clone();
        mission.move_goal(&mut world, [6.0, 5.0]);
        morph_to_the_end(&mut world, &mut mission);
        assert_eq!(world.goal, [6.0, 5.0]);
        let mut before = offsets_before.clone();
        let mut after = world.slots.clone();
        before.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        after.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        assert_eq!(before, after, "the same formation");
        assert_eq!(mission.reconfigurations(), 2);
        assert!(!fits_arena(&world, [-3.0, 5.0], &world.slots));
    }

    #[test]
    fn success_means_holding_the_last_formation_at_the_goal() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(8);
        let shape = draw_shape(FormationShape::Ring, 6, &env, &mut rng);
        let mut world = world_on(&shape);
        let mut mission = Mission::new(
            vec![ShapeChange {
                tick: 3,
                offsets: draw_shape(FormationShape::Line, 6, &env, &mut rng),
                spec: spec(FormationShape::Line),
            }],
            &shape,
            spec(FormationShape::Ring),
            1,
        );
        // In formation at the goal, a change still to come: the episode goes on.
        let result = world.step(&[(0.0, 0.0); 6]);
        assert_eq!(result.outcome, Outcome::Success);
        let judged = mission.judge(result, world.steps, &world.env);
        assert_eq!((judged.outcome, judged.reward), (Outcome::Running, env.r_edge));
        // After the last change, holding the new formation at the goal is success; while the
        // formation morphs into it, holding the morphing formation is not.
        world.step(&[(0.0, 0.0); 6]);
        world.step(&[(0.0, 0.0); 6]);
        assert!(mission.after_step(&mut world, true, true));
        stand_in_slots(&mut world);
        let result = world.step(&[(0.0, 0.0); 6]);
        assert_eq!(result.outcome, Outcome::Success);
        assert_eq!(mission.judge(result, world.steps, &world.env).outcome, Outcome::Running);
        morph_to_the_end(&mut world, &mut mission);
        for robot in 0..6 {
            world.poses[robot].x = world.goal[0] + world.slots[robot][0];
            world.poses[robot].y = world.goal[1] + world.slots[robot][1];
        }
        let result = world.step(&[(0.0, 0.0); 6]);
        assert_eq!(mission.judge(result, world.steps, &world.env).outcome, Outcome::Success);
    }

    #[test]
    fn a_change_reaches_every_robots_observation_at_its_tick_and_re_forming_is_counted() {
        let env = EnvConfig {
            shape_changes: 1,
            change_shapes: vec![FormationShape::Line],
            ..EnvConfig::default()
        };
        let mut init = Episodes::new(6, &env, 1000).next().unwrap_or_else(|| unreachable!());
        let changes = std::mem::take(&mut init.changes);
        let change_tick = changes[0].tick;
        let mut mission = Mission::new(changes.clone(), &init.slots, init.spec, 1);
        let mut world = World::new(&env, init);
        let before: Vec<_> = (0..6).map(|r| world.observation(r)).collect();
        for _ in 1..change_tick {
            let result = world.step(&[(0.0, 0.0); 6]);
            assert!(!mission.after_step(&mut world, result.conditions.in_formation, true));
            assert_eq!((0..6).map(|r| world.observation(r)).collect::<Vec<_>>(), before);
        }
        let result = world.step(&[(0.0, 0.0); 6]);
        assert!(mission.after_step(&mut world, result.conditions.in_formation, true));
        assert_eq!(world.steps, change_tick);
        let layout = world.observer.layout;
        for robot in 0..6 {
            let obs = world.observation(robot);
            for k in 0..NEIGHBOURS {
                let at = layout.neighbour(k) + 4;
                assert_eq!(
                    obs[at], world.desired[robot][k] as f32,
                    "robot {robot} is told the new edge"
                );
            }
        }
        assert_ne!(world.observation(0), before[0], "the change is told at its tick");
        assert_eq!(mission.reconfigurations(), 1);
        // The formation morphs into the line; at its end the line's own edges are told.
        let end = morph_to_the_end(&mut world, &mut mission);
        assert!(end > change_tick);
        for robot in 0..6 {
            let line = &changes[0].offsets;
            let s = world.slot_of[robot];
            let d = (line[s][0] - line[(s + 1) % 6][0]).hypot(line[s][1] - line[(s + 1) % 6][1]);
            assert_eq!(world.observation(robot)[layout.neighbour(0) + 4], d as f32);
        }
        // Teleport the robots into their new slots: re-formed after 5 ticks in formation,
        // counted from the change.
        let teleported = world.steps;
        for robot in 0..6 {
            let slot = world.slots[robot];
            world.poses[robot].x = world.goal[0] + slot[0];
            world.poses[robot].y = world.goal[1] + slot[1];
        }
        for _ in 0..REFORM_HOLD_TICKS {
            let result = world.step(&[(0.0, 0.0); 6]);
            assert!(result.conditions.in_formation);
            mission.after_step(&mut world, true, true);
        }
        assert_eq!(mission.reform_ticks(), &[teleported + 1 - change_tick]);
    }

    #[test]
    fn a_scheduled_change_morphs_from_where_the_robots_stand_along_straight_lines_in_step() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(3);
        let n = 12;
        let ring = draw_shape(FormationShape::Ring, n, &env, &mut rng);
        let line = draw_shape(FormationShape::Line, n, &env, &mut rng);
        let mut world = world_on(&ring);
        // On its way: the swarm a metre short of the goal (the morph is relative to the swarm).
        for pose in &mut world.poses {
            pose.x -= 1.0;
        }
        let change = ShapeChange {
            tick: 1,
            offsets: line.clone(),
            spec: spec(FormationShape::Line),
        };
        let mut mission = Mission::new(vec![change], &ring, spec(FormationShape::Ring), 1);
        let still = vec![(0.0, 0.0); n];
        world.step(&still);
        assert!(mission.after_step(&mut world, true, true));
        let per_tick = env.morph_speed * env.v_max * env.dt_s;
        // The first tick asks for the swarm's present geometry, one tick's move away: no edge
        // jumps (a step change asked for edges up to metres off).
        for robot in 0..n {
            for k in 0..NEIGHBOURS {
                let other = world.observed[robot][k];
                let (p, q) = (world.poses[robot], world.poses[other]);
                let d = (p.x - q.x).hypot(p.y - q.y);
                assert!(
                    (world.desired[robot][k] - d).abs() <= 2.0 * per_tick + 1e-9,
                    "robot {robot} edge {k}"
                );
            }
        }
        let mut targets = vec![world.slots.clone()];
        loop {
            world.step(&still);
            if !mission.after_step(&mut world, true, true) {
                break;
            }
            targets.push(world.slots.clone());
        }
        // It ends in the line, each robot in the slot Kuhn-Munkres gave it, after as many ticks
        // as the farthest move takes.
        let last = &targets[targets.len() - 1];
        for robot in 0..n {
            assert_eq!(last[robot], line[world.slot_of[robot]]);
        }
        let start: Vec<[f64; 2]> = (0..n)
            .map(|r| {
                let a = targets[0][r];
                let b = last[r];
                let t = targets.len() as f64;
                // Back from the first tick's offset (1/T of the way) to the morph's start.
                [(a[0] * t - b[0]) / (t - 1.0), (a[1] * t - b[1]) / (t - 1.0)]
            })
            .collect();
        let distance = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
        let longest = (0..n).map(|r| distance(start[r], last[r])).fold(0.0, f64::max);
        assert!(longest > 1.0, "the line is not the ring: {longest} m");
        assert_eq!(targets.len() as u32, (longest / per_tick).ceil() as u32);
        for ticks in targets.windows(2) {
            for robot in 0..n {
                let (a, b) = (ticks[0][robot], ticks[1][robot]);
                // At most one tick's move, along the robot's straight line to its slot.
                assert!(distance(a, b) <= per_tick + 1e-9);
                let (u, v) = (
                    [b[0] - a[0], b[1] - a[1]],
                    [last[robot][0] - a[0], last[robot][1] - a[1]],
                );
                assert!(
                    (u[0] * v[1] - u[1] * v[0]).abs() < 1e-9,
                    "robot {robot} leaves its line"
                );
            }
        }
        // No two targets ever come closer than the nearer of their start and end distances
        // over root 2: the robots led by them do not have to cross each other.
        for tick in &targets {
            for i in 0..n {
                for j in i + 1..n {
                    let bound = distance(start[i], start[j]).min(distance(last[i], last[j])) / 2f64.sqrt();
                    assert!(distance(tick[i], tick[j]) >= bound - 1e-9, "robots {i} and {j}");
                }
            }
        }
    }

    #[test]
    fn the_scripted_baseline_re_forms_without_the_collisions_a_step_change_caused() {
        use crate::baseline::{BaselineGains, ScriptedBaseline};
        let env = EnvConfig {
            shape_changes: 2,
            ..EnvConfig::default()
        };
        let baseline = ScriptedBaseline::new(&env, BaselineGains::default());
        // Held-out episodes (seed 1000) in which the scripted swarm collided while re-forming
        // after a step change.
        for (n, collided) in [(16, [9, 49, 52]), (32, [13, 26, 41])] {
            for (episode, mut init) in Episodes::new(n, &env, 1000).enumerate().take(53) {
                if !collided.contains(&episode) {
                    continue;
                }
                let changes = std::mem::take(&mut init.changes);
                let mut mission = Mission::new(changes, &init.slots, init.spec, team_seed(1000, episode as u32));
                let mut world = World::new(&env, init);
                let outcome = loop {
                    let commands: Vec<(f64, f64)> = (0..n)
                        .map(|r| {
                            let (v, w) = baseline.command(&world.observation(r));
                            (f64::from(v as f32), f64::from(w as f32))
                        })
                        .collect();
                    let result = mission.judge(world.step(&commands), world.steps, &world.env);
                    if result.outcome != Outcome::Running {
                        break result.outcome;
                    }
                    mission.after_step(&mut world, result.conditions.in_formation, true);
                };
                assert_eq!(outcome, Outcome::Success, "N = {n}, episode {episode}");
                assert_eq!(mission.reconfigurations(), 2);
            }
        }
    }

    #[test]
    fn the_morph_lasts_as_long_as_env_morph_speed_says_and_a_very_fast_one_is_the_old_step() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(3);
        let n = 12;
        let ring = draw_shape(FormationShape::Ring, n, &env, &mut rng);
        let line = draw_shape(FormationShape::Line, n, &env, &mut rng);
        let ticks_at = |speed: f64| {
            let mut world = world_on(&ring);
            world.env.morph_speed = speed;
            let change = ShapeChange {
                tick: 1,
                offsets: line.clone(),
                spec: spec(FormationShape::Line),
            };
            let mut mission = Mission::new(vec![change], &ring, spec(FormationShape::Ring), 1);
            // The ticks whose formation the morph set (after_step says so), the change's first.
            let mut ticks: u32 = 0;
            loop {
                world.step(&vec![(0.0, 0.0); n]);
                if !mission.after_step(&mut world, true, true) {
                    break;
                }
                ticks += 1;
            }
            (ticks, world.slots.clone())
        };
        let (default, end) = ticks_at(env.morph_speed);
        let (twice, twice_end) = ticks_at(2.0 * env.morph_speed);
        let (step, step_end) = ticks_at(1000.0);
        assert!(default > 10, "{default} ticks");
        assert!(
            twice.abs_diff(default.div_ceil(2)) <= 1,
            "{twice} ticks at twice the speed, {default} at the default"
        );
        assert_eq!(step, 1, "a very fast morph is the step change");
        assert_eq!(end, twice_end);
        assert_eq!(end, step_end);
    }

    /// Steps `world` with every robot standing still until `mission`'s morph under way has
    /// ended; the tick of its last step.
    fn morph_to_the_end(world: &mut World, mission: &mut Mission) -> u32 {
        let n = world.n_agents();
        let mut last = world.steps;
        loop {
            world.step(&vec![(0.0, 0.0); n]);
            if !mission.after_step(world, false, true) {
                return last;
            }
            last = world.steps;
        }
    }

    /// A world of `n` robots of `kind` standing in their formation at the goal, its mission.
    fn team_of(kind: FormationShape, n: usize) -> (World, Mission) {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(n as u64);
        let shape = draw_shape(kind, n, &env, &mut rng);
        let world = world_on(&shape);
        let mission = Mission::new(Vec::new(), &shape, spec(kind), 77);
        (world, mission)
    }

    /// The robots present stand in their slots around the goal.
    fn stand_in_slots(world: &mut World) {
        for robot in 0..world.n_agents() {
            if world.slot_of[robot] != NO_SLOT {
                world.poses[robot].x = world.goal[0] + world.slots[robot][0];
                world.poses[robot].y = world.goal[1] + world.slots[robot][1];
            }
        }
    }

    #[test]
    fn removing_a_robot_gives_a_valid_formation_of_the_same_shape_for_n_minus_1() {
        for kind in FormationShape::KINDS {
            for n in [6, 16] {
                let (mut world, mut mission) = team_of(kind, n);
                let env = world.env.clone();
                mission.leave(&mut world, 2).unwrap_or_else(|why| panic!("{why}"));
                morph_to_the_end(&mut world, &mut mission);
                assert_eq!((mission.departures(), mission.reconfigurations()), (1, 1));
                // Robot 2 holds no slot and observes itself; the others hold slots 0..N-1.
                assert_eq!(world.slot_of[2], NO_SLOT);
                assert_eq!(world.observed[2], [2, 2]);
                assert_eq!(world.desired[2], [0.0; NEIGHBOURS]);
                let mut held: Vec<usize> = (0..n).filter(|&r| r != 2).map(|r| world.slot_of[r]).collect();
                held.sort_unstable();
                assert_eq!(held, (0..n - 1).collect::<Vec<_>>(), "{kind:?} n = {n}");
                // Slot order: a valid formation of N - 1, its observed edges in range, the
                // neighbours the robots in the next two slots mod N - 1, never robot 2.
                let mut offsets = vec![[0.0; 2]; n - 1];
                for r in (0..n).filter(|&r| r != 2) {
                    offsets[world.slot_of[r]] = world.slots[r];
                    for (k, &other) in world.observed[r].iter().enumerate() {
                        assert_ne!(other, 2);
                        assert_eq!(world.slot_of[other], (world.slot_of[r] + k + 1) % (n - 1));
                    }
                }
                assert!(shape_is_valid(&offsets, &env), "{kind:?} n = {n}: a valid formation");
                assert!(fits_arena(&world, world.goal, &offsets));
                let centre = offsets.iter().fold([0.0, 0.0], |c, o| [c[0] + o[0], c[1] + o[1]]);
                assert!(centre[0].hypot(centre[1]) < 1e-6, "{kind:?}: centred on the goal");
                if kind == FormationShape::Ring && n < crate::config::LARGE_SWARM {
                    // A ring of N - 1: every slot as far from the goal.
                    let r0 = offsets[0][0].hypot(offsets[0][1]);
                    assert!(offsets.iter().all(|o| (o[0].hypot(o[1]) - r0).abs() < 1e-6));
                }
                // In those slots the swarm has succeeded, wherever robot 2 stands (off the way).
                stand_in_slots(&mut world);
                world.poses[2].x = 0.05;
                world.poses[2].y = 0.05;
                let c = world.conditions();
                assert!(
                    c.success && !c.collision && c.max_edge_error < 1e-9,
                    "{kind:?} n = {n}: {c:?}"
                );
                // Back at full strength: the formation in force at capacity.
                mission.rejoin(&mut world, 2).unwrap_or_else(|why| panic!("{why}"));
                assert_eq!((mission.returns(), mission.reconfigurations()), (1, 2));
                let mut back: Vec<usize> = world.slot_of.clone();
                back.sort_unstable();
                assert_eq!(back, (0..n).collect::<Vec<_>>());
                assert!(!world.conditions().success, "robot 2 is in again, far from its slot");
            }
        }
    }

    #[test]
    fn a_formation_turns_about_the_goal_to_keep_its_slots_clear_of_a_robot_out() {
        let (mut world, _) = team_of(FormationShape::Ring, 6);
        let env = world.env.clone();
        let mut rng = StdRng::seed_from_u64(3);
        let ring = draw_shape(FormationShape::Ring, 5, &env, &mut rng);
        let mut present = vec![true; 6];
        present[2] = false;
        // Nothing in the way: unturned.
        world.poses[2].x = world.goal[0] + 3.0;
        assert_eq!(clear_of_robots_out(&world, &present, ring.clone()), ring);
        // Robot 2 stopped beside a slot, outside the ring: the ring turns until every slot is
        // edge_min away from it.
        world.poses[2].x = world.goal[0] + 2.0 * ring[0][0];
        world.poses[2].y = world.goal[1] + 2.0 * ring[0][1];
        let radius = ring[0][0].hypot(ring[0][1]);
        assert!(radius < env.edge_min_m, "slot 0 is in the way as drawn");
        let turned = clear_of_robots_out(&world, &present, ring.clone());
        let room =
            |o: &[f64; 2]| (world.goal[0] + o[0] - world.poses[2].x).hypot(world.goal[1] + o[1] - world.poses[2].y);
        assert!(turned.iter().all(|o| room(o) >= env.edge_min_m), "{turned:?}");
        // The same ring: each slot as far from the goal and from its neighbours.
        for (a, b) in ring.iter().zip(&turned) {
            assert!((a[0].hypot(a[1]) - b[0].hypot(b[1])).abs() < 1e-9);
        }
        let edge = |p: &[[f64; 2]], i: usize| (p[i][0] - p[(i + 1) % 5][0]).hypot(p[i][1] - p[(i + 1) % 5][1]);
        assert!((0..5).all(|i| (edge(&ring, i) - edge(&turned, i)).abs() < 1e-9));
    }

    #[test]
    fn removals_are_refused_for_unknown_robots_robots_out_and_below_three_present() {
        let (mut world, mut mission) = team_of(FormationShape::Random, 4);
        assert!(
            mission
                .leave(&mut world, 4)
                .is_err_and(|why| why.contains("no robot 4"))
        );
        assert!(
            mission
                .rejoin(&mut world, 1)
                .is_err_and(|why| why.contains("already in"))
        );
        assert!(mission.leave(&mut world, 1).is_ok());
        assert!(
            mission
                .leave(&mut world, 1)
                .is_err_and(|why| why.contains("already out"))
        );
        assert!(
            mission
                .leave(&mut world, 0)
                .is_err_and(|why| why.contains("fewer than 3"))
        );
        assert_eq!(mission.departures(), 1);
        // A stopped robot that left is an obstacle: running into it is a collision.
        stand_in_slots(&mut world);
        assert!(!world.conditions().collision);
        world.poses[1].x = world.poses[0].x + 0.01;
        world.poses[1].y = world.poses[0].y;
        assert!(world.conditions().collision);
    }

    #[test]
    fn absence_under_ten_ticks_keeps_a_robot_ten_make_it_leave_and_five_answers_bring_it_back() {
        let mut attendance = Attendance::new(2);
        // Nine silent ticks, losses among them (neither way): still in.
        for tick in 0..9 {
            assert_eq!(attendance.record(0, Heard::Silent), None, "tick {tick}");
            assert_eq!(attendance.record(0, Heard::Lost), None);
        }
        // An answer starts the count again: a lossy robot that misses a few stays.
        assert_eq!(attendance.record(0, Heard::Answered), None);
        for _ in 0..9 {
            assert_eq!(attendance.record(0, Heard::Silent), None);
        }
        assert_eq!(attendance.record(0, Heard::Silent), Some(Call::Leave), "the 10th");
        attendance.set_away(0, Some(Away::Silent));
        // Four answers, a silent tick, then five in a row: back at the fifth.
        for _ in 0..4 {
            assert_eq!(attendance.record(0, Heard::Answered), None);
        }
        assert_eq!(attendance.record(0, Heard::Silent), None);
        for _ in 0..4 {
            assert_eq!(attendance.record(0, Heard::Answered), None);
        }
        assert_eq!(attendance.record(0, Heard::Answered), Some(Call::Return));
        attendance.set_away(0, None);
        // A removed robot answers all along and stays out; it is in again next episode, a
        // robot away for silence is not.
        attendance.set_away(1, Some(Away::Removed));
        for _ in 0..20 {
            assert_eq!(attendance.record(1, Heard::Answered), None);
        }
        attendance.set_away(0, Some(Away::Silent));
        attendance.new_episode();
        assert_eq!((attendance.away(0), attendance.away(1)), (Some(Away::Silent), None));
    }
}
