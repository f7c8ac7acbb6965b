//! `random`: a random rigid shape: a perturbed ring pulled into the allowed edge lengths.

use crate::config::{EnvConfig, LARGE_SWARM};
use rand::Rng;

/// A random shape of `n` robots, centred on the origin, whose observed edges all lie in
/// [edge_min, edge_max] and whose robots are at least a safe distance apart.
///
/// Robots start on a perturbed ring (any N closes the triangle strip), then alternate
/// projections move each edge into range and push close pairs apart; a shape that does not
/// settle is discarded and drawn again.
/// How far a random formation of `n` robots reaches from its centre: edge_max below
/// [`LARGE_SWARM`]; from there a ring whose second-neighbour chord is at most 1.3 edge_min,
/// plus room for the zig-zag and what the relaxation moves.
pub(super) fn reach_m(n: usize, env: &EnvConfig) -> f64 {
    if n < LARGE_SWARM {
        return env.edge_max_m;
    }
    1.3 * env.edge_min_m / (2.0 * (std::f64::consts::TAU / n as f64).sin()) + env.edge_min_m
}

pub fn points<R: Rng>(n: usize, env: &EnvConfig, rng: &mut R) -> Vec<[f64; 2]> {
    let mid_edge = 0.5 * (env.edge_min_m + env.edge_max_m);
    loop {
        let step = std::f64::consts::TAU / n as f64;
        // Ring radius that puts the second neighbour (the longer chord for n >= 5) near mid range.
        let chord_angle = if n >= 5 { 2.0 * step } else { step };
        let large = n >= LARGE_SWARM;
        // Small swarms: any ring that puts the constraining chord around mid range. Large ones:
        // the most compact ring whose second-neighbour chord clears edge_min, so they fit.
        let (chord, jitter) = if large {
            (rng.random_range(1.05..1.2) * env.edge_min_m, 0.03)
        } else {
            (rng.random_range(0.6..1.2) * mid_edge, 0.25)
        };
        let base_radius = chord / (2.0 * (0.5 * chord_angle).sin());
        let mut points: Vec<[f64; 2]> = (0..n)
            .map(|i| {
                let angle = i as f64 * step + rng.random_range(-0.35..0.35) * step * if large { 0.2 } else { 1.0 };
                let zigzag = if n >= 5 && i % 2 == 1 {
                    -0.35 * env.edge_min_m
                } else {
                    0.0
                };
                let radius = base_radius * rng.random_range(1.0 - jitter..1.0 + jitter) + zigzag;
                [radius * angle.cos(), radius * angle.sin()]
            })
            .collect();
        super::relax(&mut points, env);
        if super::shape_is_valid(&points, env) {
            return super::centred(points);
        }
    }
}
