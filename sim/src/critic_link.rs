//! Flow control towards the critic: the sim never runs more than `ticks.critic_window` states
//! ahead of what the critic has acknowledged, and runs on alone while no critic speaks.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_ipc::services::{self, FileDescriptorBased};
use formation_ipc::termination_requested;
use formation_protocol::wire::PROTOCOL_VERSION;
use iceoryx2::port::listener::Listener;
use iceoryx2::prelude::*;

use crate::ports::SimPorts;

/// What the sim knows of the critic: its session (a restarted critic starts a new one and
/// counts from zero) and whether it is keeping up.
#[derive(Debug, Default)]
pub struct CriticLink {
    session: u64,
    /// States published when the current session first spoke.
    joined_at: u64,
    acknowledged: u64,
    absent: bool,
}

/// Refuses a peer of another protocol version.
pub fn check_protocol(version: u32, who: &str) -> Result<()> {
    if version != PROTOCOL_VERSION {
        bail!(
            "{who} speaks protocol version {version}, this sim speaks {PROTOCOL_VERSION}: rebuild all binaries together"
        );
    }
    Ok(())
}

impl CriticLink {
    /// Reads the critic's latest progress, `published` states having gone out; true when any
    /// arrived.
    pub fn drain<S: Service>(&mut self, ports: &SimPorts<S>, published: u64) -> Result<bool> {
        let mut any = false;
        while let Some(sample) = ports.critic_progress.receive().context("receive")? {
            let progress = *sample.payload();
            check_protocol(progress.protocol_version, "the critic")?;
            if progress.session != self.session {
                if self.session != 0 {
                    eprintln!("sim: a new critic joined at tick {published}");
                }
                self.session = progress.session;
                self.joined_at = published;
            }
            // A critic that just joined owes nothing for the states published before it came.
            self.acknowledged = progress.acknowledged_sequence.max(self.joined_at);
            if self.absent {
                eprintln!("sim: the critic is back");
                self.absent = false;
            }
            any = true;
        }
        Ok(any)
    }

    /// Blocks (event-driven) while `published` is more than `window` states ahead of the
    /// critic. A critic silent for `give_up` is treated as gone: the swarm runs on unthrottled
    /// (the agents keep their last weights) until a critic speaks again.
    pub fn wait<S: Service>(
        &mut self,
        ports: &SimPorts<S>,
        published: u64,
        window: u64,
        give_up: Duration,
    ) -> Result<()>
    where
        Listener<S>: FileDescriptorBased,
    {
        let mut last_progress = Instant::now();
        self.drain(ports, published)?;
        while !self.absent && published.saturating_sub(self.acknowledged) > window {
            services::wait_for_event(&ports.critic_progress_ready, Duration::from_millis(20))?;
            if self.drain(ports, published)? {
                last_progress = Instant::now();
                continue;
            }
            if last_progress.elapsed() >= give_up {
                eprintln!(
                    "sim: the critic has acknowledged nothing for {} ms; running on without it",
                    give_up.as_millis()
                );
                self.absent = true;
            }
            ports.wake_critic()?;
            if termination_requested() {
                return Ok(());
            }
        }
        Ok(())
    }
}
