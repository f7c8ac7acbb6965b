//! The privileged planner: a controller that knows the true poses and the episode's obstacles
//! (what the sim knows, not what robots sense), the hand-written rival a roboticist with a map
//! would write.
//!
//! It plans once per episode (or whenever it is built again) a path from the formation's
//! centroid to the goal ([`plan_path`]: the `pathfinding` crate's A* over a visibility graph,
//! its turns then pushed away from the surfaces). Over the obstacles grown by the formation's
//! radius, the formation moves along it rigidly ([`PlanMode::Formation`]). When the formation
//! fits nowhere along the way (a passage's gap, a dense forest, a trap by the arena's side),
//! the path is planned over the obstacles grown by one robot's radius and the robots go in file
//! ([`PlanMode::Column`]): foremost first, each walks onto the path where it is nearest (within
//! the formation's reach of the start and a run-up before the first narrow place) and follows
//! it [`crate::obstacles::file_spacing_m`] behind the one before; each moves out to its own
//! slot's offset from the path once the straight way out to it is clear (with room to spare)
//! until the end, so the formation re-forms behind the narrow place and arrives at the goal in
//! its slots. Without any path ([`PlanMode::Direct`]) every robot heads for its slot.
//!
//! The targets move along the path at [`PACE`] x `v_max` (slower, [`NARROW_PACE`], while a
//! target is near a surface) while every robot is within [`KEEP_UP_M`] of its target
//! ([`KEEP_UP_OPEN_M`] in the open; robots already out in their slots are not waited for), and
//! wait otherwise, so a robot held up holds the others; after [`PATIENCE_TICKS`] of waiting in
//! a row they move on by one step (robots pushing each other apart can hold one off its target
//! for good). Each robot tracks its moving target with the baseline's unicycle law (turn
//! towards the desired velocity, drive with its component along the heading), with a tracking
//! gain of its own ([`K_TRACK`]), the baseline's repulsion from robots closer than its
//! `repulsion_range` (near surfaces, [`NEAR_ROBOT_RANGE_M`] beyond `eps_coll_m`), and
//! repulsion from obstacle surfaces nearer than [`OBSTACLE_RANGE_M`].
//!
//! Everything is deterministic: robots in different processes that build the planner from the
//! same state and call [`Planner::targets`] with the same poses every tick compute the same
//! targets.

use pathfinding::directed::astar::astar;

use crate::baseline::BaselineGains;
use crate::config::EnvConfig;
use crate::obstacles::{Obstacles, file_spacing_m, robot_radius_m};
use crate::physics::{Pose, wrap_angle};

/// The least room a path in file keeps between a robot's disc and any surface, metres (a
/// 0.35 m gap leaves 0.075 m each side of a robot in its middle).
pub const FILE_MARGIN_M: f64 = 0.05;
/// The rooms a path in file is tried with, widest first: the widest that finds a path keeps
/// the file as far from surfaces as the way allows (a shortest path touches the grown
/// obstacles, so a narrow margin would run the robots along the walls).
const FILE_MARGINS_M: [f64; 7] = [0.25, 0.15, 0.1, 0.085, 0.07, 0.06, FILE_MARGIN_M];
/// Room a formation's path keeps between the formation's outermost disc and any surface, metres.
pub const FORMATION_MARGIN_M: f64 = 0.1;
/// The targets' speed along the path, as a fraction of `v_max`.
pub const PACE: f64 = 0.8;
/// Near surfaces the targets slow to this fraction of [`PACE`] (a robot then runs closer behind
/// its target and cuts the path's corners less).
pub const NARROW_PACE: f64 = 0.3;
/// A target nearer than this to a surface (beyond a robot's radius) is near, metres.
pub const NARROW_M: f64 = 0.06;
/// The targets move on by one step after waiting this many ticks in a row.
pub const PATIENCE_TICKS: u32 = 20;
/// The targets wait while a robot is farther than this from its target, metres,
pub const KEEP_UP_M: f64 = 0.25;
/// or than this from a target in the open (farther than [`OPEN_M`] from every surface beyond
/// a robot's radius), metres.
pub const KEEP_UP_OPEN_M: f64 = 0.4;
/// How far from surfaces a target is in the open, metres.
pub const OPEN_M: f64 = 0.5;
/// Gain of the tracking law, 1/s: at the targets' pace a robot runs 0.2 m behind its target.
pub const K_TRACK: f64 = 2.0;
/// Near surfaces (within [`OPEN_M`]), robots push away from robots nearer than this beyond
/// `eps_coll_m` only, metres.
pub const NEAR_ROBOT_RANGE_M: f64 = 0.15;
/// Robots push away from obstacle surfaces nearer than this to their disc, metres.
pub const OBSTACLE_RANGE_M: f64 = 0.15;
/// Step at which the path is sampled to find where each robot may leave the file, metres.
const SAMPLE_M: f64 = 0.1;
/// Robots join the file where the path keeps this much more room than the file's from
/// surfaces, metres,
const JOIN_ROOM_M: f64 = 0.3;
/// and at least this far before the first place it does not, metres (to line up behind each
/// other before a narrow place).
const JOIN_RUN_UP_M: f64 = 1.0;
/// How much more room than the file's the way out to a slot keeps from surfaces, metres: a robot
/// that fans out runs behind its target and cuts towards it, so it leaves only once clear of
/// the narrow place by that much.
const LEAVE_ROOM_M: f64 = 0.15;
/// Distance along the path over which a robot leaving the file moves out to its slot, metres.
const REFORM_M: f64 = 1.0;

/// How the planner moves the formation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PlanMode {
    /// The whole formation along one path, rigidly.
    Formation,
    /// In file along a path for one robot, re-forming behind the narrow places.
    Column,
    /// No path found: every robot heads straight for its slot.
    Direct,
}

/// Path lengths in A*'s integer costs: micrometres.
const COST_PER_M: f64 = 1e6;

/// A path from `from` to `to` for a disc of radius `inflation` that touches no obstacle and
/// stays inside the arena [0, `arena_m`]^2: the shortest by A* (the `pathfinding` crate's) over
/// the visibility graph of `from`, `to` and the corners of the grown obstacles
/// ([`Obstacles::waypoints`]) that lie `inflation` inside the arena, two points joined when the
/// straight leg between them keeps `inflation` from every surface (checked exactly, with
/// parry); then its turns are pushed away from the surfaces while every leg still keeps
/// `inflation`. `None` when `from` or `to` is not that clear, or no such path exists through
/// these corners. A visibility graph rather than a grid: a gap only a little wider than a robot is
/// found exactly, where a grid would need cells a fraction of the gap's spare room.
pub fn plan_path(
    obstacles: &Obstacles,
    from: [f64; 2],
    to: [f64; 2],
    inflation: f64,
    arena_m: f64,
) -> Option<Vec<[f64; 2]>> {
    let inside = |p: &[f64; 2]| p.iter().all(|v| (inflation..=arena_m - inflation).contains(v));
    if !obstacles.is_clear(from, inflation) || !obstacles.is_clear(to, inflation) {
        return None;
    }
    let mut corners = Vec::new();
    obstacles.waypoints(inflation, &mut corners);
    let mut points = vec![from, to];
    points.extend(
        corners
            .into_iter()
            .filter(|p| inside(p) && obstacles.is_clear(*p, inflation)),
    );
    let length = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let (nodes, _) = astar(
        &0usize,
        |&k| {
            let here = points[k];
            (0..points.len())
                .filter(|&j| j != k && obstacles.segment_is_clear(here, points[j], inflation))
                .map(|j| (j, (length(here, points[j]) * COST_PER_M).round() as u64))
                .collect::<Vec<_>>()
        },
        |&k| (length(points[k], to) * COST_PER_M).floor() as u64,
        |&k| k == 1,
    )?;
    let mut path: Vec<[f64; 2]> = nodes.into_iter().map(|k| points[k]).collect();
    centre_turns(obstacles, &mut path, inflation, arena_m);
    Some(path)
}

/// How far around a turn of a path the surfaces push it away, beyond the inflation, metres.
const CENTRING_RANGE_M: f64 = 0.6;
/// Steps each turn of a path may take away from the surfaces, and their length, metres.
const CENTRING_STEPS: usize = 80;
const CENTRING_STEP_M: f64 = 0.01;

/// Moves each turn of `path` (not its ends) away from the surfaces near it, step by step while
/// both its legs keep `inflation` and it stays inside the arena: a shortest path turns on its
/// grown obstacles' outlines, which a unicycle tracking it would cut; a turn pushed from both
/// sides of a gap settles in the gap's middle.
fn centre_turns(obstacles: &Obstacles, path: &mut [[f64; 2]], inflation: f64, arena_m: f64) {
    let range = inflation + CENTRING_RANGE_M;
    for k in 1..path.len().saturating_sub(1) {
        for _ in 0..CENTRING_STEPS {
            let here = path[k];
            let mut push = [0.0, 0.0];
            obstacles.for_each_nearest_within(here, range, |q| {
                let (dx, dy) = (here[0] - q[0], here[1] - q[1]);
                let distance = dx.hypot(dy).max(1e-9);
                push[0] += (range - distance) * dx / distance;
                push[1] += (range - distance) * dy / distance;
            });
            let size = push[0].hypot(push[1]);
            if size < 1e-6 {
                break;
            }
            let step = CENTRING_STEP_M.min(size);
            let moved = [here[0] + step * push[0] / size, here[1] + step * push[1] / size];
            let fits = moved.iter().all(|v| (inflation..=arena_m - inflation).contains(v))
                && obstacles.segment_is_clear(path[k - 1], moved, inflation)
                && obstacles.segment_is_clear(moved, path[k + 1], inflation);
            if !fits {
                break;
            }
            path[k] = moved;
        }
    }
}

/// A polyline with its arc lengths.
#[derive(Debug, Clone)]
pub(crate) struct Polyline {
    points: Vec<[f64; 2]>,
    /// Arc length at each point, from 0.
    lengths: Vec<f64>,
}

impl Polyline {
    pub(crate) fn new(points: Vec<[f64; 2]>) -> Self {
        let mut lengths = Vec::with_capacity(points.len());
        let mut total = 0.0;
        for (k, p) in points.iter().enumerate() {
            if k > 0 {
                total += (p[0] - points[k - 1][0]).hypot(p[1] - points[k - 1][1]);
            }
            lengths.push(total);
        }
        Self { points, lengths }
    }

    pub(crate) fn length(&self) -> f64 {
        self.lengths.last().copied().unwrap_or(0.0)
    }

    /// The arc length in [0, `up_to`] of the path's point nearest `p`, and that point.
    pub(crate) fn project(&self, p: [f64; 2], up_to: f64) -> (f64, [f64; 2]) {
        let mut best = (f64::INFINITY, 0.0, self.points[0]);
        for k in 1..self.points.len() {
            let start = self.lengths[k - 1];
            if start > up_to {
                break;
            }
            let (a, b) = (self.points[k - 1], self.points[k]);
            let t = crate::obstacles::nearest_on_segment(p, a, b);
            let s = (start + t * (b[0] - a[0]).hypot(b[1] - a[1])).min(up_to);
            let q = self.at(s);
            let distance = (p[0] - q[0]).hypot(p[1] - q[1]);
            if distance < best.0 {
                best = (distance, s, q);
            }
        }
        (best.1, best.2)
    }

    /// The point at arc length `s`, clamped to the ends.
    pub(crate) fn at(&self, s: f64) -> [f64; 2] {
        let k = self.lengths.partition_point(|&l| l <= s);
        if k == 0 {
            return self.points[0];
        }
        if k >= self.points.len() {
            return self.points[self.points.len() - 1];
        }
        let (a, b) = (self.points[k - 1], self.points[k]);
        let span = self.lengths[k] - self.lengths[k - 1];
        let t = if span > 0.0 {
            (s - self.lengths[k - 1]) / span
        } else {
            0.0
        };
        [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]
    }
}

/// Where each robot of a file walks onto the path: the arc length and point it joins at, and
/// the length of its walk there from its start.
#[derive(Debug, Clone, Default)]
struct Joins {
    at: Vec<f64>,
    points: Vec<[f64; 2]>,
    walks: Vec<f64>,
}

/// The privileged planner of one episode's team (see the module's documentation).
#[derive(Debug, Clone)]
pub struct Planner {
    mode: PlanMode,
    /// How far the path keeps from every surface.
    inflation: f64,
    path: Polyline,
    obstacles: Obstacles,
    /// Each robot's position when the plan was made.
    starts: Vec<[f64; 2]>,
    /// Each robot's slot: its offset from the path's point in formation.
    offsets: Vec<[f64; 2]>,
    /// Each robot's distance behind the head of the file (0 in formation).
    lags: Vec<f64>,
    /// Where each robot joins the file (none in formation).
    joins: Joins,
    /// Arc length from which each robot's way out to its slot stays clear to the end.
    leave_at: Vec<f64>,
    /// How far the head of the plan has come along the path (plus the joins), metres.
    progress: f64,
    /// Where the progress ends: every robot at its slot at the goal.
    progress_end: f64,
    /// The robots the targets wait for (every robot unless [`Planner::wait_only_for`]).
    waits_for: Vec<bool>,
    /// Ticks the targets have waited in a row.
    waited: u32,
    /// The tick the targets were last advanced to.
    tick: Option<u32>,
    step_m: f64,
    robot_radius: f64,
    gains: BaselineGains,
    v_max: f64,
    w_max: f64,
    targets: Vec<[f64; 2]>,
    commands: Vec<(f64, f64)>,
}

impl Planner {
    /// The plan for robots at `poses` to bring the formation to `goal`, robot i into its slot
    /// `goal + slots[i]` (`slots[i]` being robot i's offset, world frame), around `obstacles`,
    /// in the arena of `env` for this many robots; `gains` are the baseline's (its turn gain
    /// and robot repulsion).
    pub fn new(
        poses: &[Pose],
        goal: [f64; 2],
        slots: &[[f64; 2]],
        obstacles: &Obstacles,
        env: &EnvConfig,
        gains: BaselineGains,
    ) -> Self {
        let n = poses.len();
        let arena = env.effective_arena_m(n);
        let robot_radius = robot_radius_m(env);
        let starts: Vec<[f64; 2]> = poses.iter().map(|p| [p.x, p.y]).collect();
        let centroid = starts
            .iter()
            .fold([0.0, 0.0], |c, p| [c[0] + p[0] / n as f64, c[1] + p[1] / n as f64]);
        let reach = slots.iter().map(|o| o[0].hypot(o[1])).fold(0.0, f64::max);
        let formation_radius = reach + robot_radius + FORMATION_MARGIN_M;
        let in_file = || {
            FILE_MARGINS_M.iter().find_map(|margin| {
                let inflation = robot_radius + margin;
                plan_path(obstacles, centroid, goal, inflation, arena).map(|path| (inflation, path))
            })
        };
        let (mode, inflation, points) = match plan_path(obstacles, centroid, goal, formation_radius, arena) {
            Some(path) => (PlanMode::Formation, formation_radius, path),
            None => match in_file() {
                Some((inflation, path)) => (PlanMode::Column, inflation, path),
                None => (PlanMode::Direct, 0.0, vec![goal]),
            },
        };
        let path = Polyline::new(points);
        let length = path.length();
        let (lags, joins, leave_at) = match mode {
            PlanMode::Formation | PlanMode::Direct => (vec![0.0; n], Joins::default(), vec![0.0; n]),
            PlanMode::Column => {
                // Each robot joins the file at the path's point nearest it within the
                // formation's reach of the start and a run-up before the first narrow place;
                // the foremost joins first.
                let spacing = file_spacing_m(env);
                let join_before = (first_narrow(&path, obstacles, inflation + JOIN_ROOM_M) - JOIN_RUN_UP_M).max(0.0);
                let entries: Vec<(f64, [f64; 2])> = starts
                    .iter()
                    .map(|&p| path.project(p, reach.min(join_before)))
                    .collect();
                let walk = |k: usize| (starts[k][0] - entries[k].1[0]).hypot(starts[k][1] - entries[k].1[1]);
                // Foremost first: by where a robot joins, and for those that join at the
                // path's start, by how far behind it they stand along the path's first leg (to
                // the tenth of a millimetre). The formation at the goal is the start's shape,
                // so on a path that does not turn much the file's order is the slots' order
                // along the way, and no two robots fanning out behind the narrow place head
                // for one spot.
                let entry = path.at(0.0);
                let first_leg = path.at(path.length().min(1.0));
                let (dx, dy) = (first_leg[0] - entry[0], first_leg[1] - entry[1]);
                let span = dx.hypot(dy).max(1e-9);
                let ahead = |k: usize| {
                    let behind = ((starts[k][0] - entry[0]) * dx + (starts[k][1] - entry[1]) * dy) / span;
                    entries[k].0 + behind.min(0.0)
                };
                let key = |k: usize| (-(ahead(k) * 1e4).round() as i64, (walk(k) * 1e4).round() as i64, k);
                let mut order: Vec<usize> = (0..n).collect();
                order.sort_by_key(|&k| key(k));
                let mut lags = vec![0.0; n];
                for (rank, &k) in order.iter().enumerate() {
                    lags[k] = rank as f64 * spacing;
                }
                let joins = Joins {
                    at: entries.iter().map(|e| e.0).collect(),
                    points: entries.iter().map(|e| e.1).collect(),
                    walks: (0..n).map(walk).collect(),
                };
                let leave_at = slots
                    .iter()
                    .map(|offset| leave_file_at(&path, obstacles, *offset, inflation + LEAVE_ROOM_M, arena))
                    .collect();
                (lags, joins, leave_at)
            }
        };
        let progress_end = length + lags.iter().copied().fold(0.0, f64::max);
        // The first robot to move starts walking at once.
        let progress = (0..joins.walks.len())
            .map(|k| joins.at[k] + lags[k] - joins.walks[k])
            .fold(f64::INFINITY, f64::min)
            .min(0.0);
        Self {
            mode,
            inflation,
            path,
            obstacles: obstacles.clone(),
            starts,
            offsets: slots.to_vec(),
            lags,
            joins,
            leave_at,
            progress,
            progress_end,
            tick: None,
            waited: 0,
            waits_for: vec![true; n],
            step_m: PACE * env.v_max * env.dt_s,
            robot_radius,
            gains,
            v_max: env.v_max,
            w_max: env.w_max,
            targets: vec![[0.0; 2]; n],
            commands: vec![(0.0, 0.0); n],
        }
    }

    /// Makes the targets wait only for the robots marked in `driven` (one flag per robot): those
    /// the planner drives, when others run controllers of their own that need not follow its
    /// targets (the others' targets are still computed).
    pub fn wait_only_for(&mut self, driven: &[bool]) {
        debug_assert_eq!(driven.len(), self.waits_for.len());
        self.waits_for.copy_from_slice(driven);
    }

    /// How the plan moves the formation.
    pub fn mode(&self) -> PlanMode {
        self.mode
    }

    /// How far every leg of the path keeps from every surface, metres: the formation's radius
    /// (its farthest slot plus a robot's radius and [`FORMATION_MARGIN_M`]), or in file a
    /// robot's radius plus the widest margin that found a path (at least [`FILE_MARGIN_M`]);
    /// 0 without a path.
    pub fn inflation(&self) -> f64 {
        self.inflation
    }

    /// The planned path (from the centroid at planning to the goal; the goal alone when
    /// [`PlanMode::Direct`]).
    pub fn path(&self) -> &[[f64; 2]] {
        &self.path.points
    }

    /// Each robot's target at tick `tick` for robots now at `poses`: the targets first advance
    /// along the plan by [`PACE`] x `v_max` x dt for each tick since the last call if every
    /// robot is within [`KEEP_UP_M`] of its target, else they wait. Calling again for the same
    /// tick advances nothing.
    pub fn targets(&mut self, poses: &[Pose], tick: u32) -> &[[f64; 2]] {
        let steps = match self.tick {
            None => 0,
            Some(last) => tick.saturating_sub(last),
        };
        if self.tick.is_none() {
            self.place_targets();
        }
        self.tick = Some(tick);
        if steps > 0 && self.mode != PlanMode::Direct {
            // Robots out in their slots behind the narrow places are not waited for: they are
            // in the clear, and robots fanning out can hold each other off their targets.
            let kept_up = (0..poses.len()).all(|k| {
                let (p, t) = (poses[k], self.targets[k]);
                let joining = self.mode == PlanMode::Column && self.progress - self.lags[k] < self.joins.at[k];
                let keep_up = if !joining && self.obstacles.is_clear(t, self.robot_radius + OPEN_M) {
                    KEEP_UP_OPEN_M
                } else {
                    KEEP_UP_M
                };
                !self.waits_for[k] || self.fanned_out(k) || (p.x - t[0]).hypot(p.y - t[1]) <= keep_up
            });
            self.waited = if kept_up { 0 } else { self.waited + steps };
            let patience_out = self.waited >= PATIENCE_TICKS;
            if patience_out {
                self.waited = 0;
            }
            if kept_up || patience_out {
                let near = self.robot_radius + NARROW_M;
                let pace = if self.targets.iter().all(|&t| self.obstacles.is_clear(t, near)) {
                    1.0
                } else {
                    NARROW_PACE
                };
                self.progress = (self.progress + f64::from(steps) * pace * self.step_m).min(self.progress_end);
            }
            self.place_targets();
        }
        &self.targets
    }

    /// Each robot's (v, w) at tick `tick` for robots now at `poses` ([`Planner::targets`], then
    /// the tracking law), clamped to the robots' limits.
    pub fn commands(&mut self, poses: &[Pose], tick: u32) -> &[(f64, f64)] {
        self.targets(poses, tick);
        for agent in 0..poses.len() {
            self.commands[agent] = self.track(poses, agent);
        }
        &self.commands
    }

    /// Whether robot `k` of a file has left it for its slot (never in formation).
    fn fanned_out(&self, k: usize) -> bool {
        self.mode == PlanMode::Column
            && self.progress - self.lags[k] >= self.leave_at[k].max(self.joins.at[k]) + REFORM_M
    }

    /// The targets at the current progress.
    fn place_targets(&mut self) {
        let length = self.path.length();
        for k in 0..self.targets.len() {
            let offset = self.offsets[k];
            self.targets[k] = match self.mode {
                PlanMode::Direct => {
                    let goal = self.path.at(length);
                    [goal[0] + offset[0], goal[1] + offset[1]]
                }
                PlanMode::Formation => {
                    let p = self.path.at(self.progress);
                    [p[0] + offset[0], p[1] + offset[1]]
                }
                PlanMode::Column => {
                    let along = self.progress - self.lags[k];
                    let (joins_at, walk) = (self.joins.at[k], self.joins.walks[k]);
                    if along < joins_at - walk {
                        self.starts[k]
                    } else if along < joins_at {
                        // Walking from its start onto the path.
                        let (start, entry) = (self.starts[k], self.joins.points[k]);
                        let t = (along - (joins_at - walk)) / walk.max(1e-9);
                        [
                            start[0] + t * (entry[0] - start[0]),
                            start[1] + t * (entry[1] - start[1]),
                        ]
                    } else {
                        let s = along.min(length);
                        let p = self.path.at(s);
                        let leave = self.leave_at[k].max(joins_at);
                        let room = (length - leave).min(REFORM_M);
                        let out = if s >= length {
                            1.0
                        } else if room > 0.0 {
                            ((s - leave) / room).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        [p[0] + out * offset[0], p[1] + out * offset[1]]
                    }
                }
            };
        }
    }

    /// The baseline's unicycle law towards robot `agent`'s target ([`Tracking::command`]).
    fn track(&self, poses: &[Pose], agent: usize) -> (f64, f64) {
        let tracking = Tracking {
            obstacles: &self.obstacles,
            robot_radius: self.robot_radius,
            gains: self.gains,
            v_max: self.v_max,
            w_max: self.w_max,
        };
        tracking.command(poses, agent, self.targets[agent], self.v_max)
    }
}

/// The tracking law both planners drive their robots with: the baseline's unicycle law towards
/// a target, with repulsion from robots and obstacle surfaces.
pub(crate) struct Tracking<'a> {
    pub obstacles: &'a Obstacles,
    pub robot_radius: f64,
    pub gains: BaselineGains,
    pub v_max: f64,
    pub w_max: f64,
}

impl Tracking<'_> {
    /// Robot `agent`'s (v, w) towards `target`: [`K_TRACK`] x the way there, at most `speed`,
    /// plus the baseline's repulsion from robots closer than its `repulsion_range` (near
    /// surfaces, [`NEAR_ROBOT_RANGE_M`] beyond `eps_coll_m`) and from obstacle surfaces nearer
    /// than [`OBSTACLE_RANGE_M`]; turn towards the result, drive with its component along the
    /// heading.
    pub fn command(&self, poses: &[Pose], agent: usize, target: [f64; 2], speed: f64) -> (f64, f64) {
        let me = poses[agent];
        let mut u = [K_TRACK * (target[0] - me.x), K_TRACK * (target[1] - me.y)];
        let wanted = u[0].hypot(u[1]);
        if wanted > speed {
            u = [u[0] * speed / wanted, u[1] * speed / wanted];
        }
        let g = self.gains;
        let mut push_from = |q: [f64; 2], range: f64| {
            let (dx, dy) = (me.x - q[0], me.y - q[1]);
            let distance = dx.hypot(dy);
            if distance > 1e-9 && distance < range {
                let push = g.k_repulsion * (range - distance) / distance;
                u[0] += push * dx;
                u[1] += push * dy;
            }
        };
        // Near surfaces robots push each other less far, so as not to push one into a wall.
        let robot_range = if self.obstacles.is_clear([me.x, me.y], self.robot_radius + OPEN_M) {
            g.repulsion_range
        } else {
            g.repulsion_range.min(2.0 * self.robot_radius + NEAR_ROBOT_RANGE_M)
        };
        for (k, other) in poses.iter().enumerate() {
            if k != agent {
                push_from([other.x, other.y], robot_range);
            }
        }
        // Every surface in range pushes, so that a robot in a gap is held in its middle.
        let range = OBSTACLE_RANGE_M + self.robot_radius;
        self.obstacles
            .for_each_nearest_within([me.x, me.y], range, |surface| push_from(surface, range));
        let bearing = wrap_angle(u[1].atan2(u[0]) - me.theta);
        let speed = u[0].hypot(u[1]);
        let v = (speed * bearing.cos()).clamp(0.0, self.v_max);
        let w = (g.k_turn * bearing).clamp(-self.w_max, self.w_max);
        (v, w)
    }
}

/// The arc length of the first point of `path` (sampled every [`SAMPLE_M`]) nearer than
/// `clearance` to a surface; the path's length if none is.
fn first_narrow(path: &Polyline, obstacles: &Obstacles, clearance: f64) -> f64 {
    let length = path.length();
    let samples = (length / SAMPLE_M).ceil() as usize;
    (0..=samples)
        .map(|k| (k as f64 * SAMPLE_M).min(length))
        .find(|&s| !obstacles.is_clear(path.at(s), clearance))
        .unwrap_or(length)
}

/// The arc length from which a robot in file at the path's point may move out by `offset` to
/// its slot: from there to the end, the straight way out (sampled every [`SAMPLE_M`]) keeps
/// `clearance` from every surface and stays inside the arena. The path's length when even the
/// goal's is not clear (the robot then leaves the file at the goal, whose slots are clear).
fn leave_file_at(path: &Polyline, obstacles: &Obstacles, offset: [f64; 2], clearance: f64, arena_m: f64) -> f64 {
    let length = path.length();
    let way_out_is_clear = |s: f64| {
        let p = path.at(s);
        let slot = [p[0] + offset[0], p[1] + offset[1]];
        slot.iter().all(|v| (clearance..=arena_m - clearance).contains(v))
            && obstacles.segment_is_clear(p, slot, clearance)
    };
    let mut leave = length;
    let mut s = length;
    while s > 0.0 {
        let earlier = (s - SAMPLE_M).max(0.0);
        if !way_out_is_clear(earlier) {
            break;
        }
        leave = earlier;
        s = earlier;
    }
    if way_out_is_clear(length) { leave } else { length }
}

/// The planner as a privileged robot runs it on the true state, tick after tick: planned at the
/// first tick it is asked and again whenever the formation's slots change (a shape or team
/// change). Each oracle agent and the in-process players run this, so they plan alike.
#[derive(Debug, Clone, Default)]
pub struct Replanner {
    /// The plan and the slots it was made for.
    plan: Option<(Vec<[f64; 2]>, Planner)>,
}

impl Replanner {
    /// Every robot's (v, w) at `tick` for robots at `poses` bringing the formation of `slots`
    /// to `goal` around `obstacles` (see [`Planner::new`]), planning again first if the slots
    /// changed.
    #[allow(clippy::too_many_arguments)]
    pub fn commands(
        &mut self,
        poses: &[Pose],
        goal: [f64; 2],
        slots: &[[f64; 2]],
        obstacles: &Obstacles,
        tick: u32,
        env: &EnvConfig,
        gains: BaselineGains,
    ) -> &[(f64, f64)] {
        if !matches!(&self.plan, Some((planned, _)) if planned == slots) {
            self.plan = None;
        }
        let (_, planner) = self
            .plan
            .get_or_insert_with(|| (slots.to_vec(), Planner::new(poses, goal, slots, obstacles, env, gains)));
        planner.commands(poses, tick)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::obstacles::tests::rates_among_obstacles;
    use crate::obstacles::{Obstacle, ObstacleKind};
    use crate::world::World;

    /// Plays `episodes` episodes of `n` robots among obstacles of `kind` with every robot driven
    /// by the planner ([`rates_among_obstacles`]): success, robot collisions, obstacle hits, the
    /// episodes planned in file, and the mean time to plan, milliseconds.
    pub(crate) fn planner_rates(kind: ObstacleKind, n: usize, episodes: usize, seed: u64) -> [f64; 5] {
        let (mut column, mut planning) = (0usize, std::time::Duration::ZERO);
        let [success, collisions, hits] =
            rates_among_obstacles(EnvConfig::default(), kind, n, episodes, seed, |init, env| {
                let started = std::time::Instant::now();
                let mut planner = Planner::new(
                    &init.poses,
                    init.goal,
                    &init.slots,
                    &init.obstacles,
                    env,
                    BaselineGains::default(),
                );
                planning += started.elapsed();
                column += usize::from(planner.mode() == PlanMode::Column);
                move |world: &World| planner.commands(&world.poses, world.steps).to_vec()
            });
        let planning_ms = 1e3 * planning.as_secs_f64() / episodes as f64;
        [success, collisions, hits, column as f64 / episodes as f64, planning_ms]
    }

    #[test]
    fn the_planner_brings_small_teams_through_every_kind() {
        for kind in ObstacleKind::KINDS {
            let [success, collisions, hits, ..] = planner_rates(kind, 4, 20, 2000);
            assert!(success >= 0.9, "{kind}: success {success}");
            assert!(
                collisions + hits <= 0.05,
                "{kind}: collisions {collisions}, obstacle hits {hits}"
            );
        }
    }

    /// Prints the planner's rates by kind and team size:
    /// `cargo test --release -p formation-core planner_report -- --ignored --nocapture`.
    #[test]
    #[ignore = "a report, not a check"]
    fn planner_report() {
        for kind in ObstacleKind::KINDS {
            for n in [4, 8, 16] {
                let [success, collisions, hits, column, planning_ms] = planner_rates(kind, n, 100, 3000);
                println!(
                    "{kind:>8} N={n:>2}: success {success:.2}  robot collisions {collisions:.2}  obstacle hits {hits:.2}  in file {column:.2}  planning {planning_ms:.1} ms"
                );
            }
        }
    }

    /// Three robots facing +x in a small triangle, and the slots of that triangle.
    fn three_robots() -> (Vec<Pose>, [[f64; 2]; 3]) {
        let poses = [[2.0, 2.0], [2.5, 2.0], [2.25, 2.5]]
            .iter()
            .map(|p| Pose {
                x: p[0],
                y: p[1],
                theta: 0.0,
            })
            .collect();
        (poses, [[-0.25, -1.0 / 6.0], [0.25, -1.0 / 6.0], [0.0, 1.0 / 3.0]])
    }

    #[test]
    fn the_targets_wait_for_the_robots_they_drive_only() {
        let env = EnvConfig::default();
        let (poses, slots) = three_robots();
        // Robots 0 and 1 sit on their targets, robot 2 stays put: 30 ticks later its target
        // waited near it (within the keep-up and a step), unless the planner drives only 0 and 1.
        let run = |planner: &mut Planner| {
            let mut moved = poses.clone();
            for tick in 0..30 {
                let targets = planner.targets(&moved, tick).to_vec();
                for k in 0..2 {
                    (moved[k].x, moved[k].y) = (targets[k][0], targets[k][1]);
                }
            }
            let target = planner.targets(&moved, 30)[2];
            (target[0] - poses[2].x).hypot(target[1] - poses[2].y)
        };
        let step = PACE * env.v_max * env.dt_s;
        let plan = || {
            Planner::new(
                &poses,
                [6.0, 2.0],
                &slots,
                &Obstacles::none(),
                &env,
                BaselineGains::default(),
            )
        };
        let waited = run(&mut plan());
        assert!(waited <= KEEP_UP_OPEN_M + step + 1e-9, "{waited}");
        let mut some = plan();
        some.wait_only_for(&[true, true, false]);
        let moved_on = run(&mut some);
        assert!((moved_on - 30.0 * step).abs() < 1e-9, "{moved_on}");
    }

    #[test]
    fn an_open_arena_gives_a_straight_formation_path() {
        let env = EnvConfig::default();
        let (poses, slots) = three_robots();
        let planner = Planner::new(
            &poses,
            [6.0, 6.0],
            &slots,
            &Obstacles::none(),
            &env,
            BaselineGains::default(),
        );
        assert_eq!(planner.mode(), PlanMode::Formation);
        assert_eq!(planner.path().len(), 2, "{:?}", planner.path());
    }

    #[test]
    fn a_wall_with_a_narrow_gap_is_crossed_in_file_through_the_gap() {
        let env = EnvConfig::default();
        // Walls across the whole arena (11 m for 3 robots) at y = 5.
        let across = |gap: [f64; 2]| {
            Obstacles::new(vec![
                Obstacle::Wall {
                    a: [-0.1, 5.0],
                    b: [gap[0], 5.0],
                    thickness: 0.1,
                },
                Obstacle::Wall {
                    a: [gap[1], 5.0],
                    b: [env.effective_arena_m(3) + 0.1, 5.0],
                    thickness: 0.1,
                },
            ])
        };
        let poses: Vec<Pose> = [[4.0, 2.0], [5.0, 2.0], [4.5, 2.8]]
            .iter()
            .map(|p| Pose {
                x: p[0],
                y: p[1],
                theta: 1.5,
            })
            .collect();
        let slots = [[-0.5, -0.27], [0.5, -0.27], [0.0, 0.53]];
        let planner = Planner::new(
            &poses,
            [4.5, 8.0],
            &slots,
            &across([4.7, 5.3]),
            &env,
            BaselineGains::default(),
        );
        assert_eq!(planner.mode(), PlanMode::Column);
        let crossing = planner
            .path()
            .windows(2)
            .find(|leg| (leg[0][1] - 5.0) * (leg[1][1] - 5.0) <= 0.0)
            .expect("the path crosses the wall's line");
        let t = (5.0 - crossing[0][1]) / (crossing[1][1] - crossing[0][1]);
        let x = crossing[0][0] + t * (crossing[1][0] - crossing[0][0]);
        assert!((4.87..=5.13).contains(&x), "crosses at x = {x}");
        // A gap narrower than a robot with its least margin leaves no path at all.
        let shut = Planner::new(
            &poses,
            [4.5, 8.0],
            &slots,
            &across([5.0, 5.2]),
            &env,
            BaselineGains::default(),
        );
        assert_eq!(shut.mode(), PlanMode::Direct);
    }
}
