//! What the critic sees of a tick: a [`Scene`], written as the critic network's floats.
//!
//! The critic state of a tick: each robot's position relative to that tick's centroid (of the
//! robots in the formation: a robot out of it does not move the frame) and its
//! heading (cos, sin), the goal relative to the centroid, the desired edge lengths, and for
//! the observation models with slots each robot's slot offset. All of it is rotated into one
//! frame per window, the heading of robot 0 at the window's last tick, so the critic does not
//! have to learn every rotation of the same scene.
//!
//! For N = 3 and the paper's observation that is 4 * 3 + 2 + 2 * 3 = 20 floats a tick; the
//! paper's critic sees every robot's observation instead (3 * 12 = 36 floats), which holds the
//! same relative geometry in three frames.
//!
//! With `learn.critic_map_points` = K > 0 (the `pooled` critic only) each robot's token also
//! holds the nearest points of its K nearest obstacles within [`CRITIC_MAP_RANGE_M`], read from
//! the episode's map: what lies beyond the robots' 2 m rays, for the central critic alone (no
//! robot runs it, so no robot needs the map).
//!
//! The arithmetic is `f32`, the precision of the state stream the replay's scenes come from
//! (their values are that stream's `f32`s, widened exactly), so the features are the same
//! floats whether a scene is read from the replay or from a `World`'s stream.

use crate::config::{CriticArchitecture, ObservationModel};
use formation_protocol::NEIGHBOURS;

use crate::observation::Layout;
use crate::physics::Pose;
use crate::scene::Scene;
use crate::task::is_present;

/// How far round each robot the `pooled` critic's map points reach, metres: twice the range
/// of the robots' own rays.
pub const CRITIC_MAP_RANGE_M: f64 = 4.0;

/// Layout of one tick of critic state for a swarm of `n_agents`.
///
/// Team-major for the `mlp` critic: every robot's pose, the goal, every robot's desired
/// edges, every robot's slot. Robot-major for the `pooled` critic: each robot's own token
/// ([`CriticFeatures::token_dim`] floats), which the critic's encoder reads alone.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CriticFeatures {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Whether the robots' slot offsets are part of the state.
    pub slots: bool,
    /// Robot-major tokens (the `pooled` critic) instead of the team-major layout.
    pub per_robot: bool,
    /// Obstacle points in each robot's token ([`CriticFeatures::with_map_points`]).
    pub map_points: usize,
}

impl CriticFeatures {
    /// The features for `n_agents` robots observing with `model`, laid out for `critic`.
    pub fn new(n_agents: usize, model: ObservationModel, critic: CriticArchitecture) -> Self {
        Self {
            n_agents,
            slots: Layout::of(model).slot().is_some(),
            per_robot: critic == CriticArchitecture::Pooled,
            map_points: 0,
        }
    }

    /// These features with the nearest points of each robot's `points` nearest obstacles in
    /// its token (`learn.critic_map_points`; robot-major tokens only, as the config checks).
    pub fn with_map_points(self, points: usize) -> Self {
        debug_assert!(points == 0 || self.per_robot, "map points need robot-major tokens");
        Self {
            map_points: points,
            ..self
        }
    }

    /// Floats per tick.
    pub fn dim(&self) -> usize {
        let n = self.n_agents;
        if self.per_robot {
            return n * self.token_dim();
        }
        4 * n + 2 + NEIGHBOURS * n + if self.slots { 2 * n } else { 0 }
    }

    /// Floats of one robot's token: its position relative to the centroid and heading (4),
    /// the displacement to each of its two observed neighbours (4), its desired edges (2), the
    /// goal relative to the centroid (2), with slots its slot offset (2), and with map points
    /// each point's offset from the robot and a 1 (3 each; zeros where it has fewer obstacles
    /// that near).
    pub fn token_dim(&self) -> usize {
        self.map_at() + 3 * self.map_points
    }

    /// Where a token's map points start.
    fn map_at(&self) -> usize {
        4 + 2 * NEIGHBOURS + NEIGHBOURS + 2 + if self.slots { 2 } else { 0 }
    }

    /// Writes one tick into `out` (length [`CriticFeatures::dim`]), rotated by `-frame`.
    pub fn write(&self, out: &mut [f32], scene: &Scene, frame: f32) {
        debug_assert_eq!(out.len(), self.dim());
        if self.per_robot {
            self.write_tokens(out, scene, frame);
        } else {
            self.write_team(out, scene, frame);
        }
    }

    fn write_tokens(&self, out: &mut [f32], scene: &Scene, frame: f32) {
        let c = centroid(scene);
        let (s, co) = frame.sin_cos();
        let rotate = |dx: f32, dy: f32| [co * dx + s * dy, -s * dx + co * dy];
        let goal = narrow(scene.goal);
        let goal = rotate(goal[0] - c[0], goal[1] - c[1]);
        let mut nearest: Vec<(f64, [f64; 2])> = Vec::new();
        for (i, token) in out.chunks_exact_mut(self.token_dim()).enumerate() {
            let p = position(&scene.poses[i]);
            let (hs, hc) = (scene.poses[i].theta as f32 - frame).sin_cos();
            let [a, b] = scene.observed[i].map(|j| {
                let q = position(&scene.poses[j]);
                rotate(q[0] - p[0], q[1] - p[1])
            });
            let r = rotate(p[0] - c[0], p[1] - c[1]);
            let [d1, d2] = narrow(scene.desired[i]);
            token[..12].copy_from_slice(&[r[0], r[1], hc, hs, a[0], a[1], b[0], b[1], d1, d2, goal[0], goal[1]]);
            if self.slots {
                let slot = narrow(scene.slots[i]);
                token[12..14].copy_from_slice(&rotate(slot[0], slot[1]));
            }
            if self.map_points > 0 {
                let at = [scene.poses[i].x, scene.poses[i].y];
                nearest_points(scene, at, self.map_points, &mut nearest);
                let map = &mut token[self.map_at()..];
                map.fill(0.0);
                for (point, &(_, q)) in map.chunks_exact_mut(3).zip(&nearest) {
                    let offset = rotate(q[0] as f32 - p[0], q[1] as f32 - p[1]);
                    point.copy_from_slice(&[offset[0], offset[1], 1.0]);
                }
            }
        }
    }

    fn write_team(&self, out: &mut [f32], scene: &Scene, frame: f32) {
        let n = self.n_agents;
        let c = centroid(scene);
        let (s, co) = frame.sin_cos();
        let rotate = |dx: f32, dy: f32| [co * dx + s * dy, -s * dx + co * dy];
        for (i, pose) in scene.poses.iter().enumerate() {
            let p = position(pose);
            let r = rotate(p[0] - c[0], p[1] - c[1]);
            let (hs, hc) = (pose.theta as f32 - frame).sin_cos();
            out[4 * i..4 * i + 4].copy_from_slice(&[r[0], r[1], hc, hs]);
        }
        let goal = narrow(scene.goal);
        let g = rotate(goal[0] - c[0], goal[1] - c[1]);
        out[4 * n..4 * n + 2].copy_from_slice(&g);
        let desired_at = 4 * n + 2;
        for (i, d) in scene.desired.iter().enumerate() {
            out[desired_at + NEIGHBOURS * i..desired_at + NEIGHBOURS * (i + 1)].copy_from_slice(&narrow(*d));
        }
        if self.slots {
            let slots_at = desired_at + NEIGHBOURS * n;
            for (i, slot) in scene.slots.iter().enumerate() {
                let slot = narrow(*slot);
                out[slots_at + 2 * i..slots_at + 2 * i + 2].copy_from_slice(&rotate(slot[0], slot[1]));
            }
        }
    }
}

/// The nearest points of the `k` obstacles nearest `at` within [`CRITIC_MAP_RANGE_M`], nearest
/// first, into `out` (as (distance, point)).
fn nearest_points(scene: &Scene, at: [f64; 2], k: usize, out: &mut Vec<(f64, [f64; 2])>) {
    out.clear();
    scene.obstacles.for_each_nearest_within(at, CRITIC_MAP_RANGE_M, |q| {
        out.push(((q[0] - at[0]).hypot(q[1] - at[1]), q));
    });
    out.sort_by(|a, b| a.0.total_cmp(&b.0));
    out.truncate(k);
}

/// `f64` values in the features' `f32`.
fn narrow<const K: usize>(values: [f64; K]) -> [f32; K] {
    values.map(|v| v as f32)
}

/// A pose's position in `f32`.
fn position(pose: &Pose) -> [f32; 2] {
    [pose.x as f32, pose.y as f32]
}

/// The centroid of the positions of a tick's robots in the formation ([`is_present`]; of
/// every robot when none is, as [`crate::task::present_centroid`]), in `f32`: a robot out of
/// the formation does not move the frame the members are placed in.
fn centroid(scene: &Scene) -> [f32; 2] {
    let members = |agent: &usize| is_present(*agent, scene.observed);
    let everyone = !(0..scene.poses.len()).any(|agent| members(&agent));
    let (mut sx, mut sy, mut m) = (0.0f32, 0.0f32, 0usize);
    for (agent, p) in scene.poses.iter().enumerate() {
        if everyone || members(&agent) {
            let [x, y] = position(p);
            (sx, sy, m) = (sx + x, sy + y, m + 1);
        }
    }
    let m = m as f32;
    [sx / m, sy / m]
}

#[cfg(test)]
mod tests {
    use super::*;

    const fn pose(x: f64, y: f64, theta: f64) -> Pose {
        Pose { x, y, theta }
    }

    const POSES: [Pose; 3] = [
        pose(1.0, 0.0, std::f64::consts::FRAC_PI_2),
        pose(2.0, 2.0, 0.0),
        pose(0.0, 1.0, std::f64::consts::PI),
    ];
    const COMMANDS: [(f64, f64); 3] = [(0.1, 0.2), (0.3, -0.4), (0.0, 0.0)];
    const DESIRED: [[f64; NEIGHBOURS]; 3] = [[1.0, 1.5], [1.2, 1.3], [1.4, 1.6]];
    const SLOTS: [[f64; 2]; 3] = [[0.0, -1.0], [1.0, 1.0], [-1.0, 0.0]];

    /// Robot 0 faces +y; the centroid is (1, 1); the goal is 2 m along +y from it.
    fn three_robots() -> Scene<'static> {
        Scene {
            obstacles: &crate::obstacles::NO_OBSTACLES,
            arena_m: 10.0,
            ways: None,
            poses: &POSES,
            commands: &COMMANDS,
            desired: &DESIRED,
            observed: &[[1, 2], [2, 0], [0, 1]],
            slots: &SLOTS,
            goal: [1.0, 3.0],
        }
    }

    #[test]
    fn state_is_centroid_relative_and_rotated_into_robot_zeros_heading() {
        let tick = three_robots();
        let features = CriticFeatures::new(3, ObservationModel::Slot, CriticArchitecture::Mlp);
        assert_eq!(features.dim(), 12 + 2 + 6 + 6);
        let mut out = vec![0.0; features.dim()];
        features.write(&mut out, &tick, std::f32::consts::FRAC_PI_2);
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        // World +y is the frame's +x, world +x its -y.
        assert!(close(&out[0..4], &[-1.0, 0.0, 1.0, 0.0]), "robot 0: {:?}", &out[0..4]);
        assert!(close(&out[4..8], &[1.0, -1.0, 0.0, -1.0]), "robot 1: {:?}", &out[4..8]);
        assert!(close(&out[8..12], &[0.0, 1.0, 0.0, 1.0]), "robot 2: {:?}", &out[8..12]);
        assert!(close(&out[12..14], &[2.0, 0.0]), "goal: {:?}", &out[12..14]);
        assert!(close(&out[14..20], &[1.0, 1.5, 1.2, 1.3, 1.4, 1.6]), "desired");
        assert!(
            close(&out[20..26], &[-1.0, 0.0, 1.0, -1.0, 0.0, 1.0]),
            "slots: {:?}",
            &out[20..26]
        );
        // The paper's observation has no slots in the critic state.
        assert_eq!(
            CriticFeatures::new(3, ObservationModel::Paper, CriticArchitecture::Mlp).dim(),
            20
        );
    }

    #[test]
    fn pooled_tokens_hold_each_robot_its_neighbours_and_the_goal_in_one_frame() {
        let tick = three_robots();
        let features = CriticFeatures::new(3, ObservationModel::SlotProximity, CriticArchitecture::Pooled);
        assert_eq!(features.token_dim(), 14);
        assert_eq!(features.dim(), 3 * 14);
        let mut out = vec![0.0; features.dim()];
        features.write(&mut out, &tick, std::f32::consts::FRAC_PI_2);
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        // In the frame, world +y is +x and world +x is -y: (dx, dy) -> (dy, -dx).
        let robot0 = [-1.0, 0.0, 1.0, 0.0, 2.0, -1.0, 1.0, 1.0, 1.0, 1.5, 2.0, 0.0, -1.0, 0.0];
        assert!(close(&out[..14], &robot0), "robot 0: {:?}", &out[..14]);
        // Robot 2 observes robots 0 and 1.
        let robot2 = [0.0, 1.0, 0.0, 1.0, -1.0, -1.0, 1.0, -2.0, 1.4, 1.6, 2.0, 0.0, 0.0, 1.0];
        assert!(close(&out[28..], &robot2), "robot 2: {:?}", &out[28..]);
        // A robot out of the formation (it observes itself) does not move the members' frame:
        // with a fourth robot out, far away, the three members' tokens are the same floats.
        let poses = [POSES[0], POSES[1], POSES[2], pose(9.0, -7.0, 1.0)];
        let four = Scene {
            obstacles: &crate::obstacles::NO_OBSTACLES,
            arena_m: 10.0,
            ways: None,
            poses: &poses,
            commands: &[(0.0, 0.0); 4],
            desired: &[DESIRED[0], DESIRED[1], DESIRED[2], [0.0; NEIGHBOURS]],
            observed: &[[1, 2], [2, 0], [0, 1], [3, 3]],
            slots: &[SLOTS[0], SLOTS[1], SLOTS[2], [0.0; 2]],
            goal: tick.goal,
        };
        let features4 = CriticFeatures::new(4, ObservationModel::SlotProximity, CriticArchitecture::Pooled);
        let mut out4 = vec![0.0; features4.dim()];
        features4.write(&mut out4, &four, std::f32::consts::FRAC_PI_2);
        assert_eq!(&out4[..3 * 14], &out[..]);
        // A token does not depend on N: the paper's observation drops only the slot.
        assert_eq!(
            CriticFeatures::new(64, ObservationModel::Paper, CriticArchitecture::Pooled).token_dim(),
            12
        );
    }

    #[test]
    fn map_points_give_each_robot_its_nearest_obstacles_in_the_frame() {
        use crate::obstacles::{Obstacle, Obstacles};
        let disc = |centre: [f64; 2], radius: f64| Obstacle::Disc { centre, radius };
        // Robot 0 stands at (1, 0): the disc at (1, 2) is nearest, its surface 1.5 m away in
        // world +y; the one at (-1, 0) next, 1.75 m away in world -x; the third is beyond 4 m.
        let obstacles = Obstacles::new(vec![
            disc([-1.0, 0.0], 0.25),
            disc([1.0, 2.0], 0.5),
            disc([9.0, 9.0], 0.5),
        ]);
        let tick = Scene {
            obstacles: &obstacles,
            ..three_robots()
        };
        let plain = CriticFeatures::new(3, ObservationModel::SlotProximity, CriticArchitecture::Pooled);
        let mapped = plain.with_map_points(3);
        assert_eq!(mapped.token_dim(), 14 + 9);
        let mut out = vec![0.0; mapped.dim()];
        mapped.write(&mut out, &tick, std::f32::consts::FRAC_PI_2);
        let mut without = vec![0.0; plain.dim()];
        plain.write(&mut without, &tick, std::f32::consts::FRAC_PI_2);
        let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
        // The rest of the token is unchanged; nearest first, world +y is the frame's +x.
        assert_eq!(&out[..14], &without[..14]);
        let map = [1.5, 0.0, 1.0, 0.0, 1.75, 1.0, 0.0, 0.0, 0.0];
        assert!(close(&out[14..23], &map), "robot 0's map: {:?}", &out[14..23]);
        // With one point only the nearest is kept.
        let one = plain.with_map_points(1);
        let mut out1 = vec![0.0; one.dim()];
        one.write(&mut out1, &tick, std::f32::consts::FRAC_PI_2);
        assert!(
            close(&out1[14..17], &map[..3]),
            "robot 0's nearest: {:?}",
            &out1[14..17]
        );
    }
}
