//! One episode's world: poses, formation, goal, and the step that applies the robots' commands.

use crate::config::EnvConfig;
use formation_protocol::{MAX_OBS_DIM, NEIGHBOURS};

use crate::formation::EpisodeInit;
use crate::geodesic::Ways;
use crate::observation::Observer;
use crate::obstacles::{ObstacleKind, Obstacles};
use crate::physics::{Pose, integrate};
use crate::scene::{Scene, index_neighbours};
use crate::task::{Conditions, StepResult, conditions, score};

/// The true state of an episode.
#[derive(Debug, Clone)]
pub struct World {
    /// Environment settings.
    pub env: EnvConfig,
    /// Side of the arena for this swarm, metres.
    pub arena_m: f64,
    /// Current poses.
    pub poses: Vec<Pose>,
    /// The commands (v, w) the last step applied, clamped; zero before the first step.
    pub commands: Vec<(f64, f64)>,
    /// Desired length of each robot's observed edges.
    pub desired: Vec<[f64; NEIGHBOURS]>,
    /// Goal of the centroid.
    pub goal: [f64; 2],
    /// Each robot's offset from the goal in the goal formation, world frame.
    pub slots: Vec<[f64; 2]>,
    /// Each robot's slot in the formation (robot i holds slot i until the mission planner
    /// reassigns them, [`crate::mission`]).
    pub slot_of: Vec<usize>,
    /// The robots each robot observes: those in the next two slots.
    pub observed: Vec<[usize; NEIGHBOURS]>,
    /// The episode's obstacles.
    pub obstacles: Obstacles,
    /// The kind of obstacles the episode drew (`none` in the open arena).
    pub obstacle_kind: ObstacleKind,
    /// The run's observation model.
    pub observer: Observer,
    /// Steps taken in this episode.
    pub steps: u32,
    /// Each robot's way round the obstacles to its slot, with `env.geodesic_progress` among
    /// obstacles (rebuilt when the goal or the formation changes).
    ways: Option<Ways>,
}

impl World {
    /// A world at the start of `init` (its shape changes are the mission planner's), with the
    /// episode's time limit (`init.time_limit`) as `env.max_steps`.
    pub fn new(env: &EnvConfig, init: EpisodeInit) -> Self {
        let n = init.poses.len();
        let arena_m = env.effective_arena_m(n);
        let mut env = env.clone();
        env.max_steps = init.time_limit;
        Self {
            observer: Observer::new(&env),
            env,
            arena_m,
            slot_of: (0..n).collect(),
            observed: index_neighbours(n),
            commands: vec![(0.0, 0.0); init.poses.len()],
            poses: init.poses,
            desired: init.desired,
            goal: init.goal,
            slots: init.slots,
            obstacles: init.obstacles,
            obstacle_kind: init.obstacle_kind,
            steps: 0,
            ways: None,
        }
    }

    /// Builds the robots' ways round the obstacles when the progress is measured along them and
    /// the goal or the formation is not the one they lead to.
    fn update_ways(&mut self) {
        if !self.env.geodesic_progress || self.obstacles.is_empty() {
            return;
        }
        if !self
            .ways
            .as_ref()
            .is_some_and(|ways| ways.lead_to(self.goal, &self.slots))
        {
            self.ways = Some(Ways::new(self.goal, &self.slots, &self.obstacles, self.arena_m));
        }
    }

    /// Robots in the swarm.
    pub fn n_agents(&self) -> usize {
        self.poses.len()
    }

    /// The current tick: what the observations, the reward and the state stream are
    /// computed from.
    pub fn scene(&self) -> Scene<'_> {
        Scene {
            poses: &self.poses,
            commands: &self.commands,
            desired: &self.desired,
            observed: &self.observed,
            goal: self.goal,
            slots: &self.slots,
            obstacles: &self.obstacles,
            arena_m: self.arena_m,
            ways: self.ways.as_ref(),
        }
    }

    /// Robot `agent`'s observation now (entries past the model's dimension are zero).
    pub fn observation(&self, agent: usize) -> [f32; MAX_OBS_DIM] {
        self.observer.observation(agent, &self.scene())
    }

    /// C1-C3 now.
    pub fn conditions(&self) -> Conditions {
        conditions(
            &self.poses,
            &self.desired,
            &self.observed,
            self.goal,
            &self.obstacles,
            &self.env,
        )
    }

    /// Applies one (v, w) per robot (clamped to the limits, and kept in the scene),
    /// integrates over dt, keeps the robots in the arena and scores the new scene.
    pub fn step(&mut self, commands: &[(f64, f64)]) -> StepResult {
        debug_assert_eq!(commands.len(), self.poses.len());
        for ((pose, applied), &(v, w)) in self.poses.iter_mut().zip(&mut self.commands).zip(commands) {
            *applied = self.env.clamp_command(v, w);
            let mut next = integrate(*pose, applied.0, applied.1, self.env.dt_s);
            next.x = next.x.clamp(0.0, self.arena_m);
            next.y = next.y.clamp(0.0, self.arena_m);
            *pose = next;
        }
        self.steps += 1;
        self.update_ways();
        score(&self.scene(), self.steps, &self.env)
    }
}

#[cfg(test)]
mod tests {
    use rand::SeedableRng;
    use rand::rngs::StdRng;

    use super::*;
    use crate::formation::random_episode;

    #[test]
    fn the_scene_carries_the_commands_the_step_applied_clamped() {
        let env = EnvConfig::default();
        let mut rng = StdRng::seed_from_u64(3);
        let mut world = World::new(&env, random_episode(3, &env, &mut rng));
        assert_eq!(world.scene().commands, &[(0.0, 0.0); 3], "nothing applied yet");
        let asked = [(0.1, -0.2), (10.0, 10.0), (-1.0, -10.0)];
        let result = world.step(&asked);
        let applied: Vec<(f64, f64)> = asked.iter().map(|&(v, w)| env.clamp_command(v, w)).collect();
        assert_eq!(world.scene().commands, applied.as_slice());
        assert_eq!(applied[1], (env.v_max, env.w_max), "over the limits: clamped");
        // The step scores the scene it hands out.
        assert_eq!(score(&world.scene(), world.steps, &env), result);
    }
}
