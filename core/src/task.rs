//! The task: the paper's conditions C1-C3, its reward table and how an episode ends.
//!
//! Pure functions shared by the sim (online) and the replay (HER relabelling), so a relabelled
//! reward is computed by exactly the code that produced the original one: both call [`score`]
//! on a [`Scene`], which carries the commands applied into its tick, so a reward term on the
//! actions goes there and HER recomputes it too.

use crate::config::EnvConfig;
use formation_protocol::NEIGHBOURS;
use formation_protocol::wire::{OUTCOME_ABORTED, OUTCOME_COLLISION, OUTCOME_RUNNING, OUTCOME_SUCCESS, OUTCOME_TIMEOUT};

use crate::obstacles::{Obstacles, robot_radius_m};
use crate::physics::Pose;
use crate::scene::Scene;

/// Centroid of the robots' positions.
pub fn centroid(poses: &[Pose]) -> [f64; 2] {
    let n = poses.len().max(1) as f64;
    let (sx, sy) = poses.iter().fold((0.0, 0.0), |(sx, sy), p| (sx + p.x, sy + p.y));
    [sx / n, sy / n]
}

/// Whether robot `agent` is in the formation: a robot out of it (its controller failed, it was
/// removed or is silent, [`crate::mission`]) observes only itself.
pub fn is_present(agent: usize, observed: &[[usize; NEIGHBOURS]]) -> bool {
    observed[agent][0] != agent
}

/// Centroid of the positions of the robots in the formation ([`is_present`]); of every robot
/// when none is.
pub fn present_centroid(poses: &[Pose], observed: &[[usize; NEIGHBOURS]]) -> [f64; 2] {
    let (mut sx, mut sy, mut m) = (0.0, 0.0, 0usize);
    for (agent, p) in poses.iter().enumerate() {
        if is_present(agent, observed) {
            (sx, sy, m) = (sx + p.x, sy + p.y, m + 1);
        }
    }
    if m == 0 {
        return centroid(poses);
    }
    [sx / m as f64, sy / m as f64]
}

/// The conditions of the paper's Table I at one state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Conditions {
    /// C1: every observed edge within eps_form of its desired length.
    pub in_formation: bool,
    /// C2: two robots closer than eps_coll, or a robot's centre within eps_coll / 2 of an
    /// obstacle's surface.
    pub collision: bool,
    /// The part of C2 an obstacle caused: a robot touched one.
    pub obstacle_collision: bool,
    /// A robot in the formation is within `formation_excuse_m` of an obstacle: the tick's
    /// formation reward does not ask for C1.
    pub excused: bool,
    /// C3: C1 and the centroid within eps_goal of the goal.
    pub success: bool,
    /// Mean |d_ij - dbar_ij| over the observed edges, metres.
    pub mean_edge_error: f64,
    /// Largest |d_ij - dbar_ij|, metres.
    pub max_edge_error: f64,
    /// |centroid - goal|, metres.
    pub goal_distance: f64,
}

/// Edge error of robot `agent`'s `k`-th observed edge (to robot `observed[agent][k]`).
pub fn edge_error(
    agent: usize,
    k: usize,
    poses: &[Pose],
    desired: &[[f64; NEIGHBOURS]],
    observed: &[[usize; NEIGHBOURS]],
) -> f64 {
    let other = observed[agent][k];
    let d = (poses[agent].x - poses[other].x).hypot(poses[agent].y - poses[other].y);
    (d - desired[agent][k]).abs()
}

/// Evaluates C1, C2 and C3 on the robots in the formation; `observed` names each robot's two
/// observed robots (only itself for a robot out of the formation, [`is_present`]). The edges
/// and the centroid are the present robots'; a collision counts between two robots of which at
/// least one is present (a robot that left and stands still is an obstacle). Any robot whose
/// disc (radius eps_coll / 2) touches one of `obstacles` has collided.
pub fn conditions(
    poses: &[Pose],
    desired: &[[f64; NEIGHBOURS]],
    observed: &[[usize; NEIGHBOURS]],
    goal: [f64; 2],
    obstacles: &Obstacles,
    env: &EnvConfig,
) -> Conditions {
    let n = poses.len();
    let (mut sum, mut max, mut edges) = (0.0f64, 0.0f64, 0usize);
    for agent in (0..n).filter(|&a| is_present(a, observed)) {
        for k in 0..NEIGHBOURS {
            let err = edge_error(agent, k, poses, desired, observed);
            sum += err;
            max = max.max(err);
            edges += 1;
        }
    }
    let mut collision = false;
    for i in 0..n {
        for j in i + 1..n {
            if (is_present(i, observed) || is_present(j, observed))
                && (poses[i].x - poses[j].x).hypot(poses[i].y - poses[j].y) < env.eps_coll_m
            {
                collision = true;
            }
        }
    }
    let radius = robot_radius_m(env);
    let obstacle_collision = !obstacles.is_empty() && poses.iter().any(|p| obstacles.hits_robot([p.x, p.y], radius));
    let excused = env.formation_excuse_m > 0.0
        && !obstacles.is_empty()
        && poses
            .iter()
            .enumerate()
            .any(|(agent, p)| is_present(agent, observed) && !obstacles.is_clear([p.x, p.y], env.formation_excuse_m));
    let c = present_centroid(poses, observed);
    let goal_distance = (c[0] - goal[0]).hypot(c[1] - goal[1]);
    let in_formation = max <= env.eps_form_m;
    Conditions {
        in_formation,
        collision: collision || obstacle_collision,
        obstacle_collision,
        excused,
        success: in_formation && goal_distance <= env.eps_goal_m,
        mean_edge_error: sum / edges.max(1) as f64,
        max_edge_error: max,
        goal_distance,
    }
}

/// How a transition ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// The episode goes on.
    Running,
    /// C3 (terminal).
    Success,
    /// C2 (terminal).
    Collision,
    /// Time limit (truncation: the value of the next state still counts).
    Timeout,
    /// The run was stopped mid-episode (truncation, like the time limit).
    Aborted,
}

impl Outcome {
    /// True for the outcomes that end the episode's return (no bootstrapping past them).
    pub fn is_terminal(self) -> bool {
        matches!(self, Outcome::Success | Outcome::Collision)
    }

    /// The wire code (`StateMsg::outcome`).
    pub fn code(self) -> u32 {
        match self {
            Outcome::Running => OUTCOME_RUNNING,
            Outcome::Success => OUTCOME_SUCCESS,
            Outcome::Collision => OUTCOME_COLLISION,
            Outcome::Timeout => OUTCOME_TIMEOUT,
            Outcome::Aborted => OUTCOME_ABORTED,
        }
    }

    /// The name used in files and reports.
    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Running => "running",
            Outcome::Success => "success",
            Outcome::Collision => "collision",
            Outcome::Timeout => "timeout",
            Outcome::Aborted => "aborted",
        }
    }
}

impl TryFrom<u32> for Outcome {
    type Error = u32;

    /// Reads a wire code; an unknown code is handed back.
    fn try_from(code: u32) -> Result<Self, u32> {
        [
            Outcome::Running,
            Outcome::Success,
            Outcome::Collision,
            Outcome::Timeout,
            Outcome::Aborted,
        ]
        .into_iter()
        .find(|outcome| outcome.code() == code)
        .ok_or(code)
    }
}

/// The paper's reward and the outcome of reaching a state with `conditions` after `steps`
/// steps. Priority: collision, then success, then formation, else the penalty.
pub fn reward(conditions: &Conditions, steps: u32, env: &EnvConfig) -> (f64, Outcome) {
    let (reward, outcome) = if conditions.collision {
        (env.r_collision, Outcome::Collision)
    } else if conditions.success {
        (env.r_goal, Outcome::Success)
    } else if conditions.in_formation || conditions.excused {
        (env.r_edge, Outcome::Running)
    } else {
        (env.r_penalty, Outcome::Running)
    };
    let outcome = if outcome == Outcome::Running && steps >= env.max_steps {
        Outcome::Timeout
    } else {
        outcome
    };
    (reward, outcome)
}

/// What reaching a scene scores.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepResult {
    /// Shared reward of the transition into the scene.
    pub reward: f64,
    /// How the transition ends.
    pub outcome: Outcome,
    /// C1-C3 at the scene.
    pub conditions: Conditions,
}

/// The world-frame vector from robot `agent` to its slot at the goal, metres.
fn to_slot(scene: &Scene, agent: usize) -> [f64; 2] {
    let (pose, slot) = (scene.poses[agent], scene.slots[agent]);
    [scene.goal[0] + slot[0] - pose.x, scene.goal[1] + slot[1] - pose.y]
}

/// Each robot's approach to its slot at the goal in the transition into `scene`, metres: its
/// applied speed times the cosine between its heading and the bearing of its slot, times dt (a
/// robot on its slot approaches by 0); with the scene's ways round the obstacles
/// (`env.geodesic_progress`), the bearing of its way on round them instead
/// ([`crate::geodesic::DistanceField::descent`]); `None` for a robot out of the formation.
pub fn robot_progress(scene: &Scene, env: &EnvConfig) -> Vec<Option<f64>> {
    let ways = scene.ways.filter(|ways| ways.lead_to(scene.goal, scene.slots));
    scene
        .poses
        .iter()
        .zip(scene.commands)
        .enumerate()
        .map(|(agent, (pose, &(v, _)))| {
            if !is_present(agent, scene.observed) {
                return None;
            }
            let [dx, dy] = to_slot(scene, agent);
            let distance = dx.hypot(dy);
            if distance <= 1e-9 {
                return Some(0.0);
            }
            let [ux, uy] = ways
                .and_then(|ways| ways.field(agent).descent([pose.x, pose.y], scene.obstacles))
                .unwrap_or([dx / distance, dy / distance]);
            Some(v * env.dt_s * (pose.theta.cos() * ux + pose.theta.sin() * uy))
        })
        .collect()
}

/// The mean of [`robot_progress`]'s approaches over the robots in the formation (0 for none).
pub fn mean_progress(approaches: &[Option<f64>]) -> f64 {
    let present: Vec<f64> = approaches.iter().flatten().copied().collect();
    present.iter().sum::<f64>() / present.len().max(1) as f64
}

/// The mean [`robot_progress`] of the robots in the formation, metres.
pub fn progress(scene: &Scene, env: &EnvConfig) -> f64 {
    mean_progress(&robot_progress(scene, env))
}

/// The mean distance of the robots in the formation from their slots at the goal, metres (0
/// for none).
pub fn slot_distance(scene: &Scene) -> f64 {
    let (sum, count) = (0..scene.poses.len())
        .filter(|&agent| is_present(agent, scene.observed))
        .map(|agent| {
            let [dx, dy] = to_slot(scene, agent);
            dx.hypot(dy)
        })
        .fold((0.0, 0usize), |(sum, count), d| (sum + d, count + 1));
    sum / count.max(1) as f64
}

/// Scores the transition into `scene`, the `steps`-th of its episode: C1-C3 at its poses, the
/// reward (the paper's table, plus `r_progress` x [`progress`] and `r_distance` x
/// [`slot_distance`] when set) and the outcome. The sim's step and HER's relabelling both call
/// this.
pub fn score(scene: &Scene, steps: u32, env: &EnvConfig) -> StepResult {
    let conditions = conditions(
        scene.poses,
        scene.desired,
        scene.observed,
        scene.goal,
        scene.obstacles,
        env,
    );
    let (mut reward, outcome) = reward(&conditions, steps, env);
    if env.r_progress != 0.0 {
        reward += env.r_progress * progress(scene, env);
    }
    if env.r_distance != 0.0 {
        reward += env.r_distance * slot_distance(scene);
    }
    StepResult {
        reward,
        outcome,
        conditions,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::index_neighbours;
    use formation_protocol::neighbours;

    fn triangle() -> (Vec<Pose>, Vec<[f64; 2]>) {
        let poses = vec![
            Pose {
                x: 0.0,
                y: 0.0,
                theta: 0.0,
            },
            Pose {
                x: 1.0,
                y: 0.0,
                theta: 0.0,
            },
            Pose {
                x: 0.5,
                y: 0.8,
                theta: 0.0,
            },
        ];
        let desired = (0..3)
            .map(|i| {
                let nb = neighbours(i, 3);
                let d = |j: usize| (poses[i].x - poses[j].x).hypot(poses[i].y - poses[j].y);
                [d(nb[0]), d(nb[1])]
            })
            .collect();
        (poses, desired)
    }

    #[test]
    fn reward_table_and_priority() {
        let env = EnvConfig::default();
        let (poses, desired) = triangle();
        let observed = index_neighbours(3);
        let c = centroid(&poses);
        // In formation at the goal: success.
        let at_goal = conditions(&poses, &desired, &observed, c, &Obstacles::none(), &env);
        assert_eq!(reward(&at_goal, 5, &env), (env.r_goal, Outcome::Success));
        // In formation far from the goal: r_edge.
        let far = conditions(
            &poses,
            &desired,
            &observed,
            [c[0] + 1.0, c[1]],
            &Obstacles::none(),
            &env,
        );
        assert_eq!(reward(&far, 5, &env), (env.r_edge, Outcome::Running));
        // Formation broken: penalty; at the time limit: timeout.
        let mut broken = poses.clone();
        broken[2].y += 0.5;
        let off = conditions(
            &broken,
            &desired,
            &observed,
            [c[0] + 1.0, c[1]],
            &Obstacles::none(),
            &env,
        );
        assert_eq!(reward(&off, 5, &env), (env.r_penalty, Outcome::Running));
        assert_eq!(reward(&off, env.max_steps, &env), (env.r_penalty, Outcome::Timeout));
        // At the goal but out of formation is not success.
        let off_goal = conditions(
            &broken,
            &desired,
            &observed,
            centroid(&broken),
            &Obstacles::none(),
            &env,
        );
        assert_eq!(reward(&off_goal, 5, &env).1, Outcome::Running);
        // Collision beats everything, even at the goal and at the time limit.
        let mut crashed = poses.clone();
        crashed[1].x = 0.1;
        let col = conditions(
            &crashed,
            &desired,
            &observed,
            centroid(&crashed),
            &Obstacles::none(),
            &env,
        );
        assert_eq!(reward(&col, env.max_steps, &env), (env.r_collision, Outcome::Collision));
        assert!(Outcome::Collision.is_terminal() && Outcome::Success.is_terminal() && !Outcome::Timeout.is_terminal());
        assert!(!Outcome::Aborted.is_terminal());
    }

    #[test]
    fn along_the_way_round_a_wall_a_detour_is_progress_where_the_straight_measure_charges_it() {
        use crate::geodesic::Ways;
        use crate::obstacles::{Obstacle, Obstacles};
        // Robot 0 at (3, 5) behind a wall at x = 5 (y 2 to 8), its slot at (7, 5); it drives
        // north-north-west, round the wall's upper end, at 0.2 m/s.
        let obstacles = Obstacles::new(vec![Obstacle::Wall {
            a: [5.0, 2.0],
            b: [5.0, 8.0],
            thickness: 0.2,
        }]);
        let heading = std::f64::consts::FRAC_PI_2 + 0.2;
        let poses = [
            Pose {
                x: 3.0,
                y: 5.0,
                theta: heading,
            },
            Pose {
                x: 3.0,
                y: 4.0,
                theta: 0.0,
            },
            Pose {
                x: 2.0,
                y: 4.5,
                theta: 0.0,
            },
        ];
        let (goal, slots) = ([7.0, 5.0], [[0.0, 0.0], [0.0, -1.0], [-1.0, -0.5]]);
        let commands = [(0.2, 0.0), (0.0, 0.0), (0.0, 0.0)];
        let ways = Ways::new(goal, &slots, &obstacles, 10.0);
        let env = EnvConfig::default();
        let scene = |ways: Option<&Ways>, goal: [f64; 2]| {
            let desired = [[1.0; NEIGHBOURS]; 3];
            let observed = crate::scene::index_neighbours(3);
            robot_progress(
                &Scene {
                    poses: &poses,
                    commands: &commands,
                    desired: &desired,
                    observed: &observed,
                    goal,
                    slots: &slots,
                    obstacles: &obstacles,
                    arena_m: 10.0,
                    ways,
                },
                &env,
            )[0]
            .expect("robot 0 is in the formation")
        };
        let straight = scene(None, goal);
        let round = scene(Some(&ways), goal);
        assert!(straight < 0.0, "straight: moving away from the slot, {straight}");
        assert!(round > 0.01, "round the wall: progress, {round}");
        assert!(round <= 0.2 * env.dt_s + 1e-12, "no more than its speed: {round}");
        let elsewhere = scene(Some(&ways), [7.0, 5.5]);
        assert_eq!(elsewhere, scene(None, [7.0, 5.5]), "ways to another goal are not used");
    }

    #[test]
    fn outcome_codes_round_trip_and_unknown_codes_are_refused() {
        for outcome in [
            Outcome::Running,
            Outcome::Success,
            Outcome::Collision,
            Outcome::Timeout,
            Outcome::Aborted,
        ] {
            assert_eq!(Outcome::try_from(outcome.code()), Ok(outcome));
        }
        assert_eq!(Outcome::try_from(99), Err(99));
    }
}
