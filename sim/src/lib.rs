//! The physics process: unicycle robots, the paper's reward, random episodes and the lockstep
//! tick loop that drives the agents over iceoryx2.

pub mod formation;
pub mod lockstep;
pub mod physics;
pub mod plots;
pub mod report;
pub mod task;
pub mod view;
pub mod world;
