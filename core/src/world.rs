//! One episode's world: poses, formation, goal, and the step that applies the robots' commands.

use formation_protocol::config::EnvConfig;
use formation_protocol::{MAX_OBS_DIM, NEIGHBOURS};

use crate::formation::EpisodeInit;
use crate::observation::{Observer, Scene};
use crate::physics::{Pose, integrate};
use crate::task::{Conditions, Outcome, conditions, reward};

/// The true state of an episode.
#[derive(Debug, Clone)]
pub struct World {
    /// Environment settings.
    pub env: EnvConfig,
    /// Side of the arena for this swarm, metres.
    pub arena_m: f64,
    /// Current poses.
    pub poses: Vec<Pose>,
    /// Desired length of each robot's observed edges.
    pub desired: Vec<[f64; NEIGHBOURS]>,
    /// Goal of the centroid.
    pub goal: [f64; 2],
    /// Each robot's offset from the goal in the goal formation, world frame.
    pub slots: Vec<[f64; 2]>,
    /// The run's observation model.
    pub observer: Observer,
    /// Steps taken in this episode.
    pub steps: u32,
}

/// What one step did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepResult {
    /// Shared reward.
    pub reward: f64,
    /// How the transition ends.
    pub outcome: Outcome,
    /// C1-C3 at the new state.
    pub conditions: Conditions,
}

impl World {
    /// A world at the start of `init`.
    pub fn new(env: &EnvConfig, init: EpisodeInit) -> Self {
        let arena_m = env.effective_arena_m(init.poses.len());
        Self {
            env: env.clone(),
            arena_m,
            poses: init.poses,
            desired: init.desired,
            goal: init.goal,
            slots: init.slots,
            observer: Observer::new(env),
            steps: 0,
        }
    }

    /// Robots in the swarm.
    pub fn n_agents(&self) -> usize {
        self.poses.len()
    }

    /// The true state the observations are computed from.
    pub fn scene(&self) -> Scene<'_> {
        Scene {
            poses: &self.poses,
            desired: &self.desired,
            goal: self.goal,
            slots: &self.slots,
        }
    }

    /// Robot `agent`'s observation now (entries past the model's dimension are zero).
    pub fn observation(&self, agent: usize) -> [f32; MAX_OBS_DIM] {
        self.observer.observation(agent, &self.scene())
    }

    /// C1-C3 now.
    pub fn conditions(&self) -> Conditions {
        conditions(&self.poses, &self.desired, self.goal, &self.env)
    }

    /// Applies one (v, w) per robot (clamped to the limits), integrates over dt, keeps the
    /// robots in the arena and scores the new state.
    pub fn step(&mut self, commands: &[(f64, f64)]) -> StepResult {
        debug_assert_eq!(commands.len(), self.poses.len());
        for (pose, &(v, w)) in self.poses.iter_mut().zip(commands) {
            let (v, w) = self.env.clamp_command(v, w);
            let mut next = integrate(*pose, v, w, self.env.dt_s);
            next.x = next.x.clamp(0.0, self.arena_m);
            next.y = next.y.clamp(0.0, self.arena_m);
            *pose = next;
        }
        self.steps += 1;
        let conditions = self.conditions();
        let (reward, outcome) = reward(&conditions, self.steps, &self.env);
        StepResult {
            reward,
            outcome,
            conditions,
        }
    }
}
