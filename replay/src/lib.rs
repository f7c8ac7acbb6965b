//! The central replay of the critic process. What it recomputes for HER (observations,
//! rewards, the critic's features) is `formation_core`'s code, the sim's own.
//!
//! * [`buffer`]: whole episodes of joint ticks (true poses, the commands applied, every robot's
//!   observation, shared reward, terminal flag), each tick handed out as the sim's own
//!   [`formation_core::scene::Scene`], evicted oldest first;
//! * [`record`]: an episode played in-process and recorded as the collector would;
//! * [`sample`]: B concurrent sequences of H ticks from one episode each (the same ticks for
//!   every robot), their next sequences, and the HER relabelling, as a named [`sample::Batch`].

pub mod buffer;
pub mod record;
pub mod sample;
