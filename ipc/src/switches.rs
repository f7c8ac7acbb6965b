//! Context-switch counters, to count what a lockstep tick costs in wake-ups: the calling
//! thread's own (`getrusage(RUSAGE_THREAD)`) and the whole machine's (`/proc/stat`).

/// Context switches of the calling thread so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ThreadSwitches {
    /// The thread went to sleep (waiting for an event, a timer, a lock): each is one wake-up.
    pub voluntary: u64,
    /// The thread was preempted while it could still run.
    pub involuntary: u64,
}

impl ThreadSwitches {
    /// The calling thread's counters (zero where the system does not keep them).
    pub fn now() -> Self {
        // SAFETY: an all-zero rusage is valid; getrusage only writes into it.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: a valid pointer to a rusage the call may fill.
        if unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut usage) } != 0 {
            return Self::default();
        }
        Self {
            voluntary: usage.ru_nvcsw as u64,
            involuntary: usage.ru_nivcsw as u64,
        }
    }

    /// The switches between `earlier` and `self`.
    pub fn since(self, earlier: Self) -> Self {
        Self {
            voluntary: self.voluntary.saturating_sub(earlier.voluntary),
            involuntary: self.involuntary.saturating_sub(earlier.involuntary),
        }
    }
}

/// Context switches of every CPU since boot (`ctxt` in `/proc/stat`), if the system says.
pub fn machine_switches() -> Option<u64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    stat.lines()
        .find_map(|line| line.strip_prefix("ctxt "))
        .and_then(|count| count.trim().parse().ok())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sleeping_counts_as_a_voluntary_switch_of_this_thread() {
        let before = ThreadSwitches::now();
        let machine_before = machine_switches().expect("/proc/stat");
        for _ in 0..5 {
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        let slept = ThreadSwitches::now().since(before);
        assert!(slept.voluntary >= 5, "{slept:?}");
        assert!(machine_switches().expect("/proc/stat") >= machine_before + 5);
    }
}
