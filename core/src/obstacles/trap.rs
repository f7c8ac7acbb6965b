//! `trap`: a U on the straight line to the goal, opening towards the start, wider inside than
//! the formation: a formation that drives straight at the goal ends up in it.

use rand::Rng;
use rand::rngs::StdRng;

use super::{Obstacle, ObstacleConfig, Obstacles, Way, draw_spread, wall_across};

/// A back wall across the way and two side walls along it, centred on the straight line; the
/// U's mouth lies ahead of the start formation's front and its back wall before the goal
/// formation's back, each with the clearance. Inside, it is as wide as the formation (its
/// widest robot's centre plus a robot's radius, each side) plus the drawn margin each side.
pub(super) fn draw(config: &ObstacleConfig, way: &Way, rng: &mut StdRng) -> Obstacles {
    let thickness = draw_spread(config.wall_thickness_m, rng);
    let depth = draw_spread(config.trap_depth_m, rng);
    let margin = draw_spread(config.trap_margin_m, rng);
    let first = way.front + way.clearance + depth + 0.5 * thickness;
    let last = way.length - way.back - way.clearance - 0.5 * thickness;
    if first > last {
        return Obstacles::none();
    }
    // The back wall's centre line.
    let along = rng.random_range(first..=last);
    let inner = way.half_width + way.robot_radius + margin;
    let outer = inner + thickness;
    let side = |across: f64| Obstacle::Wall {
        a: way.at(along - 0.5 * thickness - depth, across),
        b: way.at(along + 0.5 * thickness, across),
        thickness,
    };
    Obstacles::new(vec![
        wall_across(way, along, -outer, outer, thickness),
        side(inner + 0.5 * thickness),
        side(-inner - 0.5 * thickness),
    ])
}
