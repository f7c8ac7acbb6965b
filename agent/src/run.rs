//! The agent's loop over iceoryx2: wait (event-driven) for its own observation, keep the
//! window, pick up new weights between ticks, publish (v, w) with the policy version.

use std::time::Duration;

use anyhow::{Result, bail};
use formation_core::config::RunConfig;
use formation_ipc::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_ipc::termination_requested;
use formation_protocol::wire::*;
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::oracle::Oracle;
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
    /// Stalls it explored with a held offset (`learn.stall_noise_std`; learned, train mode).
    pub stall_bursts: u64,
}

/// What drives the robot; only the learned actor takes weights, only the oracle reads the
/// true state.
pub enum AgentPolicy {
    /// The scripted baseline (or any fixed controller).
    Fixed(Box<dyn Policy>),
    /// The learned actor.
    Learned(Box<LearnedPolicy>),
    /// The privileged planner that knows the map.
    Oracle(Box<Oracle>),
}

impl AgentPolicy {
    /// The command for the tick `header` names.
    fn command(
        &mut self,
        history: &ObservationHistory,
        header: &Header,
        truth: Option<(&TruthMsg, &ObstaclesMsg)>,
    ) -> Result<(f64, f64)> {
        match self {
            AgentPolicy::Fixed(policy) => policy.command(history),
            AgentPolicy::Learned(policy) => policy.command(history),
            // Without the tick's truth (not arrived), the robot waits still for the next tick.
            AgentPolicy::Oracle(oracle) => Ok(truth
                .and_then(|(truth, obstacles)| oracle.command(header, truth, obstacles))
                .unwrap_or((0.0, 0.0))),
        }
    }

    fn version(&self) -> u32 {
        match self {
            AgentPolicy::Fixed(policy) => policy.version(),
            AgentPolicy::Learned(policy) => policy.version(),
            AgentPolicy::Oracle(_) => 0,
        }
    }

    fn begin_episode(&mut self, episode: u32, explore: bool) {
        match self {
            AgentPolicy::Fixed(policy) => policy.begin_episode(episode, explore),
            AgentPolicy::Learned(policy) => policy.begin_episode(episode, explore),
            AgentPolicy::Oracle(_) => {}
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
    if matches!(policy, AgentPolicy::Oracle(_)) {
        ports.read_truth(&node, &sizing)?;
    }
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
            services::check_sim_protocol(&msg.header, &format!("agent {agent}"), "agent")?;
            if !sim_watch.heard_any() {
                eprintln!(
                    "agent {agent}: first observation at episode {} tick {} (session {:08x})",
                    msg.header.episode, msg.header.tick, ports.session
                );
            }
            sim_watch.heard();
            if msg.header.has(FLAG_RUN_END) {
                if let AgentPolicy::Learned(learned) = &policy {
                    stats.stall_bursts = learned.stall_bursts();
                }
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
                policy.begin_episode(msg.header.episode, !msg.header.has(FLAG_EVAL_EPISODE));
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
        let (v, w) = policy.command(&history, &header, ports.latest_truth()?)?;
        let version = policy.version();
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

#[cfg(test)]
mod tests {
    use std::time::Instant;

    use formation_ipc::services::Sizing;
    use formation_ipc::tick_gate::{ALL_ANSWERED_EVENT_ID, TickGate};
    use formation_model::history::ObservationHistory;
    use formation_protocol::MAX_OBS_DIM;

    use super::*;

    /// Answers (0.3, the first float of the newest observation), as weights version 7.
    struct Echo;

    impl Policy for Echo {
        fn command(&mut self, history: &ObservationHistory) -> Result<(f64, f64)> {
            Ok((0.3, f64::from(history.latest()[0])))
        }

        fn version(&self) -> u32 {
            7
        }
    }

    /// The next command (not a greeting) robot 1 sends, waiting up to 5 s.
    fn next_command(commands: &iceoryx2::port::subscriber::Subscriber<local::Service, CommandMsg, ()>) -> CommandMsg {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            while let Some(sample) = commands.receive().expect("receive") {
                if !sample.payload().header.has(FLAG_HELLO) {
                    return *sample.payload();
                }
            }
            assert!(Instant::now() < deadline, "no command from the agent");
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// The event ids raised on `ready` within `patience` (returns at the first).
    fn raised(ready: &Listener<local::Service>, patience: Duration) -> Vec<usize> {
        let mut ids = Vec::new();
        services::wait_for_events(ready, patience, |id| ids.push(id)).expect("wait");
        ids
    }

    #[test]
    fn an_agent_answers_each_tick_counts_itself_in_the_gate_sleeps_on_the_bell_and_leaves_at_the_run_end() {
        let identity = RunIdentity::new(&format!("agentloop{}", std::process::id())).expect("id");
        let config = RunConfig::default();
        let dim = Layout::of(config.env.observation).dim();
        let sizing = Sizing::new(3, config.ticks.critic_window, dim);
        let node = services::create_node::<local::Service>(&identity, "sim").expect("node");
        let gate = TickGate::create(&identity).expect("gate");
        let observations = services::observation_stream(&node, &sizing, 1)
            .expect("stream")
            .publisher_builder()
            .create()
            .expect("publisher");
        let wake = services::observation_event(&node, &sizing, 1)
            .expect("event")
            .notifier_builder()
            .create()
            .expect("notifier");
        let commands = services::command_stream(&node, &sizing, 1)
            .expect("stream")
            .subscriber_builder()
            .create()
            .expect("subscriber");
        let ready = services::command_event(&node, &sizing)
            .expect("event")
            .listener_builder()
            .create()
            .expect("listener");
        let options = AgentOptions {
            agent: 1,
            n_agents: 3,
            weights_from: None,
            config,
        };
        let agent = {
            let identity = identity.clone();
            std::thread::spawn(move || run::<local::Service>(&identity, &options, AgentPolicy::Fixed(Box::new(Echo))))
        };
        // Wakes the robot with its event, or with the bell once it sleeps on it.
        let send = |tick: u32, flags: u32, first: f32, bell: bool| {
            let mut obs = [0.0; MAX_OBS_DIM];
            obs[0] = first;
            observations
                .send_copy(ObservationMsg {
                    header: Header::new(0, tick, flags),
                    agent: 1,
                    n_agents: 3,
                    dim: dim as u32,
                    obs,
                })
                .expect("observation");
            if bell {
                gate.ring().expect("ring");
            } else {
                wake.notify().expect("wake");
            }
        };

        // As the sim does: wait for the greeting, so the robot's subscriber exists.
        let deadline = Instant::now() + Duration::from_secs(5);
        while !commands
            .receive()
            .expect("receive")
            .is_some_and(|sample| sample.payload().header.has(FLAG_HELLO))
        {
            assert!(Instant::now() < deadline, "no greeting");
            std::thread::sleep(Duration::from_millis(10));
        }

        // Tick 0: the robot finds the gate with its first answer; the round expected nobody,
        // so its answer wakes the sim with the all-answered id.
        gate.open_round(0, 0, 0);
        send(0, FLAG_EPISODE_START, 0.5, false);
        let command = next_command(&commands);
        assert_eq!((command.header.episode, command.header.tick, command.agent), (0, 0, 1));
        assert_eq!((command.v, command.w, command.policy_version), (0.3, 0.5, 7));
        assert_eq!(gate.member_session(1), command.session, "attached with its session");
        assert_eq!(
            gate.bell_session(1),
            command.session,
            "and sleeps on the bell from now on"
        );
        let ids = raised(&ready, Duration::from_secs(5));
        assert!(ids.contains(&ALL_ANSWERED_EVENT_ID), "{ids:?}");

        // Tick 1, rung with the bell: another robot's answer is still expected, so this one
        // wakes nobody.
        gate.open_round(0, 1, 2);
        send(1, 0, -0.25, true);
        let command = next_command(&commands);
        assert_eq!((command.header.tick, command.w), (1, -0.25));
        let ids = raised(&ready, Duration::from_millis(100));
        assert!(ids.is_empty(), "a quiet answer raised {ids:?}");

        // The episode's last state is not answered; the run's end ends the agent.
        send(2, FLAG_EPISODE_END, 0.0, true);
        send(0, FLAG_RUN_END | FLAG_EPISODE_END, 0.0, true);
        let stats = agent.join().expect("thread").expect("agent");
        assert_eq!(stats.commands, 2);
        assert_eq!(stats.policy_version, 7);
    }
}
