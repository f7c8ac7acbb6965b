//! The central critic process: it subscribes to the true state, every observation and every
//! command, assembles joint episodes into the replay, trains the critic(s) and actor(s), and
//! streams actor weights back to the agents.

pub mod collector;
pub mod learner;
pub mod run;
