//! Formation shapes, one file each (`random`, `ring`, `line`, `wedge`, `grid`), and what every
//! shape must satisfy.
//!
//! Robot i observes (i+1) mod N and (i+2) mod N, so a shape's robots are numbered along a
//! closed tour of it: every tour step and every second step is an observed edge and must lie in
//! [edge_min, edge_max]. A line is therefore two staggered files (the tour goes up one and down
//! the other), a wedge is that band bent into a V, and a grid is toured by a boustrophedon that
//! returns along its first column. A new shape is a file here, a variant of `FormationShape` and
//! an arm in [`draw_shape`].

mod grid;
mod line;
mod random;
mod ring;
mod wedge;

use crate::config::{EnvConfig, FormationShape};
use formation_protocol::neighbours;
use rand::Rng;

pub use random::points as random_shape;

/// Closest two robots of a formation may be, as a multiple of eps_coll (keeps starts safe).
pub const MIN_SEPARATION_FACTOR: f64 = 2.5;
/// Relaxation sweeps that pull a drawn shape into the allowed edge lengths.
const RELAX_SWEEPS: usize = 400;
/// Lattice spacing of the named shapes, as a fraction of edge_max / 2 (so two steps fit).
const SPACING_RANGE: std::ops::Range<f64> = 0.85..0.95;

/// The observed (directed) edges of a swarm of `n` robots.
pub fn observed_edges(n: usize) -> impl Iterator<Item = (usize, usize, usize)> {
    (0..n).flat_map(move |i| neighbours(i, n).into_iter().enumerate().map(move |(k, j)| (i, k, j)))
}

pub(crate) fn edge_ok(length: f64, env: &EnvConfig) -> bool {
    length >= env.edge_min_m && length <= env.edge_max_m
}

fn distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// True when every observed edge is in range and no two robots are closer than the margin.
pub fn shape_is_valid(points: &[[f64; 2]], env: &EnvConfig) -> bool {
    let n = points.len();
    let min_sep = env.eps_coll_m * MIN_SEPARATION_FACTOR;
    observed_edges(n).all(|(i, _, j)| edge_ok(distance(points[i], points[j]), env))
        && (0..n).all(|i| (i + 1..n).all(|j| distance(points[i], points[j]) >= min_sep))
}

/// Alternate projections: each observed edge towards the allowed range, each too-close pair
/// apart. Returns true once a sweep changed nothing that mattered.
fn relax(points: &mut [[f64; 2]], env: &EnvConfig) -> bool {
    let n = points.len();
    let min_sep = env.eps_coll_m * MIN_SEPARATION_FACTOR;
    for _ in 0..RELAX_SWEEPS {
        let mut settled = true;
        for (i, _, j) in observed_edges(n) {
            let (dx, dy) = (points[j][0] - points[i][0], points[j][1] - points[i][1]);
            let d = dx.hypot(dy).max(1e-9);
            if !edge_ok(d, env) {
                settled = false;
            }
            let target = d.clamp(env.edge_min_m * 1.02, env.edge_max_m * 0.98);
            let corr = 0.5 * (d - target) / d;
            points[i][0] += corr * dx;
            points[i][1] += corr * dy;
            points[j][0] -= corr * dx;
            points[j][1] -= corr * dy;
        }
        for i in 0..n {
            for j in i + 1..n {
                let (dx, dy) = (points[j][0] - points[i][0], points[j][1] - points[i][1]);
                let d = dx.hypot(dy).max(1e-9);
                if d < min_sep {
                    settled = false;
                    let corr = 0.5 * (min_sep * 1.05 - d) / d;
                    points[i][0] -= corr * dx;
                    points[i][1] -= corr * dy;
                    points[j][0] += corr * dx;
                    points[j][1] += corr * dy;
                }
            }
        }
        if settled {
            return true;
        }
    }
    false
}

/// Moves the points so that their centroid is the origin.
fn centred(mut points: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    let n = points.len() as f64;
    let (sx, sy) = points.iter().fold((0.0, 0.0), |(sx, sy), p| (sx + p[0], sy + p[1]));
    for p in &mut points {
        p[0] -= sx / n;
        p[1] -= sy / n;
    }
    points
}

/// How far from its centre a formation of `n` robots of kind `shape` reaches at most, metres
/// (`mixed`: the farthest of its kinds): each shape's own formula, in its file, from the
/// largest lattice spacing a draw picks and room for what the relaxation moves.
pub fn reach_m(shape: FormationShape, n: usize, env: &EnvConfig) -> f64 {
    let spacing = (SPACING_RANGE.end * 0.5 * env.edge_max_m).max(1.05 * env.edge_min_m);
    let relax = env.edge_min_m;
    let count = n as f64;
    match shape {
        FormationShape::Mixed => FormationShape::KINDS
            .map(|kind| reach_m(kind, n, env))
            .into_iter()
            .fold(0.0, f64::max),
        FormationShape::Random => random::reach_m(n, env),
        FormationShape::Ring => ring::reach_m(count, spacing, relax),
        FormationShape::Line | FormationShape::Wedge => line::reach_m(count, spacing, relax),
        FormationShape::Grid => grid::reach_m(count, spacing, relax),
    }
}

/// A shape of `n` robots of kind `shape`, centred on the origin, numbered along its tour, with
/// every observed edge in [edge_min, edge_max] and no two robots closer than a safe margin.
/// The x axis is the shape's forward direction (a wedge points along +x).
pub fn draw_shape<R: Rng>(shape: FormationShape, n: usize, env: &EnvConfig, rng: &mut R) -> Vec<[f64; 2]> {
    match shape {
        FormationShape::Random => return random::points(n, env, rng),
        FormationShape::Mixed => {
            let kind = FormationShape::KINDS[rng.random_range(0..FormationShape::KINDS.len())];
            return draw_shape(kind, n, env, rng);
        }
        _ => {}
    }
    loop {
        // Two tour steps along a straight file must fit under edge_max.
        let shortest = env.edge_min_m * 1.05;
        let spacing = shortest.max(rng.random_range(SPACING_RANGE) * 0.5 * env.edge_max_m);
        let mut points = match shape {
            FormationShape::Random | FormationShape::Mixed => unreachable!("drawn above"),
            FormationShape::Ring => ring::points(n, spacing),
            FormationShape::Line => line::points(n, spacing),
            FormationShape::Wedge => wedge::points(line::points(n, spacing), rng.random_range(wedge::HALF_ANGLE)),
            FormationShape::Grid => grid::points(n, spacing),
        };
        if shape_is_valid(&points, env) || (relax(&mut points, env) && shape_is_valid(&points, env)) {
            return centred(points);
        }
    }
}
