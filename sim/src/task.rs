//! The task: what each robot observes, the paper's conditions C1-C3 and its reward table.
//!
//! Pure functions shared by the sim (online) and the replay (HER relabelling), so a relabelled
//! reward is computed by exactly the code that produced the original one.

use formation_protocol::config::EnvConfig;
use formation_protocol::{NEIGHBOURS, OBS_DIM, neighbours};

use crate::physics::Pose;

/// Centroid of the robots' positions.
pub fn centroid(poses: &[Pose]) -> [f64; 2] {
    let n = poses.len().max(1) as f64;
    let (sx, sy) = poses.iter().fold((0.0, 0.0), |(sx, sy), p| (sx + p.x, sy + p.y));
    [sx / n, sy / n]
}

/// A world-frame point expressed in the frame of a robot at `pose` (x ahead, y to the left).
pub fn to_robot_frame(pose: &Pose, point: [f64; 2]) -> [f64; 2] {
    let (dx, dy) = (point[0] - pose.x, point[1] - pose.y);
    let (s, c) = pose.theta.sin_cos();
    [c * dx + s * dy, -s * dx + c * dy]
}

/// What robot `agent` observes: for each neighbour its position, relative heading (cos, sin)
/// and desired distance, then the goal, all in the robot's own frame.
pub fn observe(agent: usize, poses: &[Pose], desired: &[[f64; NEIGHBOURS]], goal: [f64; 2]) -> [f32; OBS_DIM] {
    let me = &poses[agent];
    let mut obs = [0.0f32; OBS_DIM];
    for (k, &other) in neighbours(agent, poses.len()).iter().enumerate() {
        let rel = to_robot_frame(me, [poses[other].x, poses[other].y]);
        let (s, c) = (poses[other].theta - me.theta).sin_cos();
        let base = k * formation_protocol::NEIGHBOUR_FEATURES;
        obs[base] = rel[0] as f32;
        obs[base + 1] = rel[1] as f32;
        obs[base + 2] = c as f32;
        obs[base + 3] = s as f32;
        obs[base + 4] = desired[agent][k] as f32;
    }
    let g = to_robot_frame(me, goal);
    obs[OBS_DIM - 2] = g[0] as f32;
    obs[OBS_DIM - 1] = g[1] as f32;
    obs
}

/// The conditions of the paper's Table I at one state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Conditions {
    /// C1: every observed edge within eps_form of its desired length.
    pub in_formation: bool,
    /// C2: two robots closer than eps_coll.
    pub collision: bool,
    /// C3: C1 and the centroid within eps_goal of the goal.
    pub success: bool,
    /// Mean |d_ij - dbar_ij| over the observed edges, metres.
    pub mean_edge_error: f64,
    /// Largest |d_ij - dbar_ij|, metres.
    pub max_edge_error: f64,
    /// |centroid - goal|, metres.
    pub goal_distance: f64,
}

/// Edge error of robot `agent`'s `k`-th observed edge.
pub fn edge_error(agent: usize, k: usize, poses: &[Pose], desired: &[[f64; NEIGHBOURS]]) -> f64 {
    let other = neighbours(agent, poses.len())[k];
    let d = (poses[agent].x - poses[other].x).hypot(poses[agent].y - poses[other].y);
    (d - desired[agent][k]).abs()
}

/// Evaluates C1, C2 and C3.
pub fn conditions(poses: &[Pose], desired: &[[f64; NEIGHBOURS]], goal: [f64; 2], env: &EnvConfig) -> Conditions {
    let n = poses.len();
    let (mut sum, mut max) = (0.0f64, 0.0f64);
    for agent in 0..n {
        for k in 0..NEIGHBOURS {
            let err = edge_error(agent, k, poses, desired);
            sum += err;
            max = max.max(err);
        }
    }
    let mut collision = false;
    for i in 0..n {
        for j in i + 1..n {
            if (poses[i].x - poses[j].x).hypot(poses[i].y - poses[j].y) < env.eps_coll_m {
                collision = true;
            }
        }
    }
    let c = centroid(poses);
    let goal_distance = (c[0] - goal[0]).hypot(c[1] - goal[1]);
    let in_formation = max <= env.eps_form_m;
    Conditions {
        in_formation,
        collision,
        success: in_formation && goal_distance <= env.eps_goal_m,
        mean_edge_error: sum / (n * NEIGHBOURS) as f64,
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
}

impl Outcome {
    /// True for the outcomes that end the episode's return (no bootstrapping past them).
    pub fn is_terminal(self) -> bool {
        matches!(self, Outcome::Success | Outcome::Collision)
    }

    /// The wire code (`OUTCOME_*`).
    pub fn code(self) -> u32 {
        use formation_protocol::wire::*;
        match self {
            Outcome::Running => OUTCOME_RUNNING,
            Outcome::Success => OUTCOME_SUCCESS,
            Outcome::Collision => OUTCOME_COLLISION,
            Outcome::Timeout => OUTCOME_TIMEOUT,
        }
    }
}

/// The paper's reward and the outcome of reaching a state with `conditions` after `steps`
/// steps. Priority: collision, then success, then formation, else the penalty.
pub fn reward(conditions: &Conditions, steps: u32, env: &EnvConfig) -> (f64, Outcome) {
    let (reward, outcome) = if conditions.collision {
        (env.r_collision, Outcome::Collision)
    } else if conditions.success {
        (env.r_goal, Outcome::Success)
    } else if conditions.in_formation {
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

#[cfg(test)]
mod tests {
    use super::*;

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
    fn neighbour_straight_ahead_is_plus_x() {
        let me = Pose {
            x: 1.0,
            y: 1.0,
            theta: std::f64::consts::FRAC_PI_2,
        };
        let p = to_robot_frame(&me, [1.0, 3.0]);
        assert!((p[0] - 2.0).abs() < 1e-12 && p[1].abs() < 1e-12);
        let left = to_robot_frame(&me, [0.0, 1.0]);
        assert!(
            left[0].abs() < 1e-12 && (left[1] - 1.0).abs() < 1e-12,
            "a point to the robot's left is at +y"
        );
    }

    #[test]
    fn observation_layout() {
        let (mut poses, desired) = triangle();
        poses[1].theta = 0.5;
        let obs = observe(0, &poses, &desired, [0.0, 2.0]);
        assert!((obs[0] - 1.0).abs() < 1e-6 && obs[1].abs() < 1e-6);
        assert!((obs[2] - 0.5f32.cos()).abs() < 1e-6 && (obs[3] - 0.5f32.sin()).abs() < 1e-6);
        assert!((obs[4] - 1.0).abs() < 1e-6);
        assert!((obs[5] - 0.5).abs() < 1e-6 && (obs[6] - 0.8).abs() < 1e-6);
        assert!(obs[10].abs() < 1e-6 && (obs[11] - 2.0).abs() < 1e-6);
    }

    #[test]
    fn reward_table_and_priority() {
        let env = EnvConfig::default();
        let (poses, desired) = triangle();
        let c = centroid(&poses);
        // In formation at the goal: success.
        let at_goal = conditions(&poses, &desired, c, &env);
        assert_eq!(reward(&at_goal, 5, &env), (env.r_goal, Outcome::Success));
        // In formation far from the goal: r_edge.
        let far = conditions(&poses, &desired, [c[0] + 1.0, c[1]], &env);
        assert_eq!(reward(&far, 5, &env), (env.r_edge, Outcome::Running));
        // Formation broken: penalty; at the time limit: timeout.
        let mut broken = poses.clone();
        broken[2].y += 0.5;
        let off = conditions(&broken, &desired, [c[0] + 1.0, c[1]], &env);
        assert_eq!(reward(&off, 5, &env), (env.r_penalty, Outcome::Running));
        assert_eq!(reward(&off, env.max_steps, &env), (env.r_penalty, Outcome::Timeout));
        // At the goal but out of formation is not success.
        let off_goal = conditions(&broken, &desired, centroid(&broken), &env);
        assert_eq!(reward(&off_goal, 5, &env).1, Outcome::Running);
        // Collision beats everything, even at the goal and at the time limit.
        let mut crashed = poses.clone();
        crashed[1].x = 0.1;
        let col = conditions(&crashed, &desired, centroid(&crashed), &env);
        assert_eq!(reward(&col, env.max_steps, &env), (env.r_collision, Outcome::Collision));
        assert!(Outcome::Collision.is_terminal() && Outcome::Success.is_terminal() && !Outcome::Timeout.is_terminal());
    }
}
