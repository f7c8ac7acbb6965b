//! Streaming the actors' weights to the agents: one `[f32]` service per actor, history 1, so
//! an agent that (re)connects gets the latest weights at once.

use anyhow::{Context, Result};
use formation_ipc::services::{self, Sizing};
use formation_protocol::wire::{PROTOCOL_VERSION, WeightsHeader};
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::prelude::*;

use crate::learner::Learner;

/// The critic's ends of the weights services.
pub struct WeightsPublisher<S: Service> {
    publishers: Vec<Publisher<S, [f32], WeightsHeader>>,
    /// The version last published (the update count at the time; 0 before the first).
    pub version: u32,
}

impl<S: Service> WeightsPublisher<S> {
    /// One publisher per actor of `learner`, sized for its flat weights.
    pub fn new(node: &Node<S>, sizing: &Sizing, learner: &Learner) -> Result<Self> {
        let len = learner.actor_shape().parameter_count();
        let publishers = (0..learner.n_actors())
            .map(|index| {
                services::weights_stream(node, sizing, index)?
                    .publisher_builder()
                    .initial_max_slice_len(len)
                    .create()
                    .with_context(|| format!("critic: weights publisher {index}"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { publishers, version: 0 })
    }

    /// Connects subscribers that appeared since the last publication (they get the history).
    pub fn update_connections(&self) -> Result<()> {
        for publisher in &self.publishers {
            publisher.update_connections().context("critic: weights connections")?;
        }
        Ok(())
    }

    /// Publishes every actor's current weights; the version is the update count, so it keeps
    /// growing across a resume from a checkpoint.
    pub fn publish(&mut self, learner: &Learner) -> Result<()> {
        self.version = u32::try_from(learner.updates().max(1)).unwrap_or(u32::MAX);
        for (index, publisher) in self.publishers.iter().enumerate() {
            let flat = learner.actor_weights(index)?;
            let mut sample = publisher
                .loan_slice_uninit(flat.len())
                .context("critic: loan weights")?;
            *sample.user_header_mut() = WeightsHeader {
                protocol_version: PROTOCOL_VERSION,
                actor_index: index as u32,
                version: self.version,
                len: flat.len() as u32,
            };
            let sample = sample.write_from_slice(&flat);
            sample.send().context("critic: send weights")?;
        }
        Ok(())
    }
}
