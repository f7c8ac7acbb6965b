//! The contract between the processes of a formation-control run.
//!
//! * [`wire`]: the `#[repr(C)]` payloads that travel over iceoryx2 shared memory;
//! * [`services`]: service names, the run-unique iceoryx2 configuration and port helpers;
//! * [`config`]: the one serde configuration every process reads (environment, ticks, learning);
//! * [`placement`]: which CPU each process works on;
//! * [`tick_gate`]: the shared answer counter that lets only a tick's last robot wake the sim;
//! * [`switches`]: context-switch counters (wake-ups per tick);
//! * [`summary`]: the figures a run leaves behind in `summary.json`;
//! * [`layout`]: the payloads' memory layout as JSON, for bindings in other languages.

pub mod cli;
pub mod config;
pub mod layout;
pub mod placement;
pub mod services;
pub mod summary;
pub mod switches;
pub mod tick_gate;
pub mod wire;

/// Largest swarm the wire types have room for.
pub const MAX_AGENTS: usize = 64;
/// Smallest swarm: every robot needs two distinct neighbours.
pub const MIN_AGENTS: usize = 3;
/// Neighbours each robot observes: (i+1) mod N and (i+2) mod N.
pub const NEIGHBOURS: usize = 2;
/// Room for the largest observation model's floats (layouts in `formation_core::observation`).
pub const MAX_OBS_DIM: usize = 16;
/// Actions are (v, w).
pub const ACTION_DIM: usize = 2;

/// The agents agent `agent` observes in a swarm of `n_agents`.
pub fn neighbours(agent: usize, n_agents: usize) -> [usize; NEIGHBOURS] {
    [(agent + 1) % n_agents, (agent + 2) % n_agents]
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
