//! One robot's process: it reads only its own observations, keeps the last H of them and
//! answers each tick with (v, w) from the scripted baseline or the learned actor (whose network
//! is `formation_model`), or, as the privileged planner that knows the map, from the true state.

pub mod oracle;
pub mod policy;
pub mod ports;
pub mod run;
