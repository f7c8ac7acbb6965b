//! Gap search: how a robot whose way is barred by a straight wall finds the wall's gap from
//! its own window of observations, the scripted baseline's `gap_search_m` option
//! ([`crate::baseline::BaselineGains::gap_search_m`]).
//!
//! Everything here is computed in the robot's frame from what it observes: its scan (a wall is
//! the line through the nearest hit that most other hits lie on) and its goal. The goal is a
//! fixed point and the wall a fixed line, so the robot's position along the wall relative to
//! the goal (its *lateral* position) is the same quantity in every observation of the window,
//! whatever the robot's heading was then. So is the gap's lateral position. The window is the
//! only memory the search needs:
//! * a ray that passes through the wall's line (reads farther than the line, or stops at a
//!   tracked robot standing in it) shows a gap, and a gap an earlier observation of the window
//!   showed is still there: the robot lines up in front of it, funnelling in (the farther off
//!   its centre line, the farther from the wall), queues behind a tracked robot nearer its
//!   mouth, and once in the mouth (a surface close on either side) drives on square through it;
//! * otherwise the robot sweeps along the wall at [`SWEEP_DISTANCE_M`] from it, on in the way it
//!   moved over the last [`LOOK_BACK`] ticks, and back once it is `gap_search_m` past the
//!   straight line through the goal (the way, on which the wall's gap is centred within a known
//!   offset); when it has not been moving along the wall, towards that line.
//!
//! The baseline's brake (`ScriptedBaseline::command_in`) adds one rule for a searching robot:
//! stopped by a hit beside its line, it turns away from that hit (a gap's corner stops a robot
//! a few centimetres off the mouth's middle, and it cannot back out).

use std::f64::consts::PI;

/// Hits within this of a wall's line lie on it, metres (the range noise of a field preset
/// stays inside).
const ON_THE_LINE_M: f64 = 0.06;

/// Fewest hits a wall is read from.
const WALL_HITS: usize = 3;

/// A wall's normal lies within this of the direction from the goal to the robot: the wall
/// barring the way, not the arena's side wall the robot sweeps towards, radians.
const WALL_FACING_RAD: f64 = 0.4 * PI;

/// A ray that reads this much past the wall's line passes through a gap, metres.
const THROUGH_BY_M: f64 = 0.25;

/// How far from the wall's line a sweeping robot keeps, and where it lines up in front of a
/// gap, metres.
pub const SWEEP_DISTANCE_M: f64 = 0.4;

/// The lateral movement over the window below which a robot is taken as not moving along the
/// wall, metres.
const MOVING_M: f64 = 0.03;

/// How many observations back a robot looks to tell which way it is moving along the wall.
pub const LOOK_BACK: usize = 3;

/// How far in front of the wall a robot lines up on a gap per metre it is off the gap's centre
/// line: it funnels in, reaching the line when lined up.
const FUNNEL: f64 = 5.0;

/// A robot whose nearest hits on its left and on its right are both nearer than this may be in
/// a gap's mouth, metres.
const IN_A_GAP_M: f64 = 0.45;

/// ... when those two hits are less than this apart, metres (a gap, not open ground).
const GAP_SPAN_M: f64 = 0.65;

/// ... and when the robot's centre is within this of the line joining them, metres.
const IN_THE_MOUTH_M: f64 = 0.15;

/// How far past the middle of a gap's mouth a robot in it aims, metres.
const IN_A_GAP_LEAD_M: f64 = 0.3;

/// A robot waits for another nearer a gap's mouth than itself when that one is within this of
/// the mouth, metres.
const QUEUE_REACH_M: f64 = 0.8;

/// How far behind the robot ahead a queueing robot waits, metres.
const QUEUE_SPACING_M: f64 = 0.3;

/// A straight wall seen in one scan, in the robot's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wall {
    /// Unit normal, from the wall towards the robot.
    pub normal: [f64; 2],
    /// The robot's distance from the wall's line, metres.
    pub distance: f64,
}

impl Wall {
    /// The straight wall barring the way to `goal` in `hits` (the scan's hits on anything but
    /// a tracked robot, robot frame): the line through the nearest hit with the most other hits
    /// on it (at least [`WALL_HITS`] in all), among lines between the robot and the goal that
    /// face the robot from the goal's side.
    pub fn seen(hits: &[[f64; 2]], goal: [f64; 2]) -> Option<Wall> {
        let nearest = *hits
            .iter()
            .min_by(|a, b| a[0].hypot(a[1]).total_cmp(&b[0].hypot(b[1])))?;
        let goal_distance = goal[0].hypot(goal[1]);
        let from_goal = [-goal[0] / goal_distance, -goal[1] / goal_distance];
        let mut best: Option<(usize, Wall)> = None;
        for other in hits {
            let along = [other[0] - nearest[0], other[1] - nearest[1]];
            let length = along[0].hypot(along[1]);
            if length < 0.1 {
                continue;
            }
            let mut normal = [-along[1] / length, along[0] / length];
            let mut distance = -(nearest[0] * normal[0] + nearest[1] * normal[1]);
            if distance < 0.0 {
                normal = [-normal[0], -normal[1]];
                distance = -distance;
            }
            if (normal[0] * from_goal[0] + normal[1] * from_goal[1]) < WALL_FACING_RAD.cos() {
                continue;
            }
            let wall = Wall { normal, distance };
            if wall.offset(goal) > 0.0 {
                continue;
            }
            let on_it = hits.iter().filter(|h| wall.offset(**h).abs() < ON_THE_LINE_M).count();
            if on_it >= WALL_HITS && best.is_none_or(|(count, _)| on_it > count) {
                best = Some((on_it, wall));
            }
        }
        best.map(|(_, wall)| wall)
    }

    /// The unit direction along the wall, a quarter turn to the left of its normal.
    pub fn along(&self) -> [f64; 2] {
        [-self.normal[1], self.normal[0]]
    }

    /// How far `point` lies from the wall's line, towards the robot's side (negative beyond).
    pub fn offset(&self, point: [f64; 2]) -> f64 {
        point[0] * self.normal[0] + point[1] * self.normal[1] + self.distance
    }

    /// The robot's position along the wall relative to `goal` (both robot frame): 0 on the
    /// straight line through the goal across the wall.
    pub fn lateral(&self, goal: [f64; 2]) -> f64 {
        let along = self.along();
        -(goal[0] * along[0] + goal[1] * along[1])
    }

    /// The nearest gap `rays` (unit direction, range read, whether the hit is a tracked robot)
    /// show in the wall, as its centre's position along the wall from the robot's foot on the
    /// line. A ray passes through when it reads more than [`THROUGH_BY_M`] past the line, or
    /// stops at a tracked robot within a robot's diameter of it. The centre is the midpoint of
    /// the nearest hits on the line either side of the ray, or the ray's own crossing when no
    /// hit bounds it within a metre.
    pub fn gap(&self, rays: &[([f64; 2], f64, bool)], scan_range: f64, robot_radius: f64) -> Option<f64> {
        let along = self.along();
        let crossing = |towards: [f64; 2]| {
            let square = -(towards[0] * self.normal[0] + towards[1] * self.normal[1]);
            (square > 0.2).then(|| self.distance / square)
        };
        let through = rays
            .iter()
            .filter_map(|&(towards, range, tracked)| {
                let at = crossing(towards)?;
                let passes = if tracked {
                    range > at - 2.0 * robot_radius
                } else {
                    range > at + THROUGH_BY_M
                };
                (at < scan_range - THROUGH_BY_M && passes)
                    .then_some(at * (towards[0] * along[0] + towards[1] * along[1]))
            })
            .min_by(|a, b| a.abs().total_cmp(&b.abs()))?;
        let on_line: Vec<f64> = surface_hits(rays, scan_range)
            .into_iter()
            .filter(|hit| self.offset(*hit).abs() < ON_THE_LINE_M)
            .map(|hit| hit[0] * along[0] + hit[1] * along[1])
            .collect();
        let below = on_line.iter().copied().filter(|&s| s < through).max_by(f64::total_cmp);
        let above = on_line.iter().copied().filter(|&s| s > through).min_by(f64::total_cmp);
        Some(match (below, above) {
            (Some(low), Some(high)) if high - low < 1.0 => 0.5 * (low + high),
            _ => through,
        })
    }
}

/// The points (robot frame) where `rays` (unit direction, range read, whether the hit is a
/// tracked robot) hit something other than a tracked robot within `scan_range`.
pub fn surface_hits(rays: &[([f64; 2], f64, bool)], scan_range: f64) -> Vec<[f64; 2]> {
    rays.iter()
        .filter(|&&(_, range, tracked)| range < scan_range && !tracked)
        .map(|&(towards, range, _)| [range * towards[0], range * towards[1]])
        .collect()
}

/// Where a robot in a gap's mouth aims (unit, robot frame), or `None` when it is not in one:
/// the nearest of `hits` (robot frame) on its left and on its right are both within
/// [`IN_A_GAP_M`], less than [`GAP_SPAN_M`] apart, and the robot stands between them within
/// [`IN_THE_MOUTH_M`] of the line joining them; it aims through the middle between them,
/// square to the line joining them, on the side of `goal`.
pub fn in_a_gap(hits: &[[f64; 2]], goal: [f64; 2]) -> Option<[f64; 2]> {
    let nearest = |left: bool| {
        hits.iter()
            .filter(|h| (h[1] > 0.0) == left)
            .min_by(|a, b| a[0].hypot(a[1]).total_cmp(&b[0].hypot(b[1])))
            .copied()
            .filter(|h| h[0].hypot(h[1]) < IN_A_GAP_M)
    };
    let (left, right) = (nearest(true)?, nearest(false)?);
    let across = [left[0] - right[0], left[1] - right[1]];
    let span = across[0].hypot(across[1]);
    if !(1e-6..GAP_SPAN_M).contains(&span) {
        return None;
    }
    // The robot stands between the two, in the mouth's line, not in front of a surface.
    let share = -(right[0] * across[0] + right[1] * across[1]) / (span * span);
    let off_line = (right[0] * across[1] - right[1] * across[0]).abs() / span;
    if !(0.0..=1.0).contains(&share) || off_line > IN_THE_MOUTH_M {
        return None;
    }
    let mut axis = [across[1] / span, -across[0] / span];
    if axis[0] * goal[0] + axis[1] * goal[1] < 0.0 {
        axis = [-axis[0], -axis[1]];
    }
    let middle = [0.5 * (left[0] + right[0]), 0.5 * (left[1] + right[1])];
    let target = [
        middle[0] + IN_A_GAP_LEAD_M * axis[0],
        middle[1] + IN_A_GAP_LEAD_M * axis[1],
    ];
    let length = target[0].hypot(target[1]).max(1e-9);
    Some([target[0] / length, target[1] / length])
}

/// Where a robot at a wall aims (unit, robot frame): through the gap the newest scan shows,
/// else along the wall.
///
/// * `wall`, `gap`: the newest observation's wall and gap ([`Wall::seen`], [`Wall::gap`]);
/// * `lateral_now`, `lateral_before`: the robot's lateral position in the newest observation
///   and [`LOOK_BACK`] observations earlier (`None` where that one saw no wall);
/// * `band`: how far either side of the goal's line the sweep goes;
/// * `robots`: the robots it tracks (robot frame), for queueing at a gap.
pub fn aim(
    wall: &Wall,
    gap: Option<f64>,
    lateral_now: f64,
    lateral_before: Option<f64>,
    band: f64,
    robots: &[[f64; 2]],
) -> [f64; 2] {
    let (normal, along) = (wall.normal, wall.along());
    let point = |sideways: f64, out: f64| {
        // Robot frame: the foot on the wall's line is -distance x normal.
        [
            sideways * along[0] + (out - wall.distance) * normal[0],
            sideways * along[1] + (out - wall.distance) * normal[1],
        ]
    };
    let target = match gap {
        Some(centre) => {
            let funnel = (FUNNEL * centre.abs() - SWEEP_DISTANCE_M).clamp(-SWEEP_DISTANCE_M, SWEEP_DISTANCE_M);
            // Queue behind a robot nearer the gap's mouth, not yet through.
            let mouth = point(centre, 0.0);
            let from_mouth = |q: [f64; 2]| (q[0] - mouth[0]).hypot(q[1] - mouth[1]);
            let mine = from_mouth([0.0, 0.0]);
            let queue = robots
                .iter()
                .filter(|q| wall.offset(**q) > -THROUGH_BY_M && from_mouth(**q) < mine.min(QUEUE_REACH_M))
                .map(|q| wall.offset(*q) + QUEUE_SPACING_M)
                .fold(funnel, f64::max);
            point(centre, queue)
        }
        None => {
            let moved = lateral_before.map_or(0.0, |before| lateral_now - before);
            let mut way = if moved.abs() > MOVING_M {
                moved.signum()
            } else if lateral_now > 0.0 {
                -1.0
            } else {
                1.0
            };
            if way * lateral_now > band {
                way = -way;
            }
            point(way, SWEEP_DISTANCE_M)
        }
    };
    let length = target[0].hypot(target[1]).max(1e-9);
    [target[0] / length, target[1] / length]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hits of 16 rays from a robot `distance` in front of an endless wall along x = 0
    /// (robot at (distance, 0) heading -x), robot frame.
    fn wall_hits(distance: f64) -> Vec<[f64; 2]> {
        (0..16)
            .filter_map(|k| {
                let angle = 2.0 * PI * k as f64 / 16.0;
                let (s, c) = angle.sin_cos();
                // Heading -x: the ray's world x component is -c.
                (c > 0.0)
                    .then(|| distance / c)
                    .filter(|&r| r < 2.0)
                    .map(|r| [r * c, r * s])
            })
            .collect()
    }

    #[test]
    fn a_wall_ahead_is_read_with_its_normal_and_distance() {
        let wall = Wall::seen(&wall_hits(0.5), [3.0, 0.4]).expect("a wall");
        assert!((wall.distance - 0.5).abs() < 1e-9, "{wall:?}");
        assert!(
            (wall.normal[0] + 1.0).abs() < 1e-9 && wall.normal[1].abs() < 1e-9,
            "{wall:?}"
        );
        assert!((wall.lateral([3.0, 0.4]) - 0.4).abs() < 1e-9);
    }

    #[test]
    fn a_wall_behind_the_robot_does_not_bar_the_way() {
        let behind: Vec<[f64; 2]> = wall_hits(0.5).iter().map(|h| [-h[0], h[1]]).collect();
        assert_eq!(Wall::seen(&behind, [3.0, 0.0]), None);
    }

    #[test]
    fn a_ray_through_the_gap_is_lined_up_on_and_driven_through() {
        let wall = Wall {
            normal: [-1.0, 0.0],
            distance: 0.4,
        };
        // Straight ahead reads far past the line; the rays either side hit it.
        let rays: Vec<([f64; 2], f64, bool)> = (0..16)
            .map(|k| {
                let angle = 2.0 * PI * k as f64 / 16.0;
                let (s, c) = angle.sin_cos();
                let range = if k == 0 {
                    2.0
                } else if c > 0.0 {
                    (0.4 / c).min(2.0)
                } else {
                    2.0
                };
                ([c, s], range, false)
            })
            .collect();
        let centre = wall.gap(&rays, 2.0, 0.1).expect("a gap");
        assert!(centre.abs() < 1e-9, "{centre}");
        let through = aim(&wall, Some(centre), 0.0, None, 1.8, &[]);
        assert!(through[0] > 0.99, "{through:?}");
        // The same gap farther along the wall is lined up on first.
        let beside = aim(&wall, Some(0.5), 0.0, None, 1.8, &[]);
        assert!(beside[1] < -0.99, "{beside:?}");
    }

    #[test]
    fn a_robot_in_a_gap_s_mouth_aims_square_through_its_middle() {
        // Turned 0.4 rad left of the gap's axis (+x), 0.05 m right of its middle, sides at y = +-0.2.
        let (s, c) = (-0.4f64).sin_cos();
        let to_robot = |p: [f64; 2]| [c * p[0] - s * p[1], s * p[0] + c * p[1]];
        let hits = [to_robot([0.0, 0.25]), to_robot([0.0, -0.15])];
        let through = in_a_gap(&hits, to_robot([3.0, 0.0])).expect("in a gap");
        let world = [c * through[0] + s * through[1], -s * through[0] + c * through[1]];
        assert!(
            world[0] > 0.9 && world[1] > 0.0,
            "square through, towards the middle: {world:?}"
        );
        assert_eq!(
            in_a_gap(&[[0.0, 0.3], [0.0, -0.5]], [3.0, 0.0]),
            None,
            "too wide for a gap"
        );
        assert_eq!(in_a_gap(&[[0.3, 0.1], [0.3, -0.1]], [3.0, 0.0]), None, "a wall ahead");
    }

    #[test]
    fn the_sweep_keeps_its_way_and_turns_back_past_the_band() {
        let wall = Wall {
            normal: [-1.0, 0.0],
            distance: 0.4,
        };
        // along = (0, -1): lateral grows towards -y.
        let going = aim(&wall, None, 0.5, Some(0.3), 1.8, &[]);
        assert!(going[1] < 0.0, "on in the way it moves: {going:?}");
        let back = aim(&wall, None, 1.9, Some(1.7), 1.8, &[]);
        assert!(back[1] > 0.0, "back past the band: {back:?}");
        let still = aim(&wall, None, 0.5, Some(0.5), 1.8, &[]);
        assert!(still[1] > 0.0, "towards the goal's line when not moving: {still:?}");
    }
}
