//! One tick's commands: waiting (event-driven) until every present robot has answered or the
//! deadline passes, keeping each robot's valid answer, rejecting malformed ones, and settling
//! each robot by one accounting rule. With the tick gate the sim sleeps through the robots'
//! answers until the last one it expects is in.
//!
//! The rule, at each tick's deadline, for each robot: *on time* (its answer to this tick
//! arrived: it is used), *late* (no answer to this tick, but an answer to an earlier tick of
//! the episode arrived after that tick's deadline and is newer than the command in use: it is
//! used from now on, the newest winning), or *missed* (nothing new: the command in use stays).
//! Two more cases come from the reality model ([`formation_core::reality`]): a command lost on
//! the radio is dropped as if never received (and the sim stops waiting for an answer lost to
//! this tick), and a robot whose observation was lost is not waited for; both keep the command
//! in use, are counted apart and do not count towards the robot's absence.

use std::time::{Duration, Instant};

use anyhow::Result;
use formation_ipc::services::{self, FileDescriptorBased};
use formation_ipc::tick_gate::TickGate;
use formation_protocol::wire::{CommandMsg, FLAG_HELLO, Header, PROTOCOL_VERSION};
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::ports::SimPorts;

/// Consecutive missed ticks after which the sim stops waiting for a robot.
pub const ABSENT_AFTER: u32 = 3;
/// Malformed commands logged one by one before the log goes quiet (they are still counted).
const REJECTIONS_LOGGED: u64 = 10;

/// Which robots the sim waits for: one that missed [`ABSENT_AFTER`] ticks in a row is treated
/// as gone (its last command is held without waiting) until it answers (even late, to an
/// earlier tick: a robot behind a slow or lossy link) or greets again.
#[derive(Debug, Clone)]
pub struct Presence {
    consecutive_misses: Vec<u32>,
    sessions: Vec<u32>,
}

impl Presence {
    /// Nobody has greeted yet.
    pub fn new(n: usize) -> Self {
        Self {
            consecutive_misses: vec![0; n],
            sessions: vec![0; n],
        }
    }

    /// True while the sim does not wait for `agent`.
    pub fn is_absent(&self, agent: usize) -> bool {
        self.consecutive_misses[agent] >= ABSENT_AFTER
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

    /// A robot answered an earlier tick: it is alive, so its count of silent ticks starts
    /// again and an absent robot is waited for again from the next tick.
    fn heard_late(&mut self, agent: usize) {
        self.consecutive_misses[agent] = 0;
    }

    /// The session robot `agent` last greeted with (0: none yet).
    pub fn session(&self, agent: usize) -> u32 {
        self.sessions[agent]
    }

    /// Records a greeting; true when it comes from a new process of a robot already known.
    pub fn greeted(&mut self, agent: usize, session: u32) -> bool {
        let previous = std::mem::replace(&mut self.sessions[agent], session);
        if previous == session {
            return false;
        }
        self.consecutive_misses[agent] = 0;
        previous != 0
    }
}

/// Why a command read from robot `agent`'s stream during tick `now` cannot be applied, if so.
pub fn rejection(cmd: &CommandMsg, agent: usize, now: (u32, u32)) -> Option<&'static str> {
    if cmd.header.protocol_version != PROTOCOL_VERSION {
        Some("protocol version")
    } else if cmd.agent as usize != agent {
        Some("robot index")
    } else if !(cmd.v.is_finite() && cmd.w.is_finite()) {
        Some("non-finite (v, w)")
    } else if (cmd.header.episode, cmd.header.tick) > now {
        Some("episode or tick in the future")
    } else {
        None
    }
}

/// What the command rounds have counted, over the run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CommandCounters {
    /// Robot-ticks with nothing new (no answer to the tick, no newer late one, nothing lost):
    /// the command in use stayed.
    pub missed: u64,
    /// Robot-ticks that took up a late answer to an earlier tick.
    pub late: u64,
    /// Commands lost on the way (the reality model's `command_loss`).
    pub lost_commands: u64,
    /// Observations not delivered (the reality model's `observation_loss`).
    pub lost_observations: u64,
    /// Malformed commands refused.
    pub rejected: u64,
    /// Robots that greeted again from a new process.
    pub rejoins: u64,
    /// Robot wake-ups by the tick bell (the others were by each robot's own event).
    pub belled: u64,
}

/// How one robot's round ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Settled {
    /// Its answer to this tick arrived.
    OnTime,
    /// A late answer to an earlier tick, newer than the command in use, is used from now on.
    Late,
    /// Nothing new arrived: the command in use stays.
    Missed,
    /// Its answer to this tick was lost, or nothing arrived after its observation was lost:
    /// the command in use stays, and the robot's absence is not counted.
    Lost,
}

/// Collects the commands of one tick after another; allocation-free after construction.
#[derive(Debug)]
pub struct CommandRound {
    received: Vec<bool>,
    notified: Vec<usize>,
    /// The command in use by each robot.
    last_commands: Vec<(f64, f64)>,
    /// The tick of the answer in use, per robot (None: none this episode).
    in_use_tick: Vec<Option<u32>>,
    /// The newest late answer to an earlier tick read this round and not yet taken up.
    late: Vec<Option<(u32, (f64, f64))>>,
    /// This round's answer was lost on the way: not waited for any more.
    lost: Vec<bool>,
    /// This round's observation was not delivered: not waited for.
    unasked: Vec<bool>,
    /// How each robot's last round ended.
    settled: Vec<Settled>,
    /// The shared answer counter and tick bell, when the sim could create them.
    gate: Option<TickGate>,
    /// The robots this round wakes with the bell, not their own event.
    belled: Vec<bool>,
    /// Who is waited for.
    pub presence: Presence,
    /// Counted so far.
    pub counters: CommandCounters,
}

impl CommandRound {
    /// Rounds for `n` robots.
    pub fn new(n: usize) -> Self {
        Self {
            received: vec![false; n],
            notified: Vec::with_capacity(n),
            last_commands: vec![(0.0, 0.0); n],
            in_use_tick: vec![None; n],
            late: vec![None; n],
            lost: vec![false; n],
            unasked: vec![false; n],
            settled: vec![Settled::OnTime; n],
            gate: None,
            belled: vec![false; n],
            presence: Presence::new(n),
            counters: CommandCounters::default(),
        }
    }

    /// Rounds that let only a tick's last robot wake the sim through `gate`.
    pub fn with_gate(mut self, gate: TickGate) -> Self {
        self.gate = Some(gate);
        self
    }

    /// Before tick `header` is published, with the robots whose observation of it is lost
    /// (`unasked`: not waited for): the gate expects an answer from every other robot that is
    /// waited for and counts itself in with the session it greeted with, and the bell is for
    /// the robots asleep on it with that session.
    pub fn open_round(&mut self, header: Header, unasked: &[bool]) {
        self.unasked.copy_from_slice(unasked);
        self.counters.lost_observations += unasked.iter().filter(|&&u| u).count() as u64;
        if let Some(gate) = &self.gate {
            let mut counted = 0;
            for (agent, belled) in self.belled.iter_mut().enumerate() {
                let session = self.presence.session(agent);
                let greeted = session != 0;
                if greeted
                    && !self.presence.is_absent(agent)
                    && !unasked[agent]
                    && gate.member_session(agent) == session
                {
                    counted += 1;
                }
                *belled = greeted && gate.bell_session(agent) == session;
            }
            gate.open_round(header.episode, header.tick, counted);
        }
    }

    /// Which robots the bell wakes this round (the others need their own event).
    pub fn belled(&self) -> &[bool] {
        &self.belled
    }

    /// Once the round's observations are out: wakes the robots asleep on the bell.
    pub fn ring_bell(&mut self) -> Result<()> {
        let belled = self.belled.iter().filter(|&&b| b).count();
        match &self.gate {
            Some(gate) if belled > 0 => {
                self.counters.belled += belled as u64;
                gate.ring()
            }
            _ => Ok(()),
        }
    }

    /// A new episode: nothing is held from the last one.
    pub fn reset_episode(&mut self) {
        self.last_commands.iter_mut().for_each(|c| *c = (0.0, 0.0));
        self.in_use_tick.iter_mut().for_each(|t| *t = None);
        self.late.iter_mut().for_each(|l| *l = None);
    }

    /// The commands in use: each robot's answer of this round, a late one taken up, or the
    /// one it had.
    pub fn commands(&self) -> &[(f64, f64)] {
        &self.last_commands
    }

    /// How each robot's last round ended.
    pub fn settled(&self) -> &[Settled] {
        &self.settled
    }

    /// Waits until every present robot has answered `header` or `deadline` passes, reading
    /// only the robots whose event id arrived (every robot after the gate's all-answered id,
    /// or any id that is not a robot's) while it waits. At the deadline, and when some robot
    /// is absent, it reads every robot's stream once more without waiting: a robot counted in
    /// the gate answers without an event of its own, so an on-time answer that went out
    /// quietly would otherwise be lost with a tick that one late robot never completed.
    ///
    /// Each command read passes the radio first: `arrives(agent)` draws whether it arrives
    /// ([`formation_core::stepper::EpisodeStepper::command_arrives`] in the sim).
    pub fn collect<S: Service>(
        &mut self,
        ports: &SimPorts<S>,
        header: Header,
        deadline: Instant,
        arrives: &mut impl FnMut(usize) -> bool,
    ) -> Result<()>
    where
        Listener<S>: FileDescriptorBased,
    {
        let n = self.received.len();
        self.received.iter_mut().for_each(|r| *r = false);
        self.lost.iter_mut().for_each(|l| *l = false);
        loop {
            let now = Instant::now();
            let answered = (0..n).all(|agent| {
                self.received[agent] || self.lost[agent] || self.unasked[agent] || self.presence.is_absent(agent)
            });
            if answered || now >= deadline {
                // Absent robots are not waited for, but what they sent is taken in: an answer
                // makes a robot present again, even when every robot was absent.
                if !answered || (0..n).any(|agent| self.presence.is_absent(agent)) {
                    services::wait_for_events(&ports.command_ready, Duration::ZERO, |_| {})?;
                    self.notified.clear();
                    self.notified.extend(0..n);
                    self.drain(ports, header, arrives);
                }
                return Ok(());
            }
            self.notified.clear();
            let mut everyone = false;
            let notified = &mut self.notified;
            services::wait_for_events(&ports.command_ready, deadline - now, |id| {
                if id < n {
                    notified.push(id);
                } else {
                    everyone = true;
                }
            })?;
            if everyone {
                self.notified.clear();
                self.notified.extend(0..n);
            }
            self.drain(ports, header, arrives);
        }
    }

    /// Ends round `tick` by the accounting rule: on time, late (the newest late answer newer
    /// than the command in use is taken up), lost, or missed; records who answered (a lost
    /// message counts neither way); returns how many robots missed it.
    pub fn settle(&mut self, tick: u32) -> u32 {
        let mut missed = 0;
        for agent in 0..self.received.len() {
            let late = self.late[agent].take();
            let settled = if self.received[agent] {
                self.in_use_tick[agent] = Some(tick);
                Settled::OnTime
            } else if let Some((answered, command)) = late.filter(|&(t, _)| self.in_use_tick[agent] < Some(t)) {
                self.last_commands[agent] = command;
                self.in_use_tick[agent] = Some(answered);
                self.counters.late += 1;
                Settled::Late
            } else if self.lost[agent] || self.unasked[agent] {
                Settled::Lost
            } else {
                missed += 1;
                Settled::Missed
            };
            match settled {
                Settled::OnTime | Settled::Late => self.presence.record(agent, true),
                Settled::Missed => self.presence.record(agent, false),
                Settled::Lost => {}
            }
            self.settled[agent] = settled;
        }
        self.counters.missed += u64::from(missed);
        missed
    }

    /// Takes every pending command of the notified robots: this tick's valid one is used, a
    /// newer answer to an earlier tick of the episode is kept for the accounting, and each
    /// passes the radio (`arrives`) first.
    fn drain<S: Service>(&mut self, ports: &SimPorts<S>, header: Header, arrives: &mut impl FnMut(usize) -> bool) {
        let now = (header.episode, header.tick);
        for &agent in &self.notified {
            while let Ok(Some(sample)) = ports.agents[agent].command.receive() {
                let cmd = sample.payload();
                if cmd.header.has(FLAG_HELLO) {
                    if cmd.header.protocol_version == PROTOCOL_VERSION && self.presence.greeted(agent, cmd.session) {
                        self.counters.rejoins += 1;
                        eprintln!("sim: agent {agent} rejoined at episode {} tick {}", now.0, now.1);
                    }
                    continue;
                }
                if let Some(reason) = rejection(cmd, agent, now) {
                    self.counters.rejected += 1;
                    if self.counters.rejected <= REJECTIONS_LOGGED {
                        eprintln!("sim: rejected a command from agent {agent} ({reason}): {cmd:?}");
                    }
                    continue;
                }
                if !arrives(agent) {
                    // Dropped as if never received; an answer to this tick is not waited for.
                    self.counters.lost_commands += 1;
                    if (cmd.header.episode, cmd.header.tick) == now {
                        self.lost[agent] = true;
                    }
                    continue;
                }
                let command = (f64::from(cmd.v), f64::from(cmd.w));
                if (cmd.header.episode, cmd.header.tick) < now {
                    // An answer to an earlier tick, after its deadline: a sign of life, and a
                    // candidate for the command in use when it is newer (newest wins).
                    self.presence.heard_late(agent);
                    if cmd.header.episode == now.0 && self.late[agent].is_none_or(|(t, _)| t < cmd.header.tick) {
                        self.late[agent] = Some((cmd.header.tick, command));
                    }
                    continue;
                }
                if self.received[agent] {
                    // A second answer to this tick: the first counts.
                    continue;
                }
                self.last_commands[agent] = command;
                self.received[agent] = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use formation_ipc::services::{RunIdentity, Sizing};

    use super::*;

    /// Fake robots over iceoryx2's in-process `local` service: their command publishers and
    /// the shared wake-up, facing a sim's real ports.
    struct FakeRobots {
        commands: Vec<iceoryx2::port::publisher::Publisher<local::Service, CommandMsg, ()>>,
        ready: iceoryx2::port::notifier::Notifier<local::Service>,
    }

    impl FakeRobots {
        fn answer(&self, agent: usize, cmd: CommandMsg) {
            self.commands[agent].send_copy(cmd).expect("send");
            self.ready
                .notify_with_custom_event_id(services::agent_event_id(agent))
                .expect("notify");
        }
    }

    fn command(agent: u32, episode: u32, tick: u32, v: f32) -> CommandMsg {
        CommandMsg {
            header: Header::new(episode, tick, 0),
            agent,
            v,
            w: 0.1,
            session: 7,
            ..CommandMsg::default()
        }
    }

    /// One round of tick `tick` of episode 0 that waits at most `wait_ms`; returns the misses.
    fn play_tick(round: &mut CommandRound, ports: &SimPorts<local::Service>, tick: u32, wait_ms: u64) -> u32 {
        round
            .collect(
                ports,
                Header::new(0, tick, 0),
                Instant::now() + Duration::from_millis(wait_ms),
                &mut ideal(),
            )
            .expect("collect");
        round.settle(tick)
    }

    /// A radio that loses nothing.
    fn ideal() -> impl FnMut(usize) -> bool {
        |_| true
    }

    fn test_identity(run: &str) -> RunIdentity {
        RunIdentity::new(&format!("{run}{}", std::process::id())).expect("identity")
    }

    fn sim_and_robots(n: usize, run: &str) -> (Node<local::Service>, SimPorts<local::Service>, FakeRobots) {
        let identity = test_identity(run);
        let node = services::create_node::<local::Service>(&identity, "sim").expect("node");
        let sizing = Sizing::new(n, 8, 12);
        let ports = SimPorts::open(&node, &sizing).expect("ports");
        let robots = FakeRobots {
            commands: (0..n)
                .map(|agent| {
                    services::command_stream(&node, &sizing, agent)
                        .expect("stream")
                        .publisher_builder()
                        .create()
                        .expect("publisher")
                })
                .collect(),
            ready: services::command_event(&node, &sizing)
                .expect("event")
                .notifier_builder()
                .create()
                .expect("notifier"),
        };
        (node, ports, robots)
    }

    #[test]
    fn a_round_keeps_valid_answers_holds_missing_ones_and_counts_the_rest() {
        let (_node, ports, robots) = sim_and_robots(3, "cmdround");
        let mut round = CommandRound::new(3);
        let tick = Header::new(2, 5, 0);
        // Robot 0 answers; robot 1 sends an answer to the last episode, a malformed one, then
        // nothing valid; robot 2 answers twice (the first counts).
        robots.answer(0, command(0, 2, 5, 0.3));
        robots.answer(1, command(1, 1, 4, 0.9));
        robots.answer(1, command(0, 2, 5, 0.9));
        robots.answer(2, command(2, 2, 5, 0.2));
        robots.answer(2, command(2, 2, 5, 0.4));
        let started = Instant::now();
        round
            .collect(&ports, tick, started + Duration::from_millis(300), &mut ideal())
            .expect("collect");
        assert!(
            started.elapsed() >= Duration::from_millis(300),
            "robot 1 is waited for until the deadline"
        );
        assert_eq!(round.settle(5), 1, "robot 1 missed the tick");
        assert_eq!(
            round.commands(),
            &[
                (0.3f32 as f64, 0.1f32 as f64),
                (0.0, 0.0),
                (0.2f32 as f64, 0.1f32 as f64)
            ]
        );
        assert_eq!(
            round.counters,
            CommandCounters {
                missed: 1,
                rejected: 1,
                ..CommandCounters::default()
            }
        );

        // Next tick: robot 1 answers, robot 0 does not; robot 0's last command is held.
        let tick = Header::new(2, 6, 0);
        robots.answer(1, command(1, 2, 6, 0.5));
        robots.answer(2, command(2, 2, 6, 0.1));
        round
            .collect(&ports, tick, Instant::now() + Duration::from_millis(50), &mut ideal())
            .expect("collect");
        assert_eq!(round.settle(6), 1);
        assert_eq!(round.commands()[0], (0.3f32 as f64, 0.1f32 as f64), "held");
        assert_eq!(round.commands()[1].0, 0.5f32 as f64);
    }

    #[test]
    fn a_round_takes_up_the_newest_late_answer_and_waits_for_no_robot_left_unasked() {
        let (_node, ports, robots) = sim_and_robots(3, "cmdlate");
        let mut round = CommandRound::new(3);
        // Tick 5: robot 0 is on time; robot 1 answers ticks 2 and 3 only (late, the newest
        // wins); robot 2 was not told this tick (its observation was lost): not waited for.
        round.open_round(Header::new(0, 5, 0), &[false, false, true]);
        robots.answer(0, command(0, 0, 5, 0.1));
        robots.answer(1, command(1, 0, 3, 0.3));
        robots.answer(1, command(1, 0, 2, 0.2));
        assert_eq!(play_tick(&mut round, &ports, 5, 300), 0, "nobody missed tick 5");
        assert_eq!(round.settled(), [Settled::OnTime, Settled::Late, Settled::Lost]);
        assert_eq!(round.commands()[1].0, 0.3f32 as f64, "the newest late answer is in use");
        // Tick 6: robot 1's answer to tick 2 arrives again, older than the one in use: missed.
        round.open_round(Header::new(0, 6, 0), &[false; 3]);
        robots.answer(0, command(0, 0, 6, 0.1));
        robots.answer(1, command(1, 0, 2, 0.2));
        robots.answer(2, command(2, 0, 6, 0.4));
        assert_eq!(play_tick(&mut round, &ports, 6, 30), 1);
        assert_eq!(round.settled(), [Settled::OnTime, Settled::Missed, Settled::OnTime]);
        assert_eq!(round.commands()[1].0, 0.3f32 as f64, "the command in use stays");
        assert_eq!(
            round.counters,
            CommandCounters {
                missed: 1,
                late: 1,
                lost_observations: 1,
                ..CommandCounters::default()
            }
        );
    }

    #[test]
    fn lost_commands_are_not_waited_for_kept_out_of_the_misses_and_never_make_a_robot_absent() {
        use formation_core::config::EnvConfig;
        use formation_core::reality::{Reality, RealityConfig};
        let (_node, ports, robots) = sim_and_robots(3, "cmdlost");
        let mut round = CommandRound::new(3);
        let config = RealityConfig::from_toml_str("[reality]\ncommand_loss = 0.999999\n").expect("config");
        let mut reality = Reality::new(&config, &EnvConfig::default(), 1, 0, 3);
        let ticks = ABSENT_AFTER + 2;
        for tick in 0..ticks {
            for agent in 0..3 {
                robots.answer(agent, command(agent as u32, 0, tick, 0.5));
            }
            let started = Instant::now();
            round
                .collect(
                    &ports,
                    Header::new(0, tick, 0),
                    started + Duration::from_secs(5),
                    &mut |agent| !reality.command_lost(agent),
                )
                .expect("collect");
            assert!(
                started.elapsed() < Duration::from_secs(1),
                "a lost answer is not waited for"
            );
            assert_eq!(round.settle(tick), 0, "a loss is not a miss");
            assert_eq!(round.settled(), [Settled::Lost; 3]);
        }
        assert_eq!(round.commands(), [(0.0, 0.0); 3], "lost as if never received");
        assert!((0..3).all(|agent| !round.presence.is_absent(agent)));
        assert_eq!(round.counters.lost_commands, 3 * u64::from(ticks));
        assert_eq!(round.counters.missed, 0);
    }

    #[test]
    fn a_robot_that_keeps_missing_is_no_longer_waited_for() {
        let (_node, ports, robots) = sim_and_robots(3, "cmdabsent");
        let mut round = CommandRound::new(3);
        for tick in 0..ABSENT_AFTER {
            robots.answer(0, command(0, 0, tick, 0.1));
            robots.answer(1, command(1, 0, tick, 0.1));
            play_tick(&mut round, &ports, tick, 30);
        }
        assert!(round.presence.is_absent(2));
        // Robot 2 is absent: a round with 0 and 1 in returns at once, not at the deadline.
        robots.answer(0, command(0, 0, 9, 0.1));
        robots.answer(1, command(1, 0, 9, 0.1));
        let started = Instant::now();
        round
            .collect(
                &ports,
                Header::new(0, 9, 0),
                started + Duration::from_secs(5),
                &mut ideal(),
            )
            .expect("collect");
        assert!(started.elapsed() < Duration::from_secs(1));
        round.settle(9);
        // A late answer (to an earlier tick, as over a slow link) proves robot 2 alive and, newer
        // than the command in use, is taken up: the next ticks wait for it again, until it is
        // silent for ABSENT_AFTER ticks again.
        robots.answer(0, command(0, 0, 10, 0.1));
        robots.answer(1, command(1, 0, 10, 0.1));
        robots.answer(2, command(2, 0, 8, 0.25));
        assert_eq!(play_tick(&mut round, &ports, 10, 30), 0, "late, not missed");
        assert_eq!(round.settled()[2], Settled::Late);
        assert_eq!(round.commands()[2].0, 0.25f32 as f64);
        assert!(!round.presence.is_absent(2), "robot 2 is waited for again");
        // Tick 11 is its first miss since then; absent again after ABSENT_AFTER of them.
        let last = 11 + ABSENT_AFTER - 1;
        for tick in 11..last {
            play_tick(&mut round, &ports, tick, 30);
            assert!(!round.presence.is_absent(2), "tick {tick}");
        }
        play_tick(&mut round, &ports, last, 30);
        assert!(round.presence.is_absent(2), "silent again for {ABSENT_AFTER} ticks");
        // A greeting from a new process of robot 2 brings it back.
        assert!(!round.presence.greeted(2, 0), "same (empty) session: not a rejoin");
        round.presence.greeted(2, 11);
        assert!(
            round.presence.greeted(2, 12),
            "a new session of a known robot is a rejoin"
        );
        assert!(!round.presence.is_absent(2));
    }

    #[test]
    fn robots_that_were_all_absent_are_heard_again_when_they_answer() {
        let (_node, ports, robots) = sim_and_robots(2, "cmdallabsent");
        let mut round = CommandRound::new(2);
        for tick in 0..ABSENT_AFTER {
            play_tick(&mut round, &ports, tick, 10);
        }
        assert!(round.presence.is_absent(0) && round.presence.is_absent(1));
        // Nobody is waited for, yet the answers that came in count.
        let tick = ABSENT_AFTER;
        robots.answer(0, command(0, 0, tick, 0.4));
        robots.answer(1, command(1, 0, tick, 0.2));
        round
            .collect(
                &ports,
                Header::new(0, tick, 0),
                Instant::now() + Duration::from_secs(5),
                &mut ideal(),
            )
            .expect("collect");
        assert_eq!(round.settle(tick), 0, "both answers were read");
        assert!(!round.presence.is_absent(0) && !round.presence.is_absent(1));
        assert_eq!(round.commands()[0].0, 0.4f32 as f64);
    }

    #[test]
    fn with_the_gate_only_the_last_answer_wakes_the_sim_every_answer_is_read_and_the_bell_is_for_members() {
        use formation_ipc::tick_gate::{ALL_ANSWERED_EVENT_ID, Answer, TickGate};
        let (_node, ports, robots) = sim_and_robots(3, "cmdgate");
        let identity = test_identity("cmdgate");
        let mut round = CommandRound::new(3).with_gate(TickGate::create(&identity).expect("gate"));
        // Robots 0 and 1 count themselves in, robot 0 also sleeps on the bell; robot 2 has no
        // gate (a Python robot, say).
        let gates: Vec<TickGate> = (0..2)
            .map(|agent| {
                let session = 10 + agent as u32;
                round.presence.greeted(agent, session);
                TickGate::attach(&identity, agent, session, agent == 0)
                    .expect("attach")
                    .expect("gate")
            })
            .collect();
        round.presence.greeted(2, 12);
        let header = Header::new(1, 3, 0);
        round.open_round(header, &[false; 3]);
        assert_eq!(
            round.belled(),
            [true, false, false],
            "only robot 0 is woken by the bell"
        );
        let rung = gates[0].bell_count();
        round.ring_bell().expect("ring");
        assert_eq!(gates[0].bell_count(), rung.wrapping_add(1));
        assert_eq!(round.counters.belled, 1);
        let counted = |agent: usize| {
            robots.commands[agent]
                .send_copy(CommandMsg {
                    session: 10 + agent as u32,
                    ..command(agent as u32, 1, 3, 0.1 * (agent + 1) as f32)
                })
                .expect("send");
            gates[agent].answer(1, 3)
        };
        assert_eq!(counted(0), Answer::Quiet, "robot 1 is still expected");
        // The uncounted robot raises its own id, as without a gate.
        robots.answer(2, command(2, 1, 3, 0.3));
        assert_eq!(counted(1), Answer::WakeSim);
        robots
            .ready
            .notify_with_custom_event_id(EventId::new(ALL_ANSWERED_EVENT_ID))
            .expect("notify");
        let started = Instant::now();
        round
            .collect(&ports, header, started + Duration::from_secs(5), &mut ideal())
            .expect("collect");
        assert!(
            started.elapsed() < Duration::from_secs(1),
            "did not wait for the deadline"
        );
        assert_eq!(round.settle(3), 0, "robot 0's silent answer was read too");
        assert_eq!(round.commands()[0].0, 0.1f32 as f64);

        // A robot that missed three ticks is absent: the gate stops expecting it.
        for tick in 4..4 + ABSENT_AFTER {
            round.open_round(Header::new(1, tick, 0), &[false; 3]);
            robots.answer(1, command(1, 1, tick, 0.1));
            robots.answer(2, command(2, 1, tick, 0.1));
            round
                .collect(
                    &ports,
                    Header::new(1, tick, 0),
                    Instant::now() + Duration::from_millis(20),
                    &mut ideal(),
                )
                .expect("collect");
            round.settle(tick);
        }
        assert!(round.presence.is_absent(0));
        let tick = 4 + ABSENT_AFTER;
        round.open_round(Header::new(1, tick, 0), &[false; 3]);
        assert_eq!(
            gates[1].answer(1, tick),
            Answer::WakeSim,
            "robot 1 is the only one counted"
        );
        assert!(
            round.belled()[0],
            "an absent robot still sleeps on the bell: it is rung"
        );

        // A new process in robot 0's place greets with another session: until it attaches,
        // it is woken by its event, not by the bell of its predecessor's session.
        round.presence.greeted(0, 99);
        round.open_round(Header::new(1, tick + 1, 0), &[false; 3]);
        assert_eq!(round.belled(), [false, false, false]);
    }

    #[test]
    fn at_the_deadline_the_quiet_answers_of_gate_members_are_read() {
        use formation_ipc::tick_gate::{ALL_ANSWERED_EVENT_ID, Answer, TickGate};
        let (_node, ports, robots) = sim_and_robots(3, "cmddeadline");
        let identity = test_identity("cmddeadline");
        let mut round = CommandRound::new(3).with_gate(TickGate::create(&identity).expect("gate"));
        let gates: Vec<TickGate> = (0..3)
            .map(|agent| {
                let session = 20 + agent as u32;
                round.presence.greeted(agent, session);
                TickGate::attach(&identity, agent, session, true)
                    .expect("attach")
                    .expect("gate")
            })
            .collect();
        // Every tick robots 0 and 1 answer in time and count themselves in quietly; robot 2
        // (killed, stopped) never answers, so the tick is never complete and nobody raises an
        // event: only the deadline ends the wait.
        for tick in 0..ABSENT_AFTER + 2 {
            let header = Header::new(0, tick, 0);
            round.open_round(header, &[false; 3]);
            for (agent, gate) in gates.iter().enumerate().take(2) {
                robots.commands[agent]
                    .send_copy(CommandMsg {
                        session: 20 + agent as u32,
                        ..command(agent as u32, 0, tick, 0.1 * (tick + 1) as f32)
                    })
                    .expect("send");
                match gate.answer(0, tick) {
                    // Once robot 2 is absent the gate expects two answers: robot 1 completes
                    // the tick and wakes the sim.
                    Answer::WakeSim => {
                        robots
                            .ready
                            .notify_with_custom_event_id(EventId::new(ALL_ANSWERED_EVENT_ID))
                            .expect("notify");
                    }
                    answer => assert_eq!(answer, Answer::Quiet, "tick {tick}"),
                }
            }
            round
                .collect(&ports, header, Instant::now() + Duration::from_millis(30), &mut ideal())
                .expect("collect");
            assert_eq!(round.settle(tick), 1, "tick {tick}: only robot 2 missed it");
            for agent in 0..2 {
                assert_eq!(
                    round.commands()[agent].0,
                    f64::from(0.1 * (tick + 1) as f32),
                    "tick {tick}: robot {agent}'s fresh command is applied"
                );
            }
        }
        assert!(round.presence.is_absent(2));
        assert!(!round.presence.is_absent(0) && !round.presence.is_absent(1));
        assert_eq!(round.counters.missed, u64::from(ABSENT_AFTER + 2));
    }

    #[test]
    fn malformed_commands_say_why() {
        let now = (3, 10);
        let ok = command(1, 3, 10, 0.2);
        assert_eq!(rejection(&ok, 1, now), None);
        assert_eq!(rejection(&ok, 2, now), Some("robot index"));
        let future = command(1, 3, 11, 0.2);
        assert_eq!(rejection(&future, 1, now), Some("episode or tick in the future"));
        let nan = CommandMsg { v: f32::NAN, ..ok };
        assert_eq!(rejection(&nan, 1, now), Some("non-finite (v, w)"));
        let old = CommandMsg {
            header: Header {
                protocol_version: PROTOCOL_VERSION - 1,
                ..ok.header
            },
            ..ok
        };
        assert_eq!(rejection(&old, 1, now), Some("protocol version"));
    }
}
