//! The sim's tick loop over iceoryx2: publish every observation and the state, wait for every
//! command of the tick (or the timeout), hold missing commands, step, score, repeat.
//!
//! Generic over the iceoryx2 service type: `ipc::Service` across processes, `local::Service`
//! for all roles in one process.

use std::path::PathBuf;
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_protocol::cli::{Mode, write_atomically};
use formation_protocol::config::RunConfig;
use formation_protocol::services::{self, FileDescriptorBased, RunIdentity, Sizing};
use formation_protocol::summary::Summary;
use formation_protocol::termination_requested;
use formation_protocol::wire::*;
use hdrhistogram::Histogram;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;

use crate::formation::random_episode;
use crate::plots::{EpisodeTrace, episode_errors, learning_curve};
use crate::report::{EpisodeLog, EpisodeRecord, fill_episode_figures, outcome_name};
use crate::task::{Conditions, Outcome, edge_error};
use crate::world::World;

/// How the sim runs.
#[derive(Debug, Clone)]
pub struct SimOptions {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Train or eval (recorded in the summary).
    pub mode: Mode,
    /// Stop after this many episodes.
    pub episodes: Option<u64>,
    /// Stop after this much wall-clock time.
    pub minutes: Option<f64>,
    /// Seed of the episode generator.
    pub seed: u64,
    /// Pace ticks at dt of wall-clock time instead of running as fast as possible.
    pub realtime: bool,
    /// Wait for the critic at start-up and never run more than `critic_window` ticks ahead.
    pub expect_critic: bool,
    /// Robots that run the scripted baseline (recorded in the summary).
    pub scripted: Vec<usize>,
    /// Where results go.
    pub run_dir: PathBuf,
    /// The configuration as run.
    pub config: RunConfig,
    /// Write `learning_curve.png` and `episode_errors.png` at the end.
    pub plots: bool,
}

/// Where the view gets its states: the sim offers each logged state without ever waiting.
pub type StateTap = SyncSender<StateMsg>;

struct AgentPorts<S: Service> {
    observation: Publisher<S, ObservationMsg, ()>,
    wake: Notifier<S>,
    command: Subscriber<S, CommandMsg, ()>,
}

struct Ports<S: Service> {
    agents: Vec<AgentPorts<S>>,
    command_ready: Listener<S>,
    state: Publisher<S, StateMsg, ()>,
    critic_wake: Notifier<S>,
    critic_progress: Subscriber<S, CriticProgressMsg, ()>,
    critic_progress_ready: Listener<S>,
}

fn open_ports<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Ports<S>> {
    let err = |what: &str| format!("sim cannot create {what}");
    let mut agents = Vec::with_capacity(sizing.n_agents);
    for agent in 0..sizing.n_agents {
        agents.push(AgentPorts {
            observation: services::observation_stream(node, sizing, agent)?
                .publisher_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("observation publisher")))?,
            wake: services::observation_event(node, sizing, agent)?
                .notifier_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("observation notifier")))?,
            command: services::command_stream(node, sizing, agent)?
                .subscriber_builder()
                .buffer_size(sizing.stream_buffer)
                .create()
                .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("command subscriber")))?,
        });
    }
    Ok(Ports {
        agents,
        command_ready: services::command_event(node, sizing)?
            .listener_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("command listener")))?,
        state: services::state_stream(node, sizing)?
            .publisher_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("state publisher")))?,
        critic_wake: services::critic_wake_event(node, sizing)?
            .notifier_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("critic notifier")))?,
        critic_progress: services::critic_progress_stream(node, sizing)?
            .subscriber_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("progress subscriber")))?,
        critic_progress_ready: services::critic_progress_event(node, sizing)?
            .listener_builder()
            .create()
            .map_err(|e| anyhow::anyhow!("{}: {e:?}", err("progress listener")))?,
    })
}

/// Counters of the stream, kept across episodes.
#[derive(Debug, Default)]
struct StreamCounters {
    env_steps: u64,
    missed_ticks: u64,
    rejected_commands: u64,
    deadline_misses: u64,
    published_ticks: u64,
    rejoins: u64,
    critic: CriticLink,
}

/// What the sim knows of the critic: its session (a restarted critic starts a new one and
/// counts from zero) and whether it is keeping up.
#[derive(Debug, Default)]
struct CriticLink {
    session: u64,
    /// States published when the current session first spoke.
    joined_at: u64,
    acknowledged: u64,
    absent: bool,
}

/// What one episode has added up so far.
struct EpisodeTally {
    episode_return: f64,
    formation_ticks: u32,
    missed_ticks: u64,
    /// C1-C3 at the latest state.
    last: Conditions,
}

impl EpisodeTally {
    /// The `episodes.csv` row of an episode that ended with `outcome` (`None`: aborted).
    fn record(&self, episode: u32, outcome: Option<Outcome>, steps: u32, started: Instant) -> EpisodeRecord {
        EpisodeRecord {
            episode,
            outcome: outcome_name(outcome),
            steps,
            episode_return: self.episode_return,
            final_edge_error_m: self.last.mean_edge_error,
            final_goal_distance_m: self.last.goal_distance,
            formation_hold_rate: f64::from(self.formation_ticks) / f64::from(steps.max(1)),
            missed_ticks: self.missed_ticks,
            wall_s: started.elapsed().as_secs_f64(),
        }
    }
}

/// Why the loop stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stop {
    Budget,
    Signal,
}

/// Runs the sim until the episode or time budget is spent or a termination signal arrives;
/// writes `episodes.csv` and `summary.json`; returns the summary.
pub fn run<S: Service>(identity: &RunIdentity, options: &SimOptions, tap: Option<StateTap>) -> Result<Summary>
where
    Listener<S>: FileDescriptorBased,
{
    let node = services::create_node::<S>(identity, "sim")?;
    let sizing = Sizing::new(options.n_agents, options.config.ticks.critic_window);
    let ports = open_ports(&node, &sizing)?;
    let mut log = EpisodeLog::create(&options.run_dir)?;
    let mut counters = StreamCounters::default();

    let mut presence = Presence::new(options.n_agents);
    wait_for_peers(&ports, options, &mut presence, &mut counters)?;

    let env = &options.config.env;
    let mut rng = StdRng::seed_from_u64(options.seed);
    let timeout = Duration::from_millis(options.config.ticks.command_timeout_ms);
    let dt = Duration::from_secs_f64(env.dt_s);
    let budget = options.minutes.map(|m| Duration::from_secs_f64(m * 60.0));
    let mut histogram = Histogram::<u64>::new_with_bounds(1, 60_000_000, 3).context("tick histogram")?;
    let n = options.n_agents;
    let mut last_commands = vec![(0.0f64, 0.0f64); n];
    let mut received = vec![false; n];
    let mut notified = Vec::with_capacity(n);
    let started = Instant::now();
    let mut stepping_time = Duration::ZERO;
    let mut next_deadline = Instant::now();
    let mut stop = Stop::Budget;
    let traced_edges = traced_edges(n);
    let mut trace = EpisodeTrace {
        dt: env.dt_s,
        edge_names: traced_edges.iter().map(|&(i, _, j)| format!("e{i}{j}")).collect(),
        ..EpisodeTrace::default()
    };
    let mut showcase: Option<EpisodeTrace> = None;

    'episodes: for episode in 0u32.. {
        if options.episodes.is_some_and(|e| u64::from(episode) >= e) || budget.is_some_and(|b| started.elapsed() >= b) {
            break;
        }
        let mut world = World::new(env, random_episode(n, env, &mut rng));
        let log_world =
            tap.is_some() && (options.mode == Mode::Eval || episode % options.config.view.world_every_episodes == 0);
        last_commands.iter_mut().for_each(|c| *c = (0.0, 0.0));
        let eval_episode = options.mode == Mode::Train && episode % options.config.learn.eval_every_episodes == 0;
        let mut tally = EpisodeTally {
            episode_return: 0.0,
            formation_ticks: 0,
            missed_ticks: 0,
            last: world.conditions(),
        };
        let mut outcome = Outcome::Running;
        let mut reward = 0.0;
        let mut missed_mask = 0u32;
        let mut applied = vec![(0.0f64, 0.0f64); n];
        trace.episode = episode;
        trace.edge_errors.clear();
        trace.mean_edge_error.clear();
        trace.goal_distance.clear();

        for tick in 0u32.. {
            let tick_started = Instant::now();
            let ends = outcome != Outcome::Running;
            let flags = if tick == 0 { FLAG_EPISODE_START } else { 0 }
                | if ends { FLAG_EPISODE_END } else { 0 }
                | if eval_episode { FLAG_EVAL_EPISODE } else { 0 };
            let header = Header::new(episode, tick, flags);
            publish_observations(&ports, &world, header)?;
            let state = publish_state(
                &ports,
                &world,
                header,
                &Transition {
                    outcome,
                    reward,
                    missed: missed_mask,
                    applied: &applied,
                },
                &mut counters,
                log_world,
            )?;
            trace.edge_errors.extend(
                traced_edges
                    .iter()
                    .map(|&(i, k, _)| edge_error(i, k, &world.poses, &world.desired)),
            );
            trace.mean_edge_error.push(tally.last.mean_edge_error);
            trace.goal_distance.push(tally.last.goal_distance);
            if let (Some(tap), Some(state)) = (&tap, state) {
                let _dropped_when_view_is_behind = tap.try_send(state);
            }
            if options.expect_critic
                && (ends || counters.published_ticks % u64::from((options.config.ticks.critic_window / 2).max(1)) == 0)
            {
                ports
                    .critic_wake
                    .notify()
                    .map_err(|e| anyhow::anyhow!("critic wake: {e:?}"))?;
            }
            if ends {
                log.push(tally.record(episode, Some(outcome), world.steps, started))?;
                // The figure shows the first episode of an evaluation, or the latest noise-free
                // episode of a training run.
                if (options.mode == Mode::Eval && showcase.is_none()) || eval_episode {
                    showcase = Some(trace.clone());
                }
                break;
            }

            // Wait for this tick's commands, reading only the robots whose event arrived; robots
            // that missed several ticks in a row are not waited for until they answer (or greet)
            // again.
            let deadline = if options.realtime {
                next_deadline.max(tick_started) + dt
            } else {
                tick_started + timeout
            };
            received.iter_mut().for_each(|r| *r = false);
            loop {
                if presence.all_present_answered(&received) {
                    break;
                }
                let now = Instant::now();
                if now >= deadline {
                    break;
                }
                notified.clear();
                let mut stranger = false;
                services::wait_for_events(&ports.command_ready, deadline - now, |id| {
                    if id < n {
                        notified.push(id);
                    } else {
                        stranger = true;
                    }
                })?;
                if stranger {
                    // An event id no robot owns: read every robot.
                    notified.clear();
                    notified.extend(0..n);
                }
                drain_commands(
                    &ports,
                    &notified,
                    header,
                    &mut received,
                    &mut last_commands,
                    &mut presence,
                    &mut counters,
                );
            }
            missed_mask = 0;
            let mut missed_now = 0u64;
            for (agent, &got) in received.iter().enumerate() {
                presence.record(agent, got);
                if !got {
                    missed_mask |= 1 << agent.min(31);
                    missed_now += 1;
                }
            }
            counters.missed_ticks += missed_now;
            tally.missed_ticks += missed_now;
            applied.copy_from_slice(&last_commands);
            let result = world.step(&applied);
            for a in applied.iter_mut() {
                *a = env.clamp_command(a.0, a.1);
            }
            counters.env_steps += 1;
            reward = result.reward;
            tally.episode_return += result.reward;
            outcome = result.outcome;
            tally.last = result.conditions;
            if tally.last.in_formation {
                tally.formation_ticks += 1;
            }
            let tick_time = tick_started.elapsed();
            stepping_time += tick_time;
            let _ = histogram.record((tick_time.as_micros() as u64).max(1));

            if options.realtime {
                next_deadline = next_deadline.max(tick_started) + dt;
                let now = Instant::now();
                if now > next_deadline {
                    counters.deadline_misses += 1;
                    next_deadline = now;
                } else {
                    std::thread::sleep(next_deadline - now);
                }
            }
            if options.expect_critic {
                wait_for_critic(&ports, options, &mut counters)?;
            }
            if termination_requested() {
                stop = Stop::Signal;
                // Close the episode as aborted so the critic sees a truncation.
                let header = Header::new(episode, tick + 1, FLAG_EPISODE_END);
                publish_observations(&ports, &world, header)?;
                publish_state(
                    &ports,
                    &world,
                    header,
                    &Transition {
                        outcome: Outcome::Timeout,
                        reward,
                        missed: missed_mask,
                        applied: &applied,
                    },
                    &mut counters,
                    false,
                )?;
                log.push(tally.record(episode, None, world.steps, started))?;
                break 'episodes;
            }
        }
    }

    let mut summary = Summary {
        mode: options.mode.as_str().into(),
        n_agents: n,
        seed: options.seed,
        scripted_agents: options.scripted.clone(),
        env_steps: counters.env_steps,
        env_steps_per_s: counters.env_steps as f64 / stepping_time.as_secs_f64().max(1e-9),
        tick_p50_us: histogram.value_at_quantile(0.5) as f64,
        tick_p99_us: histogram.value_at_quantile(0.99) as f64,
        missed_ticks: counters.missed_ticks,
        rejected_commands: counters.rejected_commands,
        rejoined_agents: counters.rejoins,
        deadline_misses: counters.deadline_misses,
        wall_s: started.elapsed().as_secs_f64(),
        ..Summary::default()
    };
    fill_episode_figures(&mut summary, log.records());
    if options.plots {
        let curve = options.run_dir.join("learning_curve.png");
        if let Err(err) = learning_curve(&curve, log.records()) {
            eprintln!("sim: cannot draw {}: {err:#}", curve.display());
        }
        if let Some(trace) = showcase
            .as_ref()
            .or((!trace.goal_distance.is_empty()).then_some(&trace))
        {
            let errors = options.run_dir.join("episode_errors.png");
            if let Err(err) = episode_errors(&errors, trace) {
                eprintln!("sim: cannot draw {}: {err:#}", errors.display());
            }
        }
    }
    let path = options.run_dir.join("summary.json");
    write_atomically(&path, serde_json::to_string_pretty(&summary)?.as_bytes())?;

    // Tell everyone the run is over (after summary.json exists, so the critic can extend it).
    let header = Header::new(u32::MAX, 0, FLAG_RUN_END | FLAG_EPISODE_END);
    for agent in &ports.agents {
        let mut sample = agent.observation.loan().map_err(|e| anyhow::anyhow!("loan: {e:?}"))?;
        sample.payload_mut().header = header;
        sample.send().map_err(|e| anyhow::anyhow!("send: {e:?}"))?;
        agent.wake.notify().map_err(|e| anyhow::anyhow!("notify: {e:?}"))?;
    }
    let mut sample = ports.state.loan().map_err(|e| anyhow::anyhow!("loan: {e:?}"))?;
    sample.payload_mut().header = header;
    sample.send().map_err(|e| anyhow::anyhow!("send: {e:?}"))?;
    ports
        .critic_wake
        .notify()
        .map_err(|e| anyhow::anyhow!("notify: {e:?}"))?;
    if stop == Stop::Signal {
        eprintln!("sim: stopped by signal after {} episodes", log.records().len());
    }
    Ok(summary)
}

/// The edges shown in `episode_errors.png`: each undirected observed edge once, at most eight.
fn traced_edges(n: usize) -> Vec<(usize, usize, usize)> {
    let mut seen = Vec::new();
    for (i, k, j) in crate::formation::observed_edges(n) {
        if !seen.iter().any(|&(a, _, b)| (a, b) == (j, i)) {
            seen.push((i, k, j));
        }
    }
    seen.truncate(8);
    seen
}

/// Waits until every agent has greeted (and the critic, when expected).
fn wait_for_peers<S: Service>(
    ports: &Ports<S>,
    options: &SimOptions,
    presence: &mut Presence,
    counters: &mut StreamCounters,
) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    let deadline = Instant::now() + Duration::from_secs(options.config.ticks.startup_timeout_s);
    let mut greeted = vec![false; ports.agents.len()];
    let mut critic_ready = !options.expect_critic;
    loop {
        for (agent, ports) in ports.agents.iter().enumerate() {
            while let Some(sample) = ports.command.receive().map_err(|e| anyhow::anyhow!("receive: {e:?}"))? {
                if sample.payload().header.has(FLAG_HELLO) {
                    check_protocol(sample.payload().header.protocol_version, &format!("agent {agent}"))?;
                    presence.greeted(agent, sample.payload().session);
                    greeted[agent] = true;
                }
            }
        }
        if !critic_ready {
            critic_ready = drain_progress(ports, counters)?;
        }
        if critic_ready && greeted.iter().all(|&g| g) {
            return Ok(());
        }
        if termination_requested() {
            bail!("sim: stopped by signal while waiting for the swarm to connect");
        }
        if Instant::now() >= deadline {
            let missing: Vec<usize> = (0..greeted.len()).filter(|&a| !greeted[a]).collect();
            bail!(
                "sim: after {} s, agents {missing:?} {}have not connected (run id and --agents must match)",
                options.config.ticks.startup_timeout_s,
                if critic_ready { "" } else { "and the critic " }
            );
        }
        services::wait_for_event(&ports.command_ready, Duration::from_millis(50))?;
    }
}

fn check_protocol(version: u32, who: &str) -> Result<()> {
    if version != PROTOCOL_VERSION {
        bail!(
            "{who} speaks protocol version {version}, this sim speaks {PROTOCOL_VERSION}: rebuild all binaries together"
        );
    }
    Ok(())
}

/// Reads the critic's latest progress; true when any arrived.
fn drain_progress<S: Service>(ports: &Ports<S>, counters: &mut StreamCounters) -> Result<bool> {
    let mut any = false;
    while let Some(sample) = ports
        .critic_progress
        .receive()
        .map_err(|e| anyhow::anyhow!("receive: {e:?}"))?
    {
        let progress = *sample.payload();
        check_protocol(progress.protocol_version, "the critic")?;
        let link = &mut counters.critic;
        if progress.session != link.session {
            if link.session != 0 {
                eprintln!("sim: a new critic joined at tick {}", counters.published_ticks);
            }
            link.session = progress.session;
            link.joined_at = counters.published_ticks;
        }
        // A critic that just joined owes nothing for the states published before it came.
        link.acknowledged = progress.acknowledged_sequence.max(link.joined_at);
        if link.absent {
            eprintln!("sim: the critic is back");
            link.absent = false;
        }
        any = true;
    }
    Ok(any)
}

/// Blocks (event-driven) while the sim is more than `critic_window` ticks ahead of the critic.
/// A critic silent for a quarter of the agents' silence limit is treated as gone: the swarm runs on
/// unthrottled (the agents keep their last weights) until a critic speaks again.
fn wait_for_critic<S: Service>(ports: &Ports<S>, options: &SimOptions, counters: &mut StreamCounters) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    let window = u64::from(options.config.ticks.critic_window);
    let give_up = Duration::from_millis(options.config.ticks.sim_silence_ms / 4);
    let mut last_progress = Instant::now();
    drain_progress(ports, counters)?;
    while !counters.critic.absent && counters.published_ticks.saturating_sub(counters.critic.acknowledged) > window {
        services::wait_for_event(&ports.critic_progress_ready, Duration::from_millis(20))?;
        if drain_progress(ports, counters)? {
            last_progress = Instant::now();
            continue;
        }
        if last_progress.elapsed() >= give_up {
            eprintln!(
                "sim: the critic has acknowledged nothing for {} ms; running on without it",
                give_up.as_millis()
            );
            counters.critic.absent = true;
        }
        ports
            .critic_wake
            .notify()
            .map_err(|e| anyhow::anyhow!("critic wake: {e:?}"))?;
        if termination_requested() {
            return Ok(());
        }
    }
    Ok(())
}

/// Which robots the sim waits for: one that missed `ABSENT_AFTER` ticks in a row is treated as
/// gone (its last command is held without waiting) until it answers or greets again.
struct Presence {
    consecutive_misses: Vec<u32>,
    sessions: Vec<u32>,
}

/// Consecutive missed ticks after which the sim stops waiting for a robot.
const ABSENT_AFTER: u32 = 3;
/// Malformed commands logged one by one before the log goes quiet (they are still counted).
const REJECTIONS_LOGGED: u64 = 10;

impl Presence {
    fn new(n: usize) -> Self {
        Self {
            consecutive_misses: vec![0; n],
            sessions: vec![0; n],
        }
    }

    fn is_absent(&self, agent: usize) -> bool {
        self.consecutive_misses[agent] >= ABSENT_AFTER
    }

    fn all_present_answered(&self, received: &[bool]) -> bool {
        received
            .iter()
            .enumerate()
            .all(|(agent, &got)| got || self.is_absent(agent))
    }

    fn record(&mut self, agent: usize, answered: bool) {
        if answered {
            self.consecutive_misses[agent] = 0;
        } else {
            self.consecutive_misses[agent] = self.consecutive_misses[agent].saturating_add(1);
            if self.consecutive_misses[agent] == ABSENT_AFTER {
                eprintln!(
                    "sim: agent {agent} missed {ABSENT_AFTER} ticks in a row; holding its last command without waiting"
                );
            }
        }
    }

    /// Records a greeting; true when it comes from a new process of a robot already known.
    fn greeted(&mut self, agent: usize, session: u32) -> bool {
        let previous = std::mem::replace(&mut self.sessions[agent], session);
        if previous == session {
            return false;
        }
        self.consecutive_misses[agent] = 0;
        previous != 0
    }
}

/// Takes every pending command of `agents`, keeping this tick's valid one per robot.
fn drain_commands<S: Service>(
    ports: &Ports<S>,
    agents: &[usize],
    header: Header,
    received: &mut [bool],
    last_commands: &mut [(f64, f64)],
    presence: &mut Presence,
    counters: &mut StreamCounters,
) {
    for &agent in agents {
        while let Ok(Some(sample)) = ports.agents[agent].command.receive() {
            let cmd = sample.payload();
            if cmd.header.has(FLAG_HELLO) {
                if cmd.header.protocol_version == PROTOCOL_VERSION && presence.greeted(agent, cmd.session) {
                    counters.rejoins += 1;
                    eprintln!(
                        "sim: agent {agent} rejoined at episode {} tick {}",
                        header.episode, header.tick
                    );
                }
                continue;
            }
            let key = (cmd.header.episode, cmd.header.tick);
            let now = (header.episode, header.tick);
            let rejection = if cmd.header.protocol_version != PROTOCOL_VERSION {
                Some("protocol version")
            } else if cmd.agent as usize != agent {
                Some("robot index")
            } else if !(cmd.v.is_finite() && cmd.w.is_finite()) {
                Some("non-finite (v, w)")
            } else if key > now {
                Some("episode or tick in the future")
            } else {
                None
            };
            if let Some(reason) = rejection {
                counters.rejected_commands += 1;
                if counters.rejected_commands <= REJECTIONS_LOGGED {
                    eprintln!("sim: rejected a command from agent {agent} ({reason}): {cmd:?}");
                }
                continue;
            }
            if key < now || received[agent] {
                // A late answer to an earlier tick: already counted as missed.
                continue;
            }
            last_commands[agent] = (f64::from(cmd.v), f64::from(cmd.w));
            received[agent] = true;
        }
    }
}

fn publish_observations<S: Service>(ports: &Ports<S>, world: &World, header: Header) -> Result<()> {
    let n = world.n_agents() as u32;
    for (agent, agent_ports) in ports.agents.iter().enumerate() {
        let mut sample = agent_ports
            .observation
            .loan()
            .map_err(|e| anyhow::anyhow!("loan observation: {e:?}"))?;
        let msg = sample.payload_mut();
        msg.header = header;
        msg.agent = agent as u32;
        msg.n_agents = n;
        msg.obs = world.observation(agent);
        sample.send().map_err(|e| anyhow::anyhow!("send observation: {e:?}"))?;
        if !header.has(FLAG_EPISODE_END) {
            agent_ports
                .wake
                .notify()
                .map_err(|e| anyhow::anyhow!("wake agent {agent}: {e:?}"))?;
        }
    }
    Ok(())
}

/// What led to the state being published.
struct Transition<'a> {
    outcome: Outcome,
    reward: f64,
    missed: u32,
    applied: &'a [(f64, f64)],
}

fn publish_state<S: Service>(
    ports: &Ports<S>,
    world: &World,
    header: Header,
    transition: &Transition,
    counters: &mut StreamCounters,
    keep_copy: bool,
) -> Result<Option<StateMsg>> {
    counters.published_ticks += 1;
    let sequence = counters.published_ticks;
    let Transition {
        outcome,
        reward,
        missed,
        applied,
    } = *transition;
    let mut sample = ports.state.loan().map_err(|e| anyhow::anyhow!("loan state: {e:?}"))?;
    let msg = sample.payload_mut();
    msg.header = header;
    msg.n_agents = world.n_agents() as u32;
    msg.outcome = outcome.code();
    msg.reward = reward as f32;
    msg.missed = missed;
    msg.sequence = sequence;
    for (agent, pose) in world.poses.iter().enumerate() {
        msg.poses[agent] = [pose.x as f32, pose.y as f32, pose.theta as f32];
        msg.applied[agent] = [applied[agent].0 as f32, applied[agent].1 as f32];
        msg.desired[agent] = [world.desired[agent][0] as f32, world.desired[agent][1] as f32];
    }
    msg.goal = [world.goal[0] as f32, world.goal[1] as f32];
    let copy = keep_copy.then_some(*msg);
    sample.send().map_err(|e| anyhow::anyhow!("send state: {e:?}"))?;
    Ok(copy)
}
