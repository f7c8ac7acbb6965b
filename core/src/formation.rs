//! Formations and episodes: robots start exactly in formation around a random centroid, with
//! a random goal 1 to 2.5 m away. Shapes are random rigid ones or named ones (ring, line,
//! wedge, grid), all drawn at a random size and orientation.
//!
//! Robot i observes (i+1) mod N and (i+2) mod N, so a shape's robots are numbered along a
//! closed tour of it: every tour step and every second step is an observed edge and must lie in
//! [edge_min, edge_max]. A line is therefore two staggered files (the tour goes up one and down
//! the other), a wedge is that band bent into a V, and a grid is toured by a boustrophedon that
//! returns along its first column.

use formation_protocol::config::{EnvConfig, FormationShape, LARGE_SWARM};
use formation_protocol::{NEIGHBOURS, neighbours};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::physics::{Pose, wrap_angle};

/// Closest two robots of a formation may be, as a multiple of eps_coll (keeps starts safe).
pub const MIN_SEPARATION_FACTOR: f64 = 2.5;
/// Relaxation sweeps that pull a drawn shape into the allowed edge lengths.
const RELAX_SWEEPS: usize = 400;
/// Lattice spacing of the named shapes, as a fraction of edge_max / 2 (so two steps fit).
const SPACING_RANGE: std::ops::Range<f64> = 0.85..0.95;

/// Where an episode starts and where it must go.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeInit {
    /// Start poses (in formation).
    pub poses: Vec<Pose>,
    /// Desired length of each robot's two observed edges.
    pub desired: Vec<[f64; NEIGHBOURS]>,
    /// Goal for the centroid.
    pub goal: [f64; 2],
    /// Each robot's offset from the goal in the goal formation (the start shape translated to
    /// the goal, same orientation), world frame.
    pub slots: Vec<[f64; 2]>,
}

/// The observed (directed) edges of a swarm of `n` robots.
pub fn observed_edges(n: usize) -> impl Iterator<Item = (usize, usize, usize)> {
    (0..n).flat_map(move |i| neighbours(i, n).into_iter().enumerate().map(move |(k, j)| (i, k, j)))
}

fn edge_ok(length: f64, env: &EnvConfig) -> bool {
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

/// A shape of `n` robots of kind `shape`, centred on the origin, numbered along its tour, with
/// every observed edge in [edge_min, edge_max] and no two robots closer than a safe margin.
/// The x axis is the shape's forward direction (a wedge points along +x).
pub fn draw_shape<R: Rng>(shape: FormationShape, n: usize, env: &EnvConfig, rng: &mut R) -> Vec<[f64; 2]> {
    match shape {
        FormationShape::Random => return random_shape(n, env, rng),
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
            FormationShape::Ring => ring(n, spacing),
            FormationShape::Line => files(n, spacing),
            FormationShape::Wedge => wedge(files(n, spacing), rng.random_range(0.45..0.7)),
            FormationShape::Grid => grid(n, spacing),
        };
        if shape_is_valid(&points, env) || (relax(&mut points, env) && shape_is_valid(&points, env)) {
            return centred(points);
        }
    }
}

/// Robots evenly on a circle whose chord between tour neighbours is `spacing`.
fn ring(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    let step = std::f64::consts::TAU / n as f64;
    let radius = spacing / (2.0 * (0.5 * step).sin());
    (0..n)
        .map(|i| [radius * (i as f64 * step).cos(), radius * (i as f64 * step).sin()])
        .collect()
}

/// Two staggered files along x, `spacing` apart along and across: the tour runs forward along
/// the first file and back along the second.
fn files(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    let front = n.div_ceil(2);
    let back = n - front;
    let across = spacing;
    let first = (0..front).map(|k| [k as f64 * spacing, 0.0]);
    let second = (0..back).rev().map(|k| [(k as f64 + 0.5) * spacing, across]);
    first.chain(second).collect()
}

/// A band of two files bent at its middle into a V whose arms open at `half_angle` (radians)
/// behind an apex at the front.
fn wedge(band: Vec<[f64; 2]>, half_angle: f64) -> Vec<[f64; 2]> {
    let middle = band.iter().map(|p| p[0]).fold(0.0, f64::max) * 0.5;
    let (s, c) = half_angle.sin_cos();
    band.iter()
        .map(|p| {
            let along = p[0] - middle;
            let across = p[1];
            let side = if along < 0.0 { 1.0 } else { -1.0 };
            // Each arm runs back from the apex; the second file sits on the arm's outer side.
            [-c * along.abs() + s * across, side * (s * along.abs() + c * across)]
        })
        .collect()
}

/// A block of `rows` (even) by `columns` lattice points `spacing` apart, toured by a
/// boustrophedon over columns 1.. that returns along column 0; odd `n` gets a nose robot ahead
/// of the block's first row.
fn grid(n: usize, spacing: f64) -> Vec<[f64; 2]> {
    if n < 5 {
        return ring(n, spacing);
    }
    let even = n - n % 2;
    let mut rows = 2;
    while (rows + 2) * (rows + 2) <= even {
        rows += 2;
    }
    let columns = even.div_ceil(rows);
    // Lattice points the block leaves out: pairs of rows at the end of the last column.
    let missing_pairs = (rows * columns - even) / 2;
    let present = |row: usize, column: usize| column + 1 < columns || row < rows - 2 * missing_pairs;
    let point = |row: usize, column: usize| [column as f64 * spacing, -(row as f64) * spacing];
    let mut tour = Vec::with_capacity(n);
    for row in 0..rows {
        let columns_of_row: Vec<usize> = if row % 2 == 0 {
            (1..columns).collect()
        } else {
            (1..columns).rev().collect()
        };
        tour.extend(
            columns_of_row
                .into_iter()
                .filter(|&column| present(row, column))
                .map(|column| point(row, column)),
        );
    }
    tour.extend((0..rows).rev().map(|row| point(row, 0)));
    // The tour ends at (0, 0); rotate it to start there, then put the nose between (0, 0) and
    // (0, 1), half a spacing ahead of the first row.
    tour.rotate_right(1);
    if n % 2 == 1 {
        tour.insert(1, [0.5 * spacing, 0.9 * spacing]);
    }
    tour
}

/// A random shape of `n` robots, centred on the origin, whose observed edges all lie in
/// [edge_min, edge_max] and whose robots are at least a safe distance apart.
///
/// Robots start on a perturbed ring (any N closes the triangle strip), then alternate
/// projections move each edge into range and push close pairs apart; a shape that does not
/// settle is discarded and drawn again.
pub fn random_shape<R: Rng>(n: usize, env: &EnvConfig, rng: &mut R) -> Vec<[f64; 2]> {
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
        relax(&mut points, env);
        if shape_is_valid(&points, env) {
            return centred(points);
        }
    }
}

/// A random episode: a shape of the configured kind, rotated to a common random heading, placed
/// at a random centroid, with each robot's heading jittered, and a goal in the arena.
pub fn random_episode<R: Rng>(n: usize, env: &EnvConfig, rng: &mut R) -> EpisodeInit {
    let arena = env.effective_arena_m(n);
    let shape = draw_shape(env.shape, n, env, rng);
    let reach = shape.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
    // Never more than half the arena, so the ranges below are never empty.
    let margin = (reach + 0.5).min(0.5 * arena - 0.01);
    let heading = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
    let (s, c) = heading.sin_cos();
    for attempt in 0u32.. {
        let centre = [
            rng.random_range(margin..arena - margin),
            rng.random_range(margin..arena - margin),
        ];
        let goal_angle = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let goal_dist = rng.random_range(env.goal_min_m..=env.goal_max_m);
        let goal = [
            centre[0] + goal_dist * goal_angle.cos(),
            centre[1] + goal_dist * goal_angle.sin(),
        ];
        // The goal needs the formation's room around it too; a swarm too big for that (only with
        // a hand-shrunk arena) takes a goal merely inside the arena.
        let inside =
            |v: f64| (margin..=arena - margin).contains(&v) || (attempt > 10_000 && (0.0..=arena).contains(&v));
        if !inside(goal[0]) || !inside(goal[1]) {
            continue;
        }
        let poses: Vec<Pose> = shape
            .iter()
            .map(|p| Pose {
                x: centre[0] + c * p[0] - s * p[1],
                y: centre[1] + s * p[0] + c * p[1],
                theta: wrap_angle(heading + rng.random_range(-1.0..=1.0) * env.heading_jitter_rad),
            })
            .collect();
        let desired = (0..n)
            .map(|i| {
                let nb = neighbours(i, n);
                let d = |j: usize| (poses[i].x - poses[j].x).hypot(poses[i].y - poses[j].y);
                [d(nb[0]), d(nb[1])]
            })
            .collect();
        let slots = shape
            .iter()
            .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1]])
            .collect();
        return EpisodeInit {
            poses,
            desired,
            goal,
            slots,
        };
    }
    unreachable!("the attempt counter is unbounded")
}

/// The episodes of a run, in order: episode k is the k-th [`random_episode`] drawn from one
/// generator seeded with the run's seed. The sim plays these, and the critic's model selection
/// plays the first K of its own seed, so both start every episode from the same function.
#[derive(Debug, Clone)]
pub struct Episodes {
    n: usize,
    env: EnvConfig,
    rng: StdRng,
}

impl Episodes {
    /// The episodes of `n` robots that `seed` starts.
    pub fn new(n: usize, env: &EnvConfig, seed: u64) -> Self {
        Self {
            n,
            env: env.clone(),
            rng: StdRng::seed_from_u64(seed),
        }
    }
}

impl Iterator for Episodes {
    type Item = EpisodeInit;

    /// Never `None`: a run may play as many episodes as it likes.
    fn next(&mut self) -> Option<EpisodeInit> {
        Some(random_episode(self.n, &self.env, &mut self.rng))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::{centroid, conditions};

    #[test]
    fn episodes_of_every_shape_start_in_formation_with_valid_edges_for_3_to_64_robots() {
        for shape in [
            FormationShape::Random,
            FormationShape::Ring,
            FormationShape::Line,
            FormationShape::Wedge,
            FormationShape::Grid,
            FormationShape::Mixed,
        ] {
            let env = EnvConfig {
                shape,
                ..EnvConfig::default()
            };
            episodes_start_valid(&env);
        }
    }

    fn episodes_start_valid(env: &EnvConfig) {
        let env = env.clone();
        let mut rng = StdRng::seed_from_u64(7);
        for n in 3..=64 {
            for _ in 0..if n <= 8 || n % 8 == 0 { 6 } else { 1 } {
                let init = random_episode(n, &env, &mut rng);
                // The slots are the start shape: each robot starts at centroid + its slot.
                let start = centroid(&init.poses);
                for (pose, slot) in init.poses.iter().zip(&init.slots) {
                    assert!((pose.x - start[0] - slot[0]).hypot(pose.y - start[1] - slot[1]) < 1e-9);
                }
                let c = conditions(&init.poses, &init.desired, init.goal, &env);
                assert!(c.in_formation && !c.collision, "{:?} n={n}: {c:?}", env.shape);
                for row in &init.desired {
                    for &d in row {
                        assert!(edge_ok(d, &env), "n={n}: edge {d}");
                    }
                }
                let start = centroid(&init.poses);
                let dist = (start[0] - init.goal[0]).hypot(start[1] - init.goal[1]);
                assert!((env.goal_min_m - 1e-9..=env.goal_max_m + 1e-9).contains(&dist));
                let arena = env.effective_arena_m(n);
                let start = centroid(&init.poses);
                let reach = init
                    .poses
                    .iter()
                    .map(|p| (p.x - start[0]).hypot(p.y - start[1]))
                    .fold(0.0, f64::max);
                assert!(
                    reach <= env.formation_reach_m(n),
                    "{:?} n={n}: reach {reach} > {}",
                    env.shape,
                    env.formation_reach_m(n)
                );
                assert!(
                    init.poses
                        .iter()
                        .all(|p| (0.0..=arena).contains(&p.x) && (0.0..=arena).contains(&p.y))
                );
            }
        }
    }

    #[test]
    fn a_seed_starts_the_same_episodes_every_time_and_another_seed_others() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(11);
        let drawn: Vec<EpisodeInit> = (0..4).map(|_| random_episode(3, &env, &mut rng)).collect();
        assert_eq!(Episodes::new(3, &env, 11).take(4).collect::<Vec<_>>(), drawn);
        let other: Vec<EpisodeInit> = Episodes::new(3, &env, 12).take(4).collect();
        assert!(other.iter().all(|init| !drawn.contains(init)));
    }

    #[test]
    fn neighbour_graph_is_rigid() {
        // Laman count: a minimally rigid 2-D graph on n >= 3 vertices has at least 2n - 3
        // independent edges; the triangle strip i -> i+1, i+2 has exactly 2n undirected edges for
        // n >= 5, and every vertex is in at least two triangles. Check rigidity numerically:
        // the rigidity matrix of a generic placement has rank 2n - 3.
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(3);
        for n in 3..=64 {
            let shape = random_shape(n, &env, &mut rng);
            let mut edges: Vec<(usize, usize)> = observed_edges(n).map(|(i, _, j)| (i.min(j), i.max(j))).collect();
            edges.sort_unstable();
            edges.dedup();
            let rows: Vec<Vec<f64>> = edges
                .iter()
                .map(|&(i, j)| {
                    let mut row = vec![0.0; 2 * n];
                    let (dx, dy) = (shape[i][0] - shape[j][0], shape[i][1] - shape[j][1]);
                    row[2 * i] = dx;
                    row[2 * i + 1] = dy;
                    row[2 * j] = -dx;
                    row[2 * j + 1] = -dy;
                    row
                })
                .collect();
            assert_eq!(rank(rows), 2 * n - 3, "n = {n}: the neighbour graph is not rigid");
        }
    }

    /// Rank by Gaussian elimination with partial pivoting.
    fn rank(mut rows: Vec<Vec<f64>>) -> usize {
        let cols = rows.first().map_or(0, Vec::len);
        let mut rank = 0;
        for col in 0..cols {
            let Some(pivot) = (rank..rows.len()).max_by(|&a, &b| rows[a][col].abs().total_cmp(&rows[b][col].abs()))
            else {
                break;
            };
            if rows[pivot][col].abs() < 1e-9 {
                continue;
            }
            rows.swap(rank, pivot);
            let pivot_row = rows[rank].clone();
            for (r, row) in rows.iter_mut().enumerate() {
                if r != rank {
                    let factor = row[col] / pivot_row[col];
                    for (value, pivot_value) in row[col..].iter_mut().zip(&pivot_row[col..]) {
                        *value -= factor * pivot_value;
                    }
                }
            }
            rank += 1;
        }
        rank
    }
}
