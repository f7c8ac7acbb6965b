//! The way round the obstacles: each robot's distance to its slot over the episode's map, for a
//! progress reward that pays a detour round a disc as progress (`env.geodesic_progress`).
//!
//! [`crate::task::robot_progress`] measures a robot's approach along its slot's bearing. Behind a
//! disc that bearing points into the disc: a robot going round it moves away from its slot, so
//! the straight measure charges it for the detour and pays nothing for waiting. Measured along
//! the way round ([`DistanceField::descent`]), going round is progress and waiting is not. The
//! field is the sim's (the map), a training signal only: no robot reads it.
//!
//! Each field is the `pathfinding` crate's Dijkstra over a grid of [`CELL_M`] cells, eight
//! neighbours each (no corner cut past a blocked cell), from the robot's slot at the goal. Eight
//! directions overstate a leg between them by up to 8 %; the reward reads the field's direction,
//! not its length.

use pathfinding::directed::dijkstra::dijkstra_reach;

use crate::obstacles::Obstacles;

/// Side of a grid cell, metres: a passage's 0.35 m gap keeps at least two free cells across.
pub const CELL_M: f64 = 0.1;
/// A cell whose centre is nearer a surface than this is blocked, metres (half a robot's radius:
/// a robot's centre keeps its radius from every surface, so it lies in a free cell).
pub const CLEARANCE_M: f64 = 0.05;
/// Grid steps in Dijkstra's integer costs: millimetres.
const COST_PER_M: f64 = 1e3;
/// How many cells round a robot's cell its way on is looked for.
const LOOK_CELLS: isize = 2;

/// The centre of the `i`-th cell along either axis, metres.
fn cell_centre(i: usize) -> f64 {
    (i as f64 + 0.5) * CELL_M
}

/// The distance from every grid cell to one target over the free cells, metres.
#[derive(Debug, Clone)]
pub struct DistanceField {
    target: [f64; 2],
    side: usize,
    /// Per cell, row-major from (0, 0), metres; infinite where blocked or cut off from the target.
    distance: Vec<f32>,
}

impl DistanceField {
    /// The field to `target` in the arena [0, `arena_m`]^2 among `obstacles`.
    pub fn to(target: [f64; 2], obstacles: &Obstacles, arena_m: f64) -> Self {
        let side = (arena_m / CELL_M).ceil().max(1.0) as usize;
        let free: Vec<bool> = (0..side * side)
            .map(|c| obstacles.is_clear([cell_centre(c % side), cell_centre(c / side)], CLEARANCE_M))
            .collect();
        let mut field = Self {
            target,
            side,
            distance: vec![f32::INFINITY; side * side],
        };
        let Some(start) = field.cell_of(target) else {
            return field;
        };
        let straight = CELL_M * COST_PER_M;
        let diagonal = (straight * std::f64::consts::SQRT_2).round() as u64;
        let straight = straight.round() as u64;
        let successors = |&(x, y): &(usize, usize)| {
            let is_free = |dx: isize, dy: isize| -> Option<(usize, usize)> {
                let (nx, ny) = (x.checked_add_signed(dx)?, y.checked_add_signed(dy)?);
                (nx < side && ny < side && free[ny * side + nx]).then_some((nx, ny))
            };
            let mut next = Vec::with_capacity(8);
            for (dx, dy) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                next.extend(is_free(dx, dy).map(|cell| (cell, straight)));
            }
            for (dx, dy) in [(1, 1), (1, -1), (-1, 1), (-1, -1)] {
                if is_free(dx, 0).is_some() && is_free(0, dy).is_some() {
                    next.extend(is_free(dx, dy).map(|cell| (cell, diagonal)));
                }
            }
            next
        };
        for reached in dijkstra_reach(&start, successors) {
            let (x, y) = reached.node;
            field.distance[y * side + x] = (reached.total_cost as f64 / COST_PER_M) as f32;
        }
        field
    }

    /// The target the field leads to.
    pub fn target(&self) -> [f64; 2] {
        self.target
    }

    /// The cell holding `p`, if inside the grid.
    fn cell_of(&self, p: [f64; 2]) -> Option<(usize, usize)> {
        let index = |v: f64| (v >= 0.0).then(|| (v / CELL_M) as usize).filter(|&i| i < self.side);
        Some((index(p[0])?, index(p[1])?))
    }

    /// The distance from `p` to the target over the map, metres: through the free cell within
    /// two cells of `p` that gives the shortest (infinite when none is reachable).
    pub fn distance(&self, p: [f64; 2]) -> f64 {
        self.way_on(p).map_or(f64::INFINITY, |(_, d)| d)
    }

    /// The centre of the cell round `p` (within [`LOOK_CELLS`]) through which the way to the
    /// target is shortest, with that way's length from `p`.
    fn way_on(&self, p: [f64; 2]) -> Option<([f64; 2], f64)> {
        let (x, y) = self.cell_of(p)?;
        let mut best: Option<([f64; 2], f64)> = None;
        for dy in -LOOK_CELLS..=LOOK_CELLS {
            for dx in -LOOK_CELLS..=LOOK_CELLS {
                let (Some(cx), Some(cy)) = (x.checked_add_signed(dx), y.checked_add_signed(dy)) else {
                    continue;
                };
                if cx >= self.side || cy >= self.side {
                    continue;
                }
                let rest = f64::from(self.distance[cy * self.side + cx]);
                let centre = [cell_centre(cx), cell_centre(cy)];
                let total = rest + (centre[0] - p[0]).hypot(centre[1] - p[1]);
                if total.is_finite() && best.is_none_or(|(_, d)| total < d) {
                    best = Some((centre, total));
                }
            }
        }
        best
    }

    /// The unit vector, world frame, along which a robot at `p` comes closer to the target
    /// round the obstacles: straight at it when the straight way is clear, else towards the
    /// nearby cell the way goes on through. `None` when the grid shows no way.
    pub fn descent(&self, p: [f64; 2], obstacles: &Obstacles) -> Option<[f64; 2]> {
        let towards = |to: [f64; 2]| {
            let (dx, dy) = (to[0] - p[0], to[1] - p[1]);
            let length = dx.hypot(dy);
            (length > 1e-9).then(|| [dx / length, dy / length])
        };
        if obstacles.segment_is_clear(p, self.target, CLEARANCE_M) {
            return towards(self.target);
        }
        towards(self.way_on(p)?.0)
    }
}

/// Every robot's [`DistanceField`] to its slot at the goal, for one formation and goal.
#[derive(Debug, Clone)]
pub struct Ways {
    fields: Vec<DistanceField>,
}

impl Ways {
    /// The fields to `goal + slot` for each robot's slot offset in `slots`.
    pub fn new(goal: [f64; 2], slots: &[[f64; 2]], obstacles: &Obstacles, arena_m: f64) -> Self {
        Self {
            fields: slots
                .iter()
                .map(|slot| DistanceField::to([goal[0] + slot[0], goal[1] + slot[1]], obstacles, arena_m))
                .collect(),
        }
    }

    /// Whether these are the fields to `goal + slot` for every robot.
    pub fn lead_to(&self, goal: [f64; 2], slots: &[[f64; 2]]) -> bool {
        self.fields.len() == slots.len()
            && self.fields.iter().zip(slots).all(|(field, slot)| {
                let target = field.target();
                (target[0] - goal[0] - slot[0]).abs() < 1e-9 && (target[1] - goal[1] - slot[1]).abs() < 1e-9
            })
    }

    /// Robot `agent`'s field.
    pub fn field(&self, agent: usize) -> &DistanceField {
        &self.fields[agent]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::obstacles::Obstacle;

    fn wall_between() -> Obstacles {
        // A wall from y = 2 to y = 8 at x = 5: a robot at (3, 5) must go round one end.
        Obstacles::new(vec![Obstacle::Wall {
            a: [5.0, 2.0],
            b: [5.0, 8.0],
            thickness: 0.2,
        }])
    }

    #[test]
    fn in_the_open_the_way_is_the_straight_line() {
        let field = DistanceField::to([8.0, 5.0], &Obstacles::none(), 10.0);
        let d = field.distance([2.0, 5.0]);
        assert!((d - 6.0).abs() < 0.15, "straight 6 m, grid {d:.3}");
        let along = field.descent([2.0, 5.0], &Obstacles::none()).expect("a way");
        assert!((along[0] - 1.0).abs() < 1e-9 && along[1].abs() < 1e-9, "{along:?}");
    }

    #[test]
    fn behind_a_wall_the_way_goes_round_its_end_and_is_that_long() {
        let obstacles = wall_between();
        let field = DistanceField::to([7.0, 5.0], &obstacles, 10.0);
        // Round either end: (3, 5) -> (5, 8.1) -> (7, 5), about 2 x 3.7 m.
        let round = 2.0 * (2.0f64).hypot(3.1);
        let d = field.distance([3.0, 5.0]);
        // Eight directions overstate a leg between them by up to 8 %.
        assert!(
            d > round - 0.1 && d < 1.09 * round,
            "round the wall {round:.2} m, grid {d:.2}"
        );
        let along = field.descent([3.0, 5.0], &obstacles).expect("a way");
        assert!(
            along[1].abs() > 0.6,
            "turns towards an end of the wall, not into it: {along:?}"
        );
        assert!(along[0] > 0.2, "and onwards: {along:?}");
    }

    #[test]
    fn a_target_walled_in_leaves_no_way() {
        let boxed = Obstacles::new(
            [
                ([4.0, 4.0], [6.0, 4.0]),
                ([6.0, 4.0], [6.0, 6.0]),
                ([6.0, 6.0], [4.0, 6.0]),
                ([4.0, 6.0], [4.0, 4.0]),
            ]
            .into_iter()
            .map(|(a, b)| Obstacle::Wall { a, b, thickness: 0.3 })
            .collect(),
        );
        let field = DistanceField::to([5.0, 5.0], &boxed, 10.0);
        assert!(field.distance([1.0, 1.0]).is_infinite());
        assert!(field.descent([1.0, 1.0], &boxed).is_none());
        assert!(field.distance([5.2, 5.0]) < 0.5, "inside the box the target is near");
    }

    #[test]
    fn the_ways_know_which_goal_and_slots_they_lead_to() {
        let slots = [[0.0, 0.5], [0.0, -0.5]];
        let ways = Ways::new([7.0, 5.0], &slots, &wall_between(), 10.0);
        assert!(ways.lead_to([7.0, 5.0], &slots));
        assert!(!ways.lead_to([7.0, 5.1], &slots), "another goal");
        assert!(!ways.lead_to([7.0, 5.0], &slots[..1]), "another formation");
        assert_eq!(ways.field(1).target(), [7.0, 4.5]);
    }
}
