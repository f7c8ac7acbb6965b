//! The iceoryx2 transport of a formation-control run: everything that moves the wire payloads
//! (`formation_protocol::wire`) between processes on one machine.
//!
//! * [`services`]: the run's identity and shared-memory names, service names, ports, the
//!   launcher's run lock and the sweep of abandoned runs;
//! * [`tick_gate`]: the shared answer counter that lets only a tick's last robot wake the sim,
//!   and the bell that wakes every robot at once;
//! * [`placement`]: which CPU each process works on;
//! * [`switches`]: context-switch counters (wake-ups per tick);
//! * [`cli`]: the flags every process shares (run id, run directory, config, placement);
//! * [`summary`]: the figures a run leaves behind in `summary.json`.

pub mod cli;
pub mod placement;
pub mod services;
pub mod summary;
pub mod switches;
pub mod tick_gate;

/// Catches SIGINT and SIGTERM from now on (iceoryx2's handler records them for
/// [`termination_requested`]); call it first thing in `main`. Without it the handler is installed
/// only at the first [`termination_requested`], and a signal that comes before (a sim asked to
/// stop while its first tick waits for commands) kills the process without ending the run.
pub fn catch_termination_signals() {
    termination_requested();
}

/// True once a termination signal (SIGINT, SIGTERM) has reached this process.
///
/// iceoryx2's signal handler records the signal; its flag is consumed on reading, so the answer
/// is kept here and stays true.
pub fn termination_requested() -> bool {
    static REQUESTED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if REQUESTED.load(std::sync::atomic::Ordering::Relaxed) {
        return true;
    }
    let requested = iceoryx2_bb_posix::signal::SignalHandler::termination_requested();
    if requested {
        REQUESTED.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    requested
}
