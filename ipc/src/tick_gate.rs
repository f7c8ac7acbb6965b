//! The tick gate: one word in shared memory with which the robots of a lockstep tick count their
//! answers, so that only the last one wakes the sim. Without it every robot's command wakes the
//! sim (N wake-ups a tick, N - 1 of them to find the tick incomplete); with it the sim sleeps
//! until the tick is complete: one wake-up.
//!
//! The sim creates the gate (`/dev/shm/<run prefix>tick_gate`, removed with the run's other
//! shared memory) and, before it publishes a tick's observations, opens a *round*: the tick's
//! key and how many answers it expects. A robot attaches with its session and, after sending its
//! command, counts itself in; only the answer that brings the count to the expected number
//! raises the sim's event ([`ALL_ANSWERED_EVENT_ID`]). The sim expects only robots it is waiting
//! for (present) whose attached session is the one that greeted it, so a robot that does not
//! count (a Python robot, one on another host, an old binary) is never waited for through the
//! gate: it raises its own event id with every command, as before. Every miscount errs towards
//! an extra wake-up, never a missed one: a robot that finds another round in the gate (a late
//! answer) raises its own id, and every answer at or past the expected count raises the event.
//!
//! The gate also carries the *tick bell*: a word the sim bumps once it has published a tick's
//! observations, and a robot that joined the bell sleeps on (a futex). One `FUTEX_WAKE` wakes
//! every such robot, where iceoryx2's events would cost the sim a socket send per robot and
//! each robot a poll and a receive: the bell halves the cost of a robot's wake-up (docs/
//! BENCHMARKS.md). The sim rings the bell for the robots whose bell session is the one that
//! greeted it, and notifies every other robot's own event as before, so clients that never
//! join the bell (Python, a bridge) are woken as they always were.
//!
//! iceoryx2 0.10 has no shared counter (its subscribers map payloads read-only) and its events
//! have no cheaper wake-up than a socket, hence one mapped file (`memmap2`), atomics, and
//! `rustix`'s futex calls.

use std::fs::{File, OpenOptions};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, bail};
use memmap2::MmapMut;
use rustix::io::Errno;
use rustix::thread::futex;

use crate::services::{RunIdentity, SHM_DIR};
use formation_protocol::MAX_AGENTS;

/// Event id with which the last robot of a tick wakes the sim: every answer is in, read them all.
pub const ALL_ANSWERED_EVENT_ID: usize = MAX_AGENTS;

/// Identifies a gate file.
const MAGIC: u32 = 0x6761_7465;
/// The layout below; a gate of another layout is not attached to.
const LAYOUT_VERSION: u32 = 2;
/// Bytes: magic, layout version, the round word, the bell (and 4 spare), one counting session
/// per robot, one bell session per robot.
const SIZE: usize = 24 + 8 * MAX_AGENTS;
const ROUND_OFFSET: usize = 8;
const BELL_OFFSET: usize = 16;
const MEMBERS_OFFSET: usize = 24;
const BELL_MEMBERS_OFFSET: usize = MEMBERS_OFFSET + 4 * MAX_AGENTS;
/// The round word: tick key (48 bits) | expected answers (8 bits) | answers counted (8 bits).
const KEY_SHIFT: u32 = 16;
const EXPECTED_SHIFT: u32 = 8;
const COUNT_MASK: u64 = 0xff;

/// The key of a tick in the round word (episodes wrap after 2^24, far beyond any late answer).
fn round_key(episode: u32, tick: u32) -> u64 {
    ((u64::from(episode) << 24) | u64::from(tick & 0x00ff_ffff)) & 0xffff_ffff_ffff
}

/// A mapped gate: created by the sim (which removes the file when dropped), attached by robots.
#[derive(Debug)]
pub struct TickGate {
    map: MmapMut,
    /// Set for the creator: the file to remove on drop.
    owned: Option<PathBuf>,
}

/// What a robot's answer asks of it after counting itself in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Answer {
    /// Others are still to answer: raise nothing.
    Quiet,
    /// The tick is complete as far as the gate counts: raise [`ALL_ANSWERED_EVENT_ID`].
    WakeSim,
    /// The gate holds another round (a late answer, or a round not opened yet): raise the
    /// robot's own event id, as a robot without a gate does.
    NotCounted,
}

impl TickGate {
    /// Where the gate of `identity`'s run lives.
    pub fn path(identity: &RunIdentity) -> PathBuf {
        PathBuf::from(SHM_DIR).join(format!("{}tick_gate", identity.shm_prefix()))
    }

    /// The sim's gate, new and empty (a gate left by an earlier process of the run is replaced).
    pub fn create(identity: &RunIdentity) -> Result<Self> {
        let path = Self::path(identity);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(true)
            .open(&path)
            .with_context(|| format!("cannot create the tick gate {}", path.display()))?;
        file.set_len(SIZE as u64)
            .with_context(|| format!("cannot size the tick gate {}", path.display()))?;
        let gate = Self {
            map: Self::map(&file, &path)?,
            owned: Some(path),
        };
        gate.word(ROUND_OFFSET).store(0, Ordering::Release);
        gate.header(4).store(LAYOUT_VERSION, Ordering::Release);
        gate.header(0).store(MAGIC, Ordering::Release);
        Ok(gate)
    }

    /// A robot's view of the sim's gate, with `session` recorded as robot `agent`'s (and as
    /// its bell session when it will sleep on the bell: [`TickGate::wait_for_bell`]); `None`
    /// while the sim has not created it (or it is of another layout).
    pub fn attach(identity: &RunIdentity, agent: usize, session: u32, join_bell: bool) -> Result<Option<Self>> {
        let path = Self::path(identity);
        let file = match OpenOptions::new().read(true).write(true).open(&path) {
            Ok(file) => file,
            Err(err) if err.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(err) => return Err(err).with_context(|| format!("cannot open the tick gate {}", path.display())),
        };
        if file.metadata()?.len() != SIZE as u64 {
            return Ok(None);
        }
        let gate = Self {
            map: Self::map(&file, &path)?,
            owned: None,
        };
        if gate.header(0).load(Ordering::Acquire) != MAGIC
            || gate.header(4).load(Ordering::Acquire) != LAYOUT_VERSION
            || agent >= MAX_AGENTS
        {
            return Ok(None);
        }
        gate.member(agent).store(session, Ordering::Release);
        gate.bell_member(agent)
            .store(if join_bell { session } else { 0 }, Ordering::Release);
        Ok(Some(gate))
    }

    fn map(file: &File, path: &std::path::Path) -> Result<MmapMut> {
        // SAFETY: the file is only ever accessed through the atomics below, by every process.
        let map = unsafe { MmapMut::map_mut(file) }.with_context(|| format!("cannot map {}", path.display()))?;
        if map.len() != SIZE {
            bail!("tick gate {} has {} bytes, not {SIZE}", path.display(), map.len());
        }
        Ok(map)
    }

    fn header(&self, offset: usize) -> &AtomicU32 {
        // SAFETY: in bounds (SIZE checked at mapping), 4-aligned (page-aligned map), and the
        // memory lives as long as `self`.
        unsafe { &*self.map.as_ptr().add(offset).cast::<AtomicU32>() }
    }

    fn word(&self, offset: usize) -> &AtomicU64 {
        // SAFETY: as in `header`; the offset is 8-aligned.
        unsafe { &*self.map.as_ptr().add(offset).cast::<AtomicU64>() }
    }

    fn member(&self, agent: usize) -> &AtomicU32 {
        self.header(MEMBERS_OFFSET + 4 * agent)
    }

    fn bell_member(&self, agent: usize) -> &AtomicU32 {
        self.header(BELL_MEMBERS_OFFSET + 4 * agent)
    }

    fn bell(&self) -> &AtomicU32 {
        self.header(BELL_OFFSET)
    }

    /// The session robot `agent` attached with (0: none).
    pub fn member_session(&self, agent: usize) -> u32 {
        self.member(agent).load(Ordering::Acquire)
    }

    /// The session robot `agent` sleeps on the bell with (0: it waits on its own event).
    pub fn bell_session(&self, agent: usize) -> u32 {
        self.bell_member(agent).load(Ordering::Acquire)
    }

    /// The sim, once a tick's observations are out: wakes every robot asleep on the bell
    /// (one system call for all of them).
    pub fn ring(&self) -> Result<()> {
        self.bell().fetch_add(1, Ordering::AcqRel);
        futex::wake(self.bell(), futex::Flags::empty(), i32::MAX as u32).context("tick bell: futex wake")?;
        Ok(())
    }

    /// The bell's count now: read it before looking for observations, then sleep with
    /// [`TickGate::wait_for_bell`] on what was read, so that a ring in between is not missed.
    pub fn bell_count(&self) -> u32 {
        self.bell().load(Ordering::Acquire)
    }

    /// A robot: sleeps until the bell rings past `seen` (at once if it already has), `timeout`
    /// passes, or a signal arrives.
    pub fn wait_for_bell(&self, seen: u32, timeout: Duration) -> Result<()> {
        let timeout = futex::Timespec {
            tv_sec: timeout.as_secs() as i64,
            tv_nsec: i64::from(timeout.subsec_nanos()),
        };
        match futex::wait(self.bell(), futex::Flags::empty(), seen, Some(&timeout)) {
            // Rung already (AGAIN), timed out, or a signal: the caller looks and decides.
            Ok(()) | Err(Errno::AGAIN | Errno::TIMEDOUT | Errno::INTR) => Ok(()),
            Err(err) => Err(err).context("tick bell: futex wait"),
        }
    }

    /// The sim, before publishing tick (`episode`, `tick`): the round now counts that tick's
    /// answers and expects `expected` of them.
    pub fn open_round(&self, episode: u32, tick: u32, expected: usize) {
        let expected = expected.min(MAX_AGENTS) as u64;
        self.word(ROUND_OFFSET).store(
            (round_key(episode, tick) << KEY_SHIFT) | (expected << EXPECTED_SHIFT),
            Ordering::Release,
        );
    }

    /// A robot, after sending its command for (`episode`, `tick`): counts it in.
    pub fn answer(&self, episode: u32, tick: u32) -> Answer {
        let key = round_key(episode, tick);
        let word = self.word(ROUND_OFFSET);
        let mut current = word.load(Ordering::Acquire);
        loop {
            if current >> KEY_SHIFT != key {
                return Answer::NotCounted;
            }
            let count = (current & COUNT_MASK) + 1;
            let expected = (current >> EXPECTED_SHIFT) & COUNT_MASK;
            // Counts stop at the field's top (a robot that answers twice cannot carry into
            // the expected field); past the expected number every answer wakes the sim anyway.
            let next = (current & !COUNT_MASK) | count.min(COUNT_MASK);
            match word.compare_exchange_weak(current, next, Ordering::AcqRel, Ordering::Acquire) {
                Ok(_) if count >= expected => return Answer::WakeSim,
                Ok(_) => return Answer::Quiet,
                Err(actual) => current = actual,
            }
        }
    }
}

impl Drop for TickGate {
    fn drop(&mut self) {
        if let Some(path) = &self.owned {
            let _ignored_if_already_gone = std::fs::remove_file(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn identity(name: &str) -> RunIdentity {
        RunIdentity::new(&format!("{name}{}", std::process::id())).expect("id")
    }

    #[test]
    fn only_the_last_expected_answer_wakes_the_sim() {
        let id = identity("gate");
        let sim = TickGate::create(&id).expect("create");
        let robots: Vec<TickGate> = (0..3)
            .map(|agent| {
                TickGate::attach(&id, agent, 100 + agent as u32, false)
                    .expect("attach")
                    .expect("gate")
            })
            .collect();
        assert_eq!(sim.member_session(1), 101);
        sim.open_round(4, 9, 3);
        assert_eq!(robots[2].answer(4, 9), Answer::Quiet);
        assert_eq!(robots[0].answer(4, 9), Answer::Quiet);
        assert_eq!(robots[1].answer(4, 9), Answer::WakeSim);
        // A fourth answer (a robot the sim did not expect) wakes it too: never a missed wake-up.
        assert_eq!(robots[1].answer(4, 9), Answer::WakeSim);
        // A late answer to the last tick is not counted in the next one.
        sim.open_round(4, 10, 2);
        assert_eq!(robots[0].answer(4, 9), Answer::NotCounted);
        assert_eq!(robots[0].answer(4, 10), Answer::Quiet);
        assert_eq!(robots[2].answer(4, 10), Answer::WakeSim);
        // Expecting nobody: every answer wakes the sim.
        sim.open_round(5, 0, 0);
        assert_eq!(robots[1].answer(5, 0), Answer::WakeSim);
    }

    #[test]
    fn the_bell_wakes_a_sleeping_robot_and_a_ring_before_it_sleeps_is_not_missed() {
        let id = identity("gatebell");
        let sim = TickGate::create(&id).expect("create");
        let robot = TickGate::attach(&id, 2, 42, true).expect("attach").expect("gate");
        assert_eq!((sim.bell_session(2), sim.bell_session(1)), (42, 0));
        let quiet = TickGate::attach(&id, 1, 43, false).expect("attach").expect("gate");
        assert_eq!((quiet.member_session(1), quiet.bell_session(1)), (43, 0));

        // Rung between the robot's read and its sleep: the wait returns at once.
        let seen = robot.bell_count();
        sim.ring().expect("ring");
        let started = std::time::Instant::now();
        robot.wait_for_bell(seen, Duration::from_secs(60)).expect("wait");
        assert!(started.elapsed() < Duration::from_secs(30), "slept through a ring");

        // Asleep first, rung from another thread.
        let seen = robot.bell_count();
        let (ready, asleep) = std::sync::mpsc::channel();
        let sleeper = std::thread::spawn(move || {
            ready.send(()).expect("ready");
            let started = std::time::Instant::now();
            robot.wait_for_bell(seen, Duration::from_secs(60)).expect("wait");
            (started.elapsed(), robot.bell_count())
        });
        asleep.recv().expect("asleep");
        std::thread::sleep(Duration::from_millis(50));
        sim.ring().expect("ring");
        let (slept, count) = sleeper.join().expect("join");
        assert!(slept < Duration::from_secs(30), "woken by the ring, not the timeout");
        assert_eq!(count, seen.wrapping_add(1));

        // Nothing rings: the wait ends at its timeout.
        let quiet_seen = quiet.bell_count();
        quiet
            .wait_for_bell(quiet_seen, Duration::from_millis(20))
            .expect("timeout is not an error");
    }

    #[test]
    fn the_gate_file_is_the_sims_and_goes_with_it() {
        let id = identity("gatefile");
        assert!(
            TickGate::attach(&id, 0, 1, false).expect("attach").is_none(),
            "no sim yet"
        );
        let sim = TickGate::create(&id).expect("create");
        assert!(TickGate::path(&id).exists());
        assert!(
            TickGate::attach(&id, MAX_AGENTS, 1, false).expect("attach").is_none(),
            "no such robot"
        );
        drop(sim);
        assert!(!TickGate::path(&id).exists(), "removed with the sim");
        assert!(TickGate::attach(&id, 0, 1, false).expect("attach").is_none());
    }

    #[test]
    fn robots_counting_from_threads_wake_the_sim_exactly_once_per_round() {
        let id = identity("gatethreads");
        let sim = TickGate::create(&id).expect("create");
        let n = 8;
        for tick in 0..200 {
            sim.open_round(0, tick, n);
            let wakes: usize = std::thread::scope(|scope| {
                let handles: Vec<_> = (0..n)
                    .map(|agent| {
                        let id = &id;
                        scope.spawn(move || {
                            let robot = TickGate::attach(id, agent, 1, false).expect("attach").expect("gate");
                            usize::from(robot.answer(0, tick) == Answer::WakeSim)
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().expect("join")).sum()
            });
            assert_eq!(wakes, 1, "tick {tick}");
        }
    }
}
