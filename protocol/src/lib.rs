//! The wire contract between the processes of a formation-control run, free of any transport:
//! what a client in any language must agree on to talk to the swarm.
//!
//! * [`wire`]: the `#[repr(C)]` payloads that travel over shared memory, and the protocol version;
//! * [`layout`]: the payloads' memory layout as JSON, for bindings in other languages;
//! * the constants below: swarm bounds, payload room, the neighbour graph.
//!
//! The iceoryx2 transport that carries these payloads (services, the tick gate, placement) is
//! `formation-ipc`; the task's settings (`RunConfig`) are `formation_core::config`.

pub mod layout;
pub mod wire;

/// Largest swarm the wire types have room for.
pub const MAX_AGENTS: usize = 64;
/// Smallest swarm: every robot needs two distinct neighbours.
pub const MIN_AGENTS: usize = 3;
/// Neighbours each robot observes: (i+1) mod N and (i+2) mod N.
pub const NEIGHBOURS: usize = 2;
/// Room for the largest observation model's floats (layouts in `formation_core::observation`).
pub const MAX_OBS_DIM: usize = 32;
/// Room for one episode's obstacles (`formation_core::obstacles`; a draw never makes more).
pub const MAX_OBSTACLES: usize = 128;
/// Actions are (v, w).
pub const ACTION_DIM: usize = 2;
/// Largest actuation delay, ticks: room for the commands queued at a robot's motors.
pub const MAX_DELAY_TICKS: usize = 10;

/// The agents agent `agent` observes in a swarm of `n_agents`.
pub fn neighbours(agent: usize, n_agents: usize) -> [usize; NEIGHBOURS] {
    [(agent + 1) % n_agents, (agent + 2) % n_agents]
}

/// Ports left for processes that replace a dead one before iceoryx2 has cleaned it up, and for
/// observers such as a viewer (or a Python `Observer`).
pub const SPARE_PORTS: usize = 4;
