//! Whole episodes of joint ticks.

use std::collections::VecDeque;

use formation_core::config::EnvConfig;
use formation_core::obstacles::Obstacles;
use formation_core::physics::Pose;
use formation_core::scene::Scene;
use formation_protocol::{ACTION_DIM, MAX_OBS_DIM, NEIGHBOURS};

/// One tick of one episode, for every robot: what the state stream carried for it and what the
/// robots were sent.
///
/// Stored in `f64` so that [`Episode::scene`] hands out the sim's own [`Scene`] without a
/// copy: the values are the stream's `f32`s widened exactly. That is 20 bytes more per robot
/// and tick than `f32` poses and normalised actions (104 against 84, most of it the 64 of
/// the observation): a full `learn.replay_capacity` (1M ticks) holds about 0.44 GB for N = 3
/// and 6.8 GB for N = 64, against 0.38 GB and 5.5 GB.
#[derive(Debug, Clone, PartialEq)]
pub struct Tick {
    /// Every robot's pose.
    pub poses: Vec<Pose>,
    /// The commands (v, w) applied in the transition into this tick, clamped (zero at tick 0).
    pub commands: Vec<(f64, f64)>,
    /// What each robot observed (entries past the observation model's dimension are zero).
    pub observations: Vec<[f32; MAX_OBS_DIM]>,
    /// Shared reward of the transition into this tick (0 at tick 0).
    pub reward: f32,
}

/// A formation in force from a tick of an episode on: the first from tick 0, then one per
/// shape change (the mission planner's, `env.shape_changes`). Stored per change, not per tick.
#[derive(Debug, Clone, PartialEq)]
pub struct Formation {
    /// The first tick it is in force.
    pub from_tick: usize,
    /// Desired length of each robot's observed edges.
    pub desired: Vec<[f64; NEIGHBOURS]>,
    /// Each robot's offset from the goal in the formation, world frame.
    pub slots: Vec<[f64; 2]>,
    /// The robots each robot observes (those in the next two slots).
    pub observed: Vec<[usize; NEIGHBOURS]>,
    /// Whether each robot is in the formation (the state's `present` mask): a robot out of it
    /// (its controller failed, it was removed or silent) is not trained on as a member.
    pub present: Vec<bool>,
}

/// A finished episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Episode {
    /// Episode number in the run.
    pub number: u32,
    /// Goal of the centroid, world frame.
    pub goal: [f64; 2],
    /// The formations in force, by `from_tick` (the first from tick 0).
    pub formations: Vec<Formation>,
    /// Ticks 0..=T; the transitions are t -> t+1 for t < T.
    pub ticks: Vec<Tick>,
    /// The last tick is terminal (success or collision): no bootstrapping from it.
    pub terminal: bool,
    /// The episode's obstacles (none in the open arena): a relabelled transition that hit one
    /// still collided.
    pub obstacles: Obstacles,
    /// Side of the arena the episode was played in, metres.
    pub arena_m: f64,
    /// The episode's time limit, steps (HER's relabelled successes end before it).
    pub time_limit: u32,
}

impl Formation {
    /// Whether `other` is the same formation (all but the tick it is in force from): a shape
    /// or team change when it is not.
    pub fn same_as(&self, other: &Formation) -> bool {
        (&self.desired, &self.slots, &self.observed, &self.present)
            == (&other.desired, &other.slots, &other.observed, &other.present)
    }
}

impl Episode {
    /// Robots in the episode.
    pub fn n_agents(&self) -> usize {
        self.ticks.first().map_or(0, |tick| tick.poses.len())
    }

    /// The formation in force at tick `t`.
    pub fn formation(&self, t: usize) -> &Formation {
        let at = self.formations.partition_point(|f| f.from_tick <= t).saturating_sub(1);
        &self.formations[at]
    }

    /// Whether each robot is in the formation at tick `t`.
    pub fn present(&self, t: usize) -> &[bool] {
        &self.formation(t).present
    }

    /// Tick `t` as the sim's scene, with `goal` (the episode's own, or a relabelled one) and
    /// the formation in force at `t`.
    pub fn scene(&self, t: usize, goal: [f64; 2]) -> Scene<'_> {
        self.scene_under(t, t, goal)
    }

    /// Tick `t` (t > 0) as the sim scored the transition into it: its poses and commands under
    /// the formation in force at `t - 1` (a change's tick is scored under the old formation; the
    /// new one reaches that tick's observations), with `goal`.
    pub fn scored_scene(&self, t: usize, goal: [f64; 2]) -> Scene<'_> {
        self.scene_under(t, t.saturating_sub(1), goal)
    }

    /// Tick `t`'s poses and commands under the formation in force at `formation_tick`.
    fn scene_under(&self, t: usize, formation_tick: usize, goal: [f64; 2]) -> Scene<'_> {
        let tick = &self.ticks[t];
        let formation = self.formation(formation_tick);
        Scene {
            poses: &tick.poses,
            commands: &tick.commands,
            desired: &formation.desired,
            observed: &formation.observed,
            goal,
            slots: &formation.slots,
            obstacles: &self.obstacles,
            arena_m: self.arena_m,
            ways: None,
        }
    }

    /// True when a formation comes in force after tick `t` (a change at tick t + 1 or later):
    /// until then a success does not end the episode.
    pub fn changes_after(&self, t: usize) -> bool {
        self.formations.last().is_some_and(|f| f.from_tick > t)
    }

    /// The normalised action robot `agent` executed from tick `t` (t < T): its command
    /// applied into t + 1, as the actor's output would have been.
    pub fn action(&self, t: usize, agent: usize, env: &EnvConfig) -> [f32; ACTION_DIM] {
        let (v, w) = self.ticks[t + 1].commands[agent];
        env.action_from_command(v, w)
    }

    /// Transitions (ticks with an action).
    pub fn transitions(&self) -> usize {
        self.ticks.len().saturating_sub(1)
    }

    /// True when transition t -> t+1 ends in a terminal state.
    pub fn is_terminal_transition(&self, t: usize) -> bool {
        self.terminal && t + 2 == self.ticks.len()
    }
}

/// Episodes, evicted oldest first once the total transitions exceed the capacity.
#[derive(Debug, Clone)]
pub struct ReplayBuffer {
    capacity: usize,
    episodes: VecDeque<Episode>,
    transitions: usize,
}

impl ReplayBuffer {
    /// A buffer of about `capacity` transitions.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            episodes: VecDeque::new(),
            transitions: 0,
        }
    }

    /// Adds a finished episode (episodes without a transition are dropped).
    pub fn push(&mut self, episode: Episode) {
        if episode.transitions() == 0 {
            return;
        }
        self.transitions += episode.transitions();
        self.episodes.push_back(episode);
        while self.transitions > self.capacity && self.episodes.len() > 1 {
            if let Some(old) = self.episodes.pop_front() {
                self.transitions -= old.transitions();
            }
        }
    }

    /// Transitions held.
    pub fn transitions(&self) -> usize {
        self.transitions
    }

    /// Episodes held.
    pub fn episodes(&self) -> &VecDeque<Episode> {
        &self.episodes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_tick_scene_has_the_formation_in_force_at_that_tick() {
        let formation = |from_tick: usize, d: f64, observed: [usize; NEIGHBOURS]| Formation {
            from_tick,
            desired: vec![[d; NEIGHBOURS]; 3],
            slots: vec![[d, 0.0]; 3],
            observed: vec![observed; 3],
            present: vec![from_tick != 3, true, true],
        };
        let tick = Tick {
            poses: vec![Pose::from([0.0, 0.0, 0.0]); 3],
            commands: vec![(0.0, 0.0); 3],
            observations: vec![[0.0; MAX_OBS_DIM]; 3],
            reward: 0.0,
        };
        let episode = Episode {
            number: 0,
            goal: [1.0, 2.0],
            formations: vec![
                formation(0, 1.0, [1, 2]),
                formation(3, 1.5, [2, 1]),
                formation(5, 2.0, [1, 2]),
            ],
            ticks: vec![tick; 8],
            terminal: false,
            obstacles: Obstacles::none(),
            arena_m: 10.0,
            time_limit: 120,
        };
        let desired: Vec<f64> = (0..8).map(|t| episode.scene(t, episode.goal).desired[0][0]).collect();
        assert_eq!(desired, [1.0, 1.0, 1.0, 1.5, 1.5, 2.0, 2.0, 2.0]);
        assert_eq!(episode.scene(4, episode.goal).observed[0], [2, 1]);
        assert_eq!(episode.scene(4, episode.goal).slots[0], [1.5, 0.0]);
        assert_eq!(episode.n_agents(), 3);
        assert_eq!(episode.present(4), [false, true, true]);
        assert_eq!(episode.present(5), [true; 3]);
    }
}
