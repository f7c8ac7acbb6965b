//! The scripted baseline: a classical distance-based formation controller from the robot's own
//! local observation, mapped to unicycle commands. The yardstick for the learned policy.
//!
//! In the robot's frame (own position at the origin), with neighbours at q_j and desired
//! distances dbar_j:
//! * formation term: sum_j k_form (|q_j| - dbar_j) q_j / |q_j| (gradient of the edge errors);
//! * goal term, saturated at the top speed: k_goal (s - 0) towards the robot's own slot s when
//!   the observation model has one (exact at any N), else k_goal (g - c) with c = (q_1 + q_2) / 3
//!   the centroid of the robot's triangle (exact for N = 3 only);
//! * repulsion from any neighbour closer than `repulsion_range`, and from the nearest robot it
//!   does not track when the observation model reports one;
//! * among obstacles (a model with a range sensor, `slot_proximity_scan`): a potential field,
//!   each ray that reads r < `obstacle_range_m` pushing back along the ray by
//!   k_obstacle (`obstacle_range_m` - r), except rays whose hit is explained by a robot the
//!   robot tracks (its neighbours, the nearest other robot);
//! * four options among obstacles, off by default: circulation (every push that blocks the
//!   robot's aim also turns it the same way, left), yielding (the formation pull weakens near
//!   obstacles), braking (the forward speed falls with the free distance ahead) and detouring
//!   (a robot whose way to its target is blocked aims at the first clear way to the left of it,
//!   following a wall with the wall on its right until the target's way is clear again);
//! * a fifth, gap search (module [`crate::gap_search`]), for a wall with one gap: a robot whose
//!   way is barred by a straight wall sweeps along it until its scan shows the gap, lines up and
//!   drives through; one its brake stops by a hit beside its line (a gap's corner) turns away
//!   from it. It reads the window of observations, not only the newest
//!   ([`ScriptedBaseline::command_in`]).
//!
//! The desired velocity u is then tracked by a unicycle: turn towards u, drive forward with
//! the component of u along the heading (never backwards).

use crate::config::{ConfigError, EnvConfig};
use crate::gap_search;
use crate::observation::{Layout, ObservationView};
use crate::range_sensor::{nearest_in_path, rays, speed_before};
use formation_protocol::NEIGHBOURS;
use parry2d_f64::na::{self, Isometry2, Point2};
use parry2d_f64::query::details::distance_segment_segment;
use parry2d_f64::shape::Segment;
use serde::{Deserialize, Serialize};

/// Gains of the baseline, the `[baseline]` section (unknown keys rejected, missing ones keep
/// their defaults). The defaults were tuned on random 3-robot episodes (see the tests).
#[derive(Serialize, Deserialize, Debug, Clone, Copy, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct BaselineGains {
    /// Formation (edge error) gain, 1/s.
    pub k_form: f64,
    /// Goal gain, 1/s.
    pub k_goal: f64,
    /// Heading gain, 1/s.
    pub k_turn: f64,
    /// Neighbours closer than this push the robot away, metres.
    pub repulsion_range: f64,
    /// Repulsion gain, 1/s.
    pub k_repulsion: f64,
    /// Obstacle repulsion gain of the potential field, 1/s (per ray; not one of the five gains a
    /// gain schedule outputs).
    pub k_obstacle: f64,
    /// Rays that read less than this push the robot away, metres.
    pub obstacle_range_m: f64,
    /// Circulation gain, 1/s (0: off): every push from a robot or a ray whose hit lies towards
    /// the robot's aim also pushes sideways, a quarter turn to the left of it, by this gain
    /// times the push's shortfall times how squarely it blocks the aim. Every robot turns the
    /// same way around every obstacle and robot, so a disc straight ahead or a robot head-on
    /// is no longer a balance point.
    pub k_circulation: f64,
    /// How much a robot near obstacles lets go of its formation (0: not at all): the formation
    /// pull is divided by 1 + `obstacle_yield` x |obstacle push|, so robots may go through a
    /// gap in file.
    pub obstacle_yield: f64,
    /// Braking distance, metres (0: off): the forward speed is cut to v_max x (free distance
    /// ahead - [`crate::range_sensor::BRAKE_MARGIN_M`]) / `brake_range_m`, the free distance
    /// read from the rays whose hit lies in the robot's path (any hit, robot or obstacle).
    pub brake_range_m: f64,
    /// Detour reach, metres (0: off): when what the scan sees (see [`ScriptedBaseline`]'s
    /// `detour`) lies within this distance in the robot's way to its target, within its
    /// radius plus 0.1 m of the straight line, the robot aims instead at the first direction,
    /// turning left from the target, whose way is clear that far, and drops its formation pull
    /// while it does. Memoryless wall-following: it leaves a U the way it came in and goes
    /// round a wall's end, where the field alone settles at the bottom.
    pub detour_range_m: f64,
    /// Gap search band, metres (0: off): a robot whose way is barred by a straight wall looks
    /// for the wall's gap instead of detouring (module [`crate::gap_search`]): through a gap its
    /// scan shows, else sweeping along the wall, on in the way it moves and back once this far
    /// past the straight line through the goal. Needs a window of observations
    /// ([`ScriptedBaseline::command_in`]) to tell which way it moves.
    pub gap_search_m: f64,
}

impl Default for BaselineGains {
    fn default() -> Self {
        Self {
            k_form: 1.5,
            k_goal: 0.6,
            k_turn: 2.5,
            repulsion_range: 0.5,
            k_repulsion: 3.0,
            k_obstacle: 1.0,
            obstacle_range_m: 0.5,
            k_circulation: 0.0,
            obstacle_yield: 0.0,
            brake_range_m: 0.0,
            detour_range_m: 0.0,
            gap_search_m: 0.0,
        }
    }
}

/// How far from a tracked robot's centre a ray's hit still counts as that robot, beyond its
/// radius, metres (the robot moved within the tick; a hit on it is not an obstacle).
const TRACKED_HIT_SLACK_M: f64 = 0.1;

/// How many directions a detouring robot tries, evenly spread, turning left from its target's.
const DETOUR_DIRECTIONS: usize = 64;

/// Two neighbouring rays' hits closer than this are taken as one surface by a detouring
/// robot, metres (a wall read by two rays 22.5 degrees apart up to 2 m away; a gap narrower
/// than this is not taken).
const DETOUR_JOIN_M: f64 = 1.0;

/// The slack either side of a robot's path within which its brake reads hits when it searches
/// for gaps, metres: the collision monitor's, narrow enough for the narrowest gap.
const GAP_BRAKE_SLACK_M: f64 = 0.05;

/// A gap-searching robot's repulsion range, at most, metres: robots queue close at a gap.
const GAP_REPULSION_M: f64 = 0.4;

/// The range of each gain (in the order of [`BaselineGains::to_unit`]) that a gain-scheduling
/// actor's output spans, log-uniformly from -1 to 1: the default gains, the searched sets' and
/// the teachers' with room. A teacher outside is refused ([`BaselineGains::check_schedulable`]).
pub const SCHEDULED_GAIN_RANGES: [(f64, f64); 5] = [
    (0.2, 4.0),  // k_form
    (0.25, 1.6), // k_goal
    (0.5, 5.0),  // k_turn
    (0.25, 1.0), // repulsion_range
    (0.5, 6.0),  // k_repulsion
];

impl BaselineGains {
    /// The gains' names, in the order of [`BaselineGains::values`].
    pub const NAMES: [&str; 5] = ["k_form", "k_goal", "k_turn", "repulsion_range", "k_repulsion"];

    /// The five gains in one order (that of [`SCHEDULED_GAIN_RANGES`] and [`BaselineGains::NAMES`]).
    pub fn values(&self) -> [f64; 5] {
        [
            self.k_form,
            self.k_goal,
            self.k_turn,
            self.repulsion_range,
            self.k_repulsion,
        ]
    }

    /// The gains of five values in the order of [`BaselineGains::values`], with the default
    /// obstacle gains.
    pub fn from_values(values: [f64; 5]) -> Self {
        let [k_form, k_goal, k_turn, repulsion_range, k_repulsion] = values;
        Self {
            k_form,
            k_goal,
            k_turn,
            repulsion_range,
            k_repulsion,
            ..Self::default()
        }
    }

    /// The gains as a gain-scheduling actor outputs them: each in [-1, 1], log-uniform over its
    /// [`SCHEDULED_GAIN_RANGES`] (clamped to the range).
    pub fn to_unit(&self) -> [f32; 5] {
        let values = self.values();
        std::array::from_fn(|i| {
            let (lo, hi) = SCHEDULED_GAIN_RANGES[i];
            let t = (values[i].clamp(lo, hi) / lo).ln() / (hi / lo).ln();
            (2.0 * t - 1.0) as f32
        })
    }

    /// Refuses gains a gain-scheduling actor cannot output, naming the gain and its range.
    pub fn check_schedulable(&self) -> Result<(), String> {
        for ((name, value), (lo, hi)) in Self::NAMES.iter().zip(self.values()).zip(SCHEDULED_GAIN_RANGES) {
            if !(lo..=hi).contains(&value) {
                return Err(format!(
                    "{name} = {value} lies outside the gain schedule's range [{lo}, {hi}]"
                ));
            }
        }
        Ok(())
    }

    /// The gains of a gain-scheduling actor's output (five values in [-1, 1], clamped).
    pub fn from_unit(unit: &[f32]) -> Self {
        Self::from_values(std::array::from_fn(|i| {
            let (lo, hi) = SCHEDULED_GAIN_RANGES[i];
            let t = (f64::from(unit[i].clamp(-1.0, 1.0)) + 1.0) / 2.0;
            lo * (hi / lo).powf(t)
        }))
    }

    /// Refuses gains the controller cannot use, naming the field: every gain finite and >= 0,
    /// `k_turn` > 0 (a robot that never turns never arrives).
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (field, value, ok, reason) in [
            ("baseline.k_form", self.k_form, self.k_form >= 0.0, "must be >= 0"),
            ("baseline.k_goal", self.k_goal, self.k_goal >= 0.0, "must be >= 0"),
            ("baseline.k_turn", self.k_turn, self.k_turn > 0.0, "must be > 0"),
            (
                "baseline.repulsion_range",
                self.repulsion_range,
                self.repulsion_range >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.k_repulsion",
                self.k_repulsion,
                self.k_repulsion >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.k_obstacle",
                self.k_obstacle,
                self.k_obstacle >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.obstacle_range_m",
                self.obstacle_range_m,
                self.obstacle_range_m >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.k_circulation",
                self.k_circulation,
                self.k_circulation >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.brake_range_m",
                self.brake_range_m,
                self.brake_range_m >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.obstacle_yield",
                self.obstacle_yield,
                self.obstacle_yield >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.detour_range_m",
                self.detour_range_m,
                self.detour_range_m >= 0.0,
                "must be >= 0",
            ),
            (
                "baseline.gap_search_m",
                self.gap_search_m,
                self.gap_search_m >= 0.0,
                "must be >= 0",
            ),
        ] {
            if !(value.is_finite() && ok) {
                return Err(ConfigError::Invalid {
                    field,
                    value: value.to_string(),
                    reason,
                });
            }
        }
        Ok(())
    }
}

/// The baseline controller for one robot.
#[derive(Debug, Clone)]
pub struct ScriptedBaseline {
    gains: BaselineGains,
    layout: Layout,
    proximity_range: f64,
    v_max: f64,
    w_max: f64,
    scan_range: f64,
    robot_radius: f64,
}

impl ScriptedBaseline {
    /// A controller for the robot limits and the observation model in `env`.
    pub fn new(env: &EnvConfig, gains: BaselineGains) -> Self {
        Self {
            gains,
            layout: Layout::of(env.observation),
            proximity_range: env.proximity_range_m,
            v_max: env.v_max,
            w_max: env.w_max,
            scan_range: env.scan_range_m,
            robot_radius: crate::obstacles::robot_radius_m(env),
        }
    }

    /// The desired planar velocity in the robot's frame.
    pub fn desired_velocity(&self, obs: &[f32]) -> [f64; 2] {
        self.desired_velocity_after(obs, &[])
    }

    /// The desired planar velocity for the newest observation `obs`, given the window's
    /// `earlier` ones (flat, oldest first; gap search reads them).
    fn desired_velocity_after(&self, obs: &[f32], earlier: &[f32]) -> [f64; 2] {
        let g = self.gains;
        let view = ObservationView::new(self.layout, obs);
        let neighbours: [_; NEIGHBOURS] = std::array::from_fn(|k| view.neighbour(k));
        let target = match view.slot() {
            Some(slot) => slot,
            None => {
                // The centroid of the robot's triangle (itself at the origin).
                let share = (NEIGHBOURS + 1) as f64;
                let goal = view.goal();
                let centroid = neighbours.iter().fold([0.0, 0.0], |c, n| {
                    [c[0] + n.position[0] / share, c[1] + n.position[1] / share]
                });
                [goal[0] - centroid[0], goal[1] - centroid[1]]
            }
        };
        let nearest_other = view.nearest_other(self.proximity_range);
        let tracked = self.tracked(&view);
        let detour = view
            .scan()
            .filter(|_| g.detour_range_m > 0.0)
            .and_then(|scan| self.detour(scan, tracked.clone(), target));
        let searching = (g.gap_search_m > 0.0)
            .then(|| self.gap_search(&view, tracked.clone(), earlier))
            .flatten();
        let aim = searching.or(detour).unwrap_or_else(|| unit(target));
        let mut formation = [0.0f64; 2];
        let mut u = [0.0f64; 2];
        let robots = neighbours.iter().map(|n| (n.position, Some(n.desired)));
        for (q, desired) in robots.chain(nearest_other.map(|q| (q, None))) {
            let dist = q[0].hypot(q[1]).max(1e-6);
            let towards = [q[0] / dist, q[1] / dist];
            if let Some(desired) = desired {
                let pull = g.k_form * (dist - desired);
                formation[0] += pull * towards[0];
                formation[1] += pull * towards[1];
            }
            let range = if searching.is_some() {
                g.repulsion_range.min(GAP_REPULSION_M)
            } else {
                g.repulsion_range
            };
            let shortfall = (range - dist).max(0.0);
            let push = self.away(towards, g.k_repulsion * shortfall, shortfall, aim);
            u[0] += push[0];
            u[1] += push[1];
        }
        let mut formation_share = 1.0;
        if let Some(scan) = view.scan().filter(|_| searching.is_none()) {
            let push = self.obstacle_push(scan, tracked, aim);
            u[0] += push[0];
            u[1] += push[1];
            formation_share = 1.0 / (1.0 + g.obstacle_yield * push[0].hypot(push[1]));
        }
        if detour.is_some() {
            formation_share = 0.0;
        }
        let speed = (g.k_goal * target[0].hypot(target[1])).min(self.v_max);
        let to_goal = [speed * aim[0], speed * aim[1]];
        [
            u[0] + formation_share * formation[0] + to_goal[0],
            u[1] + formation_share * formation[1] + to_goal[1],
        ]
    }

    /// The push from something in the unit direction `towards`: `strength` straight away from
    /// it and, with circulation, `k_circulation` x `shortfall` sideways (a quarter turn to the
    /// left of `towards`), weighted by how squarely it blocks the unit `aim`.
    fn away(&self, towards: [f64; 2], strength: f64, shortfall: f64, aim: [f64; 2]) -> [f64; 2] {
        let blocking = (towards[0] * aim[0] + towards[1] * aim[1]).max(0.0);
        let sideways = self.gains.k_circulation * shortfall * blocking;
        [
            -strength * towards[0] - sideways * towards[1],
            -strength * towards[1] + sideways * towards[0],
        ]
    }

    /// Whether a ray's `hit` lies on a `tracked` robot (within its radius and some slack).
    fn explained(&self, hit: [f64; 2], mut tracked: impl Iterator<Item = [f64; 2]>) -> bool {
        tracked.any(|q| (hit[0] - q[0]).hypot(hit[1] - q[1]) < self.robot_radius + TRACKED_HIT_SLACK_M)
    }

    /// The robots the robot tracks, in its frame: its neighbours and the nearest other robot
    /// when the observation model reports one.
    fn tracked<'a>(&self, view: &ObservationView<'a>) -> impl Iterator<Item = [f64; 2]> + Clone + 'a {
        view.robots(self.proximity_range)
    }

    /// The potential field's push from the rays of `scan` (normalised ranges) that read less
    /// than `obstacle_range_m`, leaving out hits on a `tracked` robot; with circulation, also
    /// sideways around hits that block the unit `aim`.
    fn obstacle_push(&self, scan: &[f32], tracked: impl Iterator<Item = [f64; 2]> + Clone, aim: [f64; 2]) -> [f64; 2] {
        let g = self.gains;
        let mut push = [0.0f64; 2];
        for (towards, range) in rays(scan, self.scan_range) {
            if range >= g.obstacle_range_m || self.explained([range * towards[0], range * towards[1]], tracked.clone())
            {
                continue;
            }
            let shortfall = g.obstacle_range_m - range;
            let ray_push = self.away(towards, g.k_obstacle * shortfall, shortfall, aim);
            push[0] += ray_push[0];
            push[1] += ray_push[1];
        }
        push
    }

    /// With detouring, where to aim instead of the unit direction to `target` when the way
    /// there is blocked within the detour reach (or before the target, if nearer): the first of
    /// [`DETOUR_DIRECTIONS`] directions, turning left from the target's, whose way is clear
    /// that far. `None` when the target's way is clear, or when no way is.
    ///
    /// A way is blocked when it passes within the robot's radius + 0.1 m of what the scan sees.
    /// The rays are sparse, so each hit no `tracked` robot explains stands for a surface across
    /// its share of the scan (half the ray spacing either side, at its range), and two
    /// neighbouring rays' hits within [`DETOUR_JOIN_M`] of each other are joined (a wall between
    /// them is not read, and the gap between their hits must not look clear).
    fn detour(
        &self,
        scan: &[f32],
        tracked: impl Iterator<Item = [f64; 2]> + Clone,
        target: [f64; 2],
    ) -> Option<[f64; 2]> {
        let reach = self.gains.detour_range_m.min(target[0].hypot(target[1]));
        let half_spacing = std::f64::consts::PI / scan.len() as f64;
        let hits: Vec<Option<(f64, f64)>> = rays(scan, self.scan_range)
            .enumerate()
            .map(|(k, (towards, range))| {
                let hit = [range * towards[0], range * towards[1]];
                (range < self.scan_range && !self.explained(hit, tracked.clone()))
                    .then_some((2.0 * half_spacing * k as f64, range))
            })
            .collect();
        let at = |(angle, range): (f64, f64)| Point2::new(range * angle.cos(), range * angle.sin());
        let seen: Vec<Segment> = (0..hits.len())
            .filter_map(|k| hits[k])
            .map(|(angle, range)| Segment::new(at((angle - half_spacing, range)), at((angle + half_spacing, range))))
            .chain((0..hits.len()).filter_map(|k| {
                let (a, b) = (at(hits[k]?), at(hits[(k + 1) % hits.len()]?));
                (na::distance(&a, &b) < DETOUR_JOIN_M).then(|| Segment::new(a, b))
            }))
            .collect();
        let clearance = self.robot_radius + TRACKED_HIT_SLACK_M;
        let clear = |bearing: f64| {
            let path = Segment::new(
                Point2::origin(),
                Point2::new(reach * bearing.cos(), reach * bearing.sin()),
            );
            seen.iter()
                .all(|surface| distance_segment_segment(&Isometry2::identity(), &path, surface) >= clearance)
        };
        let bearing = target[1].atan2(target[0]);
        if clear(bearing) {
            return None;
        }
        (1..DETOUR_DIRECTIONS)
            .map(|k| bearing + std::f64::consts::TAU * k as f64 / DETOUR_DIRECTIONS as f64)
            .find(|&way| clear(way))
            .map(|way| [way.cos(), way.sin()])
    }

    /// With gap search, where a robot whose way is barred aims: on through a gap it is in
    /// ([`gap_search::in_a_gap`]), else by the straight wall its scan shows
    /// ([`gap_search::aim`]); `None` when it sees no such wall.
    fn gap_search(
        &self,
        view: &ObservationView,
        tracked: impl Iterator<Item = [f64; 2]> + Clone,
        earlier: &[f32],
    ) -> Option<[f64; 2]> {
        let scan = view.scan()?;
        let now = self.labelled_rays(scan, tracked.clone());
        let hits = gap_search::surface_hits(&now, self.scan_range);
        let goal = view.goal();
        if let Some(through) = gap_search::in_a_gap(&hits, goal) {
            return Some(through);
        }
        let wall = gap_search::Wall::seen(&hits, goal)?;
        let lateral = wall.lateral(goal);
        // Each earlier observation's lateral position and the gap it showed, if any, as the
        // gap's lateral position (the same in every frame), newest first.
        let then: Vec<Option<(f64, Option<f64>)>> = earlier
            .chunks_exact(self.layout.dim())
            .rev()
            .map(|obs| {
                let then = ObservationView::new(self.layout, obs);
                let rays_then = self.labelled_rays(then.scan()?, self.tracked(&then));
                let hits_then = gap_search::surface_hits(&rays_then, self.scan_range);
                let wall_then = gap_search::Wall::seen(&hits_then, then.goal())?;
                let lateral_then = wall_then.lateral(then.goal());
                let gap_then = wall_then.gap(&rays_then, self.scan_range, self.robot_radius);
                Some((lateral_then, gap_then.map(|centre| lateral_then + centre)))
            })
            .collect();
        // The newest scan's gap, else the newest earlier one's, from where the robot is now.
        let gap = wall
            .gap(&now, self.scan_range, self.robot_radius)
            .or_else(|| then.iter().flatten().find_map(|(_, gap)| gap.map(|at| at - lateral)));
        let lateral_before = then.get(gap_search::LOOK_BACK - 1).copied().flatten().map(|(l, _)| l);
        let robots: Vec<[f64; 2]> = tracked.collect();
        Some(gap_search::aim(
            &wall,
            gap,
            lateral,
            lateral_before,
            self.gains.gap_search_m,
            &robots,
        ))
    }

    /// Each ray of `scan` as its unit direction, the range it reads (metres) and whether its hit
    /// lies on a `tracked` robot.
    fn labelled_rays(
        &self,
        scan: &[f32],
        tracked: impl Iterator<Item = [f64; 2]> + Clone,
    ) -> Vec<([f64; 2], f64, bool)> {
        rays(scan, self.scan_range)
            .map(|(towards, range)| {
                (
                    towards,
                    range,
                    self.explained([range * towards[0], range * towards[1]], tracked.clone()),
                )
            })
            .collect()
    }

    /// The (v, w) command for the newest observation of `window` (H observations of the
    /// layout's size, oldest first, as [`crate::observation`]'s windows): gap search reads the
    /// older ones too; everything else reads the newest alone.
    pub fn command_in(&self, window: &[f32]) -> (f64, f64) {
        let dim = self.layout.dim();
        let newest = window.len() / dim - 1;
        let (earlier, obs) = window[..(newest + 1) * dim].split_at(newest * dim);
        self.command_after(obs, earlier)
    }

    /// The (v, w) command for the newest observation, clamped to the robot's limits.
    pub fn command(&self, obs: &[f32]) -> (f64, f64) {
        self.command_after(obs, &[])
    }

    fn command_after(&self, obs: &[f32], earlier: &[f32]) -> (f64, f64) {
        let u = self.desired_velocity_after(obs, earlier);
        let bearing = u[1].atan2(u[0]);
        let speed = u[0].hypot(u[1]);
        let mut v = (speed * bearing.cos()).clamp(0.0, self.v_max);
        let mut w = (self.gains.k_turn * bearing).clamp(-self.w_max, self.w_max);
        if self.gains.brake_range_m > 0.0
            && let Some(scan) = ObservationView::new(self.layout, obs).scan()
        {
            let searching = self.gains.gap_search_m > 0.0;
            let slack = if searching {
                GAP_BRAKE_SLACK_M
            } else {
                TRACKED_HIT_SLACK_M
            };
            let wanted = v;
            let ahead = nearest_in_path(scan, self.scan_range, self.robot_radius, slack);
            let free = ahead.map_or(self.scan_range, |(free, _)| free);
            v = v.min(speed_before(free, self.gains.brake_range_m, self.v_max));
            // A searching robot stopped by a hit its disc would pass (one beside its line, in
            // the slack, as a gap's side is to a robot in the mouth a little off its middle)
            // turns away from it until the way is clear, instead of waiting for good.
            if searching
                && wanted > 0.0
                && v == 0.0
                && let Some((_, hit)) = ahead
                && hit[1].abs() >= self.robot_radius
            {
                w = -hit[1].signum() * self.w_max;
            }
        }
        (v, w)
    }
}

/// The unit vector along `v` (zero for a zero vector).
fn unit(v: [f64; 2]) -> [f64; 2] {
    let length = v[0].hypot(v[1]);
    if length > 0.0 {
        [v[0] / length, v[1] / length]
    } else {
        [0.0, 0.0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{FormationShape, ObservationModel};
    use crate::formation::random_episode;
    use crate::task::Outcome;
    use crate::world::World;
    use formation_protocol::MAX_OBS_DIM;
    use rand::SeedableRng;
    use rand::rngs::StdRng;

    fn obs_with(neighbours: [[f32; 2]; 2], desired: [f32; 2], goal: [f32; 2]) -> [f32; MAX_OBS_DIM] {
        let mut obs = [0.0; MAX_OBS_DIM];
        for k in 0..2 {
            obs[k * 5] = neighbours[k][0];
            obs[k * 5 + 1] = neighbours[k][1];
            obs[k * 5 + 2] = 1.0;
            obs[k * 5 + 4] = desired[k];
        }
        obs[10] = goal[0];
        obs[11] = goal[1];
        obs
    }

    #[derive(Deserialize)]
    struct BaselineFile {
        baseline: BaselineGains,
    }

    #[test]
    fn gains_parse_from_a_baseline_section_and_bad_ones_are_refused_naming_the_field() {
        BaselineGains::default().validate().expect("defaults are valid");
        let parse = |text: &str| toml::from_str::<BaselineFile>(text).map(|file| file.baseline);
        let soft = parse("[baseline]\nk_form = 0.75\nk_goal = 0.3\nk_turn = 1.25\n").expect("parses");
        assert_eq!(
            soft,
            BaselineGains {
                k_form: 0.75,
                k_goal: 0.3,
                k_turn: 1.25,
                ..BaselineGains::default()
            },
            "missing keys keep their defaults"
        );
        assert!(parse("[baseline]\nk_gaol = 0.3\n").is_err(), "unknown keys are refused");
        for (text, field) in [
            ("k_form = -0.1", "baseline.k_form"),
            ("k_goal = nan", "baseline.k_goal"),
            ("k_turn = 0.0", "baseline.k_turn"),
            ("repulsion_range = -0.5", "baseline.repulsion_range"),
            ("k_repulsion = inf", "baseline.k_repulsion"),
        ] {
            let gains = parse(&format!("[baseline]\n{text}\n")).expect("parses");
            let message = gains.validate().expect_err(text).to_string();
            assert!(message.contains(field), "{text}: {message}");
        }
    }

    #[test]
    fn gains_survive_the_gain_scheduling_actor_s_unit_range() {
        for gains in [
            BaselineGains::default(),
            BaselineGains {
                k_form: 0.45,
                k_goal: 1.0706,
                k_turn: 1.3015,
                repulsion_range: 0.5084,
                k_repulsion: 1.58,
                ..BaselineGains::default()
            },
        ] {
            gains.check_schedulable().expect("inside the ranges");
            let unit = gains.to_unit();
            assert!(unit.iter().all(|u| u.abs() < 0.9), "{unit:?} is near the range's ends");
            let back = BaselineGains::from_unit(&unit);
            for (a, b) in back.values().into_iter().zip(gains.values()) {
                assert!((a / b - 1.0).abs() < 1e-5, "{back:?} vs {gains:?}");
            }
        }
        let too_fast = BaselineGains {
            k_goal: 3.0,
            ..BaselineGains::default()
        };
        let refusal = too_fast.check_schedulable().expect_err("outside the range");
        assert!(refusal.contains("k_goal = 3"), "{refusal}");
        let lowest = BaselineGains::from_unit(&[-5.0; 5]);
        assert_eq!(lowest.k_form, SCHEDULED_GAIN_RANGES[0].0);
        let highest = BaselineGains::from_unit(&[1.0; 5]);
        assert!((highest.k_repulsion - SCHEDULED_GAIN_RANGES[4].1).abs() < 1e-9);
    }

    #[test]
    fn drives_straight_to_a_goal_ahead_when_in_formation() {
        let env = paper_env();
        let baseline = ScriptedBaseline::new(&env, BaselineGains::default());
        // Neighbours behind-left and behind-right at their desired distance; goal straight ahead
        // of the triangle's centroid.
        let obs = obs_with(
            [[-1.0, 0.5], [-1.0, -0.5]],
            [1.25f32.sqrt(), 1.25f32.sqrt()],
            [2.0, 0.0],
        );
        let (v, w) = baseline.command(&obs);
        assert!((v - env.v_max).abs() < 1e-9, "full speed ahead, got v = {v}");
        assert!(w.abs() < 1e-6, "no turn, got w = {w}");
    }

    #[test]
    fn turns_in_place_towards_a_goal_behind() {
        let env = paper_env();
        let baseline = ScriptedBaseline::new(&env, BaselineGains::default());
        let obs = obs_with([[0.0, 1.0], [0.0, -1.0]], [1.0, 1.0], [-2.0, 0.5]);
        let (v, w) = baseline.command(&obs);
        assert_eq!(v, 0.0, "never drives backwards");
        assert!(
            w > 0.0 && (w - env.w_max).abs() < 1e-9,
            "turns left at full rate, got {w}"
        );
    }

    #[test]
    fn pulls_towards_a_neighbour_that_is_too_far() {
        let env = paper_env();
        let baseline = ScriptedBaseline::new(&env, BaselineGains::default());
        let obs = obs_with([[2.0, 0.0], [0.0, 1.0]], [1.0, 1.0], [2.0 / 3.0, 1.0 / 3.0]);
        let u = baseline.desired_velocity(&obs);
        assert!(u[0] > 1.0, "the stretched edge pulls forward: {u:?}");
    }

    /// Runs the baseline on every robot of random episodes in-process (no IPC): success and
    /// collision rates.
    pub(crate) fn success_rate(env: &EnvConfig, n: usize, episodes: usize, seed: u64) -> (f64, f64) {
        let baseline = ScriptedBaseline::new(env, BaselineGains::default());
        let mut rng = StdRng::seed_from_u64(seed);
        let (mut successes, mut collisions) = (0, 0);
        for _ in 0..episodes {
            let mut world = World::new(env, random_episode(n, env, &mut rng));
            loop {
                let commands: Vec<(f64, f64)> = (0..n)
                    .map(|agent| baseline.command(&world.observation(agent)))
                    .collect();
                match world.step(&commands).outcome {
                    Outcome::Running => continue,
                    Outcome::Success => successes += 1,
                    Outcome::Collision => collisions += 1,
                    Outcome::Timeout | Outcome::Aborted => {}
                }
                break;
            }
        }
        (successes as f64 / episodes as f64, collisions as f64 / episodes as f64)
    }

    /// The paper's 12-float observation (the layout `obs_with` writes), random shapes.
    fn paper_env() -> EnvConfig {
        env_with(ObservationModel::Paper, FormationShape::Random)
    }

    /// `FormationShape::KINDS` is every shape but `mixed` (which draws from it), as clap's
    /// derive lists them: a shape added to the enum and not to `KINDS` fails here.
    #[test]
    fn the_kinds_a_mixed_run_draws_from_are_every_other_shape() {
        let others: Vec<FormationShape> = <FormationShape as clap::ValueEnum>::value_variants()
            .iter()
            .copied()
            .filter(|shape| *shape != FormationShape::Mixed)
            .collect();
        assert_eq!(FormationShape::KINDS.as_slice(), others.as_slice());
    }

    pub(crate) fn env_with(observation: ObservationModel, shape: FormationShape) -> EnvConfig {
        EnvConfig {
            observation,
            shape,
            ..EnvConfig::default()
        }
    }

    /// A `slot_proximity_scan` observation: neighbours behind left and right at their desired
    /// distances, the slot (and goal) `slot` ahead, every ray clear but `hits` (ray, metres).
    fn scan_obs(slot: [f32; 2], hits: &[(usize, f32)]) -> (ScriptedBaseline, [f32; MAX_OBS_DIM]) {
        let env = env_with(ObservationModel::SlotProximityScan, FormationShape::Random);
        let layout = Layout::of(env.observation);
        let mut obs = [0.0; MAX_OBS_DIM];
        for (k, y) in [(0, 0.5), (1, -0.5)] {
            let at = layout.neighbour(k);
            obs[at..at + 5].copy_from_slice(&[-1.0, y, 1.0, 0.0, 1.25f32.sqrt()]);
        }
        obs[layout.goal()..layout.goal() + 2].copy_from_slice(&slot);
        let at = layout.slot().expect("a slot");
        obs[at..at + 2].copy_from_slice(&slot);
        let scan = layout.scan().expect("a scan");
        obs[scan..scan + 16].fill(1.0);
        for &(ray, metres) in hits {
            obs[scan + ray] = metres / env.scan_range_m as f32;
        }
        (ScriptedBaseline::new(&env, BaselineGains::default()), obs)
    }

    fn with_gains(baseline: &ScriptedBaseline, gains: BaselineGains) -> ScriptedBaseline {
        ScriptedBaseline {
            gains,
            ..baseline.clone()
        }
    }

    #[test]
    fn circulation_turns_left_around_a_hit_that_blocks_the_aim_only() {
        let (plain, ahead) = scan_obs([2.0, 0.0], &[(0, 0.3)]);
        let circulating = with_gains(
            &plain,
            BaselineGains {
                k_circulation: 2.0,
                ..BaselineGains::default()
            },
        );
        let [ux, uy] = plain.desired_velocity(&ahead);
        let [cx, cy] = circulating.desired_velocity(&ahead);
        // Shortfall 0.5 - 0.3 = 0.2, squarely in the aim's way: 2 x 0.2 to the left.
        assert!(
            (cx - ux).abs() < 1e-6 && (cy - uy - 0.4).abs() < 1e-6,
            "{ux},{uy} -> {cx},{cy}"
        );
        // A hit to the right of an aim straight ahead does not block it: no sideways push.
        let (_, right) = scan_obs([2.0, 0.0], &[(12, 0.3)]);
        assert_eq!(circulating.desired_velocity(&right), plain.desired_velocity(&right));
        // Every robot turns the same way: with the aim to the left, a hit there sends it left
        // of the ray, backwards in its frame.
        let (_, left) = scan_obs([0.0, 2.0], &[(4, 0.3)]);
        let [px, _] = plain.desired_velocity(&left);
        let [qx, _] = circulating.desired_velocity(&left);
        assert!((qx - px + 0.4).abs() < 1e-6, "{px} -> {qx}");
    }

    /// The scan of a wall across the way at `x` metres ahead, read by the rays that reach it.
    fn wall_ahead(x: f32) -> Vec<(usize, f32)> {
        [0usize, 1, 2, 14, 15]
            .into_iter()
            .map(|ray| {
                let angle = std::f32::consts::TAU * ray as f32 / 16.0;
                (ray, x / angle.cos())
            })
            .filter(|&(_, range)| range < 2.0)
            .collect()
    }

    #[test]
    fn detouring_aims_left_past_a_wall_s_end_and_not_between_two_of_its_hits() {
        let (plain, _) = scan_obs([3.0, 0.0], &[]);
        let detouring = with_gains(
            &plain,
            BaselineGains {
                detour_range_m: 2.0,
                ..BaselineGains::default()
            },
        );
        let speed = plain.v_max;
        let bearing = |u: [f64; 2]| u[1].atan2(u[0]).to_degrees();
        // A wall 1.8 m ahead is read by rays 0 and +-1 only, hits 0.75 m apart: joined, the way
        // between them is blocked. The hit at 22.5 degrees stands for the surface up to 33.75
        // degrees; the first clear way (of 64, from straight ahead to the left) passes 0.2 m
        // (radius + slack) beyond that: 8 x 5.625 degrees.
        let (_, far_wall) = scan_obs([3.0, 0.0], &wall_ahead(1.8));
        let u = detouring.desired_velocity(&far_wall);
        assert!((bearing(u) - 45.0).abs() < 1e-6, "{u:?}");
        assert!(
            (u[0].hypot(u[1]) - speed).abs() < 1e-9,
            "at the goal term's speed: {u:?}"
        );
        // The plain field aims straight through it (the wall is beyond obstacle_range_m).
        assert!(bearing(plain.desired_velocity(&far_wall)).abs() < 1e-6);
        // A wall 1 m ahead, read up to 45 degrees (taken to 56.25): the first way clear of that.
        let (_, near_wall) = scan_obs([3.0, 0.0], &wall_ahead(1.0));
        let turned = bearing(detouring.desired_velocity(&near_wall));
        assert!((turned - 67.5).abs() < 1e-6, "{turned}");
        // The same wall beyond the slot does not matter, nor does a hit beside the way.
        let (_, before_the_slot) = scan_obs([0.6, 0.0], &wall_ahead(1.0));
        assert_eq!(
            detouring.desired_velocity(&before_the_slot),
            plain.desired_velocity(&before_the_slot)
        );
        let (_, beside) = scan_obs([3.0, 0.0], &[(4, 0.3)]);
        assert_eq!(detouring.desired_velocity(&beside), plain.desired_velocity(&beside));
    }

    #[test]
    fn braking_stops_short_of_a_hit_in_the_robot_s_path_and_not_of_one_beside_it() {
        let (plain, _) = scan_obs([2.0, 0.0], &[]);
        let braking = with_gains(
            &plain,
            BaselineGains {
                brake_range_m: 0.3,
                ..BaselineGains::default()
            },
        );
        let v_max = plain.v_max;
        let (_, clear) = scan_obs([2.0, 0.0], &[]);
        assert_eq!(braking.command(&clear), plain.command(&clear));
        assert!(
            (plain.command(&clear).0 - v_max).abs() < 1e-9,
            "drives at full speed when clear"
        );
        // A hit 0.3 m ahead: 0.3 - 0.1 (radius) - 0.05 (margin) = 0.15 m free, half of 0.3.
        let (_, ahead) = scan_obs([2.0, 0.0], &[(0, 0.3)]);
        assert!(
            (braking.command(&ahead).0 - 0.5 * v_max).abs() < 1e-6,
            "{:?}",
            braking.command(&ahead)
        );
        // At its margin it stops, whatever the hit is (a robot too).
        let (_, touching) = scan_obs([2.0, 0.0], &[(0, 0.15)]);
        assert!(braking.command(&touching).0 < 1e-6, "{:?}", braking.command(&touching));
        // A hit straight to the left, or ahead-left beyond its width and slack, is not in its
        // path.
        let (_, beside) = scan_obs([2.0, 0.0], &[(4, 0.15), (2, 0.3)]);
        assert_eq!(braking.command(&beside).0, plain.command(&beside).0);
    }

    #[test]
    fn a_searching_robot_stopped_by_a_hit_beside_its_line_turns_away_from_it() {
        let (plain, _) = scan_obs([2.0, 0.0], &[]);
        // No push from the hits: the turn is the brake's alone.
        let braking = BaselineGains {
            brake_range_m: 0.3,
            k_obstacle: 0.0,
            ..BaselineGains::default()
        };
        let searching = with_gains(
            &plain,
            BaselineGains {
                gap_search_m: 1.8,
                ..braking
            },
        );
        let w_max = plain.w_max;
        // 0.17 m out on the ray 45 degrees left: 0.12 m beside the robot's line (past its
        // radius, within the slack) and 0.02 m from its disc ahead: it stops.
        let (_, left) = scan_obs([2.0, 0.0], &[(2, 0.17)]);
        assert_eq!(searching.command(&left), (0.0, -w_max), "turns right, away from it");
        let (_, right) = scan_obs([2.0, 0.0], &[(14, 0.17)]);
        assert_eq!(searching.command(&right), (0.0, w_max), "turns left, away from it");
        // Without gap search it waits, facing its goal.
        assert_eq!(with_gains(&plain, braking).command(&left), (0.0, 0.0));
        // A hit its disc would reach, straight ahead, is no reason to turn.
        let (_, ahead) = scan_obs([2.0, 0.0], &[(0, 0.14)]);
        assert_eq!(searching.command(&ahead), (0.0, 0.0));
    }

    #[test]
    fn yielding_divides_the_formation_pull_by_the_obstacle_push() {
        // Neighbours 0.5 m too far: a formation pull; a hit ahead at 0.3 m pushes back by 0.2.
        let layout = Layout::of(ObservationModel::SlotProximityScan);
        let too_far = |(baseline, mut obs): (ScriptedBaseline, [f32; MAX_OBS_DIM])| {
            for k in 0..NEIGHBOURS {
                obs[layout.neighbour(k) + 4] -= 0.5;
            }
            (baseline, obs)
        };
        let (plain, obs) = too_far(scan_obs([2.0, 0.0], &[(0, 0.3)]));
        let (_, clear) = too_far(scan_obs([2.0, 0.0], &[]));
        let yielding = with_gains(
            &plain,
            BaselineGains {
                obstacle_yield: 5.0,
                ..BaselineGains::default()
            },
        );
        assert_eq!(yielding.desired_velocity(&clear), plain.desired_velocity(&clear));
        let without_formation = with_gains(
            &plain,
            BaselineGains {
                k_form: 0.0,
                ..BaselineGains::default()
            },
        );
        let rest = without_formation.desired_velocity(&obs);
        let [fx, _] = plain.desired_velocity(&obs);
        let [yx, _] = yielding.desired_velocity(&obs);
        // |push| = 0.2: the pull is divided by 1 + 5 x 0.2 = 2.
        assert!((yx - rest[0] - (fx - rest[0]) / 2.0).abs() < 1e-6, "{fx} {yx} {rest:?}");
    }

    /// The `[baseline]` gains of a shipped config file.
    fn shipped_gains(text: &str) -> BaselineGains {
        toml::from_str::<BaselineFile>(text)
            .expect("a [baseline] section")
            .baseline
    }

    /// Success, robot collisions and obstacle hits of the field with `gains` among forests,
    /// every robot reading its own `slot_proximity_scan` observation.
    fn forest_rates(gains: BaselineGains, n: usize, episodes: usize, seed: u64) -> [f64; 3] {
        rates_among(crate::obstacles::ObstacleKind::Forest, gains, n, episodes, seed)
    }

    /// The same among obstacles of `kind`.
    fn rates_among(
        kind: crate::obstacles::ObstacleKind,
        gains: BaselineGains,
        n: usize,
        episodes: usize,
        seed: u64,
    ) -> [f64; 3] {
        use crate::obstacles::tests::rates_among_obstacles;
        let base = env_with(ObservationModel::SlotProximityScan, FormationShape::Random);
        rates_among_obstacles(base, kind, n, episodes, seed, |_, env| {
            let field = ScriptedBaseline::new(env, gains);
            move |world: &World| {
                (0..world.n_agents())
                    .map(|i| field.command(&world.observation(i)))
                    .collect()
            }
        })
    }

    #[test]
    fn the_circulating_braking_field_hits_no_obstacle_and_gets_through_more_forests() {
        let tuned = shipped_gains(include_str!("../../configs/potential-field-forest.toml"));
        let circulating = shipped_gains(include_str!("../../configs/potential-field-circulating-forest.toml"));
        let [tuned_success, _, tuned_hits] = forest_rates(tuned, 4, 40, 2000);
        let [success, _, hits] = forest_rates(circulating, 4, 40, 2000);
        assert_eq!(hits, 0.0, "the braking field touched an obstacle");
        assert!(tuned_hits > 0.0, "the plain field's hits are what braking removes");
        assert!(
            success > tuned_success + 0.1,
            "circulating {success} against tuned {tuned_success}"
        );
    }

    #[test]
    fn the_detouring_field_leaves_the_trap_where_the_circulating_field_stays_in_it() {
        use crate::obstacles::ObstacleKind::Trap;
        let circulating = shipped_gains(include_str!("../../configs/potential-field-circulating-trap.toml"));
        let detouring = shipped_gains(include_str!("../../configs/potential-field-detouring-trap.toml"));
        assert_eq!(circulating.detour_range_m, 0.0, "the circulating field does not detour");
        let [stuck, ..] = rates_among(Trap, circulating, 8, 20, 2000);
        let [success, robots, hits] = rates_among(Trap, detouring, 8, 20, 2000);
        assert_eq!((robots, hits), (0.0, 0.0), "the detouring field collided");
        assert!(
            success >= stuck + 0.5,
            "detouring {success} against circulating {stuck}"
        );
    }

    #[test]
    fn baseline_solves_three_robot_episodes_on_the_papers_observation() {
        let (success, collision) = success_rate(&paper_env(), 3, 200, 11);
        assert!(success >= 0.9, "baseline success {success}");
        assert_eq!(collision, 0.0);
    }

    #[test]
    fn baseline_with_slots_solves_every_shape_at_6_and_16_robots() {
        for shape in FormationShape::KINDS {
            for n in [6, 16] {
                let env = env_with(ObservationModel::SlotProximity, shape);
                let (success, collision) = success_rate(&env, n, 40, 5);
                assert!(success >= 0.9, "{shape:?} N = {n}: success {success}");
                assert_eq!(collision, 0.0, "{shape:?} N = {n}");
            }
        }
    }
}

#[cfg(test)]
mod report {
    use super::tests::{env_with, success_rate};
    use crate::config::FormationShape;
    use crate::observation::MODELS;

    /// Prints the baseline's in-process success rates for every observation model, shape and
    /// size: `cargo test --release -p formation-core baseline_report -- --ignored --nocapture`.
    #[test]
    #[ignore = "a report, not a check"]
    fn baseline_report() {
        for model in MODELS {
            for shape in FormationShape::KINDS {
                let cells: Vec<String> = [3, 4, 6, 8, 12, 16, 32, 64]
                    .iter()
                    .map(|&n| {
                        let (success, collision) = success_rate(&env_with(model, shape), n, 100, 1000);
                        format!("N={n} {success:.2}/{collision:.2}")
                    })
                    .collect();
                println!("{:>14} {:>6}: {}", model.as_str(), shape.as_str(), cells.join("  "));
            }
        }
    }
}
