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
use iceoryx2::service::builder::event::{EventCreateError, EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{
    PublishSubscribeCreateError, PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::builder::request_response::{
    RequestResponseCreateError, RequestResponseOpenError, RequestResponseOpenOrCreateError,
};
use iceoryx2::service::port_factory::{event, publish_subscribe, request_response};

/// What [`wait_for_events`] needs of a listener: a socket to poll (every iceoryx2 service type
/// has one). Generic code over the service type names it in a `where` clause.
pub use iceoryx2_bb_posix::file_descriptor::FileDescriptorBased;

use formation_protocol::MAX_AGENTS;
use formation_protocol::wire::{
    CommandMsg, ControlReply, ControlRequest, CriticProgressMsg, Header, ObservationMsg, ObstaclesMsg,
    PROTOCOL_VERSION, StateMsg, TruthMsg, WeightsHeader,
};

pub use formation_protocol::SPARE_PORTS;

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
        formation_core::run_dir::write_atomically(&path, text.as_bytes())?;
        Ok(path)
    }

    /// Removes what a finished run leaves behind: its `/dev/shm` files (the launcher's lock
    /// file last, so that a run with files left always has its lock file) and its root path.
    /// Returns how many shared-memory files were removed.
    pub fn remove_leftovers(&self) -> usize {
        self.remove_leftovers_in(std::path::Path::new(SHM_DIR))
    }

    fn remove_leftovers_in(&self, shm_dir: &std::path::Path) -> usize {
        let prefix = self.shm_prefix();
        let lock = self.launcher_lock_in(shm_dir);
        let mut removed = 0;
        if let Ok(entries) = std::fs::read_dir(shm_dir) {
            for entry in entries.flatten() {
                if entry.file_name().to_string_lossy().starts_with(&prefix)
                    && entry.path() != lock
                    && std::fs::remove_file(entry.path()).is_ok()
                {
                    removed += 1;
                }
            }
        }
        if std::fs::remove_file(&lock).is_ok() {
            removed += 1;
        }
        let _ignored_if_absent = std::fs::remove_dir_all(self.root_path());
        removed
    }

    /// The lock file a live launcher of this run holds: `/dev/shm/<shm prefix>launcher.lock`.
    pub fn launcher_lock_path(&self) -> PathBuf {
        self.launcher_lock_in(std::path::Path::new(SHM_DIR))
    }

    fn launcher_lock_in(&self, shm_dir: &std::path::Path) -> PathBuf {
        shm_dir.join(format!("{}{LAUNCHER_LOCK}", self.shm_prefix()))
    }

    /// Takes this run's launcher lock (an exclusive `flock` on [`Self::launcher_lock_path`]),
    /// held until the returned guard drops or the launcher dies, however it dies. The lock, not
    /// a pid, is what tells another launcher (or a Python client) that the run is alive: a pid
    /// means nothing to a process in another PID namespace that shares `/dev/shm`.
    pub fn hold_launcher_lock(&self) -> Result<LauncherLock> {
        self.hold_launcher_lock_in(std::path::Path::new(SHM_DIR))
    }

    /// The file a client of the run (a Python env) holds a shared `flock` on while it has ports
    /// open: `/dev/shm/<shm prefix>clients.lock`, made with the launcher's lock.
    pub fn clients_lock_path(&self) -> PathBuf {
        std::path::Path::new(SHM_DIR).join(format!("{}{CLIENTS_LOCK}", self.shm_prefix()))
    }

    /// Waits, at most `patience`, until no client holds the run's clients lock (it has closed
    /// its ports): at the run's end, before [`Self::remove_leftovers`], so that a client whose
    /// ports outlive the sim removes those services itself instead of finding their files
    /// gone. Returns false if a client still held it.
    pub fn wait_for_clients(&self, patience: std::time::Duration) -> bool {
        let Ok(file) = std::fs::File::open(self.clients_lock_path()) else {
            return true;
        };
        if try_flock(&file).unwrap_or(true) {
            return true;
        }
        // flock(2) has no timeout: a thread waits in it; the channel's timeout bounds the wait.
        let (done, finished) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            use std::os::fd::AsRawFd;
            // SAFETY: flock(2) on a descriptor that `file`, moved here, owns.
            let _ = done.send(unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX) } == 0);
        });
        finished.recv_timeout(patience).unwrap_or(false)
    }

    fn hold_launcher_lock_in(&self, shm_dir: &std::path::Path) -> Result<LauncherLock> {
        use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
        let path = self.launcher_lock_in(shm_dir);
        let started = std::time::Instant::now();
        loop {
            let file = std::fs::OpenOptions::new()
                .create(true)
                .truncate(false)
                .read(true)
                .write(true)
                .mode(0o644)
                .open(&path)
                .with_context(|| format!("cannot create {}", path.display()))?;
            if !try_flock(&file)? {
                // A sweep that saw the new file before this lock may hold it for a moment;
                // a live launcher of the same run id holds it for good.
                anyhow::ensure!(
                    started.elapsed() < LOCK_PATIENCE,
                    "{} is held by another live launcher of run {}",
                    path.display(),
                    self.run_id
                );
                std::thread::sleep(std::time::Duration::from_millis(20));
                continue;
            }
            // Such a sweep removes the file it locked: then lock the one that is there now.
            let held = file.metadata()?;
            if std::fs::metadata(&path).is_ok_and(|now| now.dev() == held.dev() && now.ino() == held.ino()) {
                // The clients' file comes after the lock: a run with files has its lock file.
                let clients = shm_dir.join(format!("{}{CLIENTS_LOCK}", self.shm_prefix()));
                let lock = LauncherLock { file, path, clients };
                std::fs::OpenOptions::new()
                    .create(true)
                    .truncate(false)
                    .write(true)
                    .mode(0o644)
                    .open(&lock.clients)
                    .with_context(|| format!("cannot create {}", lock.clients.display()))?;
                return Ok(lock);
            }
        }
    }
}

/// Suffix (after the run's shm prefix) of the lock file a live launcher holds.
const LAUNCHER_LOCK: &str = "launcher.lock";
/// Suffix of the file clients hold a shared lock on while their ports are open.
const CLIENTS_LOCK: &str = "clients.lock";
/// How long taking a launcher lock waits for a sweep that holds it for a moment.
const LOCK_PATIENCE: std::time::Duration = std::time::Duration::from_secs(2);

/// A live launcher's hold on its run (from [`RunIdentity::hold_launcher_lock`]): dropped, it
/// removes its file and the clients' (if the run's clean-up has not already); the kernel
/// releases the lock when the launcher is killed.
#[derive(Debug)]
pub struct LauncherLock {
    file: std::fs::File,
    path: PathBuf,
    clients: PathBuf,
}

impl Drop for LauncherLock {
    fn drop(&mut self) {
        use std::os::unix::fs::MetadataExt;
        // Only the file this guard locked (still locked: nobody else can have replaced it).
        let ours = self.file.metadata().ok().map(|m| (m.dev(), m.ino()));
        if std::fs::metadata(&self.path).ok().map(|m| (m.dev(), m.ino())) == ours && ours.is_some() {
            let _ignored_if_absent = std::fs::remove_file(&self.clients);
            let _ignored_if_absent = std::fs::remove_file(&self.path);
        }
    }
}

/// Takes an exclusive `flock` on `file` without waiting: false while someone else holds it.
fn try_flock(file: &std::fs::File) -> Result<bool> {
    use std::os::fd::AsRawFd;
    // SAFETY: flock(2) on a descriptor that `file` owns for the duration of the call.
    if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
        return Ok(true);
    }
    let err = std::io::Error::last_os_error();
    if err.kind() == std::io::ErrorKind::WouldBlock {
        return Ok(false);
    }
    Err(err).context("flock")
}

/// Refuses a message from the sim of another protocol version: `receiver` names the process
/// in the error (e.g. "agent 3"), `kind` what it is ("agent", "critic").
pub fn check_sim_protocol(header: &Header, receiver: &str, kind: &str) -> Result<()> {
    if header.protocol_version != PROTOCOL_VERSION {
        bail!(
            "{receiver}: the sim speaks protocol {}, this {kind} {PROTOCOL_VERSION}: rebuild all binaries together",
            header.protocol_version
        );
    }
    Ok(())
}

/// Removes the shared memory and root path of every run whose launcher is gone: its lock file
/// is in `/dev/shm` and nobody holds it (a launcher killed outright cannot clean up after
/// itself; its members died with it). The lock is held while the files go, so a launcher that
/// is alive, in this PID namespace or another sharing `/dev/shm`, is never swept. Runs with
/// no lock file (not started by a launcher) are left alone. Returns each swept run with the
/// number of files removed.
pub fn sweep_abandoned_runs() -> Vec<(String, usize)> {
    sweep_abandoned_runs_in(std::path::Path::new(SHM_DIR))
}

fn sweep_abandoned_runs_in(shm_dir: &std::path::Path) -> Vec<(String, usize)> {
    let lock_suffix = format!("_{LAUNCHER_LOCK}");
    let mut run_ids: Vec<String> = std::fs::read_dir(shm_dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| {
            let name = entry.file_name().to_string_lossy().into_owned();
            Some(name.strip_prefix("fc_")?.strip_suffix(&lock_suffix)?.to_string())
        })
        .collect();
    run_ids.sort();
    run_ids
        .into_iter()
        .filter_map(|run_id| {
            let identity = RunIdentity::new(&run_id).ok()?;
            let file = std::fs::File::open(identity.launcher_lock_in(shm_dir)).ok()?;
            // Held: the launcher lives. Taken: it is gone, and no new one can take it meanwhile.
            try_flock(&file).ok()?.then_some(())?;
            let removed = identity.remove_leftovers_in(shm_dir);
            drop(file);
            Some((run_id, removed))
        })
        .collect()
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

/// Name of the true-pose service the privileged planners read.
pub fn truth_service_name() -> String {
    "formation/truth".into()
}

/// Name of the episode's obstacles service.
pub fn obstacles_service_name() -> String {
    "formation/obstacles".into()
}

/// Name of the event that wakes the critic to drain its subscribers.
pub fn critic_wake_event_name() -> String {
    "formation/critic/wake".into()
}

/// A reader of the state stream that the sim's flow control waits for: the sim never runs more
/// than `ticks.critic_window` states ahead of what each one it expects has acknowledged.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamReader {
    /// The critic/replay process.
    Critic,
    /// The MCAP recorder (`--record mcap`).
    Recorder,
}

impl StreamReader {
    /// Who it is, for messages.
    pub fn name(self) -> &'static str {
        match self {
            StreamReader::Critic => "the critic",
            StreamReader::Recorder => "the MCAP recorder",
        }
    }

    fn service_dir(self) -> &'static str {
        match self {
            StreamReader::Critic => "critic",
            StreamReader::Recorder => "recorder",
        }
    }

    /// Name of its progress service (flow control).
    pub fn progress_service_name(self) -> String {
        format!("formation/{}/progress", self.service_dir())
    }

    /// Name of the event raised when its progress changes.
    pub fn progress_event_name(self) -> String {
        format!("formation/{}/progress_ready", self.service_dir())
    }
}

/// Name of actor `actor_index`'s weights service.
pub fn weights_service_name(actor_index: usize) -> String {
    format!("formation/actor/{actor_index}/weights")
}

/// Name of the live control service (request-response: [`ControlRequest`] -> [`ControlReply`]).
pub fn control_service_name() -> String {
    "formation/control".into()
}

/// Name of the event the sim raises after a tick on which it answered control requests.
pub fn control_answered_event_name() -> String {
    "formation/control/answered".into()
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
            formation_protocol::wire::PROTOCOL_VERSION.to_string(),
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
            formation_protocol::wire::PROTOCOL_VERSION,
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
/// Port factory of the live control service.
pub type Control<S> = request_response::PortFactory<S, ControlRequest, (), ControlReply, ()>;

/// How long opening a service waits for another process that is still creating it.
const OPEN_PATIENCE: std::time::Duration = std::time::Duration::from_secs(10);

/// Opens (or creates) a service, retrying while iceoryx2 reports that another process is still
/// creating it (or that the service came or went during the call: `DoesNotExist` from an open or
/// create, as when another process removed an abandoned creation meanwhile): with dozens of processes starting at once on a loaded machine, a creation can
/// take longer than iceoryx2's own wait, and giving up then would fail the whole run.
///
/// A service whose creator was killed mid-creation stays "in creation" for good (iceoryx2 0.10
/// cleans up only the finished services of a dead node): before each retry the abandoned
/// creations of the node's run are removed ([`remove_abandoned_creations`]), so the next open
/// creates the service afresh instead of failing the run with `HangsInCreation`.
fn open_patiently<S: Service, T, E: std::fmt::Debug>(
    node: &Node<S>,
    mut open: impl FnMut() -> std::result::Result<T, E>,
    in_creation: impl Fn(&E) -> bool,
) -> std::result::Result<T, E> {
    let started = std::time::Instant::now();
    loop {
        match open() {
            Err(err) if in_creation(&err) && started.elapsed() < OPEN_PATIENCE => {
                let removed = remove_abandoned_creations::<S>(node.config());
                if removed > 0 {
                    eprintln!(
                        "removed {removed} iceoryx2 service(s) left in creation by a process killed while creating them"
                    );
                } else {
                    std::thread::sleep(std::time::Duration::from_millis(50));
                }
            }
            result => return result,
        }
    }
}

/// Removes the static descriptions of services of `config`'s run that a dead process left "in
/// creation"; returns how many.
///
/// iceoryx2 0.10 creates a service in this order: the creator's *service tag* (a file in its
/// node's directory), then the service's static description, still owner-writable (0600, "in
/// creation"), which it makes read-only once written. A creator killed in between leaves the
/// description in creation; the dead node's clean-up (run first here) removes its tag but not
/// the description ("Trying to remove node ... from non-existing service"), and every later
/// open of the service fails with `HangsInCreation`. A description in creation whose service
/// no node tags any more has no live creator (a live one tagged it before creating it): it is
/// removed. Services of the in-process `local` type have no such files: nothing happens.
pub fn remove_abandoned_creations<S: Service>(config: &Config) -> usize {
    // Dead nodes first: a dead creator's tag goes with its node.
    let _listed = Node::<S>::list(config, |state| {
        if let NodeState::Dead(view) = state {
            let _best_effort = view.blocking_remove_stale_resources(config.global.creation_timeout);
        }
        CallbackProgression::Continue
    });
    let text = |path: &Path| String::from_utf8_lossy(path.as_bytes()).into_owned();
    let prefix = String::from_utf8_lossy(config.global.prefix.as_bytes()).into_owned();
    let service_suffix =
        String::from_utf8_lossy(config.global.service.static_config_storage_suffix.as_bytes()).into_owned();
    let tag_suffix = String::from_utf8_lossy(config.global.node.service_tag_suffix.as_bytes()).into_owned();
    remove_abandoned_creations_in(
        std::path::Path::new(&text(&config.global.service_dir())),
        std::path::Path::new(&text(&config.global.node_dir())),
        &prefix,
        &service_suffix,
        &tag_suffix,
    )
}

/// Mode of a static service description that is still being written (iceoryx2-cal's file
/// static storage, `INIT_PERMISSIONS`).
const IN_CREATION_MODE: u32 = 0o600;

fn remove_abandoned_creations_in(
    service_dir: &std::path::Path,
    node_dir: &std::path::Path,
    prefix: &str,
    service_suffix: &str,
    tag_suffix: &str,
) -> usize {
    use std::os::unix::fs::PermissionsExt;
    let Ok(entries) = std::fs::read_dir(service_dir) else {
        return 0;
    };
    let mut removed = 0;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(hash) = name
            .strip_prefix(prefix)
            .and_then(|rest| rest.strip_suffix(service_suffix))
        else {
            continue;
        };
        let in_creation = entry
            .metadata()
            .is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o777 == IN_CREATION_MODE);
        if !in_creation {
            continue;
        }
        let tag = format!("{prefix}{hash}{tag_suffix}");
        let tagged = std::fs::read_dir(node_dir)
            .into_iter()
            .flatten()
            .flatten()
            .any(|node| node.path().join(&tag).exists());
        // Looked at again: a creator that finished meanwhile made it read-only.
        let still = std::fs::metadata(entry.path()).is_ok_and(|m| m.permissions().mode() & 0o777 == IN_CREATION_MODE);
        if !tagged && still && std::fs::remove_file(entry.path()).is_ok() {
            removed += 1;
        }
    }
    removed
}

fn publish_subscribe_in_creation(err: &PublishSubscribeOpenOrCreateError) -> bool {
    matches!(
        err,
        PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(
            PublishSubscribeOpenError::HangsInCreation | PublishSubscribeOpenError::DoesNotExist
        ) | PublishSubscribeOpenOrCreateError::PublishSubscribeCreateError(
            PublishSubscribeCreateError::AlreadyExists
                | PublishSubscribeCreateError::IsBeingCreatedByAnotherInstance
                | PublishSubscribeCreateError::HangsInCreation
        ) | PublishSubscribeOpenOrCreateError::SystemInFlux
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
    let buffer = sizing.stream_buffer.max(history);
    stream_for(node, name, sizing, (history, buffer), 2, max_nodes)
}

/// A stream with `readers` subscribers besides the spares, a history of `history.0` samples
/// and subscribers that hold at most `history.1`.
fn stream_for<S: Service, T>(
    node: &Node<S>,
    name: &str,
    sizing: &Sizing,
    (history, buffer): (usize, usize),
    readers: usize,
    max_nodes: usize,
) -> Result<Stream<S, T>>
where
    T: std::fmt::Debug + ZeroCopySend + Copy + 'static,
{
    let service = service_name(name)?;
    let contract = sizing.contract()?;
    open_patiently(
        node,
        || {
            node.service_builder(&service)
                .publish_subscribe::<T>()
                .max_publishers(1 + SPARE_PORTS)
                .max_subscribers(readers + SPARE_PORTS)
                .max_nodes(max_nodes)
                .history_size(history)
                .subscriber_max_buffer_size(buffer)
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
        node,
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
                EventOpenOrCreateError::EventOpenError(EventOpenError::HangsInCreation | EventOpenError::DoesNotExist)
                    | EventOpenOrCreateError::EventCreateError(
                        EventCreateError::AlreadyExists | EventCreateError::IsBeingCreatedByAnotherInstance
                    )
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

/// The true poses every tick, for privileged planners (one subscriber per robot at most, the
/// view and spares; history 1: a restarted planner sees the tick at once).
pub fn truth_stream<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Stream<S, TruthMsg>> {
    let readers = sizing.n_agents + 2 + SPARE_PORTS;
    stream_for(
        node,
        &truth_service_name(),
        sizing,
        (1, 2),
        readers,
        sizing.shared_nodes(),
    )
}

/// The episode's obstacles, once per episode (history 1: a process that joins mid-episode gets
/// them at once; every robot, the critic, the view and spares may read).
pub fn obstacles_stream<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Stream<S, ObstaclesMsg>> {
    let readers = sizing.n_agents + 2 + SPARE_PORTS;
    stream_for(
        node,
        &obstacles_service_name(),
        sizing,
        (1, 2),
        readers,
        sizing.shared_nodes(),
    )
}

/// Event that wakes the critic.
pub fn critic_wake_event<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Event<S>> {
    event_service(node, &critic_wake_event_name(), sizing, 1)
}

/// A reader's progress (history 1: the sim sees the latest at once). The recorder sends the
/// critic's message with `weights_version` and `updates` 0.
pub fn progress_stream<S: Service>(
    node: &Node<S>,
    sizing: &Sizing,
    reader: StreamReader,
) -> Result<Stream<S, CriticProgressMsg>> {
    stream(node, &reader.progress_service_name(), sizing, 1, sizing.shared_nodes())
}

/// Event raised when a reader's progress changes.
pub fn progress_event<S: Service>(node: &Node<S>, sizing: &Sizing, reader: StreamReader) -> Result<Event<S>> {
    event_service(node, &reader.progress_event_name(), sizing, 1)
}

/// A reader's side of the sim's flow control: how far it has read the state stream, and the
/// event that wakes a sim waiting for it.
pub struct ProgressPublisher<S: Service> {
    reader: StreamReader,
    publisher: iceoryx2::port::publisher::Publisher<S, CriticProgressMsg, ()>,
    ready: iceoryx2::port::notifier::Notifier<S>,
    /// Not from a seeded generator: a restarted reader must differ from the one it replaces.
    session: u64,
}

impl<S: Service> ProgressPublisher<S> {
    /// Opens `reader`'s progress service and event.
    pub fn open(node: &Node<S>, sizing: &Sizing, reader: StreamReader) -> Result<Self> {
        Ok(Self {
            reader,
            publisher: progress_stream(node, sizing, reader)?
                .publisher_builder()
                .create()
                .with_context(|| format!("{}: progress publisher", reader.name()))?,
            ready: progress_event(node, sizing, reader)?
                .notifier_builder()
                .create()
                .with_context(|| format!("{}: progress notifier", reader.name()))?,
            session: rand::random_range(1..u64::MAX),
        })
    }

    /// Tells the sim every state up to `acknowledged_sequence` is read (the critic adds its
    /// weights version and updates; the recorder sends 0).
    pub fn publish(&self, acknowledged_sequence: u64, weights_version: u32, updates: u64) -> Result<()> {
        self.publisher
            .send_copy(CriticProgressMsg {
                protocol_version: PROTOCOL_VERSION,
                weights_version,
                acknowledged_sequence,
                updates,
                session: self.session,
            })
            .with_context(|| format!("{}: progress", self.reader.name()))?;
        self.ready
            .notify()
            .with_context(|| format!("{}: progress notify", self.reader.name()))?;
        Ok(())
    }
}

/// Weights of one actor (history 1: a restarted agent gets the latest at once).
pub fn weights_stream<S: Service>(node: &Node<S>, sizing: &Sizing, actor_index: usize) -> Result<WeightsStream<S>> {
    let name = weights_service_name(actor_index);
    let service = service_name(&name)?;
    let contract = sizing.contract()?;
    open_patiently(
        node,
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

/// The live control service: the sim is its one server; clients (at most [`SPARE_PORTS`])
/// each keep a few requests in flight.
pub fn control_service<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Control<S>> {
    let name = control_service_name();
    let service = service_name(&name)?;
    let contract = sizing.contract()?;
    open_patiently(
        node,
        || {
            node.service_builder(&service)
                .request_response::<ControlRequest, ControlReply>()
                .max_servers(1)
                .max_clients(SPARE_PORTS)
                .max_nodes(sizing.shared_nodes())
                .max_active_requests_per_client(CONTROL_REQUESTS_IN_FLIGHT)
                .max_response_buffer_size(CONTROL_REQUESTS_IN_FLIGHT)
                .open_or_create_with_attributes(&contract)
        },
        |err| {
            matches!(
                err,
                RequestResponseOpenOrCreateError::RequestResponseOpenError(
                    RequestResponseOpenError::HangsInCreation | RequestResponseOpenError::DoesNotExist
                ) | RequestResponseOpenOrCreateError::RequestResponseCreateError(
                    RequestResponseCreateError::AlreadyExists
                        | RequestResponseCreateError::IsBeingCreatedByAnotherInstance
                        | RequestResponseCreateError::HangsInCreation
                ) | RequestResponseOpenOrCreateError::SystemInFlux
            )
        },
    )
    .with_context(|| format!("cannot open service {name} ({})", sizing.mismatch_hint()))
}

/// Requests one control client may have waiting for their replies.
pub const CONTROL_REQUESTS_IN_FLIGHT: usize = 4;

/// Raised by the sim after a tick on which it answered control requests.
pub fn control_answered_event<S: Service>(node: &Node<S>, sizing: &Sizing) -> Result<Event<S>> {
    event_service(node, &control_answered_event_name(), sizing, 1)
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
    Ok(node_presence::<S>(identity, name)? == NodePresence::Alive)
}

/// What the run's iceoryx2 node list says of the node named `name`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum NodePresence {
    /// A live process holds it.
    Alive,
    /// Its process died without removing it (killed).
    Dead,
    /// Not listed: not started yet, or ended cleanly.
    Absent,
}

fn node_presence<S: Service>(identity: &RunIdentity, name: &str) -> Result<NodePresence> {
    let config = identity.iceoryx_config()?;
    let named =
        |details: &Option<iceoryx2::node::NodeDetails>| details.as_ref().is_some_and(|d| d.name().as_str() == name);
    let mut presence = NodePresence::Absent;
    Node::<S>::list(&config, |state| {
        match &state {
            NodeState::Alive(view) if named(view.details()) => {
                presence = NodePresence::Alive;
                return CallbackProgression::Stop;
            }
            NodeState::Dead(view) if named(view.details()) => presence = NodePresence::Dead,
            _ => {}
        }
        CallbackProgression::Continue
    })
    .context("cannot list the run's iceoryx2 nodes")?;
    Ok(presence)
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
    /// gone (never heard: its process killed), or silent past `startup` whatever its state. `who` names the caller in the one
    /// warning printed while a live sim is waited for.
    pub fn gone<S: Service>(&mut self, identity: &RunIdentity, who: &str) -> Result<Option<std::time::Duration>> {
        let quiet = self.last_heard.elapsed();
        let gone = if quiet <= self.silence {
            quiet > self.startup
        } else if !self.heard_any {
            // Never heard: a sim that has not started yet is waited for up to `startup`, one
            // killed before its first message (its node left dead) is given up at once.
            quiet > self.startup || node_presence::<S>(identity, "sim")? == NodePresence::Dead
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

    /// The static descriptions of the run's services (file names in its service directory).
    fn service_files(identity: &RunIdentity) -> Vec<std::path::PathBuf> {
        let mut files: Vec<_> = std::fs::read_dir(identity.root_path().join("services"))
            .map(|entries| entries.flatten().map(|e| e.path()).collect())
            .unwrap_or_default();
        files.sort();
        files
    }

    #[test]
    fn a_service_left_in_creation_by_a_killed_creator_is_created_afresh() {
        use std::os::unix::fs::PermissionsExt;
        let identity = RunIdentity::new(&format!("increation{}", std::process::id())).expect("id");
        identity.remove_leftovers();
        let sizing = Sizing::new(3, 8, 12);
        let node = create_node::<ipc::Service>(&identity, "agent1").expect("node");
        // Learn the description's file name, then drop the service (its file goes with it).
        let stream = state_stream(&node, &sizing).expect("created");
        let files = service_files(&identity);
        assert_eq!(files.len(), 1, "{files:?}");
        let description = files[0].clone();
        drop(stream);
        assert!(service_files(&identity).is_empty());
        // What a creator killed between writing the description and finishing it leaves: the
        // description still writable (in creation), no node's tag (its dead node was cleaned).
        std::fs::write(&description, b"").expect("write");
        std::fs::set_permissions(&description, std::fs::Permissions::from_mode(0o600)).expect("chmod");
        let started = std::time::Instant::now();
        let reopened = state_stream(&node, &sizing).expect("the abandoned creation is removed and the service created");
        assert!(started.elapsed() < OPEN_PATIENCE, "took {:?}", started.elapsed());
        assert_eq!(service_files(&identity), vec![description.clone()]);
        // Finished, it is never taken for an abandoned creation; a live creator's tag keeps its
        // description in creation too.
        assert_eq!(remove_abandoned_creations::<ipc::Service>(node.config()), 0);
        drop(reopened);
        drop(node);
        identity.remove_leftovers();
    }

    #[test]
    fn only_descriptions_in_creation_that_no_node_tags_are_removed() {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("formation-abandoned-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let (services, nodes) = (dir.join("services"), dir.join("nodes"));
        std::fs::create_dir_all(&services).expect("dir");
        std::fs::create_dir_all(nodes.join("42")).expect("dir");
        let put = |name: &str, mode: u32| {
            let path = services.join(name);
            std::fs::write(&path, b"").expect("write");
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(mode)).expect("chmod");
        };
        put("fc_run_abandoned.service", 0o600);
        put("fc_run_creating.service", 0o600); // its live creator's tag is below
        put("fc_run_finished.service", 0o400);
        put("fc_other_abandoned.service", 0o600); // another run's
        std::fs::write(nodes.join("42").join("fc_run_creating.service_tag"), b"").expect("tag");
        let removed = remove_abandoned_creations_in(&services, &nodes, "fc_run_", ".service", ".service_tag");
        assert_eq!(removed, 1);
        let mut left: Vec<String> = std::fs::read_dir(&services)
            .expect("dir")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        left.sort();
        assert_eq!(
            left,
            [
                "fc_other_abandoned.service",
                "fc_run_creating.service",
                "fc_run_finished.service"
            ]
        );
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    /// A pid that does not exist (a child that has been waited for).
    fn gone_pid() -> u32 {
        let mut child = std::process::Command::new("true").spawn().expect("spawn true");
        let pid = child.id();
        child.wait().expect("wait");
        pid
    }

    #[test]
    fn a_held_launcher_lock_keeps_its_run_from_being_swept_whatever_its_pid_says() {
        let dir = std::env::temp_dir().join(format!("formation-sweep-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        // Run ids name their launcher's pid; here neither pid exists (as for a launcher in
        // another PID namespace): only the lock tells the live run from the dead one.
        let pid = gone_pid();
        let live = RunIdentity::new(&format!("r000001p{pid}")).expect("id");
        let dead = RunIdentity::new(&format!("r000002p{pid}x1")).expect("id");
        for identity in [&live, &dead] {
            std::fs::write(identity.launcher_lock_in(&dir), b"").expect("lock file");
            std::fs::write(dir.join(format!("{}state.data", identity.shm_prefix())), b"").expect("write");
        }
        std::fs::write(dir.join("fc_default_state.data"), b"").expect("write"); // no launcher's
        // The live launcher's lock, as any process holds it (the dead one's is left unheld).
        let held = std::fs::File::open(live.launcher_lock_in(&dir)).expect("open");
        assert!(try_flock(&held).expect("flock"));
        assert_eq!(sweep_abandoned_runs_in(&dir), vec![(dead.run_id.clone(), 2)]);
        let names = |dir: &std::path::Path| {
            let mut names: Vec<String> = std::fs::read_dir(dir)
                .expect("dir")
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect();
            names.sort();
            names
        };
        let prefix = live.shm_prefix();
        let expected = vec![
            "fc_default_state.data".to_string(),
            format!("{prefix}launcher.lock"),
            format!("{prefix}state.data"),
        ];
        assert_eq!(names(&dir), expected);
        // The launcher is killed outright: the kernel drops its lock, the next sweep takes all.
        // (Another test of this binary that spawns a process shares the open lock between its
        // fork and exec, so the sweep may find it held for a moment: it is asked again.)
        drop(held);
        let mut swept = sweep_abandoned_runs_in(&dir);
        for _ in 0..50 {
            if !swept.is_empty() {
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
            swept = sweep_abandoned_runs_in(&dir);
        }
        assert_eq!(swept, vec![(live.run_id.clone(), 2)]);
        assert_eq!(names(&dir), vec!["fc_default_state.data".to_string()]);
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn a_launcher_lock_is_exclusive_and_goes_with_its_guard() {
        let dir = std::env::temp_dir().join(format!("formation-lock-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        let identity = RunIdentity::new(&format!("r000003p{}", gone_pid())).expect("id");
        let lock = identity.hold_launcher_lock_in(&dir).expect("lock");
        assert!(sweep_abandoned_runs_in(&dir).is_empty());
        let err = identity.hold_launcher_lock_in(&dir).expect_err("held by the first");
        assert!(format!("{err:#}").contains("another live launcher"), "{err:#}");
        let clients = dir.join(format!("{}{CLIENTS_LOCK}", identity.shm_prefix()));
        assert!(clients.exists());
        drop(lock);
        assert!(!identity.launcher_lock_in(&dir).exists() && !clients.exists());
        std::fs::remove_dir_all(&dir).expect("cleanup");
    }

    #[test]
    fn the_run_end_waits_for_clients_that_hold_their_lock() {
        let identity = RunIdentity::new(&format!("clients{}", std::process::id())).expect("id");
        let lock = identity.hold_launcher_lock().expect("lock");
        let client = std::fs::File::open(identity.clients_lock_path()).expect("open");
        use std::os::fd::AsRawFd;
        // SAFETY: flock(2) on a descriptor `client` owns.
        assert_eq!(unsafe { libc::flock(client.as_raw_fd(), libc::LOCK_SH) }, 0);
        assert!(!identity.wait_for_clients(std::time::Duration::from_millis(100)));
        drop(client); // the client closed its ports
        assert!(identity.wait_for_clients(std::time::Duration::from_secs(60)));
        drop(lock);
        assert!(!identity.clients_lock_path().exists() && !identity.launcher_lock_path().exists());
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
