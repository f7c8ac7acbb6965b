//! The bridge on a robot's host: it recreates, in this host's own iceoryx2, the services a
//! robot uses (its observations with their wake-up, its commands with the sim's wake-up, its
//! actor's weights), so the unchanged `formation-agent` runs here. Its iceoryx2 node is named
//! `sim`: to the robot it stands for the sim, alive while the bridge is.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, sync_channel};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use formation_ipc::services::{self, Sizing};
use formation_ipc::termination_requested;
use formation_protocol::wire::{CommandMsg, FLAG_RUN_END, ObservationMsg, WeightsHeader};
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::prelude::*;
use zenoh::bytes::ZBytes;
use zenoh::sample::{Locality, Sample, SampleKind};
use zenoh::{Session, Wait};

use crate::link::{Keys, Outbox};
use crate::{Bridged, Counters, Freshness};

/// Floats a weights sample starts with room for (it grows to any actor's size).
const INITIAL_WEIGHTS_LEN: usize = 1 << 15;
/// How long the bridge stays after passing the run's end on, so its robots read it.
const LINGER: Duration = Duration::from_millis(500);

/// What arrives from the sim's host.
enum Incoming {
    Observation(usize, ZBytes),
    Weights(usize, ZBytes),
}

/// Runs a robot host's bridge until the run ends; returns what it forwarded and dropped.
pub fn run(bridged: &Bridged, session: &Session, keys: &Keys) -> Result<Arc<Counters>> {
    let counters = Arc::new(Counters::default());
    let mut tokens = Vec::new();
    for &agent in &bridged.robots {
        tokens.push(
            session
                .liveliness()
                .declare_token(keys.robot_host(agent))
                .wait()
                .map_err(|err| anyhow!("liveliness token: {err}"))?,
        );
    }
    let sim_host_seen = Arc::new(AtomicBool::new(false));
    let seen = Arc::clone(&sim_host_seen);
    let _sim_host = session
        .liveliness()
        .declare_subscriber(keys.sim_host())
        .history(true)
        .callback(move |sample| seen.store(sample.kind() == SampleKind::Put, Ordering::Release))
        .wait()
        .map_err(|err| anyhow!("liveliness subscriber: {err}"))?;
    // Zenoh's threads hand samples over; a full queue drops the newest (the robot is behind).
    let (sender, incoming) = sync_channel::<Incoming>(256);
    let observations = subscribe(
        session,
        &keys.observations(),
        "agent",
        sender.clone(),
        Incoming::Observation,
    )?;
    let weights = subscribe(session, &keys.all_weights(), "actor", sender, Incoming::Weights)?;
    crate::beside_the_commands(bridged, session, keys, &counters, commands_to_the_link, || {
        observations_in(bridged, &incoming, &counters, &sim_host_seen)
    })?;
    drop((observations, weights));
    Ok(counters)
}

/// A subscriber on `key` whose samples go into `sender`, tagged with the index after `segment`.
fn subscribe(
    session: &Session,
    key: &str,
    segment: &'static str,
    sender: SyncSender<Incoming>,
    wrap: fn(usize, ZBytes) -> Incoming,
) -> Result<zenoh::pubsub::Subscriber<()>> {
    session
        .declare_subscriber(key.to_string())
        .allowed_origin(Locality::Remote)
        .callback(move |sample: Sample| {
            if let Some(index) = Keys::index_after(sample.key_expr().as_str(), segment) {
                // A reference to Zenoh's buffer, not a copy. Full: the robot is behind, the
                // newest is dropped; disconnected: the bridge ends.
                let _ = sender.try_send(wrap(index, sample.payload().clone()));
            }
        })
        .wait()
        .map_err(|err| anyhow!("zenoh subscriber {key}: {err}"))
}

/// Robot `.0`'s observation publisher, its wake-up, and what it was last sent.
type ObservationOut = (
    usize,
    Publisher<ipc::Service, ObservationMsg, ()>,
    Notifier<ipc::Service>,
    Freshness,
);
/// Actor `.0`'s weights publisher.
type WeightsOut = (usize, Publisher<ipc::Service, [f32], WeightsHeader>);

/// The robots' observation and weights ports on this host.
struct InPorts {
    observations: Vec<ObservationOut>,
    weights: Vec<WeightsOut>,
}

fn open_in_ports(node: &Node<ipc::Service>, bridged: &Bridged, sizing: &Sizing) -> Result<InPorts> {
    let mut observations = Vec::new();
    for &agent in &bridged.robots {
        let publisher = services::observation_stream(node, sizing, agent)?
            .publisher_builder()
            .create()
            .with_context(|| format!("bridge: observation publisher of robot {agent}"))?;
        let notifier = services::observation_event(node, sizing, agent)?
            .notifier_builder()
            .create()
            .with_context(|| format!("bridge: observation notifier of robot {agent}"))?;
        observations.push((agent, publisher, notifier, Freshness::default()));
    }
    let mut weights = Vec::new();
    for actor in bridged.actors() {
        let publisher = services::weights_stream(node, sizing, actor)?
            .publisher_builder()
            .initial_max_slice_len(INITIAL_WEIGHTS_LEN)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .with_context(|| format!("bridge: weights publisher of actor {actor}"))?;
        weights.push((actor, publisher));
    }
    Ok(InPorts { observations, weights })
}

/// Messages from the sim's host into this host's iceoryx2. Returns once every robot here was
/// told the run ended; errs when the sim's host has been away longer than a sim may be silent
/// at start.
fn observations_in(
    bridged: &Bridged,
    incoming: &Receiver<Incoming>,
    counters: &Counters,
    sim_host_seen: &AtomicBool,
) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&bridged.identity, "sim")?;
    let mut ports = open_in_ports(&node, bridged, &bridged.sizing)?;
    let mut ended = vec![false; ports.observations.len()];
    let mut last_seen = Instant::now();
    while !ended.iter().all(|&e| e) {
        let message = match incoming.recv_timeout(Duration::from_millis(100)) {
            Ok(message) => Some(message),
            Err(RecvTimeoutError::Timeout) => None,
            Err(RecvTimeoutError::Disconnected) => bail!("bridge: the zenoh subscribers closed"),
        };
        if sim_host_seen.load(Ordering::Acquire) {
            last_seen = Instant::now();
        } else if last_seen.elapsed() > bridged.startup_timeout {
            bail!(
                "bridge: the sim's host has been unreachable for {} s",
                bridged.startup_timeout.as_secs()
            );
        }
        if termination_requested() {
            return Ok(());
        }
        match message {
            Some(Incoming::Observation(agent, payload)) => {
                // Borrowed when Zenoh received the message in one piece (it does at this size).
                let bytes = payload.to_bytes();
                let Some(slot) = ports.observations.iter().position(|(a, ..)| *a == agent) else {
                    continue; // another host's robot
                };
                let (_, publisher, notifier, freshness) = &mut ports.observations[slot];
                let Ok(msg) = bytemuck::try_pod_read_unaligned::<ObservationMsg>(&bytes) else {
                    counters.rejected.fetch_add(1, Ordering::Relaxed);
                    continue;
                };
                if !freshness.admit(&msg.header, &bytes) {
                    counters.dropped.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                let mut out = publisher.loan().context("bridge: loan observation")?;
                *out.payload_mut() = msg;
                out.send().context("bridge: send observation")?;
                notifier.notify().context("bridge: wake the robot")?;
                counters.observations.fetch_add(1, Ordering::Relaxed);
                ended[slot] |= msg.header.has(FLAG_RUN_END);
            }
            Some(Incoming::Weights(actor, payload)) => {
                let bytes = payload.to_bytes();
                let Some((_, publisher)) = ports.weights.iter().find(|(a, _)| *a == actor) else {
                    continue;
                };
                if publish_weights(publisher, &bytes).is_err() {
                    counters.rejected.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                counters.weights.fetch_add(1, Ordering::Relaxed);
            }
            None => {}
        }
    }
    std::thread::sleep(LINGER);
    Ok(())
}

/// Publishes one weights message (header, then the f32 values) locally.
fn publish_weights(publisher: &Publisher<ipc::Service, [f32], WeightsHeader>, bytes: &[u8]) -> Result<()> {
    let head_len = std::mem::size_of::<WeightsHeader>();
    let header: WeightsHeader = bytemuck::try_pod_read_unaligned(bytes.get(..head_len).context("short weights")?)
        .map_err(|err| anyhow!("weights header: {err}"))?;
    let values = &bytes[head_len..];
    if values.len() != header.len as usize * 4 {
        bail!("weights of {} bytes announce {} floats", values.len(), header.len);
    }
    let mut sample = publisher
        .loan_slice_uninit(header.len as usize)
        .context("bridge: loan weights")?;
    *sample.user_header_mut() = header;
    let sample = sample.write_from_fn(|i| {
        f32::from_le_bytes([values[4 * i], values[4 * i + 1], values[4 * i + 2], values[4 * i + 3]])
    });
    sample.send().context("bridge: send weights")?;
    Ok(())
}

/// Local commands (on the sim's wake-up the robot raises) to Zenoh.
fn commands_to_the_link(
    bridged: &Bridged,
    session: &Session,
    keys: &Keys,
    counters: &Counters,
    stop: &AtomicBool,
) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&bridged.identity, "bridge-commands")?;
    let sizing = &bridged.sizing;
    let mut subscribers = Vec::new();
    for &agent in &bridged.robots {
        let subscriber = services::command_stream(&node, sizing, agent)?
            .subscriber_builder()
            .buffer_size(16)
            .create()
            .with_context(|| format!("bridge: command subscriber of robot {agent}"))?;
        subscribers.push(subscriber);
    }
    let wake = services::command_event(&node, sizing)?
        .listener_builder()
        .create()
        .context("bridge: command listener")?;
    let keys: Vec<String> = bridged.robots.iter().map(|&a| keys.command(a)).collect();
    let outbox = Outbox::new(session, &keys, bridged.emulation)?;
    while !stop.load(Ordering::Acquire) {
        services::wait_for_event(&wake, Duration::from_millis(100))?;
        for (slot, subscriber) in subscribers.iter().enumerate() {
            while let Some(sample) = subscriber.receive().context("bridge: receive command")? {
                let command: &CommandMsg = sample.payload();
                outbox.send(slot, bytemuck::bytes_of(command))?;
                counters.commands.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
    counters
        .lost
        .fetch_add(outbox.lost.load(Ordering::Relaxed), Ordering::Relaxed);
    Ok(())
}
