//! The bridge on the sim's host: for each robot that lives on another host, it takes the
//! robot's observations (on their wake-up) and its actor's weights from local iceoryx2 to Zenoh,
//! and puts the robot's commands from Zenoh back into local iceoryx2 with the wake-up the sim
//! waits on, as if the robot were local. Commands for robots it does not serve, or that do not
//! parse, are rejected and counted.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::{Context, Result, anyhow};
use formation_ipc::services::{self, SimWatch, Sizing};
use formation_ipc::termination_requested;
use formation_protocol::wire::{CommandMsg, FLAG_RUN_END, ObservationMsg, WeightsHeader};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use zenoh::handlers::RingChannel;
use zenoh::sample::{Locality, SampleKind};
use zenoh::{Session, Wait};

use crate::link::{Keys, Outbox};
use crate::{Bridged, Counters, Freshness};

/// Copies of the run's end each bridged robot is sent: on a link that loses a message with
/// probability p, all are lost with p^20 (1e-6 at p = 0.5).
pub const RUN_END_COPIES: usize = 20;
/// Between two copies of the run's end (19 gaps: the last leaves 190 ms after the first), so a
/// short burst of loss does not take them all.
pub const RUN_END_SPACING: Duration = Duration::from_millis(10);

/// Runs the sim host's bridge until the run ends; returns what it forwarded and rejected.
pub fn run(bridged: &Bridged, session: &Session, outbox_keys: &Keys) -> Result<Arc<Counters>> {
    let counters = Arc::new(Counters::default());
    let resend_weights = Arc::new(AtomicBool::new(false));
    let _alive = session
        .liveliness()
        .declare_token(outbox_keys.sim_host())
        .wait()
        .map_err(|err| anyhow!("liveliness token: {err}"))?;
    // A robot host that (re)appears gets the latest weights at once.
    let resend = Arc::clone(&resend_weights);
    let _hosts = session
        .liveliness()
        .declare_subscriber(outbox_keys.robot_hosts())
        .history(true)
        .callback(move |sample| {
            if sample.kind() == SampleKind::Put {
                resend.store(true, Ordering::Release);
            }
        })
        .wait()
        .map_err(|err| anyhow!("liveliness subscriber: {err}"))?;
    crate::beside_the_commands(bridged, session, outbox_keys, &counters, commands_to_the_sim, || {
        observations_out(bridged, session, outbox_keys, &counters, &resend_weights)
    })?;
    Ok(counters)
}

/// Robot `.0`'s observation subscriber and the wake-up the sim raises for it.
type ObservationIn = (
    usize,
    Subscriber<ipc::Service, ObservationMsg, ()>,
    Listener<ipc::Service>,
);
/// Actor `.0`'s weights subscriber.
type WeightsIn = (usize, Subscriber<ipc::Service, [f32], WeightsHeader>);

/// The robots' observation and weights ports on the sim's host.
struct OutPorts {
    observations: Vec<ObservationIn>,
    weights: Vec<WeightsIn>,
}

fn open_out_ports(node: &Node<ipc::Service>, bridged: &Bridged, sizing: &Sizing) -> Result<OutPorts> {
    let mut observations = Vec::new();
    for &agent in &bridged.robots {
        let subscriber = services::observation_stream(node, sizing, agent)?
            .subscriber_builder()
            .buffer_size(16)
            .create()
            .with_context(|| format!("bridge: observation subscriber of robot {agent}"))?;
        let listener = services::observation_event(node, sizing, agent)?
            .listener_builder()
            .create()
            .with_context(|| format!("bridge: observation listener of robot {agent}"))?;
        observations.push((agent, subscriber, listener));
    }
    let mut weights = Vec::new();
    for actor in bridged.actors() {
        let subscriber = services::weights_stream(node, sizing, actor)?
            .subscriber_builder()
            .create()
            .with_context(|| format!("bridge: weights subscriber of actor {actor}"))?;
        weights.push((actor, subscriber));
    }
    Ok(OutPorts { observations, weights })
}

/// Local observations (and weights) to Zenoh, on each observation's wake-up. Returns when every
/// bridged robot was told the run ended ([`RUN_END_COPIES`] times, [`RUN_END_SPACING`] apart,
/// the delay line flushed), or the sim is gone.
fn observations_out(
    bridged: &Bridged,
    session: &Session,
    keys: &Keys,
    counters: &Counters,
    resend_weights: &AtomicBool,
) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&bridged.identity, "bridge")?;
    let ports = open_out_ports(&node, bridged, &bridged.sizing)?;
    let mut key_list: Vec<String> = bridged.robots.iter().map(|&a| keys.observation(a)).collect();
    key_list.extend(ports.weights.iter().map(|(actor, _)| keys.weights(*actor)));
    let outbox = Outbox::new(session, &key_list, bridged.emulation)?;
    let listeners: Vec<&Listener<ipc::Service>> = ports.observations.iter().map(|(_, _, l)| l).collect();
    let mut latest_weights: Vec<Option<Vec<u8>>> = vec![None; ports.weights.len()];
    let mut ended: Vec<Option<Vec<u8>>> = vec![None; bridged.robots.len()];
    let mut sim_watch = SimWatch::new(bridged.sim_silence, bridged.startup_timeout);
    let mut bytes = Vec::new();
    while !ended.iter().all(Option::is_some) {
        services::wait_for_any_event(&listeners, Duration::from_millis(100))?;
        for (slot, (_, subscriber, _)) in ports.observations.iter().enumerate() {
            while let Some(sample) = subscriber.receive().context("bridge: receive observation")? {
                sim_watch.heard();
                let msg = sample.payload();
                outbox.send(slot, bytemuck::bytes_of(msg))?;
                counters.observations.fetch_add(1, Ordering::Relaxed);
                if msg.header.has(FLAG_RUN_END) {
                    ended[slot] = Some(bytemuck::bytes_of(msg).to_vec());
                }
            }
        }
        let weights_base = ports.observations.len();
        let resend = resend_weights.swap(false, Ordering::AcqRel);
        for (slot, (_, subscriber)) in ports.weights.iter().enumerate() {
            while let Some(sample) = subscriber.receive().context("bridge: receive weights")? {
                bytes.clear();
                bytes.extend_from_slice(bytemuck::bytes_of(sample.user_header()));
                bytes.extend(sample.payload().iter().flat_map(|value| value.to_le_bytes()));
                latest_weights[slot] = Some(bytes.clone());
                outbox.send(weights_base + slot, &bytes)?;
                counters.weights.fetch_add(1, Ordering::Relaxed);
            }
            if let (true, Some(latest)) = (resend, &latest_weights[slot]) {
                outbox.send(weights_base + slot, latest)?;
                counters.weights.fetch_add(1, Ordering::Relaxed);
            }
        }
        if termination_requested() {
            break;
        }
        if let Some(quiet) = sim_watch.gone::<ipc::Service>(&bridged.identity, "bridge")? {
            anyhow::bail!(
                "bridge: no observation from the sim for {:.1} s; is it alive?",
                quiet.as_secs_f64()
            );
        }
    }
    // The run's end again (the robot's bridge drops the duplicates): one lost copy would
    // leave the robot to wait out the launcher's wind-down.
    for _ in 1..RUN_END_COPIES {
        if !ended.iter().all(Option::is_some) {
            break; // interrupted: the launcher stops everyone
        }
        std::thread::sleep(RUN_END_SPACING);
        for (slot, end) in ended.iter().enumerate() {
            if let Some(bytes) = end {
                outbox.send(slot, bytes)?;
            }
        }
    }
    outbox.flush()?;
    counters
        .lost
        .fetch_add(outbox.lost.load(Ordering::Relaxed), Ordering::Relaxed);
    Ok(())
}

/// Commands from Zenoh into local iceoryx2, each with the wake-up a local robot would send.
fn commands_to_the_sim(
    bridged: &Bridged,
    session: &Session,
    keys: &Keys,
    counters: &Counters,
    stop: &AtomicBool,
) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&bridged.identity, "bridge-commands")?;
    let sizing = &bridged.sizing;
    let mut publishers = Vec::new();
    for &agent in &bridged.robots {
        let publisher = services::command_stream(&node, sizing, agent)?
            .publisher_builder()
            .create()
            .with_context(|| format!("bridge: command publisher of robot {agent}"))?;
        publishers.push((agent, publisher, Freshness::default()));
    }
    let command_ready = services::command_event(&node, sizing)?
        .notifier_builder()
        .create()
        .context("bridge: command notifier")?;
    let incoming = session
        .declare_subscriber(keys.commands())
        .with(RingChannel::new(64))
        .allowed_origin(Locality::Remote)
        .wait()
        .map_err(|err| anyhow!("zenoh subscriber: {err}"))?;
    while !stop.load(Ordering::Acquire) {
        let Ok(Some(sample)) = incoming.recv_timeout(Duration::from_millis(100)) else {
            continue;
        };
        let agent = Keys::index_after(sample.key_expr().as_str(), "agent");
        let slot = agent.and_then(|agent| publishers.iter().position(|(a, _, _)| *a == agent));
        let payload = sample.payload().to_bytes();
        let command = bytemuck::try_pod_read_unaligned::<CommandMsg>(&payload).ok();
        let (Some(slot), Some(command)) = (slot, command) else {
            // Not a robot this bridge serves, or not a command: never reaches the sim.
            counters.rejected.fetch_add(1, Ordering::Relaxed);
            continue;
        };
        let (agent, publisher, freshness) = &mut publishers[slot];
        if command.agent as usize != *agent {
            counters.rejected.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        if !freshness.admit(&command.header, &payload) {
            counters.dropped.fetch_add(1, Ordering::Relaxed);
            continue;
        }
        let mut out = publisher.loan().context("bridge: loan command")?;
        *out.payload_mut() = command;
        out.send().context("bridge: send command")?;
        command_ready
            .notify_with_custom_event_id(services::agent_event_id(*agent))
            .context("bridge: notify the sim")?;
        counters.commands.fetch_add(1, Ordering::Relaxed);
    }
    Ok(())
}
