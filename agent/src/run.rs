//! The agent's loop over iceoryx2: wait (event-driven) for its own observation, keep the
//! window, pick up new weights between ticks, publish (v, w) with the policy version.

use std::time::Duration;

use anyhow::{Result, bail};
use formation_protocol::config::RunConfig;
use formation_protocol::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_protocol::termination_requested;
use formation_protocol::wire::*;
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::policy::{LearnedPolicy, Policy};
use crate::ports::AgentPorts;
use formation_core::observation::Layout;
use formation_model::history::ObservationHistory;

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
    let obs_dim = Layout::of(options.config.env.observation).dim();
    let sizing = Sizing::new(options.n_agents, options.config.ticks.critic_window, obs_dim);
    let mut ports = AgentPorts::open(&node, identity, &sizing, agent, options.weights_from)?;
    ports.greet()?;

    let mut history = ObservationHistory::new(options.config.env.history, obs_dim);
    let mut stats = AgentStats::default();
    let mut episode = None;
    // A sim that waits for a slow critic, or is stalled by a loaded machine, is waited for
    // while its process lives; one that died is given up after `sim_silence_ms`.
    let mut sim_watch = services::SimWatch::new(
        Duration::from_millis(options.config.ticks.sim_silence_ms),
        Duration::from_secs(options.config.ticks.startup_timeout_s),
    );

    loop {
        ports.wait(Duration::from_millis(100))?;
        let mut reply_to = None;
        while let Some(sample) = ports.receive_observation()? {
            let msg = sample.payload();
            if msg.header.protocol_version != PROTOCOL_VERSION {
                bail!(
                    "agent {agent}: the sim speaks protocol {}, this agent {PROTOCOL_VERSION}: rebuild all binaries together",
                    msg.header.protocol_version
                );
            }
            sim_watch.heard();
            if msg.header.has(FLAG_RUN_END) {
                return Ok(stats);
            }
            if msg.header.has(FLAG_EPISODE_END) {
                reply_to = None;
                continue;
            }
            if msg.dim as usize != obs_dim {
                bail!(
                    "agent {agent}: the sim sends observations of {} floats, this agent's config ({:?}) expects {obs_dim}: start every process with the same --config",
                    msg.dim,
                    options.config.env.observation.as_str()
                );
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
            if !sim_watch.heard_any() {
                // A publisher hands its history to subscribers it has seen; greet again until
                // the sim has connected and answered.
                ports.greet()?;
            }
            if termination_requested() {
                return Ok(stats);
            }
            if let Some(quiet) = sim_watch.gone::<S>(identity, &format!("agent {agent}"))? {
                bail!(
                    "agent {agent}: no observation from the sim for {:.1} s; is it alive?",
                    quiet.as_secs_f64()
                );
            }
            continue;
        };
        // New weights only between ticks, never mid-inference.
        if let AgentPolicy::Learned(learned) = &mut policy {
            while let Some(sample) = ports.receive_weights()? {
                let head = *sample.user_header();
                if head.protocol_version == PROTOCOL_VERSION && head.version > learned.version() {
                    learned.load(sample.payload(), head.version)?;
                    stats.weight_updates += 1;
                }
            }
        }
        let (v, w) = policy.policy().command(&history)?;
        let version = policy.policy().version();
        ports.send(CommandMsg {
            header: Header::new(header.episode, header.tick, 0),
            policy_version: version,
            v: v as f32,
            w: w as f32,
            ..CommandMsg::default()
        })?;
        stats.commands += 1;
        stats.policy_version = version;
    }
}
