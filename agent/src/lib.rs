//! One robot's process: it reads only its own observations, keeps the last H of them and
//! answers each tick with (v, w) from the scripted baseline or the learned actor (whose network
//! is `formation_model`).

pub mod policy;
pub mod ports;
pub mod run;
