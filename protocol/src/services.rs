//! Service names, the run-unique iceoryx2 configuration and the port factories of a run.
//!
//! Binaries never spell a service name: they call these functions, so the sim, the agents and
//! the critic cannot drift apart. Every factory is generic over the iceoryx2 service type, so
//! the same loops run across processes (`ipc::Service`) and inside one (`local::Service`).

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use iceoryx2::node::NodeView;
use iceoryx2::port::listener::{Listener, ListenerWaitError};
use iceoryx2::prelude::*;
use iceoryx2::service::attribute::{AttributeKey, AttributeValue, AttributeVerifier};
use iceoryx2::service::builder::event::{EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError};
use iceoryx2::service::port_factory::{event, publish_subscribe};

/// What [`wait_for_events`] needs of a listener: a socket to poll (every iceoryx2 service type
/// has one). Generic code over the service type names it in a `where` clause.
pub use iceoryx2_bb_posix::file_descriptor::FileDescriptorBased;

use crate::MAX_AGENTS;
use crate::wire::{CommandMsg, CriticProgressMsg, ObservationMsg, StateMsg, WeightsHeader};

/// Ports left for processes that replace a dead one before iceoryx2 has cleaned it up, and for
/// observers such as a viewer (or a Python `Observer`).
pub const SPARE_PORTS: usize = 4;

/// Where POSIX shared memory lives: iceoryx2's segments and the tick gate.
pub const SHM_DIR: &str = "/dev/shm";

/// The run's iceoryx2 configuration, in its run directory.
pub const ICEORYX_CONFIG_FILE: &str = "iceoryx2.toml";

/// Where a run's iceoryx2 files live and what their shared-memory names start with.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunIdentity {
    /// Letters, digits, `_` and `-`; at most 24 characters.
    pub run_id: String,
}

impl RunIdentity {
    /// Checks the id is usable in file names.
    pub fn new(run_id: &str) -> Result<Self> {
        if run_id.is_empty()
            || run_id.len() > 24
            || !run_id
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            bail!("run id {run_id:?} must be 1 to 24 letters, digits, '_' or '-'");
        }
        Ok(Self {
            run_id: run_id.to_string(),
        })
    }

    /// Prefix of every file of this run in `/dev/shm`.
    pub fn shm_prefix(&self) -> String {
        format!("fc_{}_", self.run_id)
    }

    /// Directory for the run's iceoryx2 node and service descriptions.
    pub fn root_path(&self) -> PathBuf {
        std::env::temp_dir().join("formation-iox2").join(&self.run_id)
    }

    /// The iceoryx2 configuration every process of this run uses.
    pub fn iceoryx_config(&self) -> Result<Config> {
        let mut config = Config::default();
        config.global.prefix = FileName::new(self.shm_prefix().as_bytes())
            .map_err(|err| anyhow::anyhow!("bad shm prefix {}: {err:?}", self.shm_prefix()))?;
        let root = format!("{}/", self.root_path().display());
        config
            .global
            .set_root_path(&Path::new(root.as_bytes()).with_context(|| format!("bad root path {root}"))?);
        Ok(config)
    }

    /// Writes the run's iceoryx2 configuration to `run_dir/iceoryx2.toml`, so that a client in
    /// any language attaches with the same prefix and root path (iceoryx2's `Config::from_file`,
    /// or `iox2_config_from_file` in C). Returns the file.
    pub fn write_iceoryx_config(&self, run_dir: &std::path::Path) -> Result<PathBuf> {
        let path = run_dir.join(ICEORYX_CONFIG_FILE);
        let text = toml::to_string(&self.iceoryx_config()?).context("cannot serialise the iceoryx2 config")?;
        crate::cli::write_atomically(&path, text.as_bytes())?;
        Ok(path)
    }

    /// Removes what a finished run leaves behind: its `/dev/shm` files and its root path.
    /// Returns how many shared-memory files were removed.
    pub fn remove_leftovers(&self) -> usize {
        let prefix = self.shm_prefix();
        let mut removed = 0;
        if let Ok(entries) = std::fs::read_dir(SHM_DIR) {
            for entry in entries.flatten() {
                if entry.file_name().to_string_lossy().starts_with(&prefix)
                    && std::fs::remove_file(entry.path()).is_ok()
                {
                    removed += 1;
                }
            }
        }
        let _ignored_if_absent = std::fs::remove_dir_all(self.root_path());
        removed
    }
}

/// Creates a node of the run with a descriptive name (shown by `iox2 node list`).
pub fn create_node<S: Service>(identity: &RunIdentity, name: &str) -> Result<Node<S>> {
    let config = identity.iceoryx_config()?;
    let node_name = NodeName::new(name).with_context(|| format!("bad node name {name}"))?;
    NodeBuilder::new()
        .name(&node_name)
        .config(&config)
        .create::<S>()
        .with_context(|| format!("cannot create iceoryx2 node {name}"))
}

fn service_name(name: &str) -> Result<ServiceName> {
    ServiceName::new(name).with_context(|| format!("bad service name {name}"))
}

/// Name of agent `agent`'s observation service.
pub fn observation_service_name(agent: usize) -> String {
    format!("formation/agent/{agent}/observation")
}

/// Name of the event that wakes agent `agent` when its observation is ready.
pub fn observation_event_name(agent: usize) -> String {
    format!("formation/agent/{agent}/observation_ready")
}

/// Name of agent `agent`'s command service.
pub fn command_service_name(agent: usize) -> String {
    format!("formation/agent/{agent}/command")
}

/// Name of the event agents raise (event id = agent index) when a command is sent.
pub fn command_event_name() -> String {
    "formation/command_ready".into()
}

/// Name of the true-state service.
pub fn state_service_name() -> String {
    "formation/state".into()
}

/// Name of the event that wakes the critic to drain its subscribers.
pub fn critic_wake_event_name() -> String {
    "formation/critic/wake".into()
}

/// Name of the critic's progress service (flow control).
pub fn critic_progress_service_name() -> String {
    "formation/critic/progress".into()
}

/// Name of the event raised when the critic's progress changes.
pub fn critic_progress_event_name() -> String {
    "formation/critic/progress_ready".into()
}

/// Name of actor `actor_index`'s weights service.
pub fn weights_service_name(actor_index: usize) -> String {
    format!("formation/actor/{actor_index}/weights")
}

/// Sizes of the run's services, derived from the swarm size, and the contract every service
/// carries as iceoryx2 attributes.
#[derive(Debug, Clone, Copy)]
pub struct Sizing {
    /// Robots in the swarm.
    pub n_agents: usize,
    /// Samples a subscriber may hold before the oldest is overwritten.
    pub stream_buffer: usize,
    /// Floats per observation of the run's observation model.
    pub observation_dim: usize,
}

/// Attribute keys of every service of a run: a process of another protocol version, swarm
/// size or observation model fails when it opens a port, naming what differs.
pub const CONTRACT_KEYS: [&str; 3] = [
    "formation.protocol_version",
    "formation.n_agents",
    "formation.observation_dim",
];

impl Sizing {
    /// Sizing for `n_agents` robots with the critic allowed `critic_window` ticks behind and
    /// observations of `observation_dim` floats.
    pub fn new(n_agents: usize, critic_window: u32, observation_dim: usize) -> Self {
        Self {
            n_agents,
            stream_buffer: 2 * critic_window as usize + 16,
            observation_dim,
        }
    }

    /// The attributes every service of the run is created with and checked against.
    pub fn contract(&self) -> Result<AttributeVerifier> {
        let values = [
            crate::wire::PROTOCOL_VERSION.to_string(),
            self.n_agents.to_string(),
            self.observation_dim.to_string(),
        ];
        let mut verifier = AttributeVerifier::new();
        for (key, value) in CONTRACT_KEYS.iter().zip(values) {
            let key = AttributeKey::try_from(*key).map_err(|err| anyhow::anyhow!("attribute key {key}: {err:?}"))?;
            let value = AttributeValue::try_from(value.as_str())
                .map_err(|err| anyhow::anyhow!("attribute value {value}: {err:?}"))?;
            verifier = verifier
                .require(&key, &value)
                .map_err(|err| anyhow::anyhow!("attribute {key:?}: {err:?}"))?;
        }
        Ok(verifier)
    }

    /// What a port that fails to open with incompatible attributes is told.
    fn mismatch_hint(&self) -> String {
        format!(
            "this process speaks protocol {}, {} robots, observations of {} floats; every process of a run needs the same build, --agents and --config",
            crate::wire::PROTOCOL_VERSION,
            self.n_agents,
            self.observation_dim
        )
    }

    fn shared_nodes(&self) -> usize {
        self.n_agents + 2 + SPARE_PORTS
    }
}

/// Port factory of a fixed-size payload.
pub type Stream<S, T> = publish_subscribe::PortFactory<S, T, ()>;
/// Port factory of actor weights.
pub type WeightsStream<S> = publish_subscribe::PortFactory<S, [f32], WeightsHeader>;
/// Port factory of an event.
pub type Event<S> = event::PortFactory<S>;

/// How long opening a service waits for another process that is still creating it.
const OPEN_PATIENCE: std::time::Duration = std::time::Duration::from_secs(10);

/// Opens (or creates) a service, retrying while iceoryx2 reports that another process is still
/// creating it: with dozens of processes starting at once on a loaded machine, a creation can
/// take longer than iceoryx2's own wait, and giving up then would fail the whole run.
fn open_patiently<T, E: std::fmt::Debug>(
    mut open: impl FnMut() -> std::result::Result<T, E>,
    in_creation: impl Fn(&E) -> bool,
) -> std::result::Result<T, E> {
    let started = std::time::Instant::now();
    loop {
        match open() {
            Err(err) if in_creation(&err) && started.elapsed() < OPEN_PATIENCE => {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            result => return result,
        }
    }
}

fn publish_subscribe_in_creation(err: &PublishSubscribeOpenOrCreateError) -> bool {
    matches!(
        err,
        PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(PublishSubscribeOpenError::HangsInCreation)
            | PublishSubscribeOpenOrCreateError::SystemInFlux
    )
}

fn stream<S: Service, T>(
    node: &Node<S>,
    name: &str,
    sizing: &Sizing,
    history: usize,
    max_nodes: usize,
) -> Result<Stream<S, T>>
where
    T: std::fmt::Debug + ZeroCopySend + Copy + 'static,
{
    let service = service_name(name)?;
    let contract = sizing.contract()?;
    open_patiently(
        || {
            node.service_builder(&service)
                .publish_subscribe::<T>()
                .max_publishers(1 + SPARE_PORTS)
                .max_subscribers(2 + SPARE_PORTS)
                .max_nodes(max_nodes)
                .history_size(history)
                .subscriber_max_buffer_size(sizing.stream_buffer.max(history))
                .open_or_create_with_attributes(&contract)
        },
        publish_subscribe_in_creation,
    )
    .with_context(|| format!("cannot open service {name} ({})", sizing.mismatch_hint()))
}

fn event_service<S: Service>(node: &Node<S>, name: &str, sizing: &Sizing, notifiers: usize) -> Result<Event<S>> {
    let service = service_name(name)?;
    let contract = sizing.contract()?;
    open_patiently(
        || {
            node.service_builder(&service)
                .event()
                .max_notifiers(notifiers + SPARE_PORTS)
                .max_listeners(1 + SPARE_PORTS)
                .max_nodes(sizing.shared_nodes())
                .event_id_max_value(MAX_AGENTS)
                .open_or_create_with_attributes(&contract)
        },
        |err| {
            matches!(
                err,
                EventOpenOrCreateError::EventOpenError(EventOpenError::HangsInCreation)
                    | EventOpenOrCreateError::SystemInFlux
            )
        },
    )
    .with_context(|| format!("cannot open event {name} ({})", sizing.mismatch_hint()))
}

/// Observation stream of one agent.
pub fn observation_stream<S: Service>(
    node: &Node<S>,
    sizing: &Sizing,
    agent: usize,
) -> Result<Stream<S, ObservationMsg>> {
    stream(node, &observation_service_name(agent), sizing, 0, 2 + SPARE_PORTS)
}

/// Event that wakes one agent.
pub fn observation_event<S: Service>(node: &Node<S>, sizing: &Sizing, agent: usize) -> Result<Event<S>> {
    event_service(node, &observation_event_name(agent), sizing, 1)
}

/// Command stream of one agent. History 1: the sim sees an agent's greeting even when the
/// agent started first.
pub fn command_stream<S: Service>(node: &Node<S>, sizing: &Sizing, agent: usize) -> Result<Stream<S, CommandMsg>> {
    stream(node, &command_service_name(agent), sizing, 1, 2 + SPARE_PORTS)
}

/// Event every agent raises after sending a command.
pub fn command_event<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Event<S>> {
    event_service(node, &command_event_name(), sizing, sizing.n_agents)
}

/// True-state stream.
pub fn state_stream<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Stream<S, StateMsg>> {
    stream(node, &state_service_name(), sizing, 0, sizing.shared_nodes())
}

/// Event that wakes the critic.
pub fn critic_wake_event<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Event<S>> {
    event_service(node, &critic_wake_event_name(), sizing, 1)
}

/// The critic's progress (history 1: the sim sees the latest at once).
pub fn critic_progress_stream<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Stream<S, CriticProgressMsg>> {
    stream(node, &critic_progress_service_name(), sizing, 1, sizing.shared_nodes())
}

/// Event raised when the critic's progress changes.
pub fn critic_progress_event<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Event<S>> {
    event_service(node, &critic_progress_event_name(), sizing, 1)
}

/// Weights of one actor (history 1: a restarted agent gets the latest at once).
pub fn weights_stream<S: Service>(node: &Node<S>, sizing: &Sizing, actor_index: usize) -> Result<WeightsStream<S>> {
    let name = weights_service_name(actor_index);
    let service = service_name(&name)?;
    let contract = sizing.contract()?;
    open_patiently(
        || {
            node.service_builder(&service)
                .publish_subscribe::<[f32]>()
                .user_header::<WeightsHeader>()
                .max_publishers(1 + SPARE_PORTS)
                .max_subscribers(sizing.n_agents + SPARE_PORTS)
                .max_nodes(sizing.shared_nodes())
                .history_size(1)
                .subscriber_max_buffer_size(2)
                .open_or_create_with_attributes(&contract)
        },
        publish_subscribe_in_creation,
    )
    .with_context(|| format!("cannot open weights service {name} ({})", sizing.mismatch_hint()))
}

/// Blocks until `listener` is notified or `timeout` passes. A signal arriving meanwhile counts
/// as a wake-up: the caller then checks [`crate::termination_requested`].
pub fn wait_for_event<S: Service>(listener: &Listener<S>, timeout: std::time::Duration) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    wait_for_events(listener, timeout, |_| {})
}

/// As [`wait_for_event`], handing every event id that arrived to `seen` (once per id, however
/// often it was notified).
///
/// Waits in `ppoll(2)` on the listener's socket, then takes the events without blocking: two or
/// three system calls a wait, where iceoryx2's own `timed_wait` makes seven (it switches the socket
/// between blocking and non-blocking each time). No wake-up is lost: a notifier marks its id
/// before it sends, and sends unless a datagram is already waiting.
pub fn wait_for_events<S: Service>(
    listener: &Listener<S>,
    timeout: std::time::Duration,
    mut seen: impl FnMut(usize),
) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    let mut socket = [libc::pollfd {
        // SAFETY: only polled; the listener keeps owning the descriptor.
        fd: unsafe { listener.file_descriptor().native_handle() },
        events: libc::POLLIN,
        revents: 0,
    }];
    poll(&mut socket, timeout)?;
    take_events(listener, &mut seen)
}

/// Blocks until any of `listeners` is notified or `timeout` passes, and takes every event
/// waiting (a critic serving several swarms waits on all their sims at once).
pub fn wait_for_any_event<S: Service>(listeners: &[&Listener<S>], timeout: std::time::Duration) -> Result<()>
where
    Listener<S>: FileDescriptorBased,
{
    let mut sockets: Vec<libc::pollfd> = listeners
        .iter()
        .map(|listener| libc::pollfd {
            // SAFETY: only polled; the listener keeps owning the descriptor.
            fd: unsafe { listener.file_descriptor().native_handle() },
            events: libc::POLLIN,
            revents: 0,
        })
        .collect();
    poll(&mut sockets, timeout)?;
    for listener in listeners {
        take_events(listener, &mut |_| {})?;
    }
    Ok(())
}

fn poll(sockets: &mut [libc::pollfd], timeout: std::time::Duration) -> Result<()> {
    let timeout = libc::timespec {
        tv_sec: timeout.as_secs().min(i64::MAX as u64) as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    // SAFETY: valid pollfds, a valid timespec, no signal mask.
    let ready = unsafe {
        libc::ppoll(
            sockets.as_mut_ptr(),
            sockets.len() as libc::nfds_t,
            &timeout,
            std::ptr::null(),
        )
    };
    if ready < 0 {
        let err = std::io::Error::last_os_error();
        if err.kind() != std::io::ErrorKind::Interrupted {
            bail!("waiting on an iceoryx2 event failed: {err}");
        }
    }
    Ok(())
}

fn take_events<S: Service>(listener: &Listener<S>, seen: &mut impl FnMut(usize)) -> Result<()> {
    match listener.try_wait(|activation| seen(activation.id.as_value())) {
        Ok(_) | Err(ListenerWaitError::InterruptSignal) => Ok(()),
        Err(err) => Err(anyhow::anyhow!("taking iceoryx2 events failed: {err:?}")),
    }
}

/// True while a live process of the run holds a node named `name` (tells a silent peer from a
/// dead one: iceoryx2 marks the node of a process that died as dead, and a clean exit removes it).
pub fn node_alive<S: Service>(identity: &RunIdentity, name: &str) -> Result<bool> {
    let config = identity.iceoryx_config()?;
    let mut alive = false;
    Node::<S>::list(&config, |state| {
        if let NodeState::Alive(view) = &state
            && view.details().as_ref().is_some_and(|d| d.name().as_str() == name)
        {
            alive = true;
            return CallbackProgression::Stop;
        }
        CallbackProgression::Continue
    })
    .context("cannot list the run's iceoryx2 nodes")?;
    Ok(alive)
}

/// Tells a sim that has gone from one that is silent but alive: a sim waiting for a slow critic,
/// or stalled by a loaded machine, still holds a live iceoryx2 node; a killed one does not.
#[derive(Debug)]
pub struct SimWatch {
    silence: std::time::Duration,
    startup: std::time::Duration,
    last_heard: std::time::Instant,
    heard_any: bool,
    warned: bool,
}

impl SimWatch {
    /// A watch that starts worrying after `silence` and gives a live sim up to `startup` (the
    /// same limit it has to start).
    pub fn new(silence: std::time::Duration, startup: std::time::Duration) -> Self {
        Self {
            silence,
            startup,
            last_heard: std::time::Instant::now(),
            heard_any: false,
            warned: false,
        }
    }

    /// The sim was just heard from.
    pub fn heard(&mut self) {
        self.last_heard = std::time::Instant::now();
        self.heard_any = true;
        self.warned = false;
    }

    /// True once anything was heard.
    pub fn heard_any(&self) -> bool {
        self.heard_any
    }

    /// `Some(silence)` when the sim is to be given up: silent past `silence` and its process
    /// gone, or silent past `startup` whatever its state. `who` names the caller in the one
    /// warning printed while a live sim is waited for.
    pub fn gone<S: Service>(&mut self, identity: &RunIdentity, who: &str) -> Result<Option<std::time::Duration>> {
        let quiet = self.last_heard.elapsed();
        let gone = if !self.heard_any || quiet <= self.silence {
            quiet > self.startup
        } else if quiet > self.startup || !node_alive::<S>(identity, "sim")? {
            true
        } else {
            if !self.warned {
                self.warned = true;
                eprintln!(
                    "{who}: the sim has been silent for {:.1} s but its process is alive; waiting up to {} s",
                    quiet.as_secs_f64(),
                    self.startup.as_secs()
                );
            }
            false
        };
        Ok(gone.then_some(quiet))
    }
}

/// Converts an agent index into its event id.
pub fn agent_event_id(agent: usize) -> EventId {
    EventId::new(agent)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_process_of_another_swarm_size_or_observation_model_cannot_open_the_runs_services() {
        let identity = RunIdentity::new(&format!("contract{}", std::process::id())).expect("id");
        let node = create_node::<local::Service>(&identity, "sim").expect("node");
        let run = Sizing::new(3, 8, 12);
        let _state = state_stream(&node, &run).expect("created");
        let _ready = command_event(&node, &run).expect("created");
        let _same = state_stream(&node, &run).expect("the same contract opens");
        for other in [Sizing::new(4, 8, 12), Sizing::new(3, 8, 16)] {
            let err = state_stream(&node, &other).expect_err("another contract");
            let text = format!("{err:#}");
            assert!(text.contains("IncompatibleAttributes"), "{text}");
            assert!(text.contains("same build, --agents and --config"), "{text}");
            assert!(command_event(&node, &other).is_err());
        }
        let contract = run.contract().expect("contract");
        assert_eq!(
            contract.required_attributes().number_of_attributes(),
            CONTRACT_KEYS.len()
        );
    }

    #[test]
    fn the_iceoryx_config_file_reads_back_as_the_runs_config() {
        let identity = RunIdentity::new("cfgfile-test").expect("id");
        let dir = std::env::temp_dir().join(format!("formation-iox2-config-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = identity.write_iceoryx_config(&dir).expect("write");
        let file = FilePath::new(path.to_str().expect("utf8").as_bytes()).expect("file path");
        let read = Config::from_file(&file).expect("iceoryx2 reads the file");
        assert_eq!(read, identity.iceoryx_config().expect("config"));
        assert_eq!(read.global.prefix.as_bytes(), b"fc_cfgfile-test_");
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }
}
