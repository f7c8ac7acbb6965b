//! The per-robot planner: each robot plans its own way to its slot at the goal over the map and
//! follows it, with no team plan. A teacher for a decentralised student: where the team planner
//! ([`crate::planner`]) makes robots wait for each other and walk in a file whose order one
//! robot's sensors cannot tell, this one's command for a robot depends only on that robot's
//! pose, its slot, the map and the robots near it.
//!
//! Each robot's path is [`plan_path`]'s over the obstacles grown by its radius and the widest of
//! [`SOLO_MARGINS_M`] that finds one, from where it stands (or, too near a surface, from the
//! nearest point clear of it) to its slot. It plans again when it
//! has drifted more than [`REPLAN_OFF_M`] from its path, every [`REPLAN_TICKS`] ticks, and when
//! its slot moves. It tracks a point [`LOOKAHEAD_M`] along its path ahead of where it is with
//! the team planner's law ([`Tracking`]: repulsion from robots and surfaces included), at
//! [`PACE`] x `v_max` and [`SOLO_NARROW_PACE`] of that near surfaces. When no path is found it heads
//! straight for its slot.

use crate::baseline::BaselineGains;
use crate::config::EnvConfig;
use crate::obstacles::{Obstacles, robot_radius_m};
use crate::physics::Pose;
use crate::planner::{PACE, Polyline, Tracking, plan_path};

/// The rooms a robot's path keeps between its disc and any surface, widest first, metres.
pub const SOLO_MARGINS_M: [f64; 5] = [0.2, 0.12, 0.08, 0.05, 0.02];
/// A robot farther than this from its path plans again, metres.
pub const REPLAN_OFF_M: f64 = 0.25;
/// A robot plans again at least this often, ticks (robots that moved may open a shorter way).
pub const REPLAN_TICKS: u32 = 40;
/// How far ahead along its path a robot aims, metres.
pub const LOOKAHEAD_M: f64 = 0.4;
/// A robot whose disc is nearer than this to a surface is near it, metres,
pub const SOLO_NARROW_M: f64 = 0.1;
/// and slows to this fraction of [`PACE`].
pub const SOLO_NARROW_PACE: f64 = 0.5;
/// Within this of a surface, a robot stops while another is nearer than [`YIELD_M`] (centre to
/// centre) within [`YIELD_COS`] of the way to its aim and nearer its aim than it, metres.
pub const YIELD_NEAR_M: f64 = 0.25;
/// See [`YIELD_NEAR_M`], metres.
pub const YIELD_M: f64 = 0.4;
/// See [`YIELD_NEAR_M`]: the cosine of the widest angle off the way to the aim.
pub const YIELD_COS: f64 = 0.5;

/// One robot's path and how far along it the robot has come.
#[derive(Debug, Clone)]
struct SoloPath {
    line: Polyline,
    /// The slot it leads to.
    to: [f64; 2],
    planned_at: u32,
    /// The farthest arc length the robot has been projected to.
    progress: f64,
}

/// The per-robot planner of one episode's team (see the module's documentation).
#[derive(Debug, Clone, Default)]
pub struct SoloPlanner {
    paths: Vec<Option<SoloPath>>,
    /// Plan over only the obstacles within this of the robot (`None`: the whole map).
    sight_m: Option<f64>,
}

impl SoloPlanner {
    /// A planner whose robots plan over only the obstacles within `sight_m` of where they plan
    /// from (what their range sensor could show), the rest of the way taken as open.
    pub fn seeing(sight_m: f64) -> Self {
        Self {
            paths: Vec::new(),
            sight_m: Some(sight_m),
        }
    }

    /// Every robot's (v, w) at `tick`: robot i heads for `goal + slots[i]` around `obstacles`
    /// in the arena of `env` for this many robots, tracking with `gains` (the baseline's turn
    /// gain and robot repulsion).
    #[allow(clippy::too_many_arguments)]
    pub fn commands(
        &mut self,
        poses: &[Pose],
        goal: [f64; 2],
        slots: &[[f64; 2]],
        obstacles: &Obstacles,
        tick: u32,
        env: &EnvConfig,
        gains: BaselineGains,
    ) -> Vec<(f64, f64)> {
        let n = poses.len();
        self.paths.resize(n, None);
        let arena = env.effective_arena_m(n);
        let robot_radius = robot_radius_m(env);
        let tracking = Tracking {
            obstacles,
            robot_radius,
            gains,
            v_max: env.v_max,
            w_max: env.w_max,
        };
        (0..n)
            .map(|agent| {
                let me = [poses[agent].x, poses[agent].y];
                let to = [goal[0] + slots[agent][0], goal[1] + slots[agent][1]];
                let path = &mut self.paths[agent];
                let stale = match path {
                    None => true,
                    Some(p) => {
                        let (_, on) = p.line.project(me, p.line.length());
                        p.to != to
                            || tick.saturating_sub(p.planned_at) >= REPLAN_TICKS
                            || (me[0] - on[0]).hypot(me[1] - on[1]) > REPLAN_OFF_M
                    }
                };
                if stale {
                    let seen = self.sight_m.map(|sight| obstacles.within(me, sight));
                    let obstacles = seen.as_ref().unwrap_or(obstacles);
                    let planned = SOLO_MARGINS_M
                        .iter()
                        .find_map(|margin| plan_path(obstacles, me, to, robot_radius + margin, arena))
                        .or_else(|| {
                            // Too near a surface to plan from: plan from the point just clear of
                            // it, straight out from the nearest surfaces.
                            let out = step_clear(obstacles, me, robot_radius + SOLO_MARGINS_M[4])?;
                            let mut points = plan_path(obstacles, out, to, robot_radius + SOLO_MARGINS_M[4], arena)?;
                            points.insert(0, me);
                            Some(points)
                        });
                    // No way found: keep the old path, else go straight.
                    let keeps_old = matches!(path, Some(p) if p.to == to);
                    if let Some(points) = planned.or_else(|| (!keeps_old).then(|| vec![me, to])) {
                        *path = Some(SoloPath {
                            line: Polyline::new(points),
                            to,
                            planned_at: tick,
                            progress: 0.0,
                        });
                    }
                }
                let path = path.as_mut().expect("planned above");
                let (s, _) = path.line.project(me, path.progress + LOOKAHEAD_M);
                path.progress = path.progress.max(s);
                let aim = path.line.at(path.progress + LOOKAHEAD_M);
                let pace = if obstacles.is_clear(me, robot_radius + SOLO_NARROW_M) {
                    PACE
                } else {
                    PACE * SOLO_NARROW_PACE
                };
                // Near surfaces a robot waits for a robot just ahead of it nearer its aim.
                let yields = !obstacles.is_clear(me, robot_radius + YIELD_NEAR_M)
                    && poses.iter().enumerate().any(|(k, other)| {
                        let (dx, dy) = (other.x - me[0], other.y - me[1]);
                        let (ax, ay) = (aim[0] - me[0], aim[1] - me[1]);
                        let (d, a) = (dx.hypot(dy), ax.hypot(ay));
                        k != agent
                            && d < YIELD_M
                            && dx * ax + dy * ay > YIELD_COS * d * a
                            && (aim[0] - other.x).hypot(aim[1] - other.y) < a
                    });
                let (v, w) = tracking.command(poses, agent, aim, pace * env.v_max);
                (if yields { 0.0 } else { v }, w)
            })
            .collect()
    }
}

/// The point `clearance` from every surface reached from `p` by moving away from the surfaces
/// nearer than that (their pushes summed), in up to 10 steps; `None` if it is not reached.
fn step_clear(obstacles: &Obstacles, p: [f64; 2], clearance: f64) -> Option<[f64; 2]> {
    let mut here = p;
    for _ in 0..10 {
        if obstacles.is_clear(here, clearance) {
            return Some(here);
        }
        let mut push = [0.0, 0.0];
        obstacles.for_each_nearest_within(here, clearance, |q| {
            let (dx, dy) = (here[0] - q[0], here[1] - q[1]);
            let distance = dx.hypot(dy).max(1e-9);
            push[0] += (clearance - distance + 1e-3) * dx / distance;
            push[1] += (clearance - distance + 1e-3) * dy / distance;
        });
        if push[0].hypot(push[1]) < 1e-9 {
            return None;
        }
        here = [here[0] + push[0], here[1] + push[1]];
    }
    obstacles.is_clear(here, clearance).then_some(here)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::obstacles::ObstacleKind;
    use crate::obstacles::tests::rates_among_obstacles;
    use crate::world::World;

    /// Success, robot collisions and obstacle hits of `episodes` episodes of `n` robots among
    /// obstacles of `kind`, every robot driven by a fresh `planner()` ([`rates_among_obstacles`]).
    fn solo_rates_with(
        planner: impl Fn() -> SoloPlanner,
        kind: ObstacleKind,
        n: usize,
        episodes: usize,
        seed: u64,
    ) -> [f64; 3] {
        rates_among_obstacles(EnvConfig::default(), kind, n, episodes, seed, |init, env| {
            let (goal, slots, obstacles, env) = (init.goal, init.slots.clone(), init.obstacles.clone(), env.clone());
            let mut planner = planner();
            move |world: &World| {
                let gains = BaselineGains::default();
                planner.commands(&world.poses, goal, &slots, &obstacles, world.steps, &env, gains)
            }
        })
    }

    fn solo_rates(kind: ObstacleKind, n: usize, episodes: usize, seed: u64) -> [f64; 3] {
        solo_rates_with(SoloPlanner::default, kind, n, episodes, seed)
    }

    #[test]
    fn the_solo_planner_brings_small_teams_through_the_forest() {
        let [success, collisions, hits] = solo_rates(ObstacleKind::Forest, 4, 20, 2000);
        assert!(success >= 0.8, "success {success}");
        assert!(
            collisions + hits <= 0.1,
            "collisions {collisions}, obstacle hits {hits}"
        );
    }

    #[test]
    fn the_solo_planner_seeing_only_its_sensor_range_still_brings_small_teams_through_the_forest() {
        let [success, collisions, hits] =
            solo_rates_with(|| SoloPlanner::seeing(2.0), ObstacleKind::Forest, 4, 20, 2000);
        assert!(success >= 0.7, "success {success}");
        assert!(
            collisions + hits <= 0.1,
            "collisions {collisions}, obstacle hits {hits}"
        );
    }

    /// Prints the per-robot planner's rates by kind and team size:
    /// `cargo test -p formation-core solo_planner_report -- --ignored --nocapture`.
    #[test]
    #[ignore = "a report, not a check"]
    fn solo_planner_report() {
        for kind in ObstacleKind::KINDS {
            for n in [4, 8, 16] {
                let [success, collisions, hits] = solo_rates(kind, n, 50, 3000);
                let [seeing, ..] = solo_rates_with(|| SoloPlanner::seeing(2.0), kind, n, 50, 3000);
                println!(
                    "{kind:>8} N={n:>2}: success {success:.2}  robot collisions {collisions:.2}  obstacle hits {hits:.2}  seeing 2 m: success {seeing:.2}"
                );
            }
        }
    }
}
