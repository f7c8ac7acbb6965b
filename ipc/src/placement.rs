//! Which CPU each process of a run works on.
//!
//! A lockstep tick is a chain of wake-ups (sim -> robots -> sim). A wake-up that lands on an
//! idle CPU pays for that CPU to come out of its idle state (tens of microseconds on a virtual
//! machine); a wake-up on the waker's own CPU costs a few. So by default the sim's tick thread
//! and the robots share one CPU (the *lockstep CPU*) and the background work (the critic's
//! training, the sim's logging), which would compete with them, gets the others. Big swarms
//! split their robots into groups of at least [`ROBOTS_PER_CPU`], one group per CPU. Measured
//! in `docs/BENCHMARKS.md`.
//!
//! Robots also run under `SCHED_BATCH`: a robot woken by the sim then waits for the sim to
//! finish publishing the tick instead of preempting it after each observation, so the sim
//! wakes every robot, sleeps once, and the robots answer one after another (with the tick
//! gate, only the last one wakes the sim). Batch threads keep their fair share of the CPU;
//! they give up only wake-up preemption.
//!
//! Every process computes its own place from the CPUs it may use, so processes started by
//! hand from the same shell agree with those the launcher starts.

use std::sync::OnceLock;

use anyhow::{Context, Result};
use clap::ValueEnum;
use iceoryx2_bb_posix::thread::{ThreadHandle, ThreadProperties};

/// How processes are placed on CPUs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Placement {
    /// Sim and robots share one CPU (big swarms: a few CPUs), background work gets the rest.
    Auto,
    /// Leave placement to the operating system.
    Off,
}

/// The process (or thread) being placed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// The sim's tick thread.
    Sim,
    /// A robot.
    Agent {
        /// Its index.
        index: usize,
        /// Robots in the swarm.
        of: usize,
    },
    /// Work that must not delay ticks: the critic and the sim's view threads.
    Background,
}

/// Fewest robots worth a CPU of their own: a CPU with fewer keeps falling idle between its
/// robots' wake-ups and pays to come back each time (measured in `docs/BENCHMARKS.md`).
pub const ROBOTS_PER_CPU: usize = 12;

/// The CPUs `role` works on, given the CPUs the process may use (ascending): the last one is
/// the lockstep CPU. `None` leaves it to the operating system (one CPU only: there is nothing
/// to separate).
///
/// Robots fill contiguous groups of at least [`ROBOTS_PER_CPU`], one group per CPU counted from
/// the last, so the sim wakes a whole group on another CPU before it is interrupted by the
/// robots that share its own.
pub fn plan(allowed: &[usize], role: Role) -> Option<Vec<usize>> {
    let (&lockstep, others) = allowed.split_last()?;
    if others.is_empty() {
        return None;
    }
    Some(match role {
        Role::Sim => vec![lockstep],
        Role::Agent { index, of } => {
            let groups = (of / ROBOTS_PER_CPU).clamp(1, allowed.len());
            let group = index / of.div_ceil(groups);
            vec![allowed[allowed.len() - groups + group]]
        }
        Role::Background => others.to_vec(),
    })
}

/// Places the calling thread (and the threads it starts afterwards) as `placement` says for
/// `role`; returns the CPUs chosen, if any. A placement the system refuses is only slower, so
/// it is reported and the operating system places the thread instead.
pub fn apply(placement: Placement, role: Role) -> Result<Option<Vec<usize>>> {
    if placement == Placement::Off {
        return Ok(None);
    }
    if let Role::Agent { .. } = role {
        wait_for_the_waker();
    }
    let Some(cpus) = plan(process_cpus()?, role) else {
        return Ok(None);
    };
    match ThreadHandle::from_self().set_affinity(&cpus) {
        Ok(()) => Ok(Some(cpus)),
        Err(err) => {
            eprintln!("cannot move {role:?} to CPUs {cpus:?} ({err:?}); leaving it to the operating system");
            Ok(None)
        }
    }
}

/// Lets the calling thread run on every CPU the process started with, whatever placement it
/// inherited from the thread that started it: for work that would otherwise leave a CPU idle
/// (the critic's second training thread, while the sim waits for the learner). A refusal is
/// reported once and changes nothing else.
pub fn widen() {
    static REPORTED: std::sync::Once = std::sync::Once::new();
    let widened = process_cpus().and_then(|cpus| {
        ThreadHandle::from_self()
            .set_affinity(cpus)
            .map_err(|err| anyhow::anyhow!("{err:?}"))
    });
    if let Err(err) = widened {
        REPORTED.call_once(|| eprintln!("cannot let a thread use every CPU ({err:#}); it stays where it was placed"));
    }
}

/// Lowers the calling thread's priority to nice 10 (or leaves it lower), for background work
/// that must not starve its process's other threads (the critic's checkpoint scoring, beside
/// the thread that drains the streams and acknowledges ticks). A refusal is reported and
/// changes nothing else.
pub fn run_in_the_background() {
    let nice = this_threads_nice().max(10);
    // SAFETY: gettid has no preconditions; setpriority on our own thread id with a valid nice.
    let refused = unsafe { libc::setpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t, nice) } != 0;
    if refused {
        eprintln!(
            "cannot lower this thread's priority ({}); it competes with the others as it is",
            std::io::Error::last_os_error()
        );
    }
}

/// The calling thread's nice value.
fn this_threads_nice() -> i32 {
    // SAFETY: getpriority on our own thread id; errno is cleared first, -1 being a valid nice.
    unsafe {
        *libc::__errno_location() = 0;
        libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t)
    }
}

/// Puts the calling thread (and those it starts) under `SCHED_BATCH`: woken, it does not
/// preempt the thread that woke it. A refusal is reported and changes nothing else.
fn wait_for_the_waker() {
    let param = libc::sched_param { sched_priority: 0 };
    // SAFETY: pid 0 is the calling thread; `param` is a valid sched_param for SCHED_BATCH.
    if unsafe { libc::sched_setscheduler(0, libc::SCHED_BATCH, &param) } != 0 {
        eprintln!(
            "cannot run this robot under SCHED_BATCH ({}); it will preempt the sim when woken",
            std::io::Error::last_os_error()
        );
    }
}

/// The CPUs the process was started with, read before any thread of it was placed.
fn process_cpus() -> Result<&'static [usize]> {
    static CPUS: OnceLock<Vec<usize>> = OnceLock::new();
    if let Some(cpus) = CPUS.get() {
        return Ok(cpus);
    }
    let cpus = ThreadHandle::from_self()
        .get_affinity()
        .context("cannot read this process's CPU affinity")?;
    Ok(CPUS.get_or_init(|| cpus))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_cpu_is_left_to_the_scheduler() {
        for role in [Role::Sim, Role::Agent { index: 0, of: 3 }, Role::Background] {
            assert_eq!(plan(&[3], role), None);
            assert_eq!(plan(&[], role), None);
        }
    }

    #[test]
    fn small_swarms_share_the_last_cpu_and_background_work_gets_the_rest() {
        let allowed = [0, 2, 5];
        let n = 2 * ROBOTS_PER_CPU - 1;
        assert_eq!(plan(&allowed, Role::Sim), Some(vec![5]));
        for index in 0..n {
            assert_eq!(plan(&allowed, Role::Agent { index, of: n }), Some(vec![5]));
        }
        assert_eq!(plan(&allowed, Role::Background), Some(vec![0, 2]));
    }

    #[test]
    fn big_swarms_fill_contiguous_groups_ending_on_the_lockstep_cpu() {
        let cpu_of = |allowed: &[usize], n: usize| -> Vec<usize> {
            (0..n)
                .map(|index| plan(allowed, Role::Agent { index, of: n }).expect("placed")[0])
                .collect()
        };
        // Two CPUs, 48 robots: the first half on CPU 0, the second beside the sim.
        let two = cpu_of(&[0, 1], 48);
        assert!(
            two[..24].iter().all(|&c| c == 0) && two[24..].iter().all(|&c| c == 1),
            "{two:?}"
        );
        // Eight CPUs, 40 robots: three groups on the last three CPUs, never fewer than the minimum.
        let eight = cpu_of(&[0, 1, 2, 3, 4, 5, 6, 7], 40);
        for cpu in 0..8 {
            let count = eight.iter().filter(|&&c| c == cpu).count();
            assert!(
                count == 0 || count >= ROBOTS_PER_CPU,
                "CPU {cpu} has {count}: {eight:?}"
            );
        }
        assert_eq!(eight[0], 5);
        assert_eq!(eight[39], 7);
        assert!(eight.windows(2).all(|w| w[0] <= w[1]), "{eight:?}");
    }

    #[test]
    fn robots_placed_automatically_run_as_batch_threads() {
        let policy = |placement| {
            std::thread::spawn(move || {
                apply(placement, Role::Agent { index: 0, of: 3 }).expect("apply");
                // SAFETY: pid 0 is the calling thread.
                unsafe { libc::sched_getscheduler(0) }
            })
            .join()
            .expect("thread")
        };
        assert_eq!(policy(Placement::Auto), libc::SCHED_BATCH);
        assert_eq!(policy(Placement::Off), libc::SCHED_OTHER);
    }

    #[test]
    fn background_work_runs_at_nice_10_on_its_own_thread_only() {
        let before = this_threads_nice();
        let inside = std::thread::spawn(|| {
            run_in_the_background();
            this_threads_nice()
        })
        .join()
        .expect("thread");
        assert_eq!(inside, before.max(10));
        assert_eq!(this_threads_nice(), before, "the spawning thread keeps its priority");
    }

    #[test]
    fn applying_off_changes_nothing_and_auto_stays_within_the_allowed_cpus() {
        let allowed = ThreadHandle::from_self().get_affinity().expect("affinity");
        assert_eq!(apply(Placement::Off, Role::Sim).expect("off"), None);
        // On a thread of its own, so the test harness's other threads keep their CPUs.
        let (chosen, now) = std::thread::spawn(|| {
            let chosen = apply(Placement::Auto, Role::Background).expect("auto");
            (chosen, ThreadHandle::from_self().get_affinity().expect("affinity"))
        })
        .join()
        .expect("thread");
        match chosen {
            Some(cpus) => {
                assert!(cpus.iter().all(|cpu| allowed.contains(cpu)) && cpus.len() < allowed.len());
                assert_eq!(now, cpus);
            }
            None => assert_eq!((allowed.len(), now), (1, allowed)),
        }
    }
}
