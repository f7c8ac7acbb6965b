//! `passage`: a wall from one side of the arena to the other, across the way, with one gap
//! whose centre lies within [`MAX_GAP_OFFSET_M`] of the straight line from start to goal.

use rand::Rng;
use rand::rngs::StdRng;

use super::{MAX_GAP_OFFSET_M, ObstacleConfig, Obstacles, Way, draw_spread, wall_across};

/// A wall across the way, anywhere between the start formation's front and the goal
/// formation's back (each with the clearance), in two pieces either side of the gap. The gap
/// keeps within the arena with a wall's thickness to spare; the pieces reach a thickness past
/// the arena's sides.
pub(super) fn draw(config: &ObstacleConfig, way: &Way, rng: &mut StdRng) -> Obstacles {
    let thickness = draw_spread(config.wall_thickness_m, rng);
    let width = draw_spread(config.gap_width_m, rng);
    let offset = rng.random_range(-MAX_GAP_OFFSET_M..=MAX_GAP_OFFSET_M);
    let first = way.front + way.clearance + 0.5 * thickness;
    let last = way.length - way.back - way.clearance - 0.5 * thickness;
    if first > last {
        return Obstacles::none();
    }
    let along = rng.random_range(first..=last);
    let Some((from, to)) = way.across_arena(along) else {
        return Obstacles::none();
    };
    let (lowest, highest) = (from + thickness + 0.5 * width, to - thickness - 0.5 * width);
    if lowest > highest {
        return Obstacles::none();
    }
    let centre = offset.clamp(lowest, highest);
    Obstacles::new(vec![
        wall_across(way, along, from - thickness, centre - 0.5 * width, thickness),
        wall_across(way, along, centre + 0.5 * width, to + thickness, thickness),
    ])
}
