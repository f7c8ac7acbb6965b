//! One tick's commands: waiting (event-driven) until every present robot has answered or the
//! deadline passes, keeping each robot's valid answer, rejecting malformed ones, dropping late
//! ones, and holding the last command of a robot that missed the tick. With the tick gate the
//! sim sleeps through the robots' answers until the last one it expects is in.

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
    /// Robot-ticks whose command was missing.
    pub missed: u64,
    /// Malformed commands refused.
    pub rejected: u64,
    /// Robots that greeted again from a new process.
    pub rejoins: u64,
    /// Robot wake-ups by the tick bell (the others were by each robot's own event).
    pub belled: u64,
}

/// Collects the commands of one tick after another; allocation-free after construction.
#[derive(Debug)]
pub struct CommandRound {
    received: Vec<bool>,
    notified: Vec<usize>,
    last_commands: Vec<(f64, f64)>,
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

    /// Before tick `header` is published: the gate expects an answer from every robot that is
    /// waited for and counts itself in with the session it greeted with, and the bell is for
    /// the robots asleep on it with that session.
    pub fn open_round(&mut self, header: Header) {
        if let Some(gate) = &self.gate {
            let mut counted = 0;
            for (agent, belled) in self.belled.iter_mut().enumerate() {
                let session = self.presence.session(agent);
                let greeted = session != 0;
                if greeted && !self.presence.is_absent(agent) && gate.member_session(agent) == session {
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
    }

    /// The commands to apply: each robot's answer of this round, or its last one held.
    pub fn commands(&self) -> &[(f64, f64)] {
        &self.last_commands
    }

    /// Waits until every present robot has answered `header` or `deadline` passes, reading
    /// only the robots whose event id arrived (every robot after the gate's all-answered id,
    /// or any id that is not a robot's) while it waits. At the deadline, and when some robot
    /// is absent, it reads every robot's stream once more without waiting: a robot counted in
    /// the gate answers without an event of its own, so an on-time answer that went out
    /// quietly would otherwise be lost with a tick that one late robot never completed.
    pub fn collect<S: Service>(&mut self, ports: &SimPorts<S>, header: Header, deadline: Instant) -> Result<()>
    where
        Listener<S>: FileDescriptorBased,
    {
        let n = self.received.len();
        self.received.iter_mut().for_each(|r| *r = false);
        loop {
            let now = Instant::now();
            let answered = self.presence.all_present_answered(&self.received);
            if answered || now >= deadline {
                // Absent robots are not waited for, but what they sent is taken in: an answer
                // makes a robot present again, even when every robot was absent.
                if !answered || (0..n).any(|agent| self.presence.is_absent(agent)) {
                    services::wait_for_events(&ports.command_ready, Duration::ZERO, |_| {})?;
                    self.notified.clear();
                    self.notified.extend(0..n);
                    self.drain(ports, header);
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
            self.drain(ports, header);
        }
    }

    /// Ends the round: records who answered; returns how many robots missed it.
    pub fn settle(&mut self) -> u32 {
        let mut missed = 0;
        for (agent, &got) in self.received.iter().enumerate() {
            self.presence.record(agent, got);
            missed += u32::from(!got);
        }
        self.counters.missed += u64::from(missed);
        missed
    }

    /// Takes every pending command of the notified robots, keeping this tick's valid one.
    fn drain<S: Service>(&mut self, ports: &SimPorts<S>, header: Header) {
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
                if (cmd.header.episode, cmd.header.tick) < now || self.received[agent] {
                    // A late answer to an earlier tick: already counted as missed.
                    self.presence.heard_late(agent);
                    continue;
                }
                self.last_commands[agent] = (f64::from(cmd.v), f64::from(cmd.w));
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
            )
            .expect("collect");
        round.settle()
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
        // Robot 0 answers; robot 1 sends a late answer, a malformed one, then nothing valid;
        // robot 2 answers twice (the first counts).
        robots.answer(0, command(0, 2, 5, 0.3));
        robots.answer(1, command(1, 2, 4, 0.9));
        robots.answer(1, command(0, 2, 5, 0.9));
        robots.answer(2, command(2, 2, 5, 0.2));
        robots.answer(2, command(2, 2, 5, 0.4));
        let started = Instant::now();
        round
            .collect(&ports, tick, started + Duration::from_millis(300))
            .expect("collect");
        assert!(
            started.elapsed() >= Duration::from_millis(300),
            "robot 1 is waited for until the deadline"
        );
        assert_eq!(round.settle(), 1, "robot 1 missed the tick");
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
                rejoins: 0,
                belled: 0
            }
        );

        // Next tick: robot 1 answers, robot 0 does not; robot 0's last command is held.
        let tick = Header::new(2, 6, 0);
        robots.answer(1, command(1, 2, 6, 0.5));
        robots.answer(2, command(2, 2, 6, 0.1));
        round
            .collect(&ports, tick, Instant::now() + Duration::from_millis(50))
            .expect("collect");
        assert_eq!(round.settle(), 1);
        assert_eq!(round.commands()[0], (0.3f32 as f64, 0.1f32 as f64), "held");
        assert_eq!(round.commands()[1].0, 0.5f32 as f64);
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
            .collect(&ports, Header::new(0, 9, 0), started + Duration::from_secs(5))
            .expect("collect");
        assert!(started.elapsed() < Duration::from_secs(1));
        round.settle();
        // A late answer (to an earlier tick, as over a slow link) proves robot 2 alive: the
        // next ticks wait for it again, until it is silent for ABSENT_AFTER ticks again.
        robots.answer(0, command(0, 0, 10, 0.1));
        robots.answer(1, command(1, 0, 10, 0.1));
        robots.answer(2, command(2, 0, 8, 0.1));
        assert_eq!(
            play_tick(&mut round, &ports, 10, 30),
            1,
            "the late answer does not count for this tick"
        );
        assert!(!round.presence.is_absent(2), "but robot 2 is waited for again");
        // Tick 10 was its first miss since then; absent again after ABSENT_AFTER of them.
        let last = 10 + ABSENT_AFTER - 1;
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
            .collect(&ports, Header::new(0, tick, 0), Instant::now() + Duration::from_secs(5))
            .expect("collect");
        assert_eq!(round.settle(), 0, "both answers were read");
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
        round.open_round(header);
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
            .collect(&ports, header, started + Duration::from_secs(5))
            .expect("collect");
        assert!(
            started.elapsed() < Duration::from_secs(1),
            "did not wait for the deadline"
        );
        assert_eq!(round.settle(), 0, "robot 0's silent answer was read too");
        assert_eq!(round.commands()[0].0, 0.1f32 as f64);

        // A robot that missed three ticks is absent: the gate stops expecting it.
        for tick in 4..4 + ABSENT_AFTER {
            round.open_round(Header::new(1, tick, 0));
            robots.answer(1, command(1, 1, tick, 0.1));
            robots.answer(2, command(2, 1, tick, 0.1));
            round
                .collect(
                    &ports,
                    Header::new(1, tick, 0),
                    Instant::now() + Duration::from_millis(20),
                )
                .expect("collect");
            round.settle();
        }
        assert!(round.presence.is_absent(0));
        let tick = 4 + ABSENT_AFTER;
        round.open_round(Header::new(1, tick, 0));
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
        round.open_round(Header::new(1, tick + 1, 0));
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
            round.open_round(header);
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
                .collect(&ports, header, Instant::now() + Duration::from_millis(30))
                .expect("collect");
            assert_eq!(round.settle(), 1, "tick {tick}: only robot 2 missed it");
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
