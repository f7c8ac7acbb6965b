//! The agent's ends of the services: its own observation stream and wake-up event, its command
//! stream and the sim's command event, the tick gate (so that only a tick's last robot wakes
//! the sim, and the robot sleeps on the gate's bell instead of its event), and (when learning)
//! its actor's weights stream.

use std::time::Duration;

use anyhow::{Context, Result};
use formation_ipc::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_ipc::tick_gate::{ALL_ANSWERED_EVENT_ID, Answer, TickGate};
use formation_protocol::wire::{CommandMsg, FLAG_HELLO, Header, ObservationMsg, ObstaclesMsg, TruthMsg, WeightsHeader};
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
    /// The true poses and the episode's obstacles, for the privileged planner.
    truth: Option<TruthPorts<S>>,
    identity: RunIdentity,
    /// The sim's tick gate, once it is found (a sim on another host has none here).
    gate: Option<TickGate>,
    looked_for_gate: bool,
    /// Whether to sleep on the gate's bell once attached (`FORMATION_TICK_BELL=off`: no).
    join_bell: bool,
    /// The bell's count read before the last look for observations.
    bell_seen: u32,
    /// Random per process start, so the sim tells a restarted robot from its predecessor.
    pub session: u32,
}

/// What the privileged planner reads beyond its robot's observation.
struct TruthPorts<S: Service> {
    truth: Subscriber<S, TruthMsg, ()>,
    obstacles: Subscriber<S, ObstaclesMsg, ()>,
    latest_truth: TruthMsg,
    latest_obstacles: ObstaclesMsg,
}

impl<S: Service> AgentPorts<S>
where
    Listener<S>: FileDescriptorBased,
{
    /// Opens robot `agent`'s ports; `weights_from` subscribes to that actor's weights.
    pub fn open(
        node: &Node<S>,
        identity: &RunIdentity,
        sizing: &Sizing,
        agent: usize,
        weights_from: Option<usize>,
    ) -> Result<Self> {
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
            truth: None,
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
                .create()
                .with_context(|| format!("agent {agent}: notifier"))?,
            weights,
            identity: identity.clone(),
            gate: None,
            looked_for_gate: false,
            join_bell: !std::env::var("FORMATION_TICK_BELL").is_ok_and(|v| v == "off"),
            bell_seen: 0,
            session: rand::random_range(1..u32::MAX),
        })
    }

    /// Also subscribes to the true poses and the episodes' obstacles (a privileged planner).
    pub fn read_truth(&mut self, node: &Node<S>, sizing: &Sizing) -> Result<()> {
        let agent = self.agent;
        self.truth = Some(TruthPorts {
            truth: services::truth_stream(node, sizing)?
                .subscriber_builder()
                .create()
                .with_context(|| format!("agent {agent}: truth subscriber"))?,
            obstacles: services::obstacles_stream(node, sizing)?
                .subscriber_builder()
                .create()
                .with_context(|| format!("agent {agent}: obstacles subscriber"))?,
            latest_truth: TruthMsg::default(),
            latest_obstacles: ObstaclesMsg::default(),
        });
        Ok(())
    }

    /// The newest true poses and obstacles received (the sim publishes a tick's truth before
    /// its observations, and an episode's obstacles before its first tick); `None` unless
    /// [`AgentPorts::read_truth`] subscribed.
    pub fn latest_truth(&mut self) -> Result<Option<(&TruthMsg, &ObstaclesMsg)>> {
        let Some(ports) = &mut self.truth else {
            return Ok(None);
        };
        while let Some(sample) = ports.truth.receive().context("receive truth")? {
            ports.latest_truth = *sample.payload();
        }
        while let Some(sample) = ports.obstacles.receive().context("receive obstacles")? {
            ports.latest_obstacles = *sample.payload();
        }
        Ok(Some((&ports.latest_truth, &ports.latest_obstacles)))
    }

    /// Sleeps until the sim signals an observation (on the bell once this robot joined it, on
    /// its own event before) or `timeout` passes; look for observations after it returns.
    pub fn wait(&mut self, timeout: Duration) -> Result<()> {
        match &self.gate {
            Some(gate) if self.join_bell => {
                gate.wait_for_bell(self.bell_seen, timeout)?;
                // Read before the caller looks for observations: a ring after this read makes
                // the next wait return at once.
                self.bell_seen = gate.bell_count();
                Ok(())
            }
            _ => services::wait_for_event(&self.wake, timeout),
        }
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
        self.publish(CommandMsg {
            header: Header::new(0, 0, FLAG_HELLO),
            ..CommandMsg::default()
        })?;
        self.notify(services::agent_event_id(self.agent))
    }

    /// Sends the command for a tick and counts it in the tick gate; wakes the sim only when
    /// this is the tick's last answer the gate expects (or when there is no gate).
    pub fn send(&mut self, command: CommandMsg) -> Result<()> {
        if self.gate.is_none() && (command.header.tick == 0 || !self.looked_for_gate) {
            // Looked for with the first answer and at each episode's start (a sim on another
            // host, behind a bridge, has none here), before the answer goes out: once the sim
            // has it, it may ring the next tick's bell, which must find this robot on it.
            self.gate = TickGate::attach(&self.identity, self.agent, self.session, self.join_bell)?;
            self.looked_for_gate = true;
            // This tick's observation is taken; the sim rings for this robot from a later one.
            self.bell_seen = self.gate.as_ref().map_or(0, TickGate::bell_count);
        }
        self.publish(command)?;
        let answer = match &self.gate {
            Some(gate) => gate.answer(command.header.episode, command.header.tick),
            None => Answer::NotCounted,
        };
        match answer {
            Answer::Quiet => Ok(()),
            Answer::WakeSim => self.notify(EventId::new(ALL_ANSWERED_EVENT_ID)),
            Answer::NotCounted => self.notify(services::agent_event_id(self.agent)),
        }
    }

    /// Publishes `command` with this robot's index and session filled in.
    fn publish(&self, command: CommandMsg) -> Result<()> {
        let agent = self.agent;
        let mut sample = self.commands.loan().with_context(|| format!("agent {agent}: loan"))?;
        *sample.payload_mut() = CommandMsg {
            agent: agent as u32,
            session: self.session,
            ..command
        };
        sample.send().with_context(|| format!("agent {agent}: send"))?;
        Ok(())
    }

    fn notify(&self, id: EventId) -> Result<()> {
        let agent = self.agent;
        self.command_ready
            .notify_with_custom_event_id(id)
            .with_context(|| format!("agent {agent}: notify"))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_robot_is_on_the_gate_and_its_bell_before_its_first_command_can_reach_the_sim() {
        let identity = RunIdentity::new(&format!("agentports{}", std::process::id())).expect("id");
        let sizing = Sizing::new(3, 8, 12);
        let node = services::create_node::<local::Service>(&identity, "sim").expect("node");
        let gate = TickGate::create(&identity).expect("gate");
        let sim_side = services::command_stream(&node, &sizing, 1)
            .expect("stream")
            .subscriber_builder()
            .create()
            .expect("subscriber");
        let mut ports = AgentPorts::open(&node, &identity, &sizing, 1, None).expect("ports");
        let first = CommandMsg {
            header: Header::new(0, 0, 0),
            v: 0.2,
            ..CommandMsg::default()
        };
        // Every sample of the robot's publisher is on loan, so its first command cannot go
        // out: whatever `send` did before publishing is all it did.
        let held: Vec<_> = (0..64).map_while(|_| ports.commands.loan().ok()).collect();
        assert!(ports.send(first).is_err(), "published with every sample on loan");
        assert!(sim_side.receive().expect("receive").is_none());
        assert_eq!(gate.member_session(1), ports.session, "counts in the gate already");
        assert_eq!(gate.bell_session(1), ports.session, "sleeps on the bell already");
        // Published for real, the first command the sim receives finds the robot on both.
        drop(held);
        ports.send(first).expect("send");
        let received = sim_side.receive().expect("receive").expect("the first command");
        assert_eq!(received.payload().v, 0.2);
        assert_eq!(gate.member_session(1), received.payload().session);
        assert_eq!(gate.bell_session(1), received.payload().session);
    }
}
