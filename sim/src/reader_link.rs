//! Flow control towards the stream's readers that must see every state (the critic, and the
//! MCAP recorder when there is one): the sim never runs more than `ticks.critic_window` states
//! ahead of what each has acknowledged, and runs on alone while one stays silent.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use formation_ipc::services::{self, FileDescriptorBased, Sizing, StreamReader};
use formation_ipc::termination_requested;
use formation_protocol::wire::{CriticProgressMsg, PROTOCOL_VERSION};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

/// What the sim knows of one reader: its session (a restarted reader starts a new one and
/// counts from zero) and whether it is keeping up.
pub struct ReaderLink<S: Service> {
    reader: StreamReader,
    progress: Subscriber<S, CriticProgressMsg, ()>,
    progress_ready: Listener<S>,
    /// The reader's current session; 0 until it first speaks (a session is never 0).
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

impl<S: Service> ReaderLink<S>
where
    Listener<S>: FileDescriptorBased,
{
    /// Subscribes to `reader`'s progress.
    pub fn open(node: &Node<S>, sizing: &Sizing, reader: StreamReader) -> Result<Self> {
        Ok(Self {
            reader,
            progress: services::progress_stream(node, sizing, reader)?
                .subscriber_builder()
                .create()
                .with_context(|| format!("sim cannot subscribe to {}'s progress", reader.name()))?,
            progress_ready: services::progress_event(node, sizing, reader)?
                .listener_builder()
                .create()
                .with_context(|| format!("sim cannot listen to {}'s progress", reader.name()))?,
            session: 0,
            joined_at: 0,
            acknowledged: 0,
            absent: false,
        })
    }

    /// Who this link follows, for messages.
    pub fn name(&self) -> &'static str {
        self.reader.name()
    }

    /// The reader has spoken at least once.
    pub fn heard(&self) -> bool {
        self.session != 0
    }

    /// Reads the reader's latest progress, `published` states having gone out; true when any
    /// arrived.
    pub fn drain(&mut self, published: u64) -> Result<bool> {
        let mut any = false;
        while let Some(sample) = self.progress.receive().context("receive")? {
            let progress = *sample.payload();
            check_protocol(progress.protocol_version, self.reader.name())?;
            if progress.session != self.session {
                if self.session != 0 {
                    eprintln!(
                        "sim: a new session of {} joined at tick {published}",
                        self.reader.name()
                    );
                }
                self.session = progress.session;
                self.joined_at = published;
            }
            // A reader that just joined owes nothing for the states published before it came.
            self.acknowledged = progress.acknowledged_sequence.max(self.joined_at);
            if self.absent {
                eprintln!("sim: {} is back", self.reader.name());
                self.absent = false;
            }
            any = true;
        }
        Ok(any)
    }

    /// Blocks (event-driven) while `published` is more than `window` states ahead of the
    /// reader, calling `wake` (the readers' wake-up) each time it waits again. A reader silent
    /// for `give_up` is treated as gone: the swarm runs on unthrottled until it speaks again.
    pub fn wait(
        &mut self,
        published: u64,
        window: u64,
        give_up: Duration,
        wake: impl Fn() -> Result<()>,
    ) -> Result<()> {
        let mut last_progress = Instant::now();
        self.drain(published)?;
        while !self.absent && published.saturating_sub(self.acknowledged) > window {
            services::wait_for_event(&self.progress_ready, Duration::from_millis(20))?;
            if self.drain(published)? {
                last_progress = Instant::now();
                continue;
            }
            if last_progress.elapsed() >= give_up {
                eprintln!(
                    "sim: {} has acknowledged nothing for {} ms; running on without it",
                    self.reader.name(),
                    give_up.as_millis()
                );
                self.absent = true;
            }
            wake()?;
            if termination_requested() {
                return Ok(());
            }
        }
        Ok(())
    }
}
