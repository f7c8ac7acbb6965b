//! The agent's loop over iceoryx2: wait (event-driven) for its own observation, keep the
//! window, pick up new weights between ticks, publish (v, w) with the policy version.

use std::time::{Duration, Instant};

use anyhow::{Result, bail};
use formation_protocol::config::RunConfig;
use formation_protocol::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_protocol::termination_requested;
use formation_protocol::wire::*;
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::history::ObservationHistory;
use crate::policy::{LearnedPolicy, Policy};

/// Who this agent is.
#[derive(Debug, Clone)]
pub struct AgentOptions {
    /// This robot's index.
    pub agent: usize,
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Which actor's weights to follow (`None`: do not subscribe, e.g. scripted or eval).
    pub weights_from: Option<usize>,
    /// The run's configuration.
    pub config: RunConfig,
}

/// What an agent did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AgentStats {
    /// Commands sent.
    pub commands: u64,
    /// Weight versions installed.
    pub weight_updates: u64,
    /// Latest policy version.
    pub policy_version: u32,
}

/// Either kind of policy; only the learned one takes weights.
pub enum AgentPolicy {
    /// The scripted baseline (or any fixed controller).
    Fixed(Box<dyn Policy>),
    /// The learned actor.
    Learned(Box<LearnedPolicy>),
}

impl AgentPolicy {
    fn policy(&mut self) -> &mut dyn Policy {
        match self {
            AgentPolicy::Fixed(policy) => policy.as_mut(),
            AgentPolicy::Learned(policy) => policy.as_mut(),
        }
    }
}

/// Runs until the sim announces the end of the run; errors when the sim falls silent.
pub fn run<S: Service>(identity: &RunIdentity, options: &AgentOptions, mut policy: AgentPolicy) -> Result<AgentStats>
where
    Listener<S>: FileDescriptorBased,
{
    let agent = options.agent;
    let node = services::create_node::<S>(identity, &format!("agent{agent}"))?;
    let sizing = Sizing::new(options.n_agents, options.config.ticks.critic_window);
    let observations = services::observation_stream(&node, &sizing, agent)?
        .subscriber_builder()
        .buffer_size(16)
        .create()
        .map_err(|e| anyhow::anyhow!("agent {agent}: observation subscriber: {e:?}"))?;
    let wake = services::observation_event(&node, &sizing, agent)?
        .listener_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("agent {agent}: listener: {e:?}"))?;
    let commands = services::command_stream(&node, &sizing, agent)?
        .publisher_builder()
        .create()
        .map_err(|e| anyhow::anyhow!("agent {agent}: command publisher: {e:?}"))?;
    let command_ready = services::command_event(&node, &sizing)?
        .notifier_builder()
        .default_event_id(services::agent_event_id(agent))
        .create()
        .map_err(|e| anyhow::anyhow!("agent {agent}: notifier: {e:?}"))?;
    let weights = match options.weights_from {
        Some(index) => Some(
            services::weights_stream(&node, &sizing, index)?
                .subscriber_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("agent {agent}: weights subscriber: {e:?}"))?,
        ),
        None => None,
    };

    // Greet the sim (history 1 keeps the greeting for a sim that starts later).
    let session = rand::random_range(1..u32::MAX);
    let hello = CommandMsg {
        header: Header::new(0, 0, FLAG_HELLO),
        agent: agent as u32,
        session,
        ..CommandMsg::default()
    };
    let greet = || -> Result<()> {
        commands
            .send_copy(hello)
            .map_err(|e| anyhow::anyhow!("agent {agent}: hello: {e:?}"))?;
        command_ready
            .notify()
            .map_err(|e| anyhow::anyhow!("agent {agent}: notify: {e:?}"))?;
        Ok(())
    };
    greet()?;

    let mut history = ObservationHistory::new(options.config.env.history);
    let mut stats = AgentStats::default();
    let mut episode = None;
    let silence = Duration::from_millis(options.config.ticks.sim_silence_ms);
    let startup = Duration::from_secs(options.config.ticks.startup_timeout_s);
    let mut last_heard = Instant::now();
    let mut heard_any = false;

    loop {
        services::wait_for_event(&wake, Duration::from_millis(100))?;
        let mut reply_to = None;
        while let Some(sample) = observations
            .receive()
            .map_err(|e| anyhow::anyhow!("agent {agent}: receive: {e:?}"))?
        {
            let msg = sample.payload();
            if msg.header.protocol_version != PROTOCOL_VERSION {
                bail!(
                    "agent {agent}: the sim speaks protocol {}, this agent {PROTOCOL_VERSION}: rebuild all binaries together",
                    msg.header.protocol_version
                );
            }
            heard_any = true;
            last_heard = Instant::now();
            if msg.header.has(FLAG_RUN_END) {
                return Ok(stats);
            }
            if msg.header.has(FLAG_EPISODE_END) {
                reply_to = None;
                continue;
            }
            if msg.header.has(FLAG_EPISODE_START) || episode != Some(msg.header.episode) {
                episode = Some(msg.header.episode);
                history.reset(&msg.obs);
                policy
                    .policy()
                    .begin_episode(msg.header.episode, !msg.header.has(FLAG_EVAL_EPISODE));
            } else {
                history.push(&msg.obs);
            }
            reply_to = Some(msg.header);
        }
        let Some(header) = reply_to else {
            if !heard_any {
                // A publisher hands its history to subscribers it has seen; greet again until
                // the sim has connected and answered.
                greet()?;
            }
            if termination_requested() {
                return Ok(stats);
            }
            let quiet = last_heard.elapsed();
            if (heard_any && quiet > silence) || (!heard_any && quiet > startup) {
                bail!(
                    "agent {agent}: no observation from the sim for {:.1} s; is it alive?",
                    quiet.as_secs_f64()
                );
            }
            continue;
        };
        // New weights only between ticks, never mid-inference.
        if let (Some(weights), AgentPolicy::Learned(learned)) = (&weights, &mut policy) {
            while let Some(sample) = weights
                .receive()
                .map_err(|e| anyhow::anyhow!("agent {agent}: weights: {e:?}"))?
            {
                let head = *sample.user_header();
                if head.protocol_version == PROTOCOL_VERSION && head.version > learned.version() {
                    learned.load(sample.payload(), head.version)?;
                    stats.weight_updates += 1;
                }
            }
        }
        let (v, w) = policy.policy().command(&history)?;
        let version = policy.policy().version();
        let mut sample = commands
            .loan()
            .map_err(|e| anyhow::anyhow!("agent {agent}: loan: {e:?}"))?;
        *sample.payload_mut() = CommandMsg {
            header: Header::new(header.episode, header.tick, 0),
            agent: agent as u32,
            policy_version: version,
            v: v as f32,
            w: w as f32,
            session,
        };
        sample
            .send()
            .map_err(|e| anyhow::anyhow!("agent {agent}: send: {e:?}"))?;
        command_ready
            .notify()
            .map_err(|e| anyhow::anyhow!("agent {agent}: notify: {e:?}"))?;
        stats.commands += 1;
        stats.policy_version = version;
    }
}
