//! The physics process: it owns the clock and the true state, runs the lockstep tick loop that
//! drives the robots over iceoryx2, and reports (episodes.csv, summary.json, the Rerun world
//! view, the paper's figures). The task itself (physics, reward, observations) is
//! `formation_core`.
//!
//! * [`lockstep`]: the process's loop: connect, play episodes tick by tick, report;
//! * [`ports`]: the sim's ends of the services, and publishing observations and states;
//! * [`commands`]: one tick's command wait and its bookkeeping (missed, late, malformed);
//! * [`reader_link`]: flow control towards the critic and the MCAP recorder;
//! * [`control`]: the live control service (a new formation or goal mid-episode);
//! * [`report`], [`plots`], [`view`]: `episodes.csv` and `summary.json`, the PNG figures,
//!   the live Rerun view.

pub mod commands;
pub mod control;
pub mod lockstep;
pub mod plots;
pub mod ports;
pub mod reader_link;
pub mod report;
pub mod view;
