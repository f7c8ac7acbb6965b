//! Concurrent sequence sampling (CERT) with HER goal relabelling.
//!
//! A sample is one stretch t -> t+k of one episode (k = 1, or up to n with n-step returns) seen
//! through windows of H ticks: the window ending at t and the one ending at t+k, for every robot
//! at the same ticks. Ticks before the episode's start repeat tick 0 (the padding the agents use
//! too).
//!
//! HER recomputes the reward with the sim's own code ([`score`]) on the replay's
//! [`formation_core::scene::Scene`]s, judged as the sim judges a step: under the formation in
//! force when the transition was scored ([`Episode::scored_scene`]), with the episode's time
//! limit ([`Episode::time_limit`]), and with success only once the episode's last
//! formation is in force ([`success_after_last_change`]); a relabelled observation is the one
//! the robot was told, its goal and slot moved to the new goal ([`Observer::move_goal`]), so
//! the sensor noise it was told with stays.
//!
//! Each robot's own reward ([`Batch::robot_rewards`], for `learn.credit = "robot"`) is the
//! team's with the team's mean approach to the slots replaced by the robot's own
//! ([`robot_progress`]), from the same scenes.

use formation_core::config::{CriticArchitecture, EnvConfig};
use formation_core::features::CriticFeatures;
use formation_core::mission::success_after_last_change;
use formation_core::observation::Observer;
use formation_core::task::{mean_progress, robot_progress, score};
use formation_protocol::ACTION_DIM;
use rand::Rng;

use crate::buffer::{Episode, ReplayBuffer};

/// A batch of B samples, every array row-major with the batch index first.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Batch {
    /// B.
    pub batch_size: usize,
    /// N.
    pub n_agents: usize,
    /// H.
    pub history: usize,
    /// Floats per observation (the observation model's dimension).
    pub obs_dim: usize,
    /// Floats per tick of critic state.
    pub state_dim: usize,
    /// [B, N, H * obs_dim]: each robot's observation window ending at t.
    pub observations: Vec<f32>,
    /// [B, N, H * obs_dim]: windows ending at t+k.
    pub next_observations: Vec<f32>,
    /// [B, H * state_dim]: critic state window ending at t.
    pub states: Vec<f32>,
    /// [B, H * state_dim]: window ending at t+k.
    pub next_states: Vec<f32>,
    /// [B, H * N * 2]: executed normalised actions of ticks t-H+1..=t, tick-major.
    pub actions: Vec<f32>,
    /// [B, H * N * 2]: executed actions of ticks t+k-H..=t+k-1, the window the target's action
    /// history comes from (its last H - 1 ticks; equal to `actions` when k = 1).
    pub bootstrap_actions: Vec<f32>,
    /// [B]: shared reward of t -> t+k, discounted within the stretch (recomputed when
    /// relabelled).
    pub rewards: Vec<f32>,
    /// [B, N]: each robot's own reward of t -> t+k, discounted as `rewards`: the shared reward
    /// plus `env.r_progress` times (its own approach to its slot minus the team's mean,
    /// [`robot_progress`]), so that the robots' mean is the shared reward. Equal to `rewards`
    /// for every robot without a progress term; empty means so too (a batch built by hand).
    pub robot_rewards: Vec<f32>,
    /// [B]: gamma^k, the discount of the bootstrapped value.
    pub discounts: Vec<f32>,
    /// [B]: 1 when t+k is terminal (success or collision); a time limit is not terminal.
    pub terminals: Vec<f32>,
    /// [B]: where each sample came from (episode number, t).
    pub origins: Vec<(u32, usize)>,
    /// [B]: the goal used (world frame); differs from the episode's when relabelled.
    pub goals: Vec<[f64; 2]>,
    /// [B]: whether HER relabelled the sample.
    pub relabelled: Vec<bool>,
    /// [B, N]: 1 for each robot in the formation at t, 0 for a robot out of it (the replay's
    /// recorded presence, kept by HER: a new goal does not change the team). Empty means every
    /// robot present (a batch built by hand).
    pub present: Vec<f32>,
    /// [B, N]: the same at t+k, the tick the TD target bootstraps from.
    pub next_present: Vec<f32>,
}

impl Batch {
    /// A batch of `batch_size` samples, every value zero, for [`Sampler::fill`] to fill.
    pub fn zeroed(batch_size: usize, n_agents: usize, history: usize, obs_dim: usize, state_dim: usize) -> Self {
        let (b, n, h) = (batch_size, n_agents, history);
        Self {
            batch_size,
            n_agents,
            history,
            obs_dim,
            state_dim,
            observations: vec![0.0; b * n * h * obs_dim],
            next_observations: vec![0.0; b * n * h * obs_dim],
            states: vec![0.0; b * h * state_dim],
            next_states: vec![0.0; b * h * state_dim],
            actions: vec![0.0; b * h * n * ACTION_DIM],
            bootstrap_actions: vec![0.0; b * h * n * ACTION_DIM],
            rewards: vec![0.0; b],
            robot_rewards: vec![0.0; b * n],
            discounts: vec![0.0; b],
            terminals: vec![0.0; b],
            origins: Vec::with_capacity(b),
            goals: Vec::with_capacity(b),
            relabelled: Vec::with_capacity(b),
            present: vec![0.0; b * n],
            next_present: vec![0.0; b * n],
        }
    }

    /// Width of one robot's observation window.
    pub fn window_dim(&self) -> usize {
        self.history * self.obs_dim
    }

    /// Width of the critic state window.
    pub fn state_window_dim(&self) -> usize {
        self.history * self.state_dim
    }

    /// Width of the joint action window.
    pub fn action_window_dim(&self) -> usize {
        self.history * self.n_agents * ACTION_DIM
    }
}

/// Draws batches from a replay buffer.
#[derive(Debug, Clone)]
pub struct Sampler {
    /// H.
    pub history: usize,
    /// Probability of relabelling a sample's goal with a centroid reached later (HER "future").
    pub her_probability: f64,
    /// Rewards summed per sample (n-step returns; 1 = one-step), fewer at a terminal tick or
    /// the episode's end.
    pub n_step: usize,
    /// Discount of the rewards within a sample and of its bootstrapped value.
    pub gamma: f64,
    /// The environment (for rewards of relabelled samples and the actions' scale).
    pub env: EnvConfig,
    /// The critic the batches are for (it decides the state's layout).
    pub critic: CriticArchitecture,
    /// Obstacle points in each robot's token (`learn.critic_map_points`; `pooled` only).
    pub critic_map_points: usize,
}

impl Sampler {
    /// The observation model of the environment (for relabelled observations).
    pub fn observer(&self) -> Observer {
        Observer::new(&self.env)
    }

    /// The critic state of `n_agents` robots.
    pub fn features(&self, n_agents: usize) -> CriticFeatures {
        CriticFeatures::new(n_agents, self.env.observation, self.critic).with_map_points(self.critic_map_points)
    }

    /// B samples, transitions drawn uniformly over the buffer; `None` when it is empty.
    pub fn sample<R: Rng>(&self, buffer: &ReplayBuffer, batch_size: usize, rng: &mut R) -> Option<Batch> {
        let episodes = buffer.episodes();
        let total = buffer.transitions();
        let first = episodes.front()?;
        let n = first.n_agents();
        // Each episode's own time limit, as the sim's world has it (set per sample below).
        let mut env = self.env.clone();
        let h = self.history;
        let sd = self.features(n).dim();
        let od = self.observer().dim();
        let mut batch = Batch::zeroed(batch_size, n, h, od, sd);
        // Cumulative transition counts to draw transitions uniformly.
        let mut ends = Vec::with_capacity(episodes.len());
        let mut acc = 0;
        for e in episodes {
            acc += e.transitions();
            ends.push(acc);
        }
        for b in 0..batch_size {
            let pick = rng.random_range(0..total);
            let index = ends.partition_point(|&end| end <= pick);
            let episode = &episodes[index];
            let start = if index == 0 { 0 } else { ends[index - 1] };
            let t = pick - start;
            env.max_steps = episode.time_limit;
            self.fill(&mut batch, b, episode, t, &env, rng);
        }
        Some(batch)
    }

    /// What each robot's own reward adds to the shared one in the transition into tick `t`
    /// under `goal`: `env.r_progress` times (its approach minus the team's mean approach), 0 for
    /// a robot out of the formation and for every robot without a progress term.
    fn own_progress_shifts(&self, episode: &Episode, t: usize, goal: [f64; 2]) -> Vec<f64> {
        let n = episode.n_agents();
        if self.env.r_progress == 0.0 {
            return vec![0.0; n];
        }
        let approaches = robot_progress(&episode.scored_scene(t, goal), &self.env);
        let mean = mean_progress(&approaches);
        approaches
            .into_iter()
            .map(|approach| approach.map_or(0.0, |a| self.env.r_progress * (a - mean)))
            .collect()
    }

    /// Fills sample `b` of `batch` with transition `t` of `episode`; relabelled rewards are
    /// judged under `env`, the sampler's environment with the episode's time limit
    /// ([`Episode::time_limit`]).
    pub fn fill<R: Rng>(&self, batch: &mut Batch, b: usize, episode: &Episode, t: usize, env: &EnvConfig, rng: &mut R) {
        let n = batch.n_agents;
        let h = self.history;
        let (sd, od) = (batch.state_dim, batch.obs_dim);
        let features = self.features(n);
        let observer = self.observer();
        let last = episode.ticks.len() - 1;
        debug_assert!(t < last);
        let relabel = rng.random_bool(self.her_probability);
        let goal = if relabel {
            let reached = rng.random_range(t + 1..=last);
            episode.scene(reached, episode.goal).centroid()
        } else {
            episode.goal
        };
        // The rewards of t -> t+1, t+1 -> t+2, ... up to n of them, the episode's end or a
        // terminal tick, whichever comes first.
        let (mut reward, mut discount, mut terminal, mut steps) = (0.0f64, 1.0f64, false, 0);
        let mut own = vec![0.0f64; n];
        while steps < self.n_step.max(1) && t + steps < last {
            let s = t + steps;
            let (r, done) = if relabel {
                let steps = (s + 1) as u32;
                let scored = success_after_last_change(
                    score(&episode.scored_scene(s + 1, goal), steps, env),
                    episode.changes_after(s),
                    steps,
                    env,
                );
                (scored.reward as f32, scored.outcome.is_terminal())
            } else {
                (episode.ticks[s + 1].reward, episode.is_terminal_transition(s))
            };
            reward += discount * f64::from(r);
            for (own, shift) in own.iter_mut().zip(self.own_progress_shifts(episode, s + 1, goal)) {
                *own += discount * (f64::from(r) + shift);
            }
            discount *= self.gamma;
            steps += 1;
            if done {
                terminal = true;
                break;
            }
        }
        let next = t + steps;
        let window_tick = |end: usize, k: usize| (end + k + 1).saturating_sub(h);
        for (end, observations, states) in [
            (t, &mut batch.observations, &mut batch.states),
            (next, &mut batch.next_observations, &mut batch.next_states),
        ] {
            let frame = episode.ticks[end].poses[0].theta as f32;
            for k in 0..h {
                let tick = &episode.ticks[window_tick(end, k)];
                let scene = episode.scene(window_tick(end, k), goal);
                for agent in 0..n {
                    let offset = ((b * n + agent) * h + k) * od;
                    let mut obs = tick.observations[agent];
                    if relabel {
                        observer.move_goal(&mut obs, &tick.poses[agent], episode.goal, goal);
                    }
                    observations[offset..offset + od].copy_from_slice(&obs[..od]);
                }
                let offset = (b * h + k) * sd;
                features.write(&mut states[offset..offset + sd], &scene, frame);
            }
        }
        for (end, actions) in [(t, &mut batch.actions), (next - 1, &mut batch.bootstrap_actions)] {
            for k in 0..h {
                let acted = window_tick(end, k);
                for agent in 0..n {
                    let offset = ((b * h + k) * n + agent) * ACTION_DIM;
                    actions[offset..offset + ACTION_DIM].copy_from_slice(&episode.action(acted, agent, &self.env));
                }
            }
        }
        for (tick, present) in [(t, &mut batch.present), (next, &mut batch.next_present)] {
            for (mask, &member) in present[b * n..(b + 1) * n].iter_mut().zip(episode.present(tick)) {
                *mask = if member { 1.0 } else { 0.0 };
            }
        }
        batch.rewards[b] = reward as f32;
        for (slot, own) in batch.robot_rewards[b * n..(b + 1) * n].iter_mut().zip(own) {
            *slot = own as f32;
        }
        batch.discounts[b] = discount as f32;
        batch.terminals[b] = if terminal { 1.0 } else { 0.0 };
        batch.origins.push((episode.number, t));
        batch.goals.push(goal);
        batch.relabelled.push(relabel);
    }
}
