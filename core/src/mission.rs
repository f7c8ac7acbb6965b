//! The mission planner: an episode's shape changes, the robots' slots, and when the swarm has
//! re-formed.
//!
//! The sim's tick loop owns one [`Mission`] per episode and calls [`Mission::after_step`]
//! after every step. At a change's tick the planner assigns the robots to the new shape's
//! slots optimally ([`assign`]: Kuhn-Munkres, minimising the sum of squared distances from
//! each robot's position to its new target, goal + slot offset), and rewrites the world's
//! slot map, each robot's observed robots (the robots in the next two slots, mod N), desired
//! edges and slot offsets; the observations of that tick carry them. The robots' history
//! windows are not reset: a change is part of the episode, as a turn of the goal would be.
//!
//! Success means holding the *last* formation at the goal: while a change is still to come,
//! C3 does not end the episode ([`Mission::judge`]: the transition scores as C1 alone would,
//! `r_edge`), and the swarm waits at the goal for its next formation.
//!
//! "Re-formed": every observed edge within C1's tolerance (`env.eps_form_m`) for
//! [`REFORM_HOLD_TICKS`] consecutive ticks; the ticks to re-form are counted from the change to
//! the first of them. An episode that ends in success before the run is complete (it holds the
//! formation at the goal) counts as re-formed at the first tick of its last run.

use formation_protocol::NEIGHBOURS;
use pathfinding::kuhn_munkres::kuhn_munkres_min;
use pathfinding::matrix::Matrix;

use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::config::{EnvConfig, FormationShape};
use crate::formation::ShapeChange;
use crate::shapes::{draw_shape, shape_is_valid};
use crate::task::{Outcome, StepResult};
use crate::world::World;

/// Consecutive ticks in formation that make a change re-formed.
pub const REFORM_HOLD_TICKS: u32 = 5;
/// Integer costs for Kuhn-Munkres: squared distances in mm² (1 m² = 10^6). The largest arena
/// (64 robots) is under 40 m across, so a cost is under 2e9 and a sum of 64 under 2^63.
const COST_PER_M2: f64 = 1e6;

/// The slot each robot takes: the assignment of robots at `positions` to the slots whose targets
/// are `targets` (same length) minimising the sum of squared distances, squared metres rounded
/// to mm² ([`COST_PER_M2`]); ties go to Kuhn-Munkres' first optimum.
pub fn assign(positions: &[[f64; 2]], targets: &[[f64; 2]]) -> Vec<usize> {
    debug_assert_eq!(positions.len(), targets.len());
    if positions.is_empty() {
        return Vec::new();
    }
    let costs = Matrix::from_fn(positions.len(), targets.len(), |(robot, slot)| {
        let (dx, dy) = (
            positions[robot][0] - targets[slot][0],
            positions[robot][1] - targets[slot][1],
        );
        ((dx * dx + dy * dy) * COST_PER_M2).round() as i64
    });
    kuhn_munkres_min(&costs).1
}

/// Each robot's observed robots under `slot_of` (robot r holds slot `slot_of[r]`): the robots
/// in slots s+1 and s+2 mod N.
pub fn observed_robots(slot_of: &[usize]) -> Vec<[usize; NEIGHBOURS]> {
    let n = slot_of.len();
    let mut robot_in = vec![0; n];
    for (robot, &slot) in slot_of.iter().enumerate() {
        robot_in[slot] = robot;
    }
    slot_of
        .iter()
        .map(|&s| std::array::from_fn(|k| robot_in[(s + k + 1) % n]))
        .collect()
}

/// Gives `world` the formation `offsets` (slot s's offset from the goal, in tour order) with
/// robot r in slot `slot_of[r]`: its slot map, observed robots, desired edges and slot offsets.
pub fn set_formation(world: &mut World, offsets: &[[f64; 2]], slot_of: Vec<usize>) {
    let n = offsets.len();
    let distance = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    for (robot, &slot) in slot_of.iter().enumerate() {
        world.slots[robot] = offsets[slot];
        world.desired[robot] = std::array::from_fn(|k| distance(offsets[slot], offsets[(slot + k + 1) % n]));
    }
    world.observed = observed_robots(&slot_of);
    world.slot_of = slot_of;
}

/// A live formation's slot offsets: `kind` as [`draw_shape`] draws it for `world`'s robots from
/// a generator seeded with `seed`, times `scale`, turned by `orientation` radians. Refused, saying why, when `kind` is
/// `mixed`, `scale` is not a positive number, an observed edge leaves [edge_min, edge_max], two
/// robots would be closer than the start margin, or a slot around the goal leaves the arena.
pub fn live_formation(
    world: &World,
    kind: FormationShape,
    scale: f64,
    orientation: f64,
    seed: u64,
) -> Result<Vec<[f64; 2]>, String> {
    if kind == FormationShape::Mixed {
        return Err("mixed is not a shape (random, ring, line, wedge, grid)".into());
    }
    if !(scale.is_finite() && scale > 0.0) {
        return Err(format!("scale {scale} is not a positive number"));
    }
    if !orientation.is_finite() {
        return Err(format!("orientation {orientation} is not a number"));
    }
    let env = &world.env;
    let (s, c) = orientation.sin_cos();
    let mut rng = StdRng::seed_from_u64(seed);
    let offsets: Vec<[f64; 2]> = draw_shape(kind, world.n_agents(), env, &mut rng)
        .iter()
        .map(|p| [scale * (c * p[0] - s * p[1]), scale * (s * p[0] + c * p[1])])
        .collect();
    if !shape_is_valid(&offsets, env) {
        return Err(format!(
            "scale {scale}: an edge leaves [{}, {}] m or two robots come too close",
            env.edge_min_m, env.edge_max_m
        ));
    }
    if !fits_arena(world, world.goal, &offsets) {
        return Err(format!("scale {scale}: the formation leaves the arena"));
    }
    Ok(offsets)
}

/// True when every slot `offsets` gives around `goal` lies in `world`'s arena.
pub fn fits_arena(world: &World, goal: [f64; 2], offsets: &[[f64; 2]]) -> bool {
    offsets.iter().all(|o| {
        [goal[0] + o[0], goal[1] + o[1]]
            .iter()
            .all(|v| (0.0..=world.arena_m).contains(v))
    })
}

/// One episode's mission: its schedule of shape changes and the re-form counts.
#[derive(Debug, Clone)]
pub struct Mission {
    changes: Vec<ShapeChange>,
    /// Index of the next change to apply.
    next: usize,
    /// The latest change's tick while the swarm has not re-formed since.
    pending: Option<u32>,
    /// First tick of the current run of ticks in formation, and its length.
    run: Option<(u32, u32)>,
    /// Changes applied so far.
    reconfigurations: u32,
    /// Ticks to re-form after each change that re-formed.
    reform_ticks: Vec<u32>,
}

impl Mission {
    /// The mission of an episode with these shape changes (in tick order).
    pub fn new(changes: Vec<ShapeChange>) -> Self {
        Self {
            changes,
            next: 0,
            pending: None,
            run: None,
            reconfigurations: 0,
            reform_ticks: Vec::new(),
        }
    }

    /// Called after the step into tick `world.steps` that C1 judged `in_formation` (under the
    /// formation in force) and that leaves the episode `running`: counts the re-form, then
    /// applies the change scheduled for this tick, if any, so that the tick's observations
    /// carry it. Returns true when the formation changed.
    pub fn after_step(&mut self, world: &mut World, in_formation: bool, running: bool) -> bool {
        let tick = world.steps;
        self.run = match (in_formation, self.run) {
            (false, _) => None,
            (true, None) => Some((tick, 1)),
            (true, Some((first, len))) => Some((first, len + 1)),
        };
        if let (Some(changed), Some((first, len))) = (self.pending, self.run)
            && (len >= REFORM_HOLD_TICKS || !running)
        {
            self.reform_ticks.push(first - changed);
            self.pending = None;
        }
        if !running {
            return false;
        }
        let Some(change) = self.changes.get(self.next).filter(|c| c.tick == tick) else {
            return false;
        };
        let offsets = change.offsets.clone();
        self.next += 1;
        self.reform(world, &offsets);
        true
    }

    /// A live change (the control service): from the current tick on, the formation is
    /// `offsets` (slot s's offset from the goal, in tour order) around the world's goal, the
    /// robots assigned to its slots as at a scheduled change. Counts as a reconfiguration. The
    /// schedule's later changes still come.
    pub fn reform(&mut self, world: &mut World, offsets: &[[f64; 2]]) {
        let positions: Vec<[f64; 2]> = world.poses.iter().map(|p| [p.x, p.y]).collect();
        let targets: Vec<[f64; 2]> = offsets
            .iter()
            .map(|o| [world.goal[0] + o[0], world.goal[1] + o[1]])
            .collect();
        let slot_of = assign(&positions, &targets);
        set_formation(world, offsets, slot_of);
        self.reconfigurations += 1;
        self.pending = Some(world.steps);
        self.run = None;
    }

    /// A live move of the goal to `goal`: the formation in force around the new goal, the
    /// robots assigned to its slots again (a reconfiguration, as [`Mission::reform`]).
    pub fn move_goal(&mut self, world: &mut World, goal: [f64; 2]) {
        let mut offsets = vec![[0.0; 2]; world.n_agents()];
        for (robot, &slot) in world.slot_of.iter().enumerate() {
            offsets[slot] = world.slots[robot];
        }
        world.goal = goal;
        self.reform(world, &offsets);
    }

    /// The step's result under the mission: a success (C3) before the last change is not the
    /// end of the episode; it scores `r_edge` (C1 holds) and the episode goes on, or times out
    /// at the limit.
    pub fn judge(&self, mut result: StepResult, steps: u32, env: &EnvConfig) -> StepResult {
        if result.outcome == Outcome::Success && self.next < self.changes.len() {
            result.reward = env.r_edge;
            result.outcome = if steps >= env.max_steps {
                Outcome::Timeout
            } else {
                Outcome::Running
            };
        }
        result
    }

    /// Shape changes applied so far this episode.
    pub fn reconfigurations(&self) -> u32 {
        self.reconfigurations
    }

    /// Ticks from each change to the swarm's re-forming, for the changes that re-formed.
    pub fn reform_ticks(&self) -> &[u32] {
        &self.reform_ticks
    }
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::config::{EnvConfig, FormationShape};
    use crate::formation::{Episodes, random_episode};
    use crate::physics::Pose;
    use crate::shapes::draw_shape;

    fn cost(positions: &[[f64; 2]], targets: &[[f64; 2]], slot_of: &[usize]) -> f64 {
        slot_of
            .iter()
            .enumerate()
            .map(|(r, &s)| (positions[r][0] - targets[s][0]).powi(2) + (positions[r][1] - targets[s][1]).powi(2))
            .sum()
    }

    /// Every permutation of 0..n (Heap's algorithm).
    fn permutations(n: usize) -> Vec<Vec<usize>> {
        fn heap(k: usize, items: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
            if k <= 1 {
                out.push(items.clone());
                return;
            }
            for i in 0..k {
                heap(k - 1, items, out);
                let j = if k.is_multiple_of(2) { i } else { 0 };
                items.swap(j, k - 1);
            }
        }
        let mut out = Vec::new();
        heap(n, &mut (0..n).collect(), &mut out);
        out
    }

    #[test]
    fn the_assignment_is_optimal_on_small_cases_checked_by_brute_force() {
        let mut rng = StdRng::seed_from_u64(29);
        for n in 1..=7 {
            let all = permutations(n);
            for _ in 0..20 {
                let mut point = || [rng.random_range(0.0..10.0), rng.random_range(0.0..10.0)];
                let positions: Vec<[f64; 2]> = (0..n).map(|_| point()).collect();
                let targets: Vec<[f64; 2]> = (0..n).map(|_| point()).collect();
                let slot_of = assign(&positions, &targets);
                let mut sorted = slot_of.clone();
                sorted.sort_unstable();
                assert_eq!(sorted, (0..n).collect::<Vec<_>>(), "a permutation");
                let best = all
                    .iter()
                    .map(|p| cost(&positions, &targets, p))
                    .fold(f64::INFINITY, f64::min);
                // Within the rounding to mm² per robot.
                assert!(
                    cost(&positions, &targets, &slot_of) <= best + n as f64 * 1e-6,
                    "n = {n}: {} > {best}",
                    cost(&positions, &targets, &slot_of)
                );
            }
        }
    }

    /// A world of `n` robots standing on `points` (heading +x), goal at the origin, robot i in
    /// slot i of that formation.
    fn world_on(points: &[[f64; 2]]) -> World {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(1);
        let mut world = World::new(&env, random_episode(points.len(), &env, &mut rng));
        world.goal = [5.0, 5.0];
        for (pose, p) in world.poses.iter_mut().zip(points) {
            *pose = Pose {
                x: 5.0 + p[0],
                y: 5.0 + p[1],
                theta: 0.0,
            };
        }
        let slot_of = (0..points.len()).collect();
        set_formation(&mut world, points, slot_of);
        world
    }

    #[test]
    fn a_line_reversed_and_a_ring_turned_by_half_a_turn_get_the_better_assignment_than_index_order() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(5);
        for kind in [FormationShape::Line, FormationShape::Ring] {
            let n = 8;
            let shape = draw_shape(kind, n, &env, &mut rng);
            // Half a turn: every slot's offset negated.
            let turned: Vec<[f64; 2]> = shape.iter().map(|p| [-p[0], -p[1]]).collect();
            let mut world = world_on(&shape);
            let mut mission = Mission::new(vec![ShapeChange {
                tick: 0,
                offsets: turned.clone(),
            }]);
            assert!(mission.after_step(&mut world, true, true));
            let positions: Vec<[f64; 2]> = world.poses.iter().map(|p| [p.x - 5.0, p.y - 5.0]).collect();
            let index: Vec<usize> = (0..n).collect();
            let kept = cost(&positions, &turned, &index);
            let planned = cost(&positions, &turned, &world.slot_of);
            assert!(world.slot_of != index, "{kind:?}: the slot map changed");
            assert!(
                planned < 0.01 * kept,
                "{kind:?}: {planned} against index order's {kept}"
            );
            // Each robot's slot is the turned shape's point nearest to it: it barely moves.
            assert!(planned < 1e-9, "{kind:?}: the turned shape is the same set of points");
            // The world follows the slot map: slots, observed robots and desired edges.
            for robot in 0..n {
                let s = world.slot_of[robot];
                assert_eq!(world.slots[robot], turned[s]);
                let next = world.observed[robot][0];
                assert_eq!(world.slot_of[next], (s + 1) % n);
                let d = (turned[s][0] - turned[(s + 1) % n][0]).hypot(turned[s][1] - turned[(s + 1) % n][1]);
                assert!((world.desired[robot][0] - d).abs() < 1e-12);
            }
            // Standing still, the swarm is in the new formation at once.
            assert!(world.conditions().in_formation, "{kind:?}");
        }
    }

    #[test]
    fn a_live_formation_is_assigned_like_a_scheduled_one_and_bad_ones_are_refused() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(12);
        let ring = draw_shape(FormationShape::Ring, 6, &env, &mut rng);
        let mut world = world_on(&ring);
        let why = |r: Result<Vec<[f64; 2]>, String>| r.err().unwrap_or_default();
        assert!(why(live_formation(&world, FormationShape::Mixed, 1.0, 0.0, 1)).contains("mixed"));
        assert!(why(live_formation(&world, FormationShape::Line, 0.0, 0.0, 1)).contains("positive"));
        assert!(why(live_formation(&world, FormationShape::Line, 20.0, 0.0, 1)).contains("edge"));
        // The same seed draws the same formation; a half turn negates every offset.
        let line = live_formation(&world, FormationShape::Line, 1.0, 0.0, 7).unwrap_or_default();
        let turned = live_formation(&world, FormationShape::Line, 1.0, std::f64::consts::PI, 7).unwrap_or_default();
        assert_eq!(line.len(), 6);
        for (a, b) in line.iter().zip(&turned) {
            assert!((a[0] + b[0]).abs() < 1e-9 && (a[1] + b[1]).abs() < 1e-9);
        }
        let mut mission = Mission::new(Vec::new());
        mission.reform(&mut world, &line);
        let positions: Vec<[f64; 2]> = world.poses.iter().map(|p| [p.x - 5.0, p.y - 5.0]).collect();
        assert_eq!(
            world.slot_of,
            assign(&positions, &line),
            "the mission planner's assignment"
        );
        for robot in 0..6 {
            assert_eq!(world.slots[robot], line[world.slot_of[robot]]);
        }
        assert_eq!(mission.reconfigurations(), 1);
        // A new goal keeps the formation, its slots reassigned around the goal.
        let offsets_before: Vec<[f64; 2]> = world.slots.clone();
        mission.move_goal(&mut world, [6.0, 5.0]);
        assert_eq!(world.goal, [6.0, 5.0]);
        let mut before = offsets_before.clone();
        let mut after = world.slots.clone();
        before.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        after.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
        assert_eq!(before, after, "the same formation");
        assert_eq!(mission.reconfigurations(), 2);
        assert!(!fits_arena(&world, [-3.0, 5.0], &world.slots));
    }

    #[test]
    fn success_means_holding_the_last_formation_at_the_goal() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(8);
        let shape = draw_shape(FormationShape::Ring, 6, &env, &mut rng);
        let mut world = world_on(&shape);
        let mut mission = Mission::new(vec![ShapeChange {
            tick: 3,
            offsets: draw_shape(FormationShape::Line, 6, &env, &mut rng),
        }]);
        // In formation at the goal, a change still to come: the episode goes on.
        let result = world.step(&[(0.0, 0.0); 6]);
        assert_eq!(result.outcome, Outcome::Success);
        let judged = mission.judge(result, world.steps, &world.env);
        assert_eq!((judged.outcome, judged.reward), (Outcome::Running, env.r_edge));
        // After the last change, holding the new formation at the goal is success.
        world.step(&[(0.0, 0.0); 6]);
        world.step(&[(0.0, 0.0); 6]);
        assert!(mission.after_step(&mut world, true, true));
        for robot in 0..6 {
            world.poses[robot].x = world.goal[0] + world.slots[robot][0];
            world.poses[robot].y = world.goal[1] + world.slots[robot][1];
        }
        let result = world.step(&[(0.0, 0.0); 6]);
        assert_eq!(mission.judge(result, world.steps, &world.env).outcome, Outcome::Success);
    }

    #[test]
    fn a_change_reaches_every_robots_observation_at_its_tick_and_re_forming_is_counted() {
        let env = EnvConfig {
            shape_changes: 1,
            change_shapes: vec![FormationShape::Line],
            ..EnvConfig::default()
        };
        let mut init = Episodes::new(6, &env, 1000).next().unwrap_or_else(|| unreachable!());
        let changes = std::mem::take(&mut init.changes);
        let change_tick = changes[0].tick;
        let mut world = World::new(&env, init);
        let mut mission = Mission::new(changes.clone());
        let before: Vec<_> = (0..6).map(|r| world.observation(r)).collect();
        for _ in 1..change_tick {
            let result = world.step(&[(0.0, 0.0); 6]);
            assert!(!mission.after_step(&mut world, result.conditions.in_formation, true));
            assert_eq!((0..6).map(|r| world.observation(r)).collect::<Vec<_>>(), before);
        }
        let result = world.step(&[(0.0, 0.0); 6]);
        assert!(mission.after_step(&mut world, result.conditions.in_formation, true));
        assert_eq!(world.steps, change_tick);
        let layout = world.observer.layout;
        for robot in 0..6 {
            let obs = world.observation(robot);
            for k in 0..NEIGHBOURS {
                let at = layout.neighbour(k) + 4;
                assert_eq!(
                    obs[at], world.desired[robot][k] as f32,
                    "robot {robot} is told the new edge"
                );
            }
            let line = &changes[0].offsets;
            let s = world.slot_of[robot];
            let d = (line[s][0] - line[(s + 1) % 6][0]).hypot(line[s][1] - line[(s + 1) % 6][1]);
            assert_eq!(obs[layout.neighbour(0) + 4], d as f32);
        }
        assert_eq!(mission.reconfigurations(), 1);
        // Teleport the robots into their new slots: re-formed after 5 ticks in formation.
        for robot in 0..6 {
            let slot = world.slots[robot];
            world.poses[robot].x = world.goal[0] + slot[0];
            world.poses[robot].y = world.goal[1] + slot[1];
        }
        for _ in 0..REFORM_HOLD_TICKS {
            let result = world.step(&[(0.0, 0.0); 6]);
            assert!(result.conditions.in_formation);
            mission.after_step(&mut world, true, true);
        }
        assert_eq!(mission.reform_ticks(), &[1]);
    }
}
