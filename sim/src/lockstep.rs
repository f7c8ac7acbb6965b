//! The sim's tick loop over iceoryx2: tell every robot its observation and publish the state,
//! wait for every command of the tick (or the timeout), settle each robot's command in use,
//! drive the motors, step, score, repeat.
//!
//! [`run`] is the whole process: connect ([`SimPorts`], greetings), play episodes one tick at a
//! time ([`Lockstep::play_episode`]), then report ([`Lockstep::finish`]). The tick's command
//! wait and accounting is [`crate::commands`], the readers' flow control [`crate::reader_link`].
//!
//! The reality model ([`formation_core::reality`], the `[reality]` section) sits at both ends
//! of a tick, one [`Reality`] per episode seeded by (run seed, episode) apart from the episode
//! generator: what each robot is told passes [`Reality::tell`] and may be lost
//! ([`Reality::observation_lost`], never on an episode's last tick, which asks for no
//! command); each command read may be lost ([`Reality::command_lost`]); the command in use
//! goes through [`Reality::actuate`] (delay line, motor lag, dead controller) and the acting
//! velocity drives the physics. With every key off all of it is the identity.
//!
//! The team: the episode's [`Mission`] takes a robot out of the formation when its controller
//! fails (at the failure's tick), when the control service removes it, or when the command
//! accounting has heard nothing from it for 10 ticks in a row ([`Attendance`]; losses of
//! `[reality]` are not silence), and back after 5 answers in a row or when restored; each
//! change is in force from the next tick's observations, like a shape change. A robot out of
//! the formation does not drive by its own commands: a silent or failed one does what
//! `dead_robot` says, one that still answers (removed, or on its way back) is commanded to
//! stand still.
//!
//! Generic over the iceoryx2 service type: `ipc::Service` across processes, `local::Service`
//! for all roles in one process.

use std::path::PathBuf;
use std::sync::mpsc::SyncSender;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_core::config::RunConfig;
use formation_core::formation::Episodes;
use formation_core::mission::{Attendance, Away, Heard};
use formation_core::observation::Layout;
use formation_core::obstacles::Obstacle;
use formation_core::run_dir::write_atomically;
use formation_core::shapes::observed_edges;
use formation_core::stepper::{EpisodeStepper, TransportCounts};
use formation_core::task::Outcome;
use formation_ipc::cli::Mode;
use formation_ipc::services::{self, FileDescriptorBased, RunIdentity, Sizing, StreamReader};
use formation_ipc::summary::Summary;
use formation_ipc::switches::{ThreadSwitches, machine_switches};
use formation_ipc::termination_requested;
use formation_ipc::tick_gate::TickGate;
use formation_protocol::wire::*;
use hdrhistogram::Histogram;
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::commands::{CommandCounters, CommandRound, Settled};
use crate::control::ControlServer;
use crate::plots::{EpisodeTrace, episode_errors, learning_curve};
use crate::ports::{SimPorts, Told, Transition};
use crate::reader_link::{ReaderLink, check_protocol};
use crate::report::{EpisodeLog, fill_episode_figures};

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
    /// Likewise for an MCAP recorder (`--record mcap`), so it loses no state.
    pub expect_recorder: bool,
    /// Robots that run the scripted baseline (recorded in the summary).
    pub scripted: Vec<usize>,
    /// Robots played by outside processes (recorded in the summary).
    pub external: Vec<usize>,
    /// Where results go.
    pub run_dir: PathBuf,
    /// The configuration as run.
    pub config: RunConfig,
    /// Write `learning_curve.png` and `episode_errors.png` at the end.
    pub plots: bool,
}

/// What the view is offered at a logged tick: the state, and at an episode's first tick the
/// episode's obstacles with it (one message, so the view never pairs a state with another
/// episode's obstacles).
pub struct Tapped {
    /// The state of the tick.
    pub state: StateMsg,
    /// The episode's obstacles, at its first tick only.
    pub obstacles: Option<Vec<Obstacle>>,
}

/// Where the view gets its states: the sim offers each logged state without ever waiting.
pub type StateTap = SyncSender<Tapped>;

/// What the transport has added up in one episode.
struct EpisodeTally {
    /// The run's command counters when the episode began.
    counters_at_start: CommandCounters,
    /// Robot-ticks missed so far.
    missed_ticks: u64,
    /// Robots that missed the latest tick.
    missed: u32,
}

impl EpisodeTally {
    /// The transport's counts for the episode's record, with the run's counters `now`.
    fn transport(&self, now: CommandCounters, run_started: Instant) -> TransportCounts {
        TransportCounts {
            missed_ticks: self.missed_ticks,
            late_commands: now.late - self.counters_at_start.late,
            wall_s: run_started.elapsed().as_secs_f64(),
        }
    }
}

/// The header of tick `tick` of `episode`: its start, its end (the episode no longer
/// `running`), and whether it is a noise-free evaluation episode of a training run.
fn tick_header(episode: u32, tick: u32, running: bool, eval_episode: bool) -> Header {
    let flags = if tick == 0 { FLAG_EPISODE_START } else { 0 }
        | if running { 0 } else { FLAG_EPISODE_END }
        | if eval_episode { FLAG_EVAL_EPISODE } else { 0 };
    Header::new(episode, tick, flags)
}

/// What the stepper told the robots this tick, as the ports publish it.
fn told(stepper: &EpisodeStepper) -> Told<'_> {
    Told {
        observations: stepper.told(),
        lost: stepper.lost(),
        applied: stepper.applied(),
        reality: stepper.reality(),
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
    let sizing = Sizing::new(
        options.n_agents,
        options.config.ticks.critic_window,
        Layout::of(options.config.env.observation).dim(),
    );
    let mut sim = Lockstep {
        ports: SimPorts::open(&node, &sizing)?,
        control: ControlServer::open(&node, &sizing)?,
        options,
        tap,
        log: EpisodeLog::create(&options.run_dir)?,
        round: command_round(identity, options.n_agents),
        readers: readers(&node, &sizing, options)?,
        published: 0,
        env_steps: 0,
        deadline_misses: 0,
        histogram: Histogram::<u64>::new_with_bounds(1, 60_000_000, 3).context("tick histogram")?,
        stepping_time: Duration::ZERO,
        started: Instant::now(),
        switches_at_start: (ThreadSwitches::now(), machine_switches()),
        next_deadline: Instant::now(),
        traced: traced_edges(options.n_agents),
        trace: EpisodeTrace::default(),
        showcase: None,
        attendance: Attendance::new(options.n_agents),
    };
    sim.wait_for_peers()?;
    sim.started = Instant::now();
    sim.switches_at_start = (ThreadSwitches::now(), machine_switches());
    sim.next_deadline = sim.started;
    sim.trace = EpisodeTrace {
        dt: options.config.env.dt_s,
        ..EpisodeTrace::default()
    };
    let episodes = Episodes::new(options.n_agents, &options.config.env, options.seed);
    let budget = options.minutes.map(|m| Duration::from_secs_f64(m * 60.0));
    let mut stop = Stop::Budget;
    for (episode, init) in (0u32..).zip(episodes) {
        if options.episodes.is_some_and(|e| u64::from(episode) >= e)
            || budget.is_some_and(|b| sim.started.elapsed() >= b)
        {
            break;
        }
        let config = &options.config;
        let stepper = EpisodeStepper::new(&config.env, &config.reality, options.seed, episode, init);
        if let Some(stopped) = sim.play_episode(episode, stepper)? {
            stop = stopped;
            break;
        }
    }
    sim.finish(stop)
}

/// The links to the readers `options` expects, in the order the sim waits for them.
fn readers<S: Service>(node: &Node<S>, sizing: &Sizing, options: &SimOptions) -> Result<Vec<ReaderLink<S>>>
where
    Listener<S>: FileDescriptorBased,
{
    [
        (options.expect_critic, StreamReader::Critic),
        (options.expect_recorder, StreamReader::Recorder),
    ]
    .into_iter()
    .filter(|(expected, _)| *expected)
    .map(|(_, reader)| ReaderLink::open(node, sizing, reader))
    .collect()
}

/// The sim's state across ticks and episodes.
struct Lockstep<'a, S: Service> {
    ports: SimPorts<S>,
    /// The live control service, served once a tick.
    control: ControlServer<S>,
    options: &'a SimOptions,
    tap: Option<StateTap>,
    log: EpisodeLog,
    round: CommandRound,
    /// The readers that must see every state (none without a critic).
    readers: Vec<ReaderLink<S>>,
    /// States published so far (the sequence number of the latest).
    published: u64,
    env_steps: u64,
    deadline_misses: u64,
    histogram: Histogram<u64>,
    stepping_time: Duration,
    started: Instant,
    /// The tick thread's and the machine's context switches when ticking began.
    switches_at_start: (ThreadSwitches, Option<u64>),
    next_deadline: Instant,
    /// The edges the trace follows (each undirected observed edge once, at most eight).
    traced: Vec<(usize, usize, usize)>,
    /// Edge errors and goal distance of the current episode (paper Fig. 5).
    trace: EpisodeTrace,
    /// The episode `episode_errors.png` shows.
    showcase: Option<EpisodeTrace>,
    /// Who is in the formation, and why not.
    attendance: Attendance,
}

impl<S: Service> Lockstep<'_, S>
where
    Listener<S>: FileDescriptorBased,
{
    /// Waits until every agent has greeted (and the critic and recorder, when expected).
    fn wait_for_peers(&mut self) -> Result<()> {
        let ticks = &self.options.config.ticks;
        let deadline = Instant::now() + Duration::from_secs(ticks.startup_timeout_s);
        let mut greeted = vec![false; self.ports.agents.len()];
        loop {
            for (agent, ports) in self.ports.agents.iter().enumerate() {
                while let Some(sample) = ports.command.receive().context("receive")? {
                    if sample.payload().header.has(FLAG_HELLO) {
                        check_protocol(sample.payload().header.protocol_version, &format!("agent {agent}"))?;
                        self.round.presence.greeted(agent, sample.payload().session);
                        greeted[agent] = true;
                    }
                }
            }
            for reader in self.readers.iter_mut().filter(|r| !r.heard()) {
                reader.drain(self.published)?;
            }
            if self.readers.iter().all(ReaderLink::heard) && greeted.iter().all(|&g| g) {
                return Ok(());
            }
            if termination_requested() {
                // Robots and the critic that did connect learn that the run is over.
                self.ports.announce_run_end()?;
                bail!("sim: stopped by signal while waiting for the swarm to connect");
            }
            if Instant::now() >= deadline {
                let missing: Vec<usize> = (0..greeted.len()).filter(|&a| !greeted[a]).collect();
                let silent: String = self
                    .readers
                    .iter()
                    .filter(|r| !r.heard())
                    .map(|r| format!("and {} ", r.name()))
                    .collect();
                bail!(
                    "sim: after {} s, agents {missing:?} {silent}have not connected (run id and --agents must match)",
                    ticks.startup_timeout_s,
                );
            }
            services::wait_for_event(&self.ports.command_ready, Duration::from_millis(50))?;
        }
    }

    /// Plays one episode tick by tick by the stepper's rules, its mission planner changing the
    /// formation on schedule; `Some(Stop::Signal)` when a termination signal cut it.
    fn play_episode(&mut self, episode: u32, mut stepper: EpisodeStepper) -> Result<Option<Stop>> {
        let options = self.options;
        let log_world = self.tap.is_some()
            && (options.mode == Mode::Eval || episode.is_multiple_of(options.config.view.world_every_episodes));
        let eval_episode =
            options.mode == Mode::Train && episode.is_multiple_of(options.config.learn.eval_every_episodes);
        self.round.reset_episode();
        stepper.start_team(&mut self.attendance);
        let mut tally = EpisodeTally {
            counters_at_start: self.round.counters,
            missed_ticks: 0,
            missed: 0,
        };
        self.trace.begin(episode);
        for tick in 0u32.. {
            let tick_started = Instant::now();
            let header = tick_header(episode, tick, stepper.running(), eval_episode);
            stepper.tell();
            if stepper.running() {
                self.round.open_round(header, stepper.lost());
            }
            self.publish_tick(&stepper, header, tally.missed, log_world)?;
            if !stepper.running() {
                self.log
                    .push(stepper.record(episode, tally.transport(self.round.counters, self.started)))?;
                // The figure shows the first episode of an evaluation, or the latest noise-free
                // episode of a training run.
                if (options.mode == Mode::Eval && self.showcase.is_none()) || eval_episode {
                    self.showcase = Some(self.trace.clone());
                }
                return Ok(None);
            }
            self.collect_commands(&mut stepper, header, tick, tick_started, &mut tally)?;
            self.step(&mut stepper, episode)?;
            self.end_tick(tick_started)?;
            if termination_requested() {
                let header = Header::new(episode, tick + 1, FLAG_EPISODE_END);
                stepper.tell_last();
                self.close_on_signal(&stepper, header, &tally)?;
                return Ok(Some(Stop::Signal));
            }
        }
        unreachable!("the tick counter is unbounded")
    }

    /// This tick's commands (rule 2 of the stepper): waits for every robot's answer until the
    /// deadline (the tick's slot in real time, the command timeout in lockstep), then settles
    /// each robot's command in use by the accounting rule.
    fn collect_commands(
        &mut self,
        stepper: &mut EpisodeStepper,
        header: Header,
        tick: u32,
        tick_started: Instant,
        tally: &mut EpisodeTally,
    ) -> Result<()> {
        let options = self.options;
        let deadline = if options.realtime {
            self.next_deadline.max(tick_started) + Duration::from_secs_f64(options.config.env.dt_s)
        } else {
            tick_started + Duration::from_millis(options.config.ticks.command_timeout_ms)
        };
        self.round.collect(&self.ports, header, deadline, &mut |agent| {
            stepper.command_arrives(agent)
        })?;
        tally.missed = self.round.settle(tick);
        tally.missed_ticks += u64::from(tally.missed);
        Ok(())
    }

    /// The step with the settled commands (rule 3), then, while the episode runs, the roll
    /// call (rule 4) and the live changes asked for meanwhile (never waiting for one): each is
    /// in force from the next tick's observations.
    fn step(&mut self, stepper: &mut EpisodeStepper, episode: u32) -> Result<()> {
        let presence = &self.round.presence;
        stepper.step(self.round.commands(), |agent| !presence.is_absent(agent));
        self.env_steps += 1;
        if !stepper.running() {
            return Ok(());
        }
        let settled = self.round.settled();
        let changes = stepper.call_the_roll(&mut self.attendance, |agent| match settled[agent] {
            Settled::OnTime | Settled::Late => Heard::Answered,
            Settled::Missed => Heard::Silent,
            Settled::Lost => Heard::Lost,
        });
        for change in changes {
            let tick = stepper.world().steps;
            match change.away {
                Some(Away::Silent) => eprintln!(
                    "sim: robot {} silent for 10 ticks: out of the formation from tick {tick}",
                    change.robot
                ),
                None => eprintln!(
                    "sim: robot {} answered 5 ticks in a row: back in the formation from tick {tick}",
                    change.robot
                ),
                Some(_) => {}
            }
        }
        let (world, mission) = stepper.live();
        self.control
            .serve(world, mission, &mut self.attendance, self.options.seed, episode)
    }

    /// After a tick's step: its time in the histogram, the real-time pacing, and the readers'
    /// flow control (never more than `critic_window` ticks ahead of any).
    fn end_tick(&mut self, tick_started: Instant) -> Result<()> {
        let tick_time = tick_started.elapsed();
        self.stepping_time += tick_time;
        let _ = self.histogram.record((tick_time.as_micros() as u64).max(1));
        self.pace(tick_started);
        let options = self.options;
        let give_up = Duration::from_millis(options.config.ticks.sim_silence_ms / 4);
        let window = u64::from(options.config.ticks.critic_window);
        for reader in &mut self.readers {
            reader.wait(self.published, window, give_up, || self.ports.wake_critic())?;
        }
        Ok(())
    }

    /// Closes an episode stopped by a signal: an outcome reached on its last tick stands (a
    /// success or collision stays terminal for the critic); otherwise it is aborted, a
    /// truncation.
    fn close_on_signal(&mut self, stepper: &EpisodeStepper, header: Header, tally: &EpisodeTally) -> Result<()> {
        let last = stepper.last();
        let transition = Transition {
            outcome: if last.outcome == Outcome::Running {
                Outcome::Aborted
            } else {
                last.outcome
            },
            reward: last.reward,
            missed: tally.missed,
        };
        let (world, told) = (stepper.world(), told(stepper));
        self.ports
            .publish_observations(world, header, &told, self.round.belled())?;
        self.published += 1;
        self.ports
            .publish_state(world, header, &transition, &told, self.published, false)?;
        let mut record = stepper.record(header.episode, tally.transport(self.round.counters, self.started));
        record.outcome = transition.outcome;
        self.log.push(record)?;
        Ok(())
    }

    /// Publishes a tick (the episode's obstacles at its first, the true poses, the observations,
    /// then the state with the transition into it), traces
    /// it, offers it to the view and wakes the critic every half window and at an episode's end.
    fn publish_tick(&mut self, stepper: &EpisodeStepper, header: Header, missed: u32, log_world: bool) -> Result<()> {
        let (world, told, last) = (stepper.world(), told(stepper), stepper.last());
        if header.tick == 0 {
            self.ports.publish_obstacles(world, header)?;
        }
        self.ports.publish_truth(world, header)?;
        self.ports
            .publish_observations(world, header, &told, self.round.belled())?;
        if !header.has(FLAG_EPISODE_END) {
            self.round.ring_bell()?;
        }
        self.published += 1;
        let transition = Transition {
            outcome: last.outcome,
            reward: last.reward,
            missed,
        };
        let state = self
            .ports
            .publish_state(world, header, &transition, &told, self.published, log_world)?;
        self.trace
            .push_edges(&self.traced, &world.poses, &world.desired, &world.observed);
        self.trace.mean_edge_error.push(last.conditions.mean_edge_error);
        self.trace.goal_distance.push(last.conditions.goal_distance);
        if let (Some(tap), Some(state)) = (&self.tap, state) {
            let obstacles = (header.tick == 0).then(|| world.obstacles.list().to_vec());
            let _dropped_when_view_is_behind = tap.try_send(Tapped { state, obstacles });
        }
        let half_window = u64::from((self.options.config.ticks.critic_window / 2).max(1));
        if !self.readers.is_empty() && (header.has(FLAG_EPISODE_END) || self.published.is_multiple_of(half_window)) {
            self.ports.wake_critic()?;
        }
        Ok(())
    }

    /// Real time: sleeps until the next tick's slot, counting a tick that overran it.
    fn pace(&mut self, tick_started: Instant) {
        if !self.options.realtime {
            return;
        }
        self.next_deadline =
            self.next_deadline.max(tick_started) + Duration::from_secs_f64(self.options.config.env.dt_s);
        let now = Instant::now();
        if now > self.next_deadline {
            self.deadline_misses += 1;
            self.next_deadline = now;
        } else {
            std::thread::sleep(self.next_deadline - now);
        }
    }

    /// Context switches per tick since ticking began: the tick thread's sleeps are its
    /// wake-ups (waiting for commands, the critic, the real-time clock).
    fn fill_switch_figures(&self, summary: &mut Summary) {
        if self.env_steps == 0 {
            return;
        }
        let ticks = self.env_steps as f64;
        let (thread_start, machine_start) = self.switches_at_start;
        let thread = ThreadSwitches::now().since(thread_start);
        summary.sim_wakeups_per_tick = Some(thread.voluntary as f64 / ticks);
        summary.sim_switches_per_tick = Some((thread.voluntary + thread.involuntary) as f64 / ticks);
        summary.machine_switches_per_tick = machine_start
            .zip(machine_switches())
            .map(|(start, end)| end.saturating_sub(start) as f64 / ticks);
    }

    /// Writes the figures and `summary.json`, then tells everyone the run is over (after
    /// `summary.json` exists, so the critic can extend it).
    fn finish(mut self, stop: Stop) -> Result<Summary> {
        let options = self.options;
        let counters = self.round.counters;
        let mut summary = Summary {
            mode: options.mode.as_str().into(),
            n_agents: options.n_agents,
            seed: options.seed,
            scripted_agents: options.scripted.clone(),
            external_agents: options.external.clone(),
            obstacles: options.config.env.obstacles.kind.as_str().into(),
            env_steps: self.env_steps,
            env_steps_per_s: self.env_steps as f64 / self.stepping_time.as_secs_f64().max(1e-9),
            tick_p50_us: self.histogram.value_at_quantile(0.5) as f64,
            tick_p99_us: self.histogram.value_at_quantile(0.99) as f64,
            missed_ticks: counters.missed,
            late_commands: counters.late,
            lost_commands: counters.lost_commands,
            lost_observations: counters.lost_observations,
            rejected_commands: counters.rejected,
            rejoined_agents: counters.rejoins,
            deadline_misses: self.deadline_misses,
            bell_robots_per_tick: (self.env_steps > 0).then(|| counters.belled as f64 / self.env_steps as f64),
            wall_s: self.started.elapsed().as_secs_f64(),
            ..Summary::default()
        };
        fill_episode_figures(&mut summary, self.log.records());
        self.fill_switch_figures(&mut summary);
        if options.plots {
            let curve = options.run_dir.join("learning_curve.png");
            if let Err(err) = learning_curve(&curve, self.log.records()) {
                eprintln!("sim: cannot draw {}: {err:#}", curve.display());
            }
            let trace = &self.trace;
            if let Some(trace) = self
                .showcase
                .as_ref()
                .or((!trace.goal_distance.is_empty()).then_some(trace))
            {
                let errors = options.run_dir.join("episode_errors.png");
                if let Err(err) = episode_errors(&errors, trace) {
                    eprintln!("sim: cannot draw {}: {err:#}", errors.display());
                }
            }
        }
        let path = options.run_dir.join("summary.json");
        write_atomically(&path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
        self.ports.announce_run_end()?;
        // Robots asleep on the bell (they also find the end with their next timed-out wait).
        self.round.ring_bell()?;
        if stop == Stop::Signal {
            eprintln!("sim: stopped by signal after {} episodes", self.log.records().len());
        }
        Ok(summary)
    }
}

/// Command rounds with the run's tick gate; without one (no `/dev/shm`, or
/// `FORMATION_TICK_GATE=off` to measure the difference) every answer wakes the sim, which is
/// slower but the same ticks.
fn command_round(identity: &RunIdentity, n: usize) -> CommandRound {
    if std::env::var("FORMATION_TICK_GATE").is_ok_and(|v| v == "off") {
        return CommandRound::new(n);
    }
    match TickGate::create(identity) {
        Ok(gate) => CommandRound::new(n).with_gate(gate),
        Err(err) => {
            eprintln!("sim: no tick gate ({err:#}); every command will wake the sim");
            CommandRound::new(n)
        }
    }
}

/// The edges shown in `episode_errors.png`: each undirected observed edge once, at most eight.
fn traced_edges(n: usize) -> Vec<(usize, usize, usize)> {
    let mut seen = Vec::new();
    for (i, k, j) in observed_edges(n) {
        if !seen.iter().any(|&(a, _, b)| (a, b) == (j, i)) {
            seen.push((i, k, j));
        }
    }
    seen.truncate(8);
    seen
}
