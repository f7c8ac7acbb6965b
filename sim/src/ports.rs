//! The sim's ends of the run's services: each robot's observation stream and wake-up, the
//! command streams and their shared wake-up, and the state stream; the
//! readers' progress is [`crate::reader_link`]'s.

use anyhow::{Context, Result};
use formation_core::mission::NO_SLOT;
use formation_core::reality::Reality;
use formation_core::task::Outcome;
use formation_core::world::World;
use formation_ipc::services::{self, Sizing};
use formation_protocol::wire::*;
use formation_protocol::{MAX_DELAY_TICKS, MAX_OBS_DIM};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

/// The sim's ports towards one robot.
pub struct AgentPorts<S: Service> {
    /// Its observations.
    pub observation: Publisher<S, ObservationMsg, ()>,
    /// Wakes it when an observation is out.
    pub wake: Notifier<S>,
    /// Its commands (and greetings).
    pub command: Subscriber<S, CommandMsg, ()>,
}

/// Every port the sim uses.
pub struct SimPorts<S: Service> {
    /// One set per robot.
    pub agents: Vec<AgentPorts<S>>,
    /// Robots raise their index here after sending a command.
    pub command_ready: Listener<S>,
    /// The true state, for the critic and observers.
    pub state: Publisher<S, StateMsg, ()>,
    /// The true poses, for privileged planners, before each tick's observations.
    pub truth: Publisher<S, TruthMsg, ()>,
    /// The episode's obstacles, once per episode.
    pub obstacles: Publisher<S, ObstaclesMsg, ()>,
    /// Wakes the critic (and the MCAP recorder).
    pub critic_wake: Notifier<S>,
}

/// What led to a published state (the velocities that acted are the world's scene's).
#[derive(Debug, Clone, Copy)]
pub struct Transition {
    /// How the transition into this state ended.
    pub outcome: Outcome,
    /// Its shared reward.
    pub reward: f64,
    /// Robots that missed the tick (nothing new arrived: the command in use stayed).
    pub missed: u32,
}

/// What the robots were told at a tick and what drove them into it, beside the world.
#[derive(Clone, Copy)]
pub struct Told<'a> {
    /// Each robot's observation after the sensor noise.
    pub observations: &'a [[f32; MAX_OBS_DIM]],
    /// Robots whose observation is lost (not published to them).
    pub lost: &'a [bool],
    /// The command in use for the transition into this tick, clamped (the replay's action).
    pub applied: &'a [(f64, f64)],
    /// The episode's reality: the commands queued at each robot's motors.
    pub reality: &'a Reality,
}

impl<S: Service> SimPorts<S> {
    /// Creates (or opens) every port for the swarm `sizing` describes.
    pub fn open(node: &Node<S>, sizing: &Sizing) -> Result<Self> {
        let err = |what: &str| format!("sim cannot create {what}");
        let mut agents = Vec::with_capacity(sizing.n_agents);
        for agent in 0..sizing.n_agents {
            agents.push(AgentPorts {
                observation: services::observation_stream(node, sizing, agent)?
                    .publisher_builder()
                    .create()
                    .with_context(|| err("observation publisher"))?,
                wake: services::observation_event(node, sizing, agent)?
                    .notifier_builder()
                    .create()
                    .with_context(|| err("observation notifier"))?,
                command: services::command_stream(node, sizing, agent)?
                    .subscriber_builder()
                    .buffer_size(sizing.stream_buffer)
                    .create()
                    .with_context(|| err("command subscriber"))?,
            });
        }
        Ok(Self {
            agents,
            command_ready: services::command_event(node, sizing)?
                .listener_builder()
                .create()
                .with_context(|| err("command listener"))?,
            state: services::state_stream(node, sizing)?
                .publisher_builder()
                .create()
                .with_context(|| err("state publisher"))?,
            truth: services::truth_stream(node, sizing)?
                .publisher_builder()
                .create()
                .with_context(|| err("truth publisher"))?,
            obstacles: services::obstacles_stream(node, sizing)?
                .publisher_builder()
                .create()
                .with_context(|| err("obstacles publisher"))?,
            critic_wake: services::critic_wake_event(node, sizing)?
                .notifier_builder()
                .create()
                .with_context(|| err("critic notifier"))?,
        })
    }

    /// Sends every robot what it is told of `world` (`told`), except those whose observation
    /// is lost, and, unless the episode ends here, wakes it with its event, except the robots
    /// `belled` (the caller rings the tick bell for them).
    pub fn publish_observations(&self, world: &World, header: Header, told: &Told, belled: &[bool]) -> Result<()> {
        let n = world.n_agents() as u32;
        for (agent, agent_ports) in self.agents.iter().enumerate() {
            if told.lost[agent] {
                continue;
            }
            let mut sample = agent_ports.observation.loan().context("loan observation")?;
            let msg = sample.payload_mut();
            msg.header = header;
            msg.agent = agent as u32;
            msg.n_agents = n;
            msg.dim = world.observer.dim() as u32;
            msg.obs = told.observations[agent];
            sample.send().context("send observation")?;
            if !header.has(FLAG_EPISODE_END) && !belled[agent] {
                agent_ports
                    .wake
                    .notify()
                    .with_context(|| format!("wake agent {agent}"))?;
            }
        }
        Ok(())
    }

    /// Publishes the true state as state number `sequence`, with what the robots were told and
    /// what drove them; returns a copy when `keep_copy` (for the view).
    pub fn publish_state(
        &self,
        world: &World,
        header: Header,
        transition: &Transition,
        told: &Told,
        sequence: u64,
        keep_copy: bool,
    ) -> Result<Option<StateMsg>> {
        let mut sample = self.state.loan().context("loan state")?;
        let msg = sample.payload_mut();
        msg.header = header;
        msg.n_agents = world.n_agents() as u32;
        msg.outcome = transition.outcome.code();
        msg.reward = transition.reward as f32;
        msg.missed = transition.missed;
        msg.sequence = sequence;
        msg.observation_lost = 0;
        msg.present = 0;
        for (agent, pose) in world.poses.iter().enumerate() {
            msg.poses[agent] = [pose.x as f32, pose.y as f32, pose.theta as f32];
            msg.applied[agent] = [told.applied[agent].0 as f32, told.applied[agent].1 as f32];
            msg.acting[agent] = [world.commands[agent].0 as f32, world.commands[agent].1 as f32];
            let queued = told.reality.queued(agent);
            msg.queued_len[agent] = queued.len().min(MAX_DELAY_TICKS) as u32;
            msg.queued[agent] = [[0.0; 2]; MAX_DELAY_TICKS];
            for (slot, (v, w)) in msg.queued[agent].iter_mut().zip(queued) {
                *slot = [v as f32, w as f32];
            }
            msg.observations[agent] = told.observations[agent];
            msg.observation_lost |= u64::from(told.lost[agent]) << agent;
            msg.desired[agent] = world.desired[agent].map(|d| d as f32);
            msg.slots[agent] = world.slots[agent].map(|d| d as f32);
            let slot = world.slot_of[agent];
            msg.slot[agent] = if slot == NO_SLOT { SLOT_NONE } else { slot as u32 };
            msg.present |= u64::from(slot != NO_SLOT) << agent;
        }
        msg.goal = world.goal.map(|g| g as f32);
        let copy = keep_copy.then_some(*msg);
        sample.send().context("send state")?;
        Ok(copy)
    }

    /// Publishes the episode's obstacles (before its first tick).
    pub fn publish_obstacles(&self, world: &World, header: Header) -> Result<()> {
        let mut sample = self.obstacles.loan().context("loan obstacles")?;
        let msg = sample.payload_mut();
        msg.header = header;
        msg.kind = world.obstacle_kind.code();
        msg.time_limit = world.env.max_steps;
        world.obstacles.write_wire(msg);
        sample.send().context("send obstacles")?;
        Ok(())
    }

    /// Publishes the true poses and the formation in force (before the tick's observations).
    pub fn publish_truth(&self, world: &World, header: Header) -> Result<()> {
        let mut sample = self.truth.loan().context("loan truth")?;
        let msg = sample.payload_mut();
        msg.header = header;
        msg.n_agents = world.n_agents() as u32;
        msg.present = 0;
        for (agent, pose) in world.poses.iter().enumerate() {
            msg.poses[agent] = [pose.x as f32, pose.y as f32, pose.theta as f32];
            msg.slots[agent] = world.slots[agent].map(|d| d as f32);
            msg.present |= u64::from(world.slot_of[agent] != NO_SLOT) << agent;
        }
        msg.goal = world.goal.map(|g| g as f32);
        sample.send().context("send truth")?;
        Ok(())
    }

    /// Wakes the critic to read what is waiting.
    pub fn wake_critic(&self) -> Result<()> {
        self.critic_wake.notify().context("critic wake")?;
        Ok(())
    }

    /// Tells every robot and the critic that the run is over.
    pub fn announce_run_end(&self) -> Result<()> {
        let header = Header::new(u32::MAX, 0, FLAG_RUN_END | FLAG_EPISODE_END);
        for agent in &self.agents {
            let mut sample = agent.observation.loan().context("loan")?;
            sample.payload_mut().header = header;
            sample.send().context("send")?;
            agent.wake.notify().context("notify")?;
        }
        let mut sample = self.state.loan().context("loan")?;
        sample.payload_mut().header = header;
        sample.send().context("send")?;
        self.wake_critic()
    }
}
