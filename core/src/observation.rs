//! What a robot is told each tick, in its own frame (x ahead, y to the left): the observation
//! models, their layout named in one place, and the function that computes them.
//!
//! Every model starts with the paper's 12 floats; the others append to them:
//!
//! | floats | `paper` | `slot` | `slot_proximity` | `slot_proximity_scan` |
//! |---|---|---|---|---|
//! | 0..5 | neighbour (i+1) mod N: x, y, cos and sin of its relative heading, desired distance | same | same | same |
//! | 5..10 | neighbour (i+2) mod N, the same five | same | same | same |
//! | 10..12 | the formation's goal (for its centroid) | same | same | same |
//! | 12..14 | - | the robot's own slot: the goal plus its offset in the goal formation | same | same |
//! | 14..16 | - | - | the nearest robot that is not a neighbour, as `(1 - d/R) * unit vector` within R, else 0 | same |
//! | 16..32 | - | - | - | the range sensor's 16 rays ([`crate::range_sensor`]), each range / `env.scan_range_m` in [0, 1] |
//!
//! The slot is what displacement-based formation control gives each robot: with it a robot
//! knows where the formation's centroid must end up relative to itself at any N, which its own
//! triangle cannot tell it once N > 3. The proximity term lets robots of a large swarm avoid
//! robots they do not track. A robot never reads the true state: the sim computes these from
//! it and sends each robot its own.

use std::cell::RefCell;

use crate::config::{EnvConfig, ObservationModel};
use formation_protocol::{MAX_OBS_DIM, NEIGHBOURS};

use crate::obstacles::robot_radius_m;
use crate::physics::Pose;
use crate::range_sensor::RangeSensor;
use crate::scene::Scene;

/// Floats per observed neighbour.
pub const NEIGHBOUR_FEATURES: usize = 5;

/// The floats of a neighbour's block, in order: its position, the cos and sin of its heading
/// relative to the observer's, the desired distance to it.
pub const NEIGHBOUR_FIELDS: [&str; NEIGHBOUR_FEATURES] = ["x", "y", "cos", "sin", "desired"];

/// The floats of a point's block (the goal, the slot, the proximity term), in order.
pub const POINT_FIELDS: [&str; 2] = ["x", "y"];

/// What a float of an observation measures: the sensor noise of `[reality]` follows it
/// ([`crate::reality::Reality::tell`]), so a new block gets the noise of its kind by declaring
/// its kinds, with no change to the noise code.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    /// A relative position's x or y, metres (`position_noise_m`, per coordinate).
    Position,
    /// The cos or sin of a relative heading (`heading_noise_rad` on the angle).
    Heading,
    /// A relative position seen as closeness, `(1 - d/R) * unit vector` (the position noise on
    /// the position it stands for).
    Closeness,
    /// A range reading, metres.
    Range,
    /// Anything no sensor measures (a desired distance): no noise.
    Other,
}

impl Quantity {
    /// Its name in `layout.json`.
    pub const fn as_str(self) -> &'static str {
        match self {
            Self::Position => "position",
            Self::Heading => "heading",
            Self::Closeness => "closeness",
            Self::Range => "range",
            Self::Other => "other",
        }
    }
}

/// The kind of each float of a neighbour's block.
pub const NEIGHBOUR_KINDS: [Quantity; NEIGHBOUR_FEATURES] = [
    Quantity::Position,
    Quantity::Position,
    Quantity::Heading,
    Quantity::Heading,
    Quantity::Other,
];

/// The kinds of a point's block (the goal, the slot).
pub const POINT_KINDS: [Quantity; 2] = [Quantity::Position; 2];

/// The kinds of the proximity term's block.
pub const CLOSENESS_KINDS: [Quantity; 2] = [Quantity::Closeness; 2];

/// Rays of the `slot_proximity_scan` model's range sensor (ray k at 2 pi k / 16 counter-clockwise
/// from straight ahead). Fixed by the model: a policy's input width is the ray count.
pub const SCAN_RAYS: usize = 16;

/// The names of the scan block's floats: ray k's normalised range.
pub const SCAN_FIELDS: [&str; SCAN_RAYS] = [
    "r0", "r1", "r2", "r3", "r4", "r5", "r6", "r7", "r8", "r9", "r10", "r11", "r12", "r13", "r14", "r15",
];

/// The kinds of the scan block.
pub const SCAN_KINDS: [Quantity; SCAN_RAYS] = [Quantity::Range; SCAN_RAYS];

/// Every observation model, smallest first: what `layout.json` lists (a test keeps it
/// exhaustive).
pub const MODELS: [ObservationModel; 4] = [
    ObservationModel::Paper,
    ObservationModel::Slot,
    ObservationModel::SlotProximity,
    ObservationModel::SlotProximityScan,
];

/// One named run of floats in an observation.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Block {
    /// `neighbour_0`, `neighbour_1`, `goal`, `slot` or `proximity`.
    pub name: String,
    /// Its first float.
    pub offset: usize,
    /// The names of its floats, in order (its length is theirs).
    pub fields: &'static [&'static str],
    /// What each of its floats measures, in order.
    pub kinds: &'static [Quantity],
}

/// Where each quantity sits in an observation of one model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Layout {
    /// The model this layout belongs to.
    pub model: ObservationModel,
}

impl Layout {
    /// The layout of `model`.
    pub const fn of(model: ObservationModel) -> Self {
        Self { model }
    }

    /// Every block of the model, in order (what `layout.json` gives other languages).
    pub fn blocks(self) -> Vec<Block> {
        let mut blocks: Vec<Block> = (0..NEIGHBOURS)
            .map(|k| Block {
                name: format!("neighbour_{k}"),
                offset: self.neighbour(k),
                fields: &NEIGHBOUR_FIELDS,
                kinds: &NEIGHBOUR_KINDS,
            })
            .collect();
        let point = |name: &str, offset: usize, kinds: &'static [Quantity]| Block {
            name: name.to_string(),
            offset,
            fields: &POINT_FIELDS,
            kinds,
        };
        blocks.push(point("goal", self.goal(), &POINT_KINDS));
        blocks.extend(self.slot().map(|at| point("slot", at, &POINT_KINDS)));
        blocks.extend(self.proximity().map(|at| point("proximity", at, &CLOSENESS_KINDS)));
        blocks.extend(self.scan().map(|offset| Block {
            name: "scan".to_string(),
            offset,
            fields: &SCAN_FIELDS,
            kinds: &SCAN_KINDS,
        }));
        blocks
    }

    /// Each block's first float and kinds, in order, without allocating (what the sensor noise
    /// walks every tick).
    pub fn kinds(self) -> impl Iterator<Item = (usize, &'static [Quantity])> {
        let neighbours = (0..NEIGHBOURS).map(move |k| (self.neighbour(k), &NEIGHBOUR_KINDS[..]));
        let points = [
            Some((self.goal(), &POINT_KINDS[..])),
            self.slot().map(|at| (at, &POINT_KINDS[..])),
            self.proximity().map(|at| (at, &CLOSENESS_KINDS[..])),
            self.scan().map(|at| (at, &SCAN_KINDS[..])),
        ];
        neighbours.chain(points.into_iter().flatten())
    }

    /// Floats in one observation.
    pub const fn dim(self) -> usize {
        match self.model {
            ObservationModel::Paper => 12,
            ObservationModel::Slot => 14,
            ObservationModel::SlotProximity => 16,
            ObservationModel::SlotProximityScan => 16 + SCAN_RAYS,
        }
    }

    /// Start of neighbour `k`'s block: x, y, cos, sin, desired distance.
    pub const fn neighbour(self, k: usize) -> usize {
        k * NEIGHBOUR_FEATURES
    }

    /// Start of the goal's (x, y).
    pub const fn goal(self) -> usize {
        NEIGHBOURS * NEIGHBOUR_FEATURES
    }

    /// Start of the robot's own slot (x, y), if the model has one.
    pub const fn slot(self) -> Option<usize> {
        match self.model {
            ObservationModel::Paper => None,
            ObservationModel::Slot | ObservationModel::SlotProximity | ObservationModel::SlotProximityScan => {
                Some(self.goal() + 2)
            }
        }
    }

    /// Start of the proximity term (x, y), if the model has one.
    pub const fn proximity(self) -> Option<usize> {
        match self.model {
            ObservationModel::SlotProximity | ObservationModel::SlotProximityScan => Some(self.goal() + 4),
            ObservationModel::Paper | ObservationModel::Slot => None,
        }
    }

    /// Start of the range sensor's rays, if the model has them.
    pub const fn scan(self) -> Option<usize> {
        match self.model {
            ObservationModel::SlotProximityScan => Some(self.goal() + 6),
            _ => None,
        }
    }
}

/// One observed neighbour, read from an observation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NeighbourView {
    /// Position in the observer's frame, metres.
    pub position: [f64; 2],
    /// cos and sin of its heading relative to the observer's.
    pub relative_heading: [f64; 2],
    /// Desired distance to it, metres.
    pub desired: f64,
}

/// Named read access to one observation.
#[derive(Debug, Clone, Copy)]
pub struct ObservationView<'a> {
    layout: Layout,
    values: &'a [f32],
}

impl<'a> ObservationView<'a> {
    /// Reads `values` (at least `layout.dim()` floats) as an observation of `layout`.
    pub fn new(layout: Layout, values: &'a [f32]) -> Self {
        debug_assert!(values.len() >= layout.dim());
        Self { layout, values }
    }

    fn pair(&self, at: usize) -> [f64; 2] {
        [f64::from(self.values[at]), f64::from(self.values[at + 1])]
    }

    /// Neighbour `k` (0: (i+1) mod N, 1: (i+2) mod N).
    pub fn neighbour(&self, k: usize) -> NeighbourView {
        let at = self.layout.neighbour(k);
        NeighbourView {
            position: self.pair(at),
            relative_heading: self.pair(at + 2),
            desired: f64::from(self.values[at + 4]),
        }
    }

    /// The formation's goal.
    pub fn goal(&self) -> [f64; 2] {
        self.pair(self.layout.goal())
    }

    /// The robot's own slot, if the model has one.
    pub fn slot(&self) -> Option<[f64; 2]> {
        self.layout.slot().map(|at| self.pair(at))
    }

    /// The proximity term, if the model has one.
    pub fn proximity(&self) -> Option<[f64; 2]> {
        self.layout.proximity().map(|at| self.pair(at))
    }

    /// The range sensor's rays, each range / `env.scan_range_m`, if the model has them.
    pub fn scan(&self) -> Option<&'a [f32]> {
        self.layout.scan().map(|at| &self.values[at..at + SCAN_RAYS])
    }

    /// Where the nearest robot the robot does not track is, in its frame, when the model
    /// reports one within `proximity_range_m` (`env.proximity_range_m`; the term is (1 - d/R)
    /// along the unit vector to it).
    pub fn nearest_other(&self, proximity_range_m: f64) -> Option<[f64; 2]> {
        let near = self.proximity()?;
        let closeness = near[0].hypot(near[1]);
        (closeness > 0.0).then(|| {
            let dist = (1.0 - closeness) * proximity_range_m;
            [near[0] / closeness * dist, near[1] / closeness * dist]
        })
    }

    /// Every robot the observation tells of, in the robot's frame: its neighbours and, when
    /// the model reports one, the nearest other ([`ObservationView::nearest_other`]).
    pub fn robots(self, proximity_range_m: f64) -> impl Iterator<Item = [f64; 2]> + Clone + 'a {
        (0..NEIGHBOURS)
            .map(move |k| self.neighbour(k).position)
            .chain(self.nearest_other(proximity_range_m))
    }
}

/// A world-frame point expressed in the frame of a robot at `pose` (x ahead, y to the left).
pub fn to_robot_frame(pose: &Pose, point: [f64; 2]) -> [f64; 2] {
    let (dx, dy) = (point[0] - pose.x, point[1] - pose.y);
    let (s, c) = pose.theta.sin_cos();
    [c * dx + s * dy, -s * dx + c * dy]
}

/// Computes observations of one model; allocation-free once its range sensor's buffers have
/// grown.
#[derive(Debug, Clone)]
pub struct Observer {
    /// The layout written.
    pub layout: Layout,
    proximity_range_m: f64,
    /// The range sensor, for a model with a scan (its buffers change under a shared borrow).
    sensor: Option<RefCell<RangeSensor>>,
    robot_radius_m: f64,
}

impl Observer {
    /// The observer the run's environment asks for.
    pub fn new(env: &EnvConfig) -> Self {
        let layout = Layout::of(env.observation);
        Self {
            layout,
            proximity_range_m: env.proximity_range_m,
            sensor: layout
                .scan()
                .map(|_| RefCell::new(RangeSensor::new(SCAN_RAYS, env.scan_range_m))),
            robot_radius_m: robot_radius_m(env),
        }
    }

    /// Floats per observation.
    pub fn dim(&self) -> usize {
        self.layout.dim()
    }

    /// Writes what robot `agent` sees in `scene` into `out[..dim]`; the rest of `out` is zeroed.
    pub fn observe(&self, agent: usize, scene: &Scene, out: &mut [f32]) {
        debug_assert!(out.len() >= self.dim());
        out.fill(0.0);
        let me = &scene.poses[agent];
        let n = scene.poses.len();
        let observed = scene.observed[agent];
        for (k, &other) in observed.iter().enumerate() {
            let at = self.layout.neighbour(k);
            let rel = to_robot_frame(me, [scene.poses[other].x, scene.poses[other].y]);
            let (s, c) = (scene.poses[other].theta - me.theta).sin_cos();
            out[at..at + NEIGHBOUR_FEATURES]
                .copy_from_slice(&[rel[0], rel[1], c, s, scene.desired[agent][k]].map(|v| v as f32));
        }
        let goal = to_robot_frame(me, scene.goal);
        let at = self.layout.goal();
        out[at..at + 2].copy_from_slice(&goal.map(|v| v as f32));
        if let Some(at) = self.layout.slot() {
            let offset = scene.slots[agent];
            let slot = to_robot_frame(me, [scene.goal[0] + offset[0], scene.goal[1] + offset[1]]);
            out[at..at + 2].copy_from_slice(&slot.map(|v| v as f32));
        }
        if let Some(at) = self.layout.proximity() {
            let range = self.proximity_range_m;
            let nearest = (0..n)
                .filter(|&j| j != agent && !observed.contains(&j))
                .map(|j| (j, (scene.poses[j].x - me.x).hypot(scene.poses[j].y - me.y)))
                .min_by(|a, b| a.1.total_cmp(&b.1));
            if let Some((j, d)) = nearest.filter(|&(_, d)| d < range) {
                let rel = to_robot_frame(me, [scene.poses[j].x, scene.poses[j].y]);
                let weight = (1.0 - d / range) / d.max(1e-9);
                out[at..at + 2].copy_from_slice(&[(rel[0] * weight) as f32, (rel[1] * weight) as f32]);
            }
        }
        if let (Some(at), Some(sensor)) = (self.layout.scan(), &self.sensor) {
            let mut sensor = sensor.borrow_mut();
            let rays = &mut out[at..at + SCAN_RAYS];
            sensor.scan(
                scene.obstacles,
                scene.poses,
                agent,
                self.robot_radius_m,
                scene.arena_m,
                rays,
            );
            let range = sensor.range_m() as f32;
            rays.iter_mut().for_each(|r| *r /= range);
        }
    }

    /// Moves the goal of `obs`, an observation told to a robot at `pose`, from `from` to `to`
    /// (world frame): the goal's and the slot's blocks shift by the goal's displacement in the
    /// robot's frame, and every other float, with whatever sensor noise it was told with, stays.
    /// HER relabels noisy observations this way, so the noise of the relabelled goal is the
    /// noise the robot was told.
    pub fn move_goal(&self, obs: &mut [f32], pose: &Pose, from: [f64; 2], to: [f64; 2]) {
        let (s, c) = pose.theta.sin_cos();
        let (dx, dy) = (to[0] - from[0], to[1] - from[1]);
        let shift = [c * dx + s * dy, -s * dx + c * dy];
        for at in std::iter::once(self.layout.goal()).chain(self.layout.slot()) {
            for (value, delta) in obs[at..at + 2].iter_mut().zip(shift) {
                *value = (f64::from(*value) + delta) as f32;
            }
        }
    }

    /// What robot `agent` sees, as a fixed-size array (entries past `dim` are zero).
    pub fn observation(&self, agent: usize, scene: &Scene) -> [f32; MAX_OBS_DIM] {
        let mut out = [0.0; MAX_OBS_DIM];
        self.observe(agent, scene, &mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::index_neighbours;

    fn pose(x: f64, y: f64, theta: f64) -> Pose {
        Pose { x, y, theta }
    }

    fn observer(model: ObservationModel) -> Observer {
        Observer::new(&EnvConfig {
            observation: model,
            ..EnvConfig::default()
        })
    }

    #[test]
    fn every_model_is_listed_named_and_laid_out_without_gaps() {
        // Every variant, as clap's derive lists them.
        assert_eq!(
            MODELS.as_slice(),
            <ObservationModel as clap::ValueEnum>::value_variants()
        );
        for model in MODELS {
            assert_eq!(ObservationModel::from_name(model.as_str()), Some(model));
            let layout = Layout::of(model);
            let mut end = 0;
            for block in layout.blocks() {
                assert_eq!(block.offset, end, "{model:?}: {} does not follow on", block.name);
                end += block.fields.len();
            }
            assert_eq!(end, layout.dim(), "{model:?}: the blocks fill the observation");
            assert!(layout.dim() <= MAX_OBS_DIM);
        }
        // ObservationView reads a neighbour's block in NEIGHBOUR_FIELDS' order.
        let at = |field: &str| NEIGHBOUR_FIELDS.iter().position(|f| *f == field);
        assert_eq!((at("x"), at("cos"), at("desired")), (Some(0), Some(2), Some(4)));
    }

    #[test]
    fn neighbour_straight_ahead_is_plus_x() {
        let me = pose(1.0, 1.0, std::f64::consts::FRAC_PI_2);
        let p = to_robot_frame(&me, [1.0, 3.0]);
        assert!((p[0] - 2.0).abs() < 1e-12 && p[1].abs() < 1e-12);
        let left = to_robot_frame(&me, [0.0, 1.0]);
        assert!(
            left[0].abs() < 1e-12 && (left[1] - 1.0).abs() < 1e-12,
            "a point to the left is at +y"
        );
    }

    #[test]
    fn paper_layout_matches_the_paper() {
        let poses = [pose(0.0, 0.0, 0.0), pose(1.0, 0.0, 0.5), pose(0.5, 0.8, 0.0)];
        let desired = [[1.0, 0.9], [1.1, 1.2], [1.3, 1.4]];
        let slots = [[0.0; 2]; 3];
        let scene = Scene {
            obstacles: &crate::obstacles::NO_OBSTACLES,
            arena_m: 10.0,
            ways: None,
            poses: &poses,
            commands: &[(0.0, 0.0); 3],
            desired: &desired,
            observed: &index_neighbours(poses.len()),
            goal: [0.0, 2.0],
            slots: &slots,
        };
        let observer = observer(ObservationModel::Paper);
        assert_eq!(observer.dim(), 12);
        let obs = observer.observation(0, &scene);
        let expected = [
            1.0,
            0.0,
            0.5f32.cos(),
            0.5f32.sin(),
            1.0,
            0.5,
            0.8,
            1.0,
            0.0,
            0.9,
            0.0,
            2.0,
        ];
        for (i, (got, want)) in obs.iter().zip(expected).enumerate() {
            assert!((got - want).abs() < 1e-6, "float {i}: {got} vs {want}");
        }
        assert!(
            obs[12..].iter().all(|&v| v == 0.0),
            "nothing past the paper's 12 floats"
        );
        let view = ObservationView::new(observer.layout, &obs);
        assert_eq!(view.neighbour(1).position, [0.5f32 as f64, 0.8f32 as f64]);
        assert_eq!(view.goal(), [0.0, 2.0]);
        assert!(view.slot().is_none() && view.proximity().is_none());
    }

    #[test]
    fn slot_is_goal_plus_offset_in_the_robots_frame() {
        // Robot 0 faces +y from (2, 1); its slot offset is (1, 0) from the goal (2, 3), so the
        // slot (3, 3) is 2 m ahead and 1 m to its right.
        let poses = [
            pose(2.0, 1.0, std::f64::consts::FRAC_PI_2),
            pose(3.0, 1.0, 0.0),
            pose(2.5, 2.0, 0.0),
        ];
        let desired = [[1.0, 1.0]; 3];
        let slots = [[1.0, 0.0], [0.0, 0.0], [0.0, 0.0]];
        let scene = Scene {
            obstacles: &crate::obstacles::NO_OBSTACLES,
            arena_m: 10.0,
            ways: None,
            poses: &poses,
            commands: &[(0.0, 0.0); 3],
            desired: &desired,
            observed: &index_neighbours(poses.len()),
            goal: [2.0, 3.0],
            slots: &slots,
        };
        let observer = observer(ObservationModel::Slot);
        let obs = observer.observation(0, &scene);
        let view = ObservationView::new(observer.layout, &obs);
        let slot = view.slot().expect("slot model");
        assert!((slot[0] - 2.0).abs() < 1e-6 && (slot[1] + 1.0).abs() < 1e-6, "{slot:?}");
        assert!(view.proximity().is_none());
        assert_eq!(observer.dim(), 14);
    }

    #[test]
    fn proximity_sees_only_close_robots_it_does_not_track() {
        // Robot 0 observes 1 and 2; robot 3 is 0.5 m to its left, robot 4 far away.
        let poses = [
            pose(0.0, 0.0, 0.0),
            pose(1.0, 0.0, 0.0),
            pose(0.0, -1.0, 0.0),
            pose(0.0, 0.5, 0.0),
            pose(5.0, 5.0, 0.0),
        ];
        let desired = [[1.0, 1.0]; 5];
        let slots = [[0.0; 2]; 5];
        let scene = Scene {
            obstacles: &crate::obstacles::NO_OBSTACLES,
            arena_m: 10.0,
            ways: None,
            poses: &poses,
            commands: &[(0.0, 0.0); 5],
            desired: &desired,
            observed: &index_neighbours(poses.len()),
            goal: [0.0, 0.0],
            slots: &slots,
        };
        let observer = observer(ObservationModel::SlotProximity);
        let view_of = |agent: usize| {
            let obs = observer.observation(agent, &scene);
            ObservationView::new(observer.layout, &obs)
                .proximity()
                .expect("proximity model")
        };
        let near = view_of(0);
        let range = EnvConfig::default().proximity_range_m;
        assert!(
            near[0].abs() < 1e-6 && (near[1] - (1.0 - 0.5 / range)).abs() < 1e-6,
            "{near:?}"
        );
        // Robot 4 tracks 0 and 1; everyone else is far: nothing in range.
        assert_eq!(view_of(4), [0.0, 0.0]);
    }
}
