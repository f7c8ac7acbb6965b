//! Episodes: robots start exactly in formation (a shape from [`crate::shapes`]) around a random
//! centroid, with a random goal 1 to 2.5 m away, at a random size and orientation; with
//! `env.shape_changes`, a schedule of new formations drawn from a stream of their own.

use crate::config::{EnvConfig, FormationShape};
use formation_protocol::{NEIGHBOURS, neighbours};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::obstacles::{
    ObstacleKind, Obstacles, clearance_m, draw as draw_obstacles, drawn_kind, episode_steps_with_obstacles,
    obstacle_seed,
};
use crate::physics::{Pose, wrap_angle};
use crate::shapes::draw_shape;

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
    /// The episode's shape changes, by tick (none unless `env.shape_changes`).
    pub changes: Vec<ShapeChange>,
    /// What the start formation is: its kind (`mixed` resolved), turn and size.
    pub spec: FormationSpec,
    /// The episode's obstacles (none unless `env.obstacles.kind` says otherwise).
    pub obstacles: Obstacles,
    /// The kind of obstacles drawn (`mixed` resolved; `none` without obstacles).
    pub obstacle_kind: ObstacleKind,
    /// The episode's time limit, steps ([`EnvConfig::episode_steps`] in the open arena,
    /// [`episode_steps_with_obstacles`] among obstacles).
    pub time_limit: u32,
}

/// What a formation is, beyond its slots: the mission planner draws the same formation again
/// for fewer or more robots when the team changes ([`crate::mission`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormationSpec {
    /// Its shape (never `mixed`).
    pub kind: FormationShape,
    /// Its rotation from the shape as drawn, radians counter-clockwise.
    pub orientation: f64,
    /// Its size as a multiple of the shape as drawn.
    pub scale: f64,
}

/// A new formation for the rest of an episode, from tick `tick` on.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeChange {
    /// The tick whose observations carry the new formation.
    pub tick: u32,
    /// Slot s's offset from the goal, world frame (rotated, centred), in the shape's tour order:
    /// the robot in slot s observes the robots in slots s+1 and s+2 (mod N).
    pub offsets: Vec<[f64; 2]>,
    /// What the new formation is.
    pub spec: FormationSpec,
}

/// Seed of the shape changes' own stream, mixed into the run's seed: drawing changes leaves
/// the episodes' starts, goals and first shapes alone.
const CHANGES_STREAM: u64 = 0xC4A9_6E5F_0A3E_5D21;
/// Draws of a change's shape and orientation before it falls back to the first shape.
const FIT_ATTEMPTS: usize = 64;
/// Room kept between a changed formation's slots and the arena's walls, metres.
const WALL_MARGIN_M: f64 = 0.3;

/// The shape changes of an episode of `n` robots starting as `init`: `env.shape_changes`
/// distinct ticks in [20, max_steps - 50], each with a shape drawn uniformly from
/// `env.change_shapes` at a random size (the shape's own) and orientation. A draw whose slots
/// around the goal leave the arena (a long line of a large swarm) or come within the clearance
/// of an obstacle is drawn again, up to 64 times, and then the change keeps the episode's first
/// shape (its slots at the goal, clear by construction).
pub fn shape_changes<R: Rng>(n: usize, init: &EpisodeInit, env: &EnvConfig, rng: &mut R) -> Vec<ShapeChange> {
    if env.shape_changes == 0 {
        return Vec::new();
    }
    let arena = env.effective_arena_m(n);
    let span = (env.max_steps - 50 - 20 + 1) as usize;
    let mut ticks: Vec<u32> = rand::seq::index::sample(rng, span, env.shape_changes as usize)
        .into_iter()
        .map(|k| 20 + k as u32)
        .collect();
    ticks.sort_unstable();
    let clearance = clearance_m(env);
    let fits = |offsets: &[[f64; 2]]| {
        offsets.iter().all(|o| {
            let slot = [init.goal[0] + o[0], init.goal[1] + o[1]];
            slot.iter().all(|v| (WALL_MARGIN_M..=arena - WALL_MARGIN_M).contains(v))
                && init.obstacles.is_clear(slot, clearance)
        })
    };
    ticks
        .into_iter()
        .map(|tick| {
            let drawn = (0..FIT_ATTEMPTS).find_map(|_| {
                let kind = env.change_shapes[rng.random_range(0..env.change_shapes.len())];
                let shape = draw_shape(kind, n, env, rng);
                let orientation = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
                let (s, c) = orientation.sin_cos();
                let offsets: Vec<[f64; 2]> = shape
                    .iter()
                    .map(|p| [c * p[0] - s * p[1], s * p[0] + c * p[1]])
                    .collect();
                let spec = FormationSpec {
                    kind,
                    orientation,
                    scale: 1.0,
                };
                fits(&offsets).then_some((offsets, spec))
            });
            let (offsets, spec) = drawn.unwrap_or_else(|| (init.slots.clone(), init.spec));
            ShapeChange { tick, offsets, spec }
        })
        .collect()
}

/// A random episode: a shape of the configured kind, rotated to a common random heading, placed
/// at a random centroid, with each robot's heading jittered, and a goal in the arena
/// ([`EnvConfig::goal_range_m`] away). No obstacles yet: [`add_obstacles`] draws them.
pub fn random_episode<R: Rng>(n: usize, env: &EnvConfig, rng: &mut R) -> EpisodeInit {
    let arena = env.effective_arena_m(n);
    // `mixed` drawn here, as `draw_shape` would, so the episode knows its kind.
    let kind = match env.shape {
        FormationShape::Mixed => FormationShape::KINDS[rng.random_range(0..FormationShape::KINDS.len())],
        kind => kind,
    };
    let shape = draw_shape(kind, n, env, rng);
    let reach = shape.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
    // Never more than half the arena, so the ranges below are never empty.
    let margin = (reach + 0.5).min(0.5 * arena - 0.01);
    let heading = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
    let (s, c) = heading.sin_cos();
    let (goal_min, goal_max) = env.goal_range_m(n);
    for attempt in 0u32.. {
        let centre = [
            rng.random_range(margin..arena - margin),
            rng.random_range(margin..arena - margin),
        ];
        let goal_angle = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let goal_dist = rng.random_range(goal_min..=goal_max);
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
            changes: Vec::new(),
            spec: FormationSpec {
                kind,
                orientation: heading,
                scale: 1.0,
            },
            obstacles: Obstacles::none(),
            obstacle_kind: ObstacleKind::None,
            time_limit: env.episode_steps(n),
        };
    }
    unreachable!("the attempt counter is unbounded")
}

/// Draws episode `episode`'s obstacles into `init` (a run seeded `seed`), from their own stream
/// ([`obstacle_seed`]), and sets its time limit for them; nothing changes with kind `none`.
pub fn add_obstacles(init: &mut EpisodeInit, env: &EnvConfig, seed: u64, episode: u64) {
    let kind = env.obstacles.kind;
    if kind == ObstacleKind::None {
        return;
    }
    let n = init.poses.len();
    let obstacle_seed = obstacle_seed(seed, episode);
    let starts: Vec<[f64; 2]> = init.poses.iter().map(|p| [p.x, p.y]).collect();
    init.obstacles = draw_obstacles(
        &env.obstacles,
        kind,
        &starts,
        init.goal,
        &init.slots,
        env,
        obstacle_seed,
    );
    init.obstacle_kind = drawn_kind(kind, obstacle_seed);
    let n_f = n as f64;
    let centroid = starts
        .iter()
        .fold([0.0, 0.0], |c, p| [c[0] + p[0] / n_f, c[1] + p[1] / n_f]);
    let distance = (init.goal[0] - centroid[0]).hypot(init.goal[1] - centroid[1]);
    init.time_limit = episode_steps_with_obstacles(init.obstacle_kind, distance, n, env);
}

/// The episodes of a run, in order: episode k is the k-th [`random_episode`] drawn from one
/// generator seeded with the run's seed, its obstacles ([`add_obstacles`]) from a stream of
/// their own, and its [`shape_changes`] drawn from a second generator (seeded with the run's
/// seed mixed with a constant). The sim plays these, and the
/// critic's model selection plays the first K of its own seed, so both start every episode
/// from the same function.
#[derive(Debug, Clone)]
pub struct Episodes {
    n: usize,
    env: EnvConfig,
    seed: u64,
    episode: u64,
    rng: StdRng,
    changes_rng: StdRng,
}

impl Episodes {
    /// The episodes of `n` robots that `seed` starts.
    pub fn new(n: usize, env: &EnvConfig, seed: u64) -> Self {
        Self {
            n,
            env: env.clone(),
            seed,
            episode: 0,
            rng: StdRng::seed_from_u64(seed),
            changes_rng: StdRng::seed_from_u64(seed ^ CHANGES_STREAM),
        }
    }
}

impl Iterator for Episodes {
    type Item = EpisodeInit;

    /// Never `None`: a run may play as many episodes as it likes.
    fn next(&mut self) -> Option<EpisodeInit> {
        let mut init = random_episode(self.n, &self.env, &mut self.rng);
        add_obstacles(&mut init, &self.env, self.seed, self.episode);
        self.episode += 1;
        init.changes = shape_changes(self.n, &init, &self.env, &mut self.changes_rng);
        Some(init)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::index_neighbours;
    use crate::shapes::{edge_ok, observed_edges, random_shape, shape_is_valid};
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
                let c = conditions(
                    &init.poses,
                    &init.desired,
                    &index_neighbours(n),
                    init.goal,
                    &init.obstacles,
                    &env,
                );
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
    fn shape_changes_leave_every_seeds_starts_goals_and_first_shapes_alone() {
        for (n, shape) in [
            (6, FormationShape::Random),
            (16, FormationShape::Random),
            (32, FormationShape::Mixed),
        ] {
            let plain = EnvConfig {
                shape,
                ..EnvConfig::default()
            };
            let changing = EnvConfig {
                shape_changes: 2,
                ..plain.clone()
            };
            let before: Vec<EpisodeInit> = Episodes::new(n, &plain, 1000).take(20).collect();
            let after: Vec<EpisodeInit> = Episodes::new(n, &changing, 1000).take(20).collect();
            for (k, (before, after)) in before.iter().zip(&after).enumerate() {
                assert!(before.changes.is_empty());
                let EpisodeInit { changes, .. } = after.clone();
                assert_eq!(
                    &EpisodeInit {
                        changes: Vec::new(),
                        time_limit: before.time_limit,
                        ..after.clone()
                    },
                    before,
                    "n = {n}, episode {k}"
                );
                assert_eq!(changes.len(), 2);
                assert!(changes[0].tick < changes[1].tick);
                let arena = plain.effective_arena_m(n);
                for change in &changes {
                    assert!((20..=plain.max_steps - 50).contains(&change.tick));
                    let points: Vec<[f64; 2]> = change.offsets.clone();
                    assert!(shape_is_valid(&points, &plain), "n = {n}: a valid formation");
                    assert!(points.iter().all(|p| {
                        [after.goal[0] + p[0], after.goal[1] + p[1]]
                            .iter()
                            .all(|v| (0.0..=arena).contains(v))
                    }));
                }
            }
            // The changes differ between episodes and seeds.
            assert_ne!(after[0].changes, after[1].changes);
        }
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
