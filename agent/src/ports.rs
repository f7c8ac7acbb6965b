//! The agent's ends of the services: its own observation stream and wake-up event, its command
//! stream and the sim's command event, and (when learning) its actor's weights stream.

use std::time::Duration;

use anyhow::{Context, Result};
use formation_protocol::services::{self, FileDescriptorBased, Sizing};
use formation_protocol::wire::{CommandMsg, FLAG_HELLO, Header, ObservationMsg, WeightsHeader};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;

/// One robot's ports.
pub struct AgentPorts<S: Service> {
    agent: usize,
    observations: Subscriber<S, ObservationMsg, ()>,
    wake: Listener<S>,
    commands: Publisher<S, CommandMsg, ()>,
    command_ready: Notifier<S>,
    weights: Option<Subscriber<S, [f32], WeightsHeader>>,
    /// Random per process start, so the sim tells a restarted robot from its predecessor.
    pub session: u32,
}

impl<S: Service> AgentPorts<S>
where
    Listener<S>: FileDescriptorBased,
{
    /// Opens robot `agent`'s ports; `weights_from` subscribes to that actor's weights.
    pub fn open(node: &Node<S>, sizing: &Sizing, agent: usize, weights_from: Option<usize>) -> Result<Self> {
        let weights = match weights_from {
            Some(index) => Some(
                services::weights_stream(node, sizing, index)?
                    .subscriber_builder()
                    .create()
                    .with_context(|| format!("agent {agent}: weights subscriber"))?,
            ),
            None => None,
        };
        Ok(Self {
            agent,
            observations: services::observation_stream(node, sizing, agent)?
                .subscriber_builder()
                .buffer_size(16)
                .create()
                .with_context(|| format!("agent {agent}: observation subscriber"))?,
            wake: services::observation_event(node, sizing, agent)?
                .listener_builder()
                .create()
                .with_context(|| format!("agent {agent}: listener"))?,
            commands: services::command_stream(node, sizing, agent)?
                .publisher_builder()
                .create()
                .with_context(|| format!("agent {agent}: command publisher"))?,
            command_ready: services::command_event(node, sizing)?
                .notifier_builder()
                .default_event_id(services::agent_event_id(agent))
                .create()
                .with_context(|| format!("agent {agent}: notifier"))?,
            weights,
            session: rand::random_range(1..u32::MAX),
        })
    }

    /// Sleeps until the sim signals an observation or `timeout` passes.
    pub fn wait(&self, timeout: Duration) -> Result<()> {
        services::wait_for_event(&self.wake, timeout)
    }

    /// The next observation received, if any.
    pub fn receive_observation(&self) -> Result<Option<Sample<S, ObservationMsg, ()>>> {
        let agent = self.agent;
        self.observations
            .receive()
            .with_context(|| format!("agent {agent}: receive"))
    }

    /// The next weights received, if this robot follows an actor and any arrived.
    pub fn receive_weights(&self) -> Result<Option<Sample<S, [f32], WeightsHeader>>> {
        let agent = self.agent;
        match &self.weights {
            Some(weights) => weights.receive().with_context(|| format!("agent {agent}: weights")),
            None => Ok(None),
        }
    }

    /// Greets the sim (history 1 keeps the greeting for a sim that starts later).
    pub fn greet(&self) -> Result<()> {
        self.send(CommandMsg {
            header: Header::new(0, 0, FLAG_HELLO),
            ..CommandMsg::default()
        })
    }

    /// Sends a command (robot index and session filled in) and wakes the sim.
    pub fn send(&self, command: CommandMsg) -> Result<()> {
        let agent = self.agent;
        let mut sample = self.commands.loan().with_context(|| format!("agent {agent}: loan"))?;
        *sample.payload_mut() = CommandMsg {
            agent: agent as u32,
            session: self.session,
            ..command
        };
        sample.send().with_context(|| format!("agent {agent}: send"))?;
        self.command_ready
            .notify()
            .with_context(|| format!("agent {agent}: notify"))?;
        Ok(())
    }
}
