//! The privileged planner as a robot's controller (`formation-agent --policy oracle`): it reads
//! the sim's true poses (`formation/truth`) and the episode's obstacles (`formation/obstacles`)
//! instead of its own observation, plans the team's way with [`Planner`] and answers with its
//! own robot's command, through the command path like any robot (so `[reality]` acts on it).
//!
//! Every oracle robot of a team builds the same plan: the planner is deterministic and each
//! builds it from the same first tick's truth. A robot that joins mid-episode (restarted) or a
//! formation that changes plans again from the tick it sees. The plan waits for every robot,
//! oracle or not, with the planner's patience ([`formation_core::planner::PATIENCE_TICKS`]).

use formation_core::baseline::BaselineGains;
use formation_core::config::EnvConfig;
use formation_core::obstacles::Obstacles;
use formation_core::physics::Pose;
use formation_core::planner::Replanner;
use formation_protocol::wire::{Header, ObstaclesMsg, TruthMsg};

/// One robot's privileged planner.
pub struct Oracle {
    agent: usize,
    env: EnvConfig,
    gains: BaselineGains,
    /// The episode planned for, its obstacles and the plan.
    episode: Option<(u32, Obstacles, Replanner)>,
    poses: Vec<Pose>,
    slots: Vec<[f64; 2]>,
}

impl Oracle {
    /// Robot `agent`'s planner in the task `env`, tracking with the baseline's `gains`.
    pub fn new(agent: usize, env: &EnvConfig, gains: BaselineGains) -> Self {
        Self {
            agent,
            env: env.clone(),
            gains,
            episode: None,
            poses: Vec::new(),
            slots: Vec::new(),
        }
    }

    /// The command for the tick `header` names, from that tick's `truth` and the episode's
    /// `obstacles`; `None` when either is not the tick's or the episode's (the caller keeps
    /// its robot still).
    pub fn command(&mut self, header: &Header, truth: &TruthMsg, obstacles: &ObstaclesMsg) -> Option<(f64, f64)> {
        if truth.header.episode != header.episode
            || truth.header.tick != header.tick
            || obstacles.header.episode != header.episode
        {
            return None;
        }
        let n = truth.n_agents as usize;
        self.poses.clear();
        self.poses.extend(truth.poses[..n].iter().map(|&p| Pose::from(p)));
        self.slots.clear();
        self.slots.extend(truth.slots[..n].iter().map(|s| s.map(f64::from)));
        if !matches!(&self.episode, Some((episode, ..)) if *episode == header.episode) {
            self.episode = Some((header.episode, Obstacles::from_wire(obstacles), Replanner::default()));
        }
        let (_, obstacles, replanner) = self.episode.as_mut()?;
        let goal = truth.goal.map(f64::from);
        let commands = replanner.commands(
            &self.poses,
            goal,
            &self.slots,
            obstacles,
            header.tick,
            &self.env,
            self.gains,
        );
        Some(commands[self.agent])
    }
}
