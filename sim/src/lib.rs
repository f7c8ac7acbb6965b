//! The physics process: unicycle robots, the paper's reward, random episodes and the lockstep
//! tick loop that drives the agents over iceoryx2.

pub mod formation;
pub mod lockstep;
pub mod physics;
pub mod report;
pub mod task;
pub mod world;
