//! The central critic process: it subscribes to the true state, every observation and every
//! command, assembles joint episodes into the replay, trains the critic(s) and actor(s), and
//! streams actor weights back to the agents.
//!
//! * [`run`]: the process's loop and the flow-control link to the sim;
//! * [`collector`]: the subscriptions, assembling each tick of every stream into episodes;
//! * [`trainer`]: replay, updates at the update-to-data ratio, weights, checkpoints;
//! * [`selection`]: each checkpoint's score, on fixed noise-free episodes played in-process;
//! * [`learner`]: the networks and one gradient update (TD3 or DDPG);
//! * [`distill`]: the offline `formation-distill` tool, the shared actor taught its teacher by
//!   DAgger on the games of [`selection`];
//! * [`probe`]: the offline `formation-critic-probe` tool, a trained critic's action values
//!   against the true returns of branched in-process episodes;
//! * [`weights`]: the weights services towards the agents;
//! * [`progress`], [`view`]: the progress display, `training.csv` and the training curves.

pub mod collector;
pub mod distill;
pub mod learner;
pub mod probe;
pub mod progress;
pub mod run;
pub mod selection;
pub mod trainer;
pub mod view;
pub mod weights;

/// Keeps glibc from handing big buffers back to the OS after every update: each update
/// allocates and frees megabytes of tensors, and the page faults of fresh mappings cost about
/// as much as the arithmetic. 32 MiB is the largest mmap threshold glibc accepts.
pub fn tune_allocator() {
    // SAFETY: mallopt only changes allocator thresholds; called before other threads start.
    let accepted = unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20) == 1 && libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30) == 1
    };
    if !accepted {
        eprintln!("critic: glibc refused the allocator tuning; updates will be slower");
    }
}
