//! A robot's range sensor: `rays` ranges to the nearest surface around it (obstacles, other
//! robots and the arena's walls), as a planar laser scanner reads them.
//!
//! Ray k points 2 pi k / rays counter-clockwise from the robot's heading (a LaserScan with
//! `angle_min = 0` and `angle_increment = 2 pi / rays`), and reads the distance from the robot's
//! centre to the first surface it meets, capped at `range_m` (nothing within range reads
//! `range_m`). Other robots are discs of radius `eps_coll_m / 2`; the robot's own disc is not
//! seen. The arena is the square [0, side]^2 in which the physics keeps every robot. Obstacles
//! and robots farther than `range_m` are culled before any ray is cast; the casts are parry's
//! (`parry2d-f64`, as [`crate::obstacles`]).

use parry2d_f64::bounding_volume::Aabb;
use parry2d_f64::na::{Isometry2, Point2, Vector2};
use parry2d_f64::query::{Ray, RayCast};
use parry2d_f64::shape::Ball;

use crate::obstacles::{Obstacles, ray_may_meet_circle};
use crate::physics::Pose;

/// A range sensor of `rays` rays up to `range_m`, with buffers kept between scans so that a
/// scan allocates nothing once they have grown.
#[derive(Debug, Clone)]
pub struct RangeSensor {
    range_m: f64,
    /// Each ray's direction in the robot's frame, (cos, sin).
    directions: Vec<[f64; 2]>,
    /// The obstacles near the scanning robot.
    near_obstacles: Vec<usize>,
    /// The other robots near it.
    near_robots: Vec<[f64; 2]>,
}

impl RangeSensor {
    /// A sensor of `rays` rays (ray k at 2 pi k / rays from straight ahead) up to `range_m`.
    pub fn new(rays: usize, range_m: f64) -> Self {
        let directions = (0..rays)
            .map(|k| {
                let (s, c) = (std::f64::consts::TAU * k as f64 / rays as f64).sin_cos();
                [c, s]
            })
            .collect();
        Self {
            range_m,
            directions,
            near_obstacles: Vec::new(),
            near_robots: Vec::new(),
        }
    }

    /// Rays per scan.
    pub fn rays(&self) -> usize {
        self.directions.len()
    }

    /// The longest range read, metres.
    pub fn range_m(&self) -> f64 {
        self.range_m
    }

    /// Robot `own`'s scan among `poses` (every robot, `own` included and not seen), the
    /// `obstacles`, other robots of radius `robot_radius` and the walls of the arena
    /// [0, `arena_m`]^2, into `out` (one range per ray, metres; `out.len()` must be
    /// [`RangeSensor::rays`]).
    pub fn scan(
        &mut self,
        obstacles: &Obstacles,
        poses: &[Pose],
        own: usize,
        robot_radius: f64,
        arena_m: f64,
        out: &mut [f32],
    ) {
        debug_assert_eq!(out.len(), self.directions.len());
        let me = poses[own];
        let origin = [me.x, me.y];
        obstacles.near(origin, self.range_m, &mut self.near_obstacles);
        self.near_robots.clear();
        let reach = self.range_m + robot_radius;
        self.near_robots.extend(
            poses
                .iter()
                .enumerate()
                .filter(|&(k, p)| k != own && (p.x - me.x).hypot(p.y - me.y) <= reach)
                .map(|(_, p)| [p.x, p.y]),
        );
        let arena = Aabb::new(Point2::origin(), Point2::new(arena_m, arena_m));
        let walls_in_range = me.x.min(me.y).min(arena_m - me.x).min(arena_m - me.y) < self.range_m;
        let robot = Ball::new(robot_radius);
        let (sin, cos) = me.theta.sin_cos();
        for (range, d) in out.iter_mut().zip(&self.directions) {
            let direction = [cos * d[0] - sin * d[1], sin * d[0] + cos * d[1]];
            let ray = Ray::new(Point2::new(me.x, me.y), Vector2::new(direction[0], direction[1]));
            // From inside the arena, a hollow cast reads the distance to the wall it leaves by
            // (no wall within range: nothing to cast).
            let mut nearest = if walls_in_range {
                arena.cast_local_ray(&ray, self.range_m, false).unwrap_or(self.range_m)
            } else {
                self.range_m
            };
            if let Some(hit) = obstacles.cast_ray_among(&self.near_obstacles, origin, direction, nearest) {
                nearest = nearest.min(hit);
            }
            for other in &self.near_robots {
                if !ray_may_meet_circle(origin, direction, *other, robot_radius, nearest) {
                    continue;
                }
                let place = Isometry2::translation(other[0], other[1]);
                if let Some(hit) = robot.cast_ray(&place, &ray, nearest, true) {
                    nearest = nearest.min(hit);
                }
            }
            *range = nearest as f32;
        }
    }
}

/// Each ray of a normalised `scan` (ranges / `scan_range`, evenly spread from straight ahead
/// anticlockwise, as [`RangeSensor::scan`] reads them) as its unit direction and its range in
/// metres.
pub fn rays(scan: &[f32], scan_range: f64) -> impl Iterator<Item = ([f64; 2], f64)> + Clone + '_ {
    let count = scan.len() as f64;
    scan.iter().enumerate().map(move |(k, &reading)| {
        let (s, c) = (std::f64::consts::TAU * k as f64 / count).sin_cos();
        ([c, s], f64::from(reading) * scan_range)
    })
}

/// The gap a braking robot keeps to the hit ahead, metres, beyond its radius.
pub const BRAKE_MARGIN_M: f64 = 0.05;

/// The top forward speed of a robot of `robot_radius` that brakes before the hits of the
/// normalised `scan` in its path (within `robot_radius + slack` of its line): `v_max` times
/// (the free distance ahead - [`BRAKE_MARGIN_M`]) / `brake_range`, clamped to [0, 1]. The
/// potential field's brake and the collision monitor both read it.
pub fn braking_speed(
    scan: &[f32],
    scan_range: f64,
    robot_radius: f64,
    slack: f64,
    brake_range: f64,
    v_max: f64,
) -> f64 {
    speed_before(
        free_distance_ahead(scan, scan_range, robot_radius, slack),
        brake_range,
        v_max,
    )
}

/// The top forward speed of a braking robot that can drive `free` metres before it touches
/// what is in its path ([`nearest_in_path`]): `v_max` times (`free` - [`BRAKE_MARGIN_M`]) /
/// `brake_range`, clamped to [0, 1].
pub fn speed_before(free: f64, brake_range: f64, v_max: f64) -> f64 {
    v_max * ((free - BRAKE_MARGIN_M) / brake_range).clamp(0.0, 1.0)
}

/// How far a robot of `robot_radius` can drive straight ahead before its disc reaches a hit of
/// the normalised `scan` that lies in its path (within `robot_radius + slack` of its line, the
/// slack standing for the surface between sparse rays), metres; `scan_range` when no hit lies
/// there.
fn free_distance_ahead(scan: &[f32], scan_range: f64, robot_radius: f64, slack: f64) -> f64 {
    nearest_in_path(scan, scan_range, robot_radius, slack).map_or(scan_range, |(free, _)| free)
}

/// The hit of the normalised `scan` in a robot's path (within `robot_radius + slack` of its
/// line, ahead of it) that its disc would reach first: how far the robot can drive before it
/// does (metres, at least 0) and the hit (robot frame). `None` when no hit lies there.
pub fn nearest_in_path(scan: &[f32], scan_range: f64, robot_radius: f64, slack: f64) -> Option<(f64, [f64; 2])> {
    rays(scan, scan_range)
        .filter(|&(towards, range)| towards[0] > 1e-9 && (range * towards[1]).abs() < robot_radius + slack)
        .map(|(towards, range)| {
            let hit = [range * towards[0], range * towards[1]];
            ((hit[0] - robot_radius).max(0.0), hit)
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::obstacles::Obstacle;

    const R: f64 = 0.1;
    const ARENA: f64 = 10.0;

    fn at(x: f64, y: f64, theta: f64) -> Pose {
        Pose { x, y, theta }
    }

    fn scan(obstacles: &Obstacles, poses: &[Pose], rays: usize, range: f64) -> Vec<f32> {
        let mut sensor = RangeSensor::new(rays, range);
        let mut out = vec![0.0; rays];
        sensor.scan(obstacles, poses, 0, R, ARENA, &mut out);
        out
    }

    fn close(a: f32, b: f64) -> bool {
        (f64::from(a) - b).abs() < 1e-5
    }

    #[test]
    fn nothing_in_range_reads_the_range_on_every_ray() {
        let out = scan(&Obstacles::none(), &[at(5.0, 5.0, 0.3)], 16, 2.0);
        assert!(out.iter().all(|&r| r == 2.0), "{out:?}");
    }

    #[test]
    fn a_disc_ahead_reads_its_near_surface_and_rays_go_counter_clockwise() {
        let disc = Obstacles::new(vec![Obstacle::Disc {
            centre: [6.0, 5.0],
            radius: 0.3,
        }]);
        // Heading +y: the disc at +x lies to the right, a quarter turn clockwise, ray 3 of 4.
        let out = scan(&disc, &[at(5.0, 5.0, std::f64::consts::FRAC_PI_2)], 4, 2.0);
        assert!(close(out[3], 0.7), "{out:?}");
        assert!(out[..3].iter().all(|&r| r == 2.0), "{out:?}");
        // An oblique ray meets the circle where |o + t d - c| = r.
        let out = scan(&disc, &[at(5.0, 5.2, 0.0)], 1, 2.0);
        let expected = 1.0 - (0.3f64.powi(2) - 0.2f64.powi(2)).sqrt();
        assert!(close(out[0], expected), "{out:?} vs {expected}");
    }

    #[test]
    fn a_wall_reads_its_face_and_its_end_is_flat() {
        // A wall along y at x = 7, 0.2 thick: its face at x = 6.9, its end at y = 6.
        let wall = Obstacles::new(vec![Obstacle::Wall {
            a: [7.0, 2.0],
            b: [7.0, 6.0],
            thickness: 0.2,
        }]);
        let out = scan(&wall, &[at(5.0, 4.0, 0.0)], 8, 3.0);
        assert!(close(out[0], 1.9), "straight at the face: {out:?}");
        // 45 degrees: the face is reached at x = 6.9 after 1.9 sqrt(2) (y = 5.9 < 6).
        assert!(close(out[1], 1.9 * std::f64::consts::SQRT_2), "{out:?}");
        // From above the wall's end, looking down the +x axis at y = 6.05: the ray passes.
        let out = scan(&wall, &[at(5.0, 6.05, 0.0)], 1, 3.0);
        assert_eq!(out[0], 3.0);
        let out = scan(&wall, &[at(7.0, 7.0, -std::f64::consts::FRAC_PI_2)], 1, 3.0);
        assert!(close(out[0], 1.0), "down onto the flat end: {out:?}");
    }

    #[test]
    fn other_robots_are_discs_and_the_own_disc_is_not_seen() {
        let poses = [at(5.0, 5.0, 0.0), at(6.0, 5.0, 0.0), at(5.0, 3.5, 0.0)];
        let out = scan(&Obstacles::none(), &poses, 4, 2.0);
        assert!(close(out[0], 1.0 - R), "robot ahead: {out:?}");
        assert!(close(out[3], 1.5 - R), "robot to the right: {out:?}");
        assert_eq!([out[1], out[2]], [2.0, 2.0], "own disc unseen: {out:?}");
        // A robot beyond range (centre at range + radius + a bit) is culled and unseen.
        let far = [at(5.0, 5.0, 0.0), at(7.2, 5.0, 0.0)];
        assert_eq!(scan(&Obstacles::none(), &far, 1, 2.0)[0], 2.0);
    }

    #[test]
    fn the_arena_walls_cap_the_ranges() {
        let out = scan(&Obstacles::none(), &[at(0.5, 9.2, 0.0)], 4, 2.0);
        // Ahead (+x) nothing within 2 m; left (+y) the wall at 0.8; behind (-x) at 0.5.
        assert_eq!(out[0], 2.0);
        assert!(close(out[1], 0.8) && close(out[2], 0.5), "{out:?}");
        assert_eq!(out[3], 2.0);
    }

    /// Prints the cost of every robot's scan in a forest episode at N = 32 (16 rays, 2 m):
    /// `cargo test --release -p formation-core scan_cost -- --ignored --nocapture`.
    #[test]
    #[ignore = "a measurement, not a check"]
    fn scan_cost() {
        use crate::config::EnvConfig;
        use crate::formation::Episodes;
        use crate::obstacles::{ObstacleConfig, ObstacleKind, draw, min_goal_distance_m, obstacle_seed};
        let n = 32;
        let base = EnvConfig::default();
        let nearest = min_goal_distance_m(&ObstacleConfig::default(), ObstacleKind::Forest, n, &base);
        let env = EnvConfig {
            goal_min_m: nearest,
            goal_max_m: nearest + 1.0,
            ..base
        };
        let init = Episodes::new(n, &env, 1).next().expect("an episode");
        let starts: Vec<[f64; 2]> = init.poses.iter().map(|p| [p.x, p.y]).collect();
        let forest = draw(
            &ObstacleConfig::default(),
            ObstacleKind::Forest,
            &starts,
            init.goal,
            &init.slots,
            &env,
            obstacle_seed(1, 0),
        );
        let mut sensor = RangeSensor::new(16, 2.0);
        let mut out = [0.0f32; 16];
        let arena = env.effective_arena_m(n);
        // The formation moved half-way to the goal, among the discs.
        let start = crate::task::centroid(&init.poses);
        let half_way = [0.5 * (init.goal[0] - start[0]), 0.5 * (init.goal[1] - start[1])];
        let poses: Vec<Pose> = init
            .poses
            .iter()
            .map(|p| at(p.x + half_way[0], p.y + half_way[1], p.theta))
            .collect();
        let ticks = 2000;
        let started = std::time::Instant::now();
        let mut sum = 0.0f32;
        for _ in 0..ticks {
            for own in 0..n {
                sensor.scan(&forest, &poses, own, R, arena, &mut out);
                sum += out[0];
            }
        }
        let per_tick = started.elapsed().as_secs_f64() / f64::from(ticks);
        println!(
            "{} discs, N = {n}: {:.1} us a tick for every robot's scan ({:.2} us a robot) [{sum}]",
            forest.list().len(),
            per_tick * 1e6,
            per_tick * 1e6 / n as f64
        );
    }

    #[test]
    fn the_nearest_of_several_surfaces_wins() {
        let obstacles = Obstacles::new(vec![
            Obstacle::Disc {
                centre: [7.0, 5.0],
                radius: 0.2,
            },
            Obstacle::Wall {
                a: [8.0, 0.0],
                b: [8.0, 10.0],
                thickness: 0.1,
            },
        ]);
        let poses = [at(5.0, 5.0, 0.0), at(6.0, 5.0, 1.0)];
        assert!(close(scan(&obstacles, &poses, 1, 5.0)[0], 0.9));
        assert!(close(scan(&obstacles, &poses[..1], 1, 5.0)[0], 1.8));
        let out = scan(&obstacles, &poses[..1], 1, 10.0);
        assert!(close(out[0], 1.8), "{out:?}");
    }
}
