//! The central replay of the critic process.
//!
//! * [`buffer`]: whole episodes of joint ticks (true poses, every robot's observation, every
//!   executed action, shared reward, terminal and truncation flags), evicted oldest first;
//! * [`features`]: the critic's view of a tick (poses relative to the centroid) and the
//!   observation recomputation HER needs;
//! * [`sample`]: B concurrent sequences of H ticks from one episode each (the same ticks for
//!   every robot), their next sequences, and the HER relabelling, as a named [`sample::Batch`].

pub mod buffer;
pub mod features;
pub mod sample;
