//! Obstacles: discs and thick wall segments drawn per episode between the start and the goal
//! (the `[obstacles]` section), one file per kind (`forest`, `passage`, `trap`), and the
//! geometry every consumer asks of them (distance to the nearest surface, a robot's hit, ray
//! casts).
//!
//! The geometry is [parry](https://parry.rs)'s, in its f64 build (`parry2d-f64`): the task is f64
//! throughout, so a robot's clearance is decided at the precision of its pose. A disc is a
//! parry `Ball`; a wall is a `Cuboid` (a rectangle whose centre line runs from `a` to `b`,
//! `thickness` across, with flat ends: a gap between two walls is exactly the distance between
//! their ends).
//!
//! Draws come from a stream of their own ([`obstacle_seed`]), so obstacles change no start, goal
//! or shape, and every controller of a run meets the same obstacles. Every start position and
//! goal slot is clear of every surface by at least [`clearance_m`] (2 x `eps_coll_m`). A new kind
//! is a file here, a variant of [`ObstacleKind`] (and of [`ObstacleKind::KINDS`]), an arm in
//! [`draw`], [`min_goal_distance_m`] and [`episode_steps_with_obstacles`], and its keys in
//! [`ObstacleConfig`].

mod forest;
mod passage;
mod trap;

use std::fmt;
use std::str::FromStr;

use parry2d_f64::na::{Isometry2, Point2, Vector2};
use parry2d_f64::query::{PointQuery, Ray, RayCast};
use parry2d_f64::shape::{Ball, Cuboid, Segment};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use serde::{Deserialize, Serialize};

use formation_protocol::MAX_OBSTACLES;
use formation_protocol::wire::{OBSTACLE_DISC, OBSTACLE_WALL, ObstaclesMsg};

use crate::config::{ConfigError, EnvConfig};
use crate::reality::Spread;

/// What an episode's obstacles are.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(any(test, feature = "clap"), derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[cfg_attr(any(test, feature = "clap"), value(rename_all = "lowercase"))]
pub enum ObstacleKind {
    /// No obstacles: the open arena.
    #[default]
    None,
    /// Discs scattered between the start and the goal.
    Forest,
    /// A wall across the whole arena with one narrow gap.
    Passage,
    /// A U on the straight line to the goal, opening towards the start.
    Trap,
    /// Every episode one of `forest`, `passage` and `trap`, drawn uniformly.
    Mixed,
}

impl ObstacleKind {
    /// The code `ObstaclesMsg::kind` carries: 0 none, 1 forest, 2 passage, 3 trap (4 mixed,
    /// which no episode plays).
    pub fn code(self) -> u32 {
        self as u32
    }

    /// The kind of a code written by [`ObstacleKind::code`].
    pub fn from_code(code: u32) -> Option<Self> {
        Self::ALL.into_iter().find(|kind| kind.code() == code)
    }

    /// The kinds a `mixed` episode draws from.
    pub const KINDS: [ObstacleKind; 3] = [Self::Forest, Self::Passage, Self::Trap];

    /// Every kind, in the order of the enum.
    pub const ALL: [ObstacleKind; 5] = [Self::None, Self::Forest, Self::Passage, Self::Trap, Self::Mixed];

    /// The name used in configs, flags and reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Forest => "forest",
            Self::Passage => "passage",
            Self::Trap => "trap",
            Self::Mixed => "mixed",
        }
    }
}

impl fmt::Display for ObstacleKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A name that is no [`ObstacleKind`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown obstacle kind {0:?}: expected one of none, forest, passage, trap, mixed")]
pub struct UnknownObstacleKind(pub String);

impl FromStr for ObstacleKind {
    type Err = UnknownObstacleKind;

    fn from_str(name: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|kind| kind.as_str() == name)
            .ok_or_else(|| UnknownObstacleKind(name.to_string()))
    }
}

/// The `[obstacles]` section (unknown keys rejected, missing ones keep their defaults). Each
/// range is a number or `[lo, hi]`, drawn uniformly per episode (as `[reality]`'s keys).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(default, deny_unknown_fields)]
pub struct ObstacleConfig {
    /// `none` (the default: today's open episodes exactly), `forest`, `passage`, `trap` or
    /// `mixed`.
    pub kind: ObstacleKind,
    /// `forest`: each disc's radius, metres.
    pub forest_radius_m: Spread,
    /// `forest`: the fraction of the corridor between the start and the goal the discs cover
    /// (the corridor is as long as the way and as wide as the formation plus 1 m each side).
    pub forest_density: Spread,
    /// `passage`: the gap's width between the two walls' ends, metres (a robot is a disc of
    /// radius `eps_coll_m / 2`: the default lets one or at most two abreast through).
    pub gap_width_m: Spread,
    /// `passage`, `trap`: the walls' thickness, metres.
    pub wall_thickness_m: Spread,
    /// `trap`: the U's inner depth from its mouth to its back wall, metres.
    pub trap_depth_m: Spread,
    /// `trap`: how much wider than the formation the U is inside, on each side, metres.
    pub trap_margin_m: Spread,
    /// Each robot's collision monitor (as a mobile base's safety layer, e.g. Nav2's
    /// `collision_monitor`): at its motors, the forward speed is capped at `v_max` times the
    /// free distance its own scan shows ahead (less a margin) over this range, metres; 0 is
    /// off. It reads the scan the robot is told, so it acts only for a robot that observes its
    /// range sensor (`slot_proximity_scan`, as every controller among obstacles does but the
    /// open-arena model), whatever drives it ([`crate::stepper`]). Default 0.5.
    pub collision_monitor_m: f64,
    /// Each robot's recovery behaviour ([`crate::recovery`], as a mobile base's progress checker
    /// and recovery behaviours, e.g. Nav2's): a robot that has come less than 0.05 m closer to
    /// its slot over 30 ticks, more than 1 m from it, with its scan's nearest hit within 0.5 m,
    /// follows that surface (left round first, then alternating) for at most this many ticks,
    /// handing back once the way to its slot reads 1 m clear. It reads what the robot is told
    /// and acts at its motors before the collision monitor, whatever drives it, for robots that
    /// observe their range sensor. 0 (the default) is off.
    pub recovery_ticks: u32,
}

impl Default for ObstacleConfig {
    fn default() -> Self {
        Self {
            kind: ObstacleKind::None,
            forest_radius_m: Spread::range(0.15, 0.35),
            forest_density: Spread::range(0.08, 0.15),
            gap_width_m: Spread::range(0.35, 0.5),
            wall_thickness_m: Spread::fixed(0.1),
            trap_depth_m: Spread::range(1.0, 1.5),
            trap_margin_m: Spread::range(0.3, 0.6),
            collision_monitor_m: 0.5,
            recovery_ticks: 0,
        }
    }
}

/// Refuses a spread unless both ends are finite, `lo <= hi` and `ok` holds for both, naming the
/// key (`Spread`'s own check is private to `[reality]`).
fn check_spread(
    spread: Spread,
    field: &'static str,
    ok: impl Fn(f64) -> bool,
    reason: &'static str,
) -> Result<(), ConfigError> {
    let reason = if !(spread.lo.is_finite() && spread.hi.is_finite()) {
        "must be finite"
    } else if spread.lo > spread.hi {
        "needs lo <= hi"
    } else if !(ok(spread.lo) && ok(spread.hi)) {
        reason
    } else {
        return Ok(());
    };
    Err(ConfigError::Invalid {
        field,
        value: spread.to_string(),
        reason,
    })
}

/// One value of `spread`; draws from `rng` only when `lo < hi`.
fn draw_spread(spread: Spread, rng: &mut StdRng) -> f64 {
    if spread.lo < spread.hi {
        rng.random_range(spread.lo..=spread.hi)
    } else {
        spread.lo
    }
}

impl ObstacleConfig {
    /// Refuses values no draw can honour, naming the key: radii, widths, depths and thicknesses
    /// > 0, a density in (0, 0.5], a margin >= 0, and `lo <= hi` everywhere.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let positive = |v: f64| v > 0.0;
        check_spread(
            self.forest_radius_m,
            "obstacles.forest_radius_m",
            positive,
            "must be > 0",
        )?;
        check_spread(
            self.forest_density,
            "obstacles.forest_density",
            |v| v > 0.0 && v <= 0.5,
            "must be in (0, 0.5]",
        )?;
        check_spread(self.gap_width_m, "obstacles.gap_width_m", positive, "must be > 0")?;
        check_spread(
            self.wall_thickness_m,
            "obstacles.wall_thickness_m",
            positive,
            "must be > 0",
        )?;
        check_spread(self.trap_depth_m, "obstacles.trap_depth_m", positive, "must be > 0")?;
        check_spread(
            self.trap_margin_m,
            "obstacles.trap_margin_m",
            |v| v >= 0.0,
            "must be >= 0",
        )?;
        if self.collision_monitor_m.is_finite() && self.collision_monitor_m >= 0.0 {
            Ok(())
        } else {
            Err(ConfigError::Invalid {
                field: "obstacles.collision_monitor_m",
                value: self.collision_monitor_m.to_string(),
                reason: "must be >= 0 (0 is off)",
            })
        }
    }
}

/// One obstacle, world frame, metres.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum Obstacle {
    /// A disc.
    Disc {
        /// Its centre.
        centre: [f64; 2],
        /// Its radius.
        radius: f64,
    },
    /// A rectangle whose centre line runs from `a` to `b` (flat ends), `thickness` across.
    Wall {
        /// One end of the centre line.
        a: [f64; 2],
        /// The other end.
        b: [f64; 2],
        /// Its full thickness.
        thickness: f64,
    },
}

/// An obstacle as parry's shape at its place, with a circle around it for culling.
#[derive(Debug, Clone)]
struct Placed {
    place: Isometry2<f64>,
    solid: Solid,
    /// Centre of the bounding circle.
    centre: [f64; 2],
    /// Radius of the bounding circle.
    bound: f64,
}

#[derive(Debug, Clone)]
enum Solid {
    Ball(Ball),
    Cuboid(Cuboid),
}

impl Placed {
    fn new(obstacle: &Obstacle) -> Self {
        match *obstacle {
            Obstacle::Disc { centre, radius } => Self {
                place: Isometry2::translation(centre[0], centre[1]),
                solid: Solid::Ball(Ball::new(radius)),
                centre,
                bound: radius,
            },
            Obstacle::Wall { a, b, thickness } => {
                let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
                let half_length = 0.5 * dx.hypot(dy);
                let centre = [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])];
                Self {
                    place: Isometry2::new(Vector2::new(centre[0], centre[1]), dy.atan2(dx)),
                    solid: Solid::Cuboid(Cuboid::new(Vector2::new(half_length, 0.5 * thickness))),
                    centre,
                    bound: half_length.hypot(0.5 * thickness),
                }
            }
        }
    }

    /// Distance from `p` to the surface, 0 inside.
    fn distance(&self, p: [f64; 2]) -> f64 {
        let point = Point2::new(p[0], p[1]);
        match &self.solid {
            Solid::Ball(ball) => ball.distance_to_point(&self.place, &point, true),
            Solid::Cuboid(cuboid) => cuboid.distance_to_point(&self.place, &point, true),
        }
    }

    /// A lower bound of [`Placed::distance`] from the bounding circle.
    fn distance_bound(&self, p: [f64; 2]) -> f64 {
        (p[0] - self.centre[0]).hypot(p[1] - self.centre[1]) - self.bound
    }

    /// Distance along the unit `ray` to the surface, if under `max` (0 from inside).
    fn cast(&self, ray: &Ray, max: f64) -> Option<f64> {
        match &self.solid {
            Solid::Ball(ball) => ball.cast_ray(&self.place, ray, max, true),
            Solid::Cuboid(cuboid) => cuboid.cast_ray(&self.place, ray, max, true),
        }
    }

    /// Distance from the segment a-b to the surface (0 when they touch).
    fn segment_distance(&self, a: [f64; 2], b: [f64; 2]) -> f64 {
        let segment = Segment::new(Point2::new(a[0], a[1]), Point2::new(b[0], b[1]));
        let distance = match &self.solid {
            Solid::Ball(ball) => parry2d_f64::query::distance(&Isometry2::identity(), &segment, &self.place, ball),
            Solid::Cuboid(cuboid) => {
                parry2d_f64::query::distance(&Isometry2::identity(), &segment, &self.place, cuboid)
            }
        };
        // Both pairs are supported; should one not be, the segment counts as touching.
        distance.unwrap_or(0.0)
    }
}

/// An episode's obstacles, with their shapes ready for queries.
#[derive(Debug, Clone, Default)]
pub struct Obstacles {
    list: Vec<Obstacle>,
    placed: Vec<Placed>,
}

impl PartialEq for Obstacles {
    fn eq(&self, other: &Self) -> bool {
        self.list == other.list
    }
}

/// No obstacles, for a scene of the open arena that owns none.
pub static NO_OBSTACLES: Obstacles = Obstacles {
    list: Vec::new(),
    placed: Vec::new(),
};

impl Obstacles {
    /// No obstacles (kind `none`).
    pub fn none() -> Self {
        Self::default()
    }

    /// These obstacles.
    pub fn new(list: Vec<Obstacle>) -> Self {
        let placed = list.iter().map(Placed::new).collect();
        Self { list, placed }
    }

    /// The obstacles whose surface lies within `range` of `p` (what a sensor of that range
    /// there could see of them; a wall is kept whole).
    pub fn within(&self, p: [f64; 2], range: f64) -> Self {
        Self::new(
            self.list
                .iter()
                .zip(&self.placed)
                .filter(|(_, placed)| placed.distance_bound(p) < range && placed.distance(p) < range)
                .map(|(obstacle, _)| *obstacle)
                .collect(),
        )
    }

    /// The obstacles an `ObstaclesMsg` carries (its first `count`).
    pub fn from_wire(msg: &ObstaclesMsg) -> Self {
        let count = (msg.count as usize).min(MAX_OBSTACLES);
        let list = msg.shapes[..count]
            .iter()
            .zip(&msg.values[..count])
            .filter_map(|(&shape, v)| match shape {
                OBSTACLE_DISC => Some(Obstacle::Disc {
                    centre: [v[0], v[1]],
                    radius: v[2],
                }),
                OBSTACLE_WALL => Some(Obstacle::Wall {
                    a: [v[0], v[1]],
                    b: [v[2], v[3]],
                    thickness: v[4],
                }),
                _ => None,
            })
            .collect();
        Self::new(list)
    }

    /// Writes the obstacles into `msg` (count, shapes, values; the rest zeroed). A draw never
    /// makes more than `MAX_OBSTACLES`; should a list have more, the first are written.
    pub fn write_wire(&self, msg: &mut ObstaclesMsg) {
        msg.count = self.list.len().min(MAX_OBSTACLES) as u32;
        msg.shapes = [0; MAX_OBSTACLES];
        msg.values = [[0.0; 5]; MAX_OBSTACLES];
        for ((shape, values), obstacle) in msg.shapes.iter_mut().zip(&mut msg.values).zip(&self.list) {
            (*shape, *values) = match *obstacle {
                Obstacle::Disc { centre, radius } => (OBSTACLE_DISC, [centre[0], centre[1], radius, 0.0, 0.0]),
                Obstacle::Wall { a, b, thickness } => (OBSTACLE_WALL, [a[0], a[1], b[0], b[1], thickness]),
            };
        }
    }

    /// The obstacles, as drawn.
    pub fn list(&self) -> &[Obstacle] {
        &self.list
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// Distance from `p` to the nearest surface (0 inside an obstacle, infinite without any).
    pub fn distance(&self, p: [f64; 2]) -> f64 {
        self.placed
            .iter()
            .map(|placed| placed.distance(p))
            .fold(f64::INFINITY, f64::min)
    }

    /// Whether a robot of radius `robot_radius` centred at `p` touches an obstacle: its centre
    /// lies within `robot_radius` of a surface (or inside).
    pub fn hits_robot(&self, p: [f64; 2], robot_radius: f64) -> bool {
        !self.is_clear(p, robot_radius)
    }

    /// Whether `p` lies at least `clearance` from every surface.
    pub fn is_clear(&self, p: [f64; 2], clearance: f64) -> bool {
        self.placed
            .iter()
            .all(|placed| placed.distance_bound(p) >= clearance || placed.distance(p) >= clearance)
    }

    /// Calls `f` with each obstacle's point nearest `p`, for those nearer than `range` (`p`
    /// itself from inside).
    pub fn for_each_nearest_within(&self, p: [f64; 2], range: f64, mut f: impl FnMut([f64; 2])) {
        let point = Point2::new(p[0], p[1]);
        for placed in self.placed.iter().filter(|placed| placed.distance_bound(p) < range) {
            let projection = match &placed.solid {
                Solid::Ball(ball) => ball.project_point(&placed.place, &point, true),
                Solid::Cuboid(cuboid) => cuboid.project_point(&placed.place, &point, true),
            };
            let q = [projection.point.x, projection.point.y];
            if (q[0] - p[0]).hypot(q[1] - p[1]) < range {
                f(q);
            }
        }
    }

    /// Distance from `origin` along `direction` (unit length) to the nearest surface, if under
    /// `max` (0 from inside an obstacle).
    pub fn cast_ray(&self, origin: [f64; 2], direction: [f64; 2], max: f64) -> Option<f64> {
        let ray = Ray::new(
            Point2::new(origin[0], origin[1]),
            Vector2::new(direction[0], direction[1]),
        );
        self.placed
            .iter()
            .filter_map(|placed| placed.cast(&ray, max))
            .min_by(f64::total_cmp)
    }

    /// The indices of the obstacles that may lie within `range` of `p` (into `out`, cleared).
    pub fn near(&self, p: [f64; 2], range: f64, out: &mut Vec<usize>) {
        out.clear();
        out.extend((0..self.placed.len()).filter(|&k| self.placed[k].distance_bound(p) <= range));
    }

    /// [`Obstacles::cast_ray`] over the obstacles of `indices` only (from [`Obstacles::near`]);
    /// an obstacle whose bounding circle the ray misses is not cast against.
    pub fn cast_ray_among(&self, indices: &[usize], origin: [f64; 2], direction: [f64; 2], max: f64) -> Option<f64> {
        let ray = Ray::new(
            Point2::new(origin[0], origin[1]),
            Vector2::new(direction[0], direction[1]),
        );
        indices
            .iter()
            .map(|&k| &self.placed[k])
            .filter(|placed| ray_may_meet_circle(origin, direction, placed.centre, placed.bound, max))
            .filter_map(|placed| placed.cast(&ray, max))
            .min_by(f64::total_cmp)
    }

    /// Whether the segment a-b stays at least `clearance` from every surface (a path of a disc
    /// of radius `clearance` that touches nothing).
    pub fn segment_is_clear(&self, a: [f64; 2], b: [f64; 2], clearance: f64) -> bool {
        self.placed.iter().all(|placed| {
            point_segment_distance(placed.centre, a, b) - placed.bound >= clearance
                || placed.segment_distance(a, b) >= clearance
        })
    }

    /// Points just outside every obstacle grown by `inflation` (into `out`, cleared), where a
    /// shortest path for a disc of that radius turns: the corners of a regular octagon around
    /// each grown disc (its sides touch it), the four corners of each grown wall's rectangle.
    /// A segment between two of them along a grown obstacle's outline keeps `inflation` (to a
    /// micrometre to spare).
    pub fn waypoints(&self, inflation: f64, out: &mut Vec<[f64; 2]>) {
        const SIDES: usize = 8;
        const SPARE_M: f64 = 1e-6;
        out.clear();
        for obstacle in &self.list {
            match *obstacle {
                Obstacle::Disc { centre, radius } => {
                    let corner = (radius + inflation + SPARE_M) / (std::f64::consts::PI / SIDES as f64).cos();
                    out.extend((0..SIDES).map(|k| {
                        let (s, c) = (std::f64::consts::TAU * k as f64 / SIDES as f64).sin_cos();
                        [centre[0] + corner * c, centre[1] + corner * s]
                    }));
                }
                Obstacle::Wall { a, b, thickness } => {
                    let length = (b[0] - a[0]).hypot(b[1] - a[1]).max(1e-12);
                    let along = [(b[0] - a[0]) / length, (b[1] - a[1]) / length];
                    let across = [-along[1], along[0]];
                    let (ends, side) = (inflation + SPARE_M, 0.5 * thickness + inflation + SPARE_M);
                    for (end, reach) in [(a, -ends), (b, ends)] {
                        for offset in [-side, side] {
                            out.push([
                                end[0] + reach * along[0] + offset * across[0],
                                end[1] + reach * along[1] + offset * across[1],
                            ]);
                        }
                    }
                }
            }
        }
    }
}

/// Where the point of the segment a-b nearest to `p` lies, as a fraction of the way from a to b
/// (0 for a zero-length segment).
pub(crate) fn nearest_on_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let span2 = dx * dx + dy * dy;
    if span2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / span2).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// Whether the ray from `origin` along the unit `direction` may meet the circle of `radius`
/// about `centre` within `max` (always from inside it): a cheap, slightly generous test that
/// lets a caller skip exact casts that cannot hit.
pub fn ray_may_meet_circle(origin: [f64; 2], direction: [f64; 2], centre: [f64; 2], radius: f64, max: f64) -> bool {
    let (dx, dy) = (centre[0] - origin[0], centre[1] - origin[1]);
    let distance2 = dx * dx + dy * dy;
    // Generous by a relative 1e-9 and 1e-9 m, so rounding never skips a hit.
    let r = radius * (1.0 + 1e-9) + 1e-9;
    if distance2 <= r * r {
        return true;
    }
    let along = dx * direction[0] + dy * direction[1];
    let across2 = distance2 - along * along;
    along > 0.0 && across2 <= r * r && along - (r * r - across2).max(0.0).sqrt() <= max + 1e-9
}

/// Distance from `p` to the segment a-b.
fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let t = nearest_on_segment(p, a, b);
    (p[0] - a[0] - t * (b[0] - a[0])).hypot(p[1] - a[1] - t * (b[1] - a[1]))
}

/// The radius of a robot: half the collision distance (two robots collide when their discs
/// touch, and a robot collides with an obstacle when its disc touches one).
pub fn robot_radius_m(env: &EnvConfig) -> f64 {
    0.5 * env.eps_coll_m
}

/// How far every start position and goal slot stays from every surface: 2 x `eps_coll_m`.
pub fn clearance_m(env: &EnvConfig) -> f64 {
    2.0 * env.eps_coll_m
}

/// The farthest the gap's centre of a `passage` lies from the straight line from start to goal
/// (so that a robot reaching the wall near that line can sense the gap with a 2 m range).
pub const MAX_GAP_OFFSET_M: f64 = 1.5;

/// Seed of the obstacles' own stream, mixed into the run's seed.
const OBSTACLES_STREAM: u64 = 0x6F62_7374_6163_6C65;

/// The splitmix64 finaliser: a bijective mix of 64 bits.
fn mix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// The `seed` of [`draw`] for episode `episode` of a run seeded with `run_seed`: a stream of the
/// obstacles' own, so drawing them changes no start, goal, shape or reality.
pub fn obstacle_seed(run_seed: u64, episode: u64) -> u64 {
    mix(mix(run_seed ^ OBSTACLES_STREAM) ^ episode)
}

/// The way from the start to the goal in the frame the kinds draw in: `u` along the straight
/// line from the start centroid to the goal, `v` to its left.
#[derive(Debug, Clone)]
struct Way {
    /// The start formation's centroid.
    start: [f64; 2],
    /// Unit vector from the start centroid to the goal.
    u: [f64; 2],
    /// `u` turned a quarter left.
    v: [f64; 2],
    /// Distance from the start centroid to the goal.
    length: f64,
    /// How far the start formation reaches ahead of its centroid along `u`.
    front: f64,
    /// How far the goal formation reaches behind the goal along `u`.
    back: f64,
    /// The farthest any start position or goal slot lies from its formation's centre across `u`.
    half_width: f64,
    /// The farthest any robot lies from its formation's centre.
    reach: f64,
    /// Every start position and goal slot, world frame: what must stay clear.
    keep_clear: Vec<[f64; 2]>,
    /// Side of the arena.
    arena: f64,
    /// [`clearance_m`].
    clearance: f64,
    /// [`robot_radius_m`].
    robot_radius: f64,
}

impl Way {
    fn new(start_positions: &[[f64; 2]], goal: [f64; 2], goal_slots: &[[f64; 2]], env: &EnvConfig) -> Self {
        let n = start_positions.len().max(1) as f64;
        let start = start_positions
            .iter()
            .fold([0.0, 0.0], |c, p| [c[0] + p[0] / n, c[1] + p[1] / n]);
        let (dx, dy) = (goal[0] - start[0], goal[1] - start[1]);
        let length = dx.hypot(dy);
        let u = if length > 1e-9 {
            [dx / length, dy / length]
        } else {
            [1.0, 0.0]
        };
        let v = [-u[1], u[0]];
        let dot = |a: [f64; 2], b: [f64; 2]| a[0] * b[0] + a[1] * b[1];
        let start_offsets = start_positions.iter().map(|p| [p[0] - start[0], p[1] - start[1]]);
        let front = start_offsets.clone().map(|o| dot(o, u)).fold(0.0, f64::max);
        let back = goal_slots.iter().map(|&o| -dot(o, u)).fold(0.0, f64::max);
        let half_width = start_offsets
            .clone()
            .chain(goal_slots.iter().copied())
            .map(|o| dot(o, v).abs())
            .fold(0.0, f64::max);
        let reach = start_offsets
            .chain(goal_slots.iter().copied())
            .map(|o| o[0].hypot(o[1]))
            .fold(0.0, f64::max);
        let keep_clear = start_positions
            .iter()
            .copied()
            .chain(goal_slots.iter().map(|o| [goal[0] + o[0], goal[1] + o[1]]))
            .collect();
        Self {
            start,
            u,
            v,
            length,
            front,
            back,
            half_width,
            reach,
            keep_clear,
            arena: env.effective_arena_m(start_positions.len()),
            clearance: clearance_m(env),
            robot_radius: robot_radius_m(env),
        }
    }

    /// The point `along` the way from the start centroid and `across` to its left.
    fn at(&self, along: f64, across: f64) -> [f64; 2] {
        [
            self.start[0] + along * self.u[0] + across * self.v[0],
            self.start[1] + along * self.u[1] + across * self.v[1],
        ]
    }

    /// The goal.
    fn goal(&self) -> [f64; 2] {
        self.at(self.length, 0.0)
    }

    /// Whether every start position and goal slot is clear of `obstacles` by the clearance.
    fn is_clear(&self, obstacles: &Obstacles) -> bool {
        self.keep_clear.iter().all(|&p| obstacles.distance(p) >= self.clearance)
    }

    /// The range of `across` over which the line `along` crosses the arena, if it does.
    fn across_arena(&self, along: f64) -> Option<(f64, f64)> {
        let origin = self.at(along, 0.0);
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        for (&o, &d) in origin.iter().zip(&self.v) {
            if d.abs() < 1e-12 {
                if !(0.0..=self.arena).contains(&o) {
                    return None;
                }
                continue;
            }
            let (t0, t1) = ((0.0 - o) / d, (self.arena - o) / d);
            lo = lo.max(t0.min(t1));
            hi = hi.min(t0.max(t1));
        }
        (lo < hi).then_some((lo, hi))
    }
}

/// A wall of `thickness` from `across` = `from` to `to` at `along` on `way`, across it.
fn wall_across(way: &Way, along: f64, from: f64, to: f64, thickness: f64) -> Obstacle {
    Obstacle::Wall {
        a: way.at(along, from),
        b: way.at(along, to),
        thickness,
    }
}

/// `kind`, or for `mixed` one of [`ObstacleKind::KINDS`] drawn from `rng` (the first draw of
/// the episode's stream).
fn resolve(kind: ObstacleKind, rng: &mut StdRng) -> ObstacleKind {
    match kind {
        ObstacleKind::Mixed => ObstacleKind::KINDS[rng.random_range(0..ObstacleKind::KINDS.len())],
        kind => kind,
    }
}

/// The kind [`draw`] draws for `kind` with `seed`: `kind` itself, or for `mixed` the one of
/// [`ObstacleKind::KINDS`] the episode plays (what its time limit,
/// [`episode_steps_with_obstacles`], needs).
pub fn drawn_kind(kind: ObstacleKind, seed: u64) -> ObstacleKind {
    resolve(kind, &mut StdRng::seed_from_u64(seed))
}

/// The obstacles of one episode of kind `kind` (`config.kind` unless the caller overrides it;
/// `mixed` draws one of [`ObstacleKind::KINDS`] first), between the start positions and the goal
/// (`goal_slots` are offsets from `goal`, as `EpisodeInit::slots`), drawn from
/// `StdRng::seed_from_u64(seed)` ([`obstacle_seed`]). Every start position and goal slot is
/// clear of every surface by [`clearance_m`]. A goal too near for the kind's obstacle (one that
/// [`min_goal_distance_m`] would refuse) gets no obstacles.
pub fn draw(
    config: &ObstacleConfig,
    kind: ObstacleKind,
    start_positions: &[[f64; 2]],
    goal: [f64; 2],
    goal_slots: &[[f64; 2]],
    env: &EnvConfig,
    seed: u64,
) -> Obstacles {
    let mut rng = StdRng::seed_from_u64(seed);
    let kind = resolve(kind, &mut rng);
    let way = Way::new(start_positions, goal, goal_slots, env);
    let obstacles = match kind {
        ObstacleKind::None | ObstacleKind::Mixed => return Obstacles::none(),
        ObstacleKind::Forest => forest::draw(config, &way, &mut rng),
        ObstacleKind::Passage => passage::draw(config, &way, &mut rng),
        ObstacleKind::Trap => trap::draw(config, &way, &mut rng),
    };
    // Each kind keeps its room by construction; this guards the promise.
    if way.is_clear(&obstacles) {
        obstacles
    } else {
        Obstacles::none()
    }
}

/// The nearest goal (from the start centroid) an episode of `n` robots with obstacles of `kind`
/// needs, metres: the formation's extent along the way (its reach ahead of the start and behind
/// the goal, 2 x `env.formation_reach_m(n)`), the clearance before and after the obstacle
/// (2 x [`clearance_m`]) and the obstacle's depth along the way at its largest (`forest`: two
/// of the largest discs' diameters; `passage`: the wall; `trap`: the U's depth and its back
/// wall). `mixed` needs the most of its kinds; `none` 0.
pub fn min_goal_distance_m(config: &ObstacleConfig, kind: ObstacleKind, n: usize, env: &EnvConfig) -> f64 {
    let depth = match kind {
        ObstacleKind::None => return 0.0,
        ObstacleKind::Mixed => {
            return ObstacleKind::KINDS
                .iter()
                .map(|&kind| min_goal_distance_m(config, kind, n, env))
                .fold(0.0, f64::max);
        }
        ObstacleKind::Forest => 4.0 * config.forest_radius_m.hi,
        ObstacleKind::Passage => config.wall_thickness_m.hi,
        ObstacleKind::Trap => config.trap_depth_m.hi + config.wall_thickness_m.hi,
    };
    2.0 * env.formation_reach_m(n) + 2.0 * clearance_m(env) + depth
}

/// Spacing of robots going in file through a narrow place, metres: what the privileged planner
/// keeps between them (2.5 x `eps_coll_m`, the closest two robots of a drawn formation are).
pub fn file_spacing_m(env: &EnvConfig) -> f64 {
    crate::shapes::MIN_SEPARATION_FACTOR * env.eps_coll_m
}

/// How many times the top speed's pace the time limit allows over an episode's estimated
/// path: the open world's own allowance (120 ticks for a goal up to 2.5 m away at 0.5 m/s and
/// 0.1 s a tick, 50 ticks at top speed).
pub const PACE_ALLOWANCE: f64 = 2.4;

/// The time limit of an episode of `n` robots whose goal lies `goal_distance` from the start
/// centroid among obstacles of `kind`, steps. Fixed before any measurement:
///
/// * the estimated path, at [`PACE_ALLOWANCE`] x the top speed's pace (1 / (`v_max` dt) ticks
///   a metre), never under `max_steps`, plus the shape changes' allowance of
///   [`EnvConfig::episode_steps`];
/// * the path: `forest` 1.3 x the straight distance (weaving between discs); `passage` the two
///   legs to a gap at the largest offset ([`MAX_GAP_OFFSET_M`]) with the wall half-way,
///   2 sqrt((d/2)^2 + 1.5^2); `trap` the straight distance plus going out past the U's side and
///   back, twice the formation's reach plus 1.2 m (the widest margin and wall, and clearance);
/// * going in file (where the formation fits nowhere along the way: a passage always, a
///   forest or a trap near the arena's side sometimes): the column's length,
///   (n - 1) x [`file_spacing_m`], plus re-forming after it (crossing the formation, 2 x reach,
///   as a shape change's allowance), at the same pace.
///
/// `none` is the open-world limit exactly; `mixed` (a caller should pass the episode's drawn
/// kind) takes the largest of its kinds.
pub fn episode_steps_with_obstacles(kind: ObstacleKind, goal_distance: f64, n: usize, env: &EnvConfig) -> u32 {
    let open = env.episode_steps(n);
    let reach = env.formation_reach_m(n);
    let in_file = (n.saturating_sub(1)) as f64 * file_spacing_m(env) + 2.0 * reach;
    let path = match kind {
        ObstacleKind::None => return open,
        ObstacleKind::Mixed => {
            return ObstacleKind::KINDS
                .iter()
                .map(|&kind| episode_steps_with_obstacles(kind, goal_distance, n, env))
                .fold(open, u32::max);
        }
        ObstacleKind::Forest => 1.3 * goal_distance,
        ObstacleKind::Passage => 2.0 * (0.5 * goal_distance).hypot(MAX_GAP_OFFSET_M),
        ObstacleKind::Trap => goal_distance + 2.0 * reach + 1.2,
    };
    let ticks = (PACE_ALLOWANCE * (path + in_file) / (env.v_max * env.dt_s)).ceil() as u32;
    open - env.max_steps + ticks.max(env.max_steps)
}

#[cfg(test)]
pub(crate) mod tests;
