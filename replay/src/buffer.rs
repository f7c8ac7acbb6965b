//! Whole episodes of joint ticks.

use std::collections::VecDeque;

use formation_core::features::TickState;
use formation_protocol::{ACTION_DIM, MAX_OBS_DIM, NEIGHBOURS};

/// One tick of one episode, for every robot.
#[derive(Debug, Clone, PartialEq)]
pub struct Tick {
    /// World poses (x, y, theta).
    pub poses: Vec<[f32; 3]>,
    /// What each robot observed (entries past the observation model's dimension are zero).
    pub observations: Vec<[f32; MAX_OBS_DIM]>,
    /// Normalised action each robot executed from this tick (zero on the last tick).
    pub actions: Vec<[f32; ACTION_DIM]>,
    /// Reward of the transition from this tick to the next (0 on the last tick).
    pub reward: f32,
}

/// A finished episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Episode {
    /// Episode number in the run.
    pub number: u32,
    /// Desired length of each robot's observed edges.
    pub desired: Vec<[f32; NEIGHBOURS]>,
    /// Goal of the centroid, world frame.
    pub goal: [f32; 2],
    /// Each robot's offset from the goal in the goal formation, world frame.
    pub slots: Vec<[f32; 2]>,
    /// Ticks 0..=T; the transitions are t -> t+1 for t < T.
    pub ticks: Vec<Tick>,
    /// The last tick is terminal (success or collision): no bootstrapping from it.
    pub terminal: bool,
}

impl Episode {
    /// Robots in the episode.
    pub fn n_agents(&self) -> usize {
        self.desired.len()
    }

    /// Tick `t`'s true state with `goal` (the episode's own, or a relabelled one).
    pub fn state(&self, t: usize, goal: [f32; 2]) -> TickState<'_> {
        TickState {
            poses: &self.ticks[t].poses,
            desired: &self.desired,
            slots: &self.slots,
            goal,
        }
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
