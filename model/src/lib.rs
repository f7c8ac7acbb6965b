//! The networks, apart from any process: the trainable actor (candle), the allocation-free
//! frozen actor the robots run, the observation window both feed from, and checkpoints that
//! record what the networks were trained on.
//!
//! * [`actor`]: [`actor::ActorShape`], [`actor::Actor`] and [`actor::FrozenActor`];
//! * [`history`]: the last H observations of one robot, padded at an episode start;
//! * [`checkpoint`]: safetensors files with metadata (observation model, sizes, training score).

pub mod actor;
pub mod checkpoint;
pub mod history;
