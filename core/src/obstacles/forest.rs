//! `forest`: discs scattered over the corridor between the start and the goal, none inside
//! either formation's room, none overlapping another; a forest the privileged planner finds no
//! path through in file is drawn again from the same stream.

use rand::Rng;
use rand::rngs::StdRng;

use super::{Obstacle, ObstacleConfig, Obstacles, Way, draw_spread};
use crate::planner;

/// How far the corridor reaches beyond the formation's width on each side, metres.
const SIDE_M: f64 = 1.0;
/// Places tried for one disc before the forest stops growing.
const PLACE_ATTEMPTS: usize = 200;
/// Forests drawn before giving up (then the episode has none; in practice a draw this unlucky
/// never came up, see the tests).
const FOREST_ATTEMPTS: usize = 32;

/// A forest through which one robot finds a path from the start centroid to the goal.
pub(super) fn draw(config: &ObstacleConfig, way: &Way, rng: &mut StdRng) -> Obstacles {
    for _ in 0..FOREST_ATTEMPTS {
        let forest = Obstacles::new(discs(config, way, rng));
        let in_file = way.robot_radius + planner::FILE_MARGIN_M;
        if planner::plan_path(&forest, way.start, way.goal(), in_file, way.arena).is_some() {
            return forest;
        }
    }
    Obstacles::none()
}

/// Discs of drawn radii until they cover the drawn density of the corridor (as long as the
/// way, the formation's width plus [`SIDE_M`] each side), until one finds no place, or until
/// the wire's room (`MAX_OBSTACLES`) is full. A disc
/// keeps out of both formations' room (their reach plus the clearance around each centre), out
/// of the other discs and its centre inside the arena.
fn discs(config: &ObstacleConfig, way: &Way, rng: &mut StdRng) -> Vec<Obstacle> {
    let density = draw_spread(config.forest_density, rng);
    let half_width = way.half_width + SIDE_M;
    let mut uncovered = density * way.length * 2.0 * half_width;
    let room = way.reach + way.clearance;
    let goal = way.goal();
    let mut discs: Vec<([f64; 2], f64)> = Vec::new();
    while uncovered > 0.0 && discs.len() < formation_protocol::MAX_OBSTACLES {
        let radius = draw_spread(config.forest_radius_m, rng);
        let placed = (0..PLACE_ATTEMPTS).find_map(|_| {
            let centre = way.at(
                rng.random_range(0.0..=way.length),
                rng.random_range(-half_width..=half_width),
            );
            let distance = |p: [f64; 2]| (centre[0] - p[0]).hypot(centre[1] - p[1]);
            let fits = distance(way.start) >= room + radius
                && distance(goal) >= room + radius
                && centre.iter().all(|c| (0.0..=way.arena).contains(c))
                && discs.iter().all(|&(other, r)| distance(other) >= r + radius);
            fits.then_some(centre)
        });
        let Some(centre) = placed else { break };
        discs.push((centre, radius));
        uncovered -= std::f64::consts::PI * radius * radius;
    }
    discs
        .into_iter()
        .map(|(centre, radius)| Obstacle::Disc { centre, radius })
        .collect()
}
