//! What the critic sees of a tick, and the observation model HER needs to re-express a new
//! goal in every robot's frame.
//!
//! The critic state of a window: for every tick, each robot's position relative to that tick's
//! centroid and its heading (cos, sin), the goal relative to the centroid, and the desired edge
//! lengths. All of it is rotated into one frame per window, the heading of robot 0 at the
//! window's last tick, so the critic does not have to learn every rotation of the same scene.

use formation_protocol::config::EnvConfig;
use formation_protocol::{NEIGHBOURS, OBS_DIM};
use formation_sim::physics::Pose;
use formation_sim::task::{Outcome, conditions, observe, reward};

/// Width of one tick of critic state for `n_agents` robots.
pub fn state_dim(n_agents: usize) -> usize {
    4 * n_agents + 2 + NEIGHBOURS * n_agents
}

/// Converts wire poses to physics poses.
pub fn to_poses(poses: &[[f32; 3]]) -> Vec<Pose> {
    poses
        .iter()
        .map(|p| Pose {
            x: f64::from(p[0]),
            y: f64::from(p[1]),
            theta: f64::from(p[2]),
        })
        .collect()
}

fn to_desired(desired: &[[f32; NEIGHBOURS]]) -> Vec<[f64; NEIGHBOURS]> {
    desired.iter().map(|d| [f64::from(d[0]), f64::from(d[1])]).collect()
}

fn centroid32(poses: &[[f32; 3]]) -> [f32; 2] {
    let n = poses.len() as f32;
    let (sx, sy) = poses.iter().fold((0.0, 0.0), |(sx, sy), p| (sx + p[0], sy + p[1]));
    [sx / n, sy / n]
}

/// The centroid of a tick's poses.
pub fn centroid(poses: &[[f32; 3]]) -> [f32; 2] {
    centroid32(poses)
}

/// Writes one tick of critic state into `out` (length [`state_dim`]), rotated by `-frame`.
pub fn write_state(out: &mut [f32], poses: &[[f32; 3]], goal: [f32; 2], desired: &[[f32; NEIGHBOURS]], frame: f32) {
    let n = poses.len();
    debug_assert_eq!(out.len(), state_dim(n));
    let c = centroid32(poses);
    let (s, co) = frame.sin_cos();
    let rotate = |dx: f32, dy: f32| [co * dx + s * dy, -s * dx + co * dy];
    for (i, p) in poses.iter().enumerate() {
        let r = rotate(p[0] - c[0], p[1] - c[1]);
        let (hs, hc) = (p[2] - frame).sin_cos();
        out[4 * i..4 * i + 4].copy_from_slice(&[r[0], r[1], hc, hs]);
    }
    let g = rotate(goal[0] - c[0], goal[1] - c[1]);
    out[4 * n] = g[0];
    out[4 * n + 1] = g[1];
    for (i, d) in desired.iter().enumerate() {
        out[4 * n + 2 + NEIGHBOURS * i..4 * n + 2 + NEIGHBOURS * (i + 1)].copy_from_slice(d);
    }
}

/// What robot `agent` observes at `poses` with `goal`: the sim's own observation model.
pub fn observation(agent: usize, poses: &[[f32; 3]], desired: &[[f32; NEIGHBOURS]], goal: [f32; 2]) -> [f32; OBS_DIM] {
    observe(
        agent,
        &to_poses(poses),
        &to_desired(desired),
        [f64::from(goal[0]), f64::from(goal[1])],
    )
}

/// Reward and terminal flag of reaching `poses` after `steps` steps with `goal`: the sim's own
/// reward code.
pub fn transition_reward(
    poses: &[[f32; 3]],
    desired: &[[f32; NEIGHBOURS]],
    goal: [f32; 2],
    steps: u32,
    env: &EnvConfig,
) -> (f32, bool) {
    let c = conditions(
        &to_poses(poses),
        &to_desired(desired),
        [f64::from(goal[0]), f64::from(goal[1])],
        env,
    );
    let (r, outcome) = reward(&c, steps, env);
    (r as f32, outcome.is_terminal() && outcome != Outcome::Running)
}
