//! The ROS 2 side's two directions. Observations: each carried robot's observation (on its
//! wake-up) leaves as `/<ns>/robot_<i>/observation`, and each state of the sim as every carried
//! robot's `odom` (and `scan`, when the observation model has the range sensor) and one
//! `/clock`; each episode's obstacles leave once as `/<ns>/obstacles` (a run with obstacles).
//! Commands: each `cmd_vel` Twist is checked and passed to the sim on the robot's command
//! stream as the answer to the newest observation published before it arrived. The robot's greeting goes out once its ROS 2 node is seen (a publisher on its
//! `cmd_vel` in the graph, or its first Twist).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context, Result, anyhow, bail, ensure};
use formation_core::run_dir::write_atomically;
use formation_ipc::services::{self, RunIdentity, SimWatch, Sizing};
use formation_ipc::termination_requested;
use formation_protocol::wire::{
    CommandMsg, FLAG_EPISODE_END, FLAG_EPISODE_START, FLAG_HELLO, FLAG_RUN_END, Header, ObservationMsg, StateMsg,
};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use zenoh::sample::{Sample, SampleKind};
use zenoh::{Config, Session, Wait};

use crate::surroundings::{self, ObstacleFeed, ScanLayout};
use crate::wire::{self, Attachment, EntityKind, NodeIdentity, RosType};

/// The ROS 2 node this side is on the graph: `/<namespace>/formation_swarm`.
const NODE_NAME: &str = "formation_swarm";
/// The QoS every entity announces: reliable, volatile, keep last 10.
const QOS_DEPTH: usize = 10;
/// How long one wait lasts before the loops check the sim, the stop flag and greetings.
const WAIT_SLICE: Duration = Duration::from_millis(100);
/// Refusals logged with their reason (the rest are only counted).
const REFUSALS_LOGGED: u64 = 10;
/// The counts' file in the run directory, folded into `summary.json` by the launcher.
pub const COUNTS_FILE: &str = "ros2.json";

/// The topic names of one swarm: `/<namespace>/robot_<i>/<leaf>` on domain `domain`.
#[derive(Debug, Clone)]
pub struct Names {
    domain: u32,
    namespace: String,
}

impl Names {
    /// `namespace` without leading or trailing `/`; each of its parts a ROS name (letters,
    /// digits and `_`, not starting with a digit).
    pub fn new(domain: u32, namespace: &str) -> Result<Self> {
        let namespace = namespace.trim_matches('/');
        let valid_part = |part: &str| {
            !part.is_empty()
                && !part.starts_with(|c: char| c.is_ascii_digit())
                && part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        };
        ensure!(
            namespace.split('/').all(valid_part),
            "--namespace must be a ROS 2 namespace like formation or lab/swarm_1, got {namespace:?}"
        );
        ensure!(
            domain <= 232,
            "--domain must be a ROS_DOMAIN_ID, 0 to 232, got {domain}"
        );
        Ok(Self {
            domain,
            namespace: namespace.to_string(),
        })
    }

    /// The namespace, without slashes.
    pub fn namespace(&self) -> &str {
        &self.namespace
    }

    /// `/<namespace>/robot_<robot>/<leaf>`.
    pub fn topic(&self, robot: usize, leaf: &str) -> String {
        format!("/{}/robot_{robot}/{leaf}", self.namespace)
    }

    /// The robot of a topic `/<namespace>/robot_<i>/<leaf>`.
    pub fn robot_of(&self, topic: &str, leaf: &str) -> Option<usize> {
        let rest = topic.strip_prefix('/')?.strip_prefix(self.namespace.as_str())?;
        let index = rest.strip_prefix("/robot_")?.strip_suffix(leaf)?.strip_suffix('/')?;
        index.parse().ok()
    }

    /// The data key of `topic` carrying `ty`.
    pub fn key(&self, topic: &str, ty: &RosType) -> String {
        wire::data_key(self.domain, topic, ty)
    }

    /// The key every robot's `cmd_vel` matches.
    pub fn every_cmd_vel(&self) -> String {
        self.key(&format!("/{}/*/cmd_vel", self.namespace), &wire::TWIST)
    }

    /// The topic of a data key of this domain (`None` for another domain).
    pub fn topic_of_key(&self, key: &str, ty: &RosType) -> Option<String> {
        let rest = key.strip_prefix(&format!("{}/", self.domain))?;
        let topic = rest.strip_suffix(&format!("/{}/{}", ty.dds, ty.hash))?;
        Some(format!("/{topic}"))
    }
}

/// What the ROS 2 side serves, and the run it belongs to.
#[derive(Debug, Clone)]
pub struct Options {
    /// The run's iceoryx2 identity.
    pub identity: RunIdentity,
    /// Where `ros2.json` goes.
    pub run_dir: PathBuf,
    /// The robots carried.
    pub robots: Vec<usize>,
    /// The services' sizing and contract.
    pub sizing: Sizing,
    /// Topic names and domain.
    pub names: Names,
    /// `layout.dim[0].label` of the observation: the observation model's name.
    pub observation_label: String,
    /// The range sensor in the observations (`None`: the model has none, no scan topic).
    pub scan: Option<ScanLayout>,
    /// The run has obstacles: `/<ns>/obstacles` is published once per episode.
    pub obstacles: bool,
    /// One tick of sim time, seconds.
    pub dt_s: f64,
    /// How long a sim may be silent before its process is checked.
    pub sim_silence: Duration,
    /// How long a sim may be away at all.
    pub startup_timeout: Duration,
}

/// What the ROS 2 side did.
#[derive(Debug, Default)]
pub struct Counts {
    /// Observations published.
    pub observations: AtomicU64,
    /// Odometry messages published.
    pub odometry: AtomicU64,
    /// Laser scans published.
    pub scans: AtomicU64,
    /// Obstacle marker arrays published (one per episode).
    pub obstacles: AtomicU64,
    /// Twists passed to the sim as a robot's command.
    pub twists: AtomicU64,
    /// Twists dropped: none of their robot's observations had been published yet.
    pub dropped: AtomicU64,
    /// Twists not passed on: a newer one came in the same batch, or the newest observation was
    /// already answered.
    pub superseded: AtomicU64,
    /// Twists refused: malformed (bad CDR header or length, non-finite values, no attachment)
    /// or for a robot not carried.
    pub rejected: AtomicU64,
}

impl Counts {
    fn get(counter: &AtomicU64) -> u64 {
        counter.load(Ordering::Relaxed)
    }

    /// One line for the log.
    pub fn report(&self) -> String {
        format!(
            "published {} observations, {} odometry, {} scans, {} obstacle marker arrays; passed {} twists on, dropped {} before any observation, superseded {}, rejected {}",
            Self::get(&self.observations),
            Self::get(&self.odometry),
            Self::get(&self.scans),
            Self::get(&self.obstacles),
            Self::get(&self.twists),
            Self::get(&self.dropped),
            Self::get(&self.superseded),
            Self::get(&self.rejected)
        )
    }

    /// Writes `ros2.json` into the run directory (the launcher adds it to `summary.json`).
    pub fn write(&self, options: &Options) -> Result<()> {
        let json = serde_json::json!({
            "ros2_agents": options.robots,
            "ros2_twists": Self::get(&self.twists),
            "ros2_twists_dropped": Self::get(&self.dropped),
            "ros2_twists_superseded": Self::get(&self.superseded),
            "ros2_twists_rejected": Self::get(&self.rejected),
        });
        std::fs::create_dir_all(&options.run_dir)
            .with_context(|| format!("cannot create {}", options.run_dir.display()))?;
        write_atomically(
            &options.run_dir.join(COUNTS_FILE),
            serde_json::to_string_pretty(&json)?.as_bytes(),
        )
    }
}

/// Opens the Zenoh session: a peer listening on `listen` and dialling `connect`, no multicast
/// scouting (as rmw_zenoh's own sessions), the rest Zenoh's defaults.
pub fn open_session(listen: &[String], connect: &[String]) -> Result<Session> {
    let mut config = Config::default();
    let list = |items: &[String]| {
        let quoted: Vec<String> = items.iter().map(|item| format!("{item:?}")).collect();
        format!("[{}]", quoted.join(","))
    };
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("listen/endpoints", list(listen)),
        ("connect/endpoints", list(connect)),
        ("scouting/multicast/enabled", "false".into()),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|err| anyhow!("zenoh config {key} = {value}: {err}"))?;
    }
    zenoh::open(config)
        .wait()
        .map_err(|err| anyhow!("cannot open the zenoh session: {err}"))
}

/// The newest observation published to each carried robot, and whether it was answered.
#[derive(Debug, Clone, Copy, Default)]
struct Newest {
    published: Option<(u32, u32)>,
    answered: bool,
}

impl Newest {
    /// Where a Twist that arrives now goes: dropped before any observation, superseded when the
    /// newest observation was answered already, else the answer to that observation.
    fn route(&mut self) -> Route {
        match self.published {
            None => Route::Dropped,
            Some(_) if self.answered => Route::Superseded,
            Some((episode, tick)) => {
                self.answered = true;
                Route::Answer(Header::new(episode, tick, 0))
            }
        }
    }
}

/// What becomes of a Twist.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Route {
    /// No observation of its robot was published yet.
    Dropped,
    /// The newest observation has its answer.
    Superseded,
    /// The answer to this observation.
    Answer(Header),
}

/// State shared by the two directions.
struct Shared {
    newest: Mutex<Vec<Newest>>,
    /// Each carried robot's ROS 2 node was seen.
    seen: Vec<AtomicBool>,
    /// Anything was heard from the sim.
    sim_heard: AtomicBool,
    counts: Arc<Counts>,
}

/// One ROS 2 publisher: its key, its GID, its sequence numbers.
struct RosPublisher {
    publisher: zenoh::pubsub::Publisher<'static>,
    gid: [u8; 16],
    sequence: i64,
}

impl RosPublisher {
    fn put<T: serde::Serialize>(&mut self, msg: &T) -> Result<()> {
        self.sequence += 1;
        let attachment = Attachment {
            sequence_number: self.sequence,
            source_timestamp_ns: now_ns(),
            gid: self.gid,
        };
        self.publisher
            .put(wire::encode(msg)?)
            .attachment(attachment.to_bytes().to_vec())
            .wait()
            .map_err(|err| anyhow!("zenoh put: {err}"))
    }
}

fn now_ns() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// This side's node on the ROS 2 graph: its liveliness tokens and its publishers.
struct Graph {
    node: NodeIdentity,
    next_entity: u32,
    tokens: Vec<zenoh::liveliness::LivelinessToken>,
}

impl Graph {
    fn new(session: &Session, names: &Names) -> Result<Self> {
        let node = NodeIdentity {
            domain: names.domain,
            zid: session.zid().to_string(),
            node_id: 0,
            namespace: format!("/{}", names.namespace),
            name: NODE_NAME.into(),
        };
        let mut graph = Self {
            node,
            next_entity: 1,
            tokens: Vec::new(),
        };
        let token = graph.node.node_token();
        graph.declare(session, token)?;
        Ok(graph)
    }

    fn declare(&mut self, session: &Session, key: String) -> Result<()> {
        let token = session
            .liveliness()
            .declare_token(key.clone())
            .wait()
            .map_err(|err| anyhow!("liveliness token {key}: {err}"))?;
        self.tokens.push(token);
        Ok(())
    }

    /// Announces an entity on `topic`; returns its GID.
    fn entity(&mut self, session: &Session, kind: EntityKind, topic: &str, ty: &RosType) -> Result<[u8; 16]> {
        let id = self.next_entity;
        self.next_entity += 1;
        let token = self
            .node
            .entity_token(id, kind, topic, ty, &wire::qos_keep_last(QOS_DEPTH));
        let gid = wire::gid_of(&token);
        self.declare(session, token)?;
        Ok(gid)
    }

    fn publisher(&mut self, session: &Session, names: &Names, topic: &str, ty: &RosType) -> Result<RosPublisher> {
        let gid = self.entity(session, EntityKind::Publisher, topic, ty)?;
        let key = names.key(topic, ty);
        let publisher = session
            .declare_publisher(key.clone())
            .wait()
            .map_err(|err| anyhow!("zenoh publisher {key}: {err}"))?;
        Ok(RosPublisher {
            publisher,
            gid,
            sequence: 0,
        })
    }
}

/// Runs until the sim ends the run (or falls silent); returns what was counted.
pub fn run(options: &Options, session: &Session) -> Result<Arc<Counts>> {
    let shared = Arc::new(Shared {
        newest: Mutex::new(vec![Newest::default(); options.robots.len()]),
        seen: options.robots.iter().map(|_| AtomicBool::new(false)).collect(),
        sim_heard: AtomicBool::new(false),
        counts: Arc::new(Counts::default()),
    });
    let mut graph = Graph::new(session, &options.names)?;
    // The graph: a publisher on a carried robot's cmd_vel is its node.
    let watched = Arc::clone(&shared);
    let (names, robots) = (options.names.clone(), options.robots.clone());
    let _graph_watch = session
        .liveliness()
        .declare_subscriber(format!("@ros2_lv/{}/**", options.names.domain))
        .history(true)
        .callback(move |sample: Sample| {
            if sample.kind() != SampleKind::Put {
                return;
            }
            let Some((kind, topic)) = wire::parse_entity_token(sample.key_expr().as_str()) else {
                return;
            };
            let robot = names.robot_of(&topic, "cmd_vel");
            if let (EntityKind::Publisher, Some(slot)) =
                (kind_of(kind), robot.and_then(|r| robots.iter().position(|&c| c == r)))
            {
                watched.seen[slot].store(true, Ordering::Release);
            }
        })
        .wait()
        .map_err(|err| anyhow!("liveliness subscriber: {err}"))?;
    let twists = session
        .declare_subscriber(options.names.every_cmd_vel())
        .wait()
        .map_err(|err| anyhow!("zenoh subscriber on cmd_vel: {err}"))?;
    let mut cmd_vel_gids = Vec::new();
    for &robot in &options.robots {
        let topic = options.names.topic(robot, "cmd_vel");
        cmd_vel_gids.push(graph.entity(session, EntityKind::Subscription, &topic, &wire::TWIST)?);
    }
    let stop = Arc::new(AtomicBool::new(false));
    let thread = {
        let (options, shared, stop) = (options.clone(), Arc::clone(&shared), Arc::clone(&stop));
        std::thread::Builder::new()
            .name("cmd_vel".into())
            .spawn(move || commands_in(&options, &twists, &shared, &stop))
            .context("cannot start the cmd_vel thread")?
    };
    let outcome = observations_out(options, session, &mut graph, &shared);
    stop.store(true, Ordering::Release);
    let commands = thread.join().map_err(|_| anyhow!("the cmd_vel thread panicked"))?;
    outcome.and(commands)?;
    Ok(Arc::clone(&shared.counts))
}

fn kind_of(letters: &str) -> EntityKind {
    match letters {
        "MP" => EntityKind::Publisher,
        "MS" => EntityKind::Subscription,
        _ => EntityKind::Node,
    }
}

/// Robot `.0`'s observation subscriber and its wake-up.
type ObservationIn = (
    usize,
    Subscriber<ipc::Service, ObservationMsg, ()>,
    Listener<ipc::Service>,
);

/// Observations and states from iceoryx2 to ROS 2 topics, on each observation's wake-up, until
/// every carried robot was told the run ended.
fn observations_out(options: &Options, session: &Session, graph: &mut Graph, shared: &Shared) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&options.identity, "ros2")?;
    let sizing = &options.sizing;
    let mut inputs: Vec<ObservationIn> = Vec::new();
    for &robot in &options.robots {
        let subscriber = services::observation_stream(&node, sizing, robot)?
            .subscriber_builder()
            .buffer_size(16)
            .create()
            .with_context(|| format!("ros2: observation subscriber of robot {robot}"))?;
        let listener = services::observation_event(&node, sizing, robot)?
            .listener_builder()
            .create()
            .with_context(|| format!("ros2: observation listener of robot {robot}"))?;
        inputs.push((robot, subscriber, listener));
    }
    let states = services::state_stream(&node, sizing)?
        .subscriber_builder()
        .create()
        .context("ros2: state subscriber")?;
    let names = &options.names;
    let mut observation_out = Vec::new();
    for &robot in &options.robots {
        observation_out.push(graph.publisher(
            session,
            names,
            &names.topic(robot, "observation"),
            &wire::FLOAT32_MULTI_ARRAY,
        )?);
    }
    let mut state_out = StateOut::new(options, session, graph, &node)?;
    let listeners: Vec<&Listener<ipc::Service>> = inputs.iter().map(|(_, _, l)| l).collect();
    let mut ended = vec![false; options.robots.len()];
    let mut sim_watch = SimWatch::new(options.sim_silence, options.startup_timeout);
    let mut observation = wire::Float32MultiArray {
        layout: observation_layout(&options.observation_label, sizing.observation_dim, 0, 0),
        data: Vec::new(),
    };
    while !ended.iter().all(|&e| e) {
        services::wait_for_any_event(&listeners, WAIT_SLICE)?;
        for (slot, (robot, subscriber, _)) in inputs.iter().enumerate() {
            while let Some(sample) = subscriber.receive().context("ros2: receive observation")? {
                let msg = sample.payload();
                services::check_sim_protocol(&msg.header, "ros2", "side")?;
                sim_watch.heard();
                shared.sim_heard.store(true, Ordering::Release);
                if msg.header.has(FLAG_RUN_END) {
                    ended[slot] = true;
                    continue;
                }
                if msg.header.has(FLAG_EPISODE_END) {
                    continue; // the episode's last state: no answer is expected
                }
                observation.layout = observation_layout(
                    &options.observation_label,
                    sizing.observation_dim,
                    msg.header.episode,
                    msg.header.tick,
                );
                observation.data.clear();
                observation.data.extend_from_slice(&msg.obs[..msg.dim as usize]);
                observation_out[slot]
                    .put(&observation)
                    .with_context(|| format!("ros2: observation of robot {robot}"))?;
                shared.counts.observations.fetch_add(1, Ordering::Relaxed);
                let mut newest = shared.newest.lock().map_err(|_| anyhow!("poisoned"))?;
                newest[slot] = Newest {
                    published: Some((msg.header.episode, msg.header.tick)),
                    answered: false,
                };
            }
        }
        while let Some(sample) = states.receive().context("ros2: receive state")? {
            if sample.payload().header.has(FLAG_RUN_END) {
                continue; // the run's end repeats the last state
            }
            state_out.publish(options, sample.payload(), &shared.counts)?;
        }
        if termination_requested() {
            break;
        }
        if let Some(quiet) = sim_watch.gone::<ipc::Service>(&options.identity, "ros2")? {
            bail!(
                "ros2: no observation from the sim for {:.1} s; is it alive?",
                quiet.as_secs_f64()
            );
        }
    }
    Ok(())
}

/// The layout of a robot's observation: `dim[0]` the observation model (its name as label, its
/// floats as size and stride), `dim[1]` of size 1 labelled `episode E tick T`, the tick the
/// observation belongs to (a node with a window of observations starts a new one when `E`
/// changes). The floats are `dim[0].size` x 1, whatever a reader makes of the labels.
pub fn observation_layout(model: &str, dim: usize, episode: u32, tick: u32) -> wire::MultiArrayLayout {
    wire::MultiArrayLayout {
        dim: vec![
            wire::MultiArrayDimension {
                label: model.to_string(),
                size: dim as u32,
                stride: dim as u32,
            },
            wire::MultiArrayDimension {
                label: format!("episode {episode} tick {tick}"),
                size: 1,
                stride: 1,
            },
        ],
        data_offset: 0,
    }
}

/// The publishers of what each state of the sim becomes.
struct StateOut {
    clock: RosPublisher,
    /// Per carried robot.
    odometry: Vec<RosPublisher>,
    /// Per carried robot, with the range sensor; else empty.
    scans: Vec<RosPublisher>,
    /// With obstacles: the sim's obstacles and `/<ns>/obstacles`.
    obstacles: Option<(ObstacleFeed, RosPublisher)>,
}

impl StateOut {
    fn new(options: &Options, session: &Session, graph: &mut Graph, node: &Node<ipc::Service>) -> Result<Self> {
        let names = &options.names;
        let mut odometry = Vec::new();
        let mut scans = Vec::new();
        for &robot in &options.robots {
            odometry.push(graph.publisher(session, names, &names.topic(robot, "odom"), &wire::ODOMETRY)?);
            if options.scan.is_some() {
                scans.push(graph.publisher(session, names, &names.topic(robot, "scan"), &wire::LASER_SCAN)?);
            }
        }
        let obstacles = match options.obstacles {
            true => Some((
                ObstacleFeed::new(node, &options.sizing).context("ros2")?,
                graph.publisher(
                    session,
                    names,
                    &surroundings::obstacles_topic(names.namespace()),
                    &wire::MARKER_ARRAY,
                )?,
            )),
            false => None,
        };
        Ok(Self {
            clock: graph.publisher(session, names, "/clock", &wire::CLOCK)?,
            odometry,
            scans,
            obstacles,
        })
    }

    /// One state of the sim as the clock, every carried robot's odometry (ground truth: pose in
    /// `world`, the velocity that acted in `robot_<i>/base_link`) and scan (what its
    /// observation told it), stamped in sim time; at an episode's first state its obstacles
    /// first.
    fn publish(&mut self, options: &Options, state: &StateMsg, counts: &Counts) -> Result<()> {
        let stamp = sim_time(state.sequence, options.dt_s);
        if state.header.has(FLAG_EPISODE_START)
            && let Some((feed, out)) = &mut self.obstacles
            && let Some(obstacles) = feed.of_episode(state.header.episode)?
        {
            out.put(&surroundings::obstacle_markers(&obstacles, stamp))?;
            counts.obstacles.fetch_add(1, Ordering::Relaxed);
        }
        self.clock.put(&wire::Clock { clock: stamp })?;
        for (slot, &robot) in options.robots.iter().enumerate() {
            self.odometry[slot].put(&odometry_of(state, robot, stamp))?;
            counts.odometry.fetch_add(1, Ordering::Relaxed);
            let scan = options
                .scan
                .and_then(|layout| layout.of_state(state, robot, stamp, options.dt_s));
            if let Some(scan) = scan {
                self.scans[slot].put(&scan)?;
                counts.scans.fetch_add(1, Ordering::Relaxed);
            }
        }
        Ok(())
    }
}

/// Sim time of the state numbered `sequence` (from 1): `(sequence - 1) * dt`, monotonic
/// across episodes.
pub fn sim_time(sequence: u64, dt_s: f64) -> wire::Time {
    let nanos = (sequence.saturating_sub(1) as f64 * dt_s * 1e9).round() as u64;
    wire::Time::from_nanos(nanos)
}

/// Robot `robot`'s odometry in `state`.
pub fn odometry_of(state: &StateMsg, robot: usize, stamp: wire::Time) -> wire::Odometry {
    let [x, y, theta] = state.poses[robot].map(f64::from);
    let [v, w] = state.acting[robot].map(f64::from);
    wire::Odometry {
        header: wire::Header {
            stamp,
            frame_id: "world".into(),
        },
        child_frame_id: format!("robot_{robot}/base_link"),
        pose: wire::PoseWithCovariance {
            pose: wire::Pose {
                position: wire::Vector3 { x, y, z: 0.0 },
                orientation: wire::Quaternion::from_yaw(theta),
            },
            covariance: wire::Covariance::default(),
        },
        twist: wire::TwistWithCovariance {
            twist: wire::Twist {
                linear: wire::Vector3 { x: v, y: 0.0, z: 0.0 },
                angular: wire::Vector3 { x: 0.0, y: 0.0, z: w },
            },
            covariance: wire::Covariance::default(),
        },
    }
}

/// A Twist taken in: for which carried robot (its slot), with which (v, w).
type Accepted = (usize, (f32, f32));

/// Checks one `cmd_vel` sample: the robot it is for must be carried, the attachment present,
/// the Twist well formed. Counts and logs a refusal.
fn accept(options: &Options, sample: &Sample, counts: &Counts) -> Option<Accepted> {
    let key = sample.key_expr().as_str();
    let topic = options.names.topic_of_key(key, &wire::TWIST);
    let robot = topic.as_deref().and_then(|t| options.names.robot_of(t, "cmd_vel"));
    let slot = robot.and_then(|r| options.robots.iter().position(|&c| c == r));
    let refusal = match slot {
        None => Some("for a robot this side does not carry".to_string()),
        Some(_) => {
            let attachment = sample.attachment().map(|a| a.to_bytes());
            match attachment.as_deref().and_then(Attachment::from_bytes) {
                None => Some(wire::Malformed::Attachment.to_string()),
                Some(_) => wire::decode_twist(&sample.payload().to_bytes())
                    .err()
                    .map(|m| m.to_string()),
            }
        }
    };
    if let Some(reason) = refusal {
        let rejected = counts.rejected.fetch_add(1, Ordering::Relaxed) + 1;
        if rejected <= REFUSALS_LOGGED {
            eprintln!("ros2: rejected a Twist on {key} ({reason})");
        }
        return None;
    }
    let twist = wire::decode_twist(&sample.payload().to_bytes()).ok()?;
    Some((slot?, (twist.linear.x as f32, twist.angular.z as f32)))
}

/// `cmd_vel` Twists from Zenoh into each robot's command stream, and the robots' greetings.
fn commands_in(
    options: &Options,
    twists: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<Sample>>,
    shared: &Shared,
    stop: &AtomicBool,
) -> Result<()> {
    let node = services::create_node::<ipc::Service>(&options.identity, "ros2-commands")?;
    let sizing = &options.sizing;
    let mut publishers = Vec::new();
    for &robot in &options.robots {
        publishers.push(
            services::command_stream(&node, sizing, robot)?
                .publisher_builder()
                .create()
                .with_context(|| format!("ros2: command publisher of robot {robot}"))?,
        );
    }
    let command_ready = services::command_event(&node, sizing)?
        .notifier_builder()
        .create()
        .context("ros2: command notifier")?;
    // Random per process start, so the sim tells a restarted side from its predecessor.
    let session: u32 = rand::random_range(1..u32::MAX);
    let send = |slot: usize, header: Header, (v, w): (f32, f32)| -> Result<()> {
        let robot = options.robots[slot];
        let mut sample = publishers[slot].loan().context("ros2: loan command")?;
        *sample.payload_mut() = CommandMsg {
            header,
            agent: robot as u32,
            session,
            v,
            w,
            ..CommandMsg::default()
        };
        sample.send().context("ros2: send command")?;
        command_ready
            .notify_with_custom_event_id(services::agent_event_id(robot))
            .context("ros2: notify the sim")?;
        Ok(())
    };
    let mut greeted = vec![false; options.robots.len()];
    let mut batch: Vec<Option<(f32, f32)>> = vec![None; options.robots.len()];
    while !stop.load(Ordering::Acquire) {
        // Greet for each robot whose node is seen, again until the sim has answered (a
        // publisher hands its history only to subscribers it has seen).
        let sim_heard = shared.sim_heard.load(Ordering::Acquire);
        for (slot, seen) in shared.seen.iter().enumerate() {
            if seen.load(Ordering::Acquire) && (!greeted[slot] || !sim_heard) {
                if !greeted[slot] {
                    eprintln!(
                        "ros2: robot {}'s ROS 2 node is here; greeting the sim",
                        options.robots[slot]
                    );
                }
                send(slot, Header::new(0, 0, FLAG_HELLO), (0.0, 0.0))?;
                greeted[slot] = true;
            }
        }
        let first = match twists.recv_timeout(WAIT_SLICE) {
            Ok(Some(sample)) => sample,
            Ok(None) => continue,
            Err(err) => bail!("ros2: cmd_vel subscriber closed: {err}"),
        };
        // Everything that arrived together: per robot the newest wins.
        let mut next = Some(first);
        while let Some(sample) = next.take() {
            if let Some((slot, command)) = accept(options, &sample, &shared.counts) {
                shared.seen[slot].store(true, Ordering::Release);
                if batch[slot].replace(command).is_some() {
                    shared.counts.superseded.fetch_add(1, Ordering::Relaxed);
                }
            }
            next = twists.try_recv().ok().flatten();
        }
        for (slot, command) in batch.iter_mut().enumerate() {
            let Some(command) = command.take() else { continue };
            let route = shared.newest.lock().map_err(|_| anyhow!("poisoned"))?[slot].route();
            match route {
                Route::Dropped => shared.counts.dropped.fetch_add(1, Ordering::Relaxed),
                Route::Superseded => shared.counts.superseded.fetch_add(1, Ordering::Relaxed),
                Route::Answer(header) => {
                    send(slot, header, command)?;
                    shared.counts.twists.fetch_add(1, Ordering::Relaxed)
                }
            };
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_map_robots_to_topics_and_keys_and_back() {
        let names = Names::new(3, "/lab/swarm_1/").expect("names");
        assert_eq!(names.topic(2, "cmd_vel"), "/lab/swarm_1/robot_2/cmd_vel");
        assert_eq!(names.robot_of("/lab/swarm_1/robot_12/cmd_vel", "cmd_vel"), Some(12));
        assert_eq!(names.robot_of("/lab/swarm_1/robot_x/cmd_vel", "cmd_vel"), None);
        assert_eq!(names.robot_of("/other/robot_1/cmd_vel", "cmd_vel"), None);
        let key = names.key(&names.topic(2, "cmd_vel"), &wire::TWIST);
        assert_eq!(
            key,
            "3/lab/swarm_1/robot_2/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
        );
        assert_eq!(
            names.topic_of_key(&key, &wire::TWIST).as_deref(),
            Some("/lab/swarm_1/robot_2/cmd_vel")
        );
        assert_eq!(names.topic_of_key(&key.replacen('3', "4", 1), &wire::TWIST), None);
        let every = zenoh::key_expr::KeyExpr::new(names.every_cmd_vel()).expect("key expression");
        assert!(every.intersects(&zenoh::key_expr::KeyExpr::new(key).expect("key")));
        for bad in ["", "a b", "1st", "lab//x"] {
            assert!(Names::new(0, bad).is_err(), "{bad:?}");
        }
        assert!(Names::new(233, "formation").is_err());
    }

    #[test]
    fn a_twist_answers_the_newest_observation_once_and_none_before_the_first() {
        let mut newest = Newest::default();
        assert_eq!(newest.route(), Route::Dropped, "no observation yet");
        newest = Newest {
            published: Some((3, 7)),
            answered: false,
        };
        assert_eq!(newest.route(), Route::Answer(Header::new(3, 7, 0)));
        assert_eq!(newest.route(), Route::Superseded, "tick 7 has its answer");
        newest = Newest {
            published: Some((3, 8)),
            answered: false,
        };
        assert_eq!(newest.route(), Route::Answer(Header::new(3, 8, 0)));
    }

    #[test]
    fn odometry_is_ground_truth_in_the_world_with_the_acting_velocity_in_the_body_frame() {
        let mut state = StateMsg::default();
        state.poses[1] = [1.0, -2.0, std::f32::consts::FRAC_PI_2];
        state.acting[1] = [0.4, -0.3];
        state.sequence = 11;
        let stamp = sim_time(state.sequence, 0.1);
        assert_eq!(stamp, wire::Time { sec: 1, nanosec: 0 });
        let odometry = odometry_of(&state, 1, stamp);
        assert_eq!(odometry.header.frame_id, "world");
        assert_eq!(odometry.child_frame_id, "robot_1/base_link");
        assert_eq!(
            odometry.pose.pose.position,
            wire::Vector3 {
                x: 1.0,
                y: -2.0,
                z: 0.0
            }
        );
        let q = odometry.pose.pose.orientation;
        assert!((2.0 * q.z.atan2(q.w) - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
        assert!((odometry.twist.twist.linear.x - 0.4).abs() < 1e-6);
        assert!((odometry.twist.twist.angular.z + 0.3).abs() < 1e-6);
        assert_eq!(sim_time(1, 0.1), wire::Time::default(), "the first state is at 0");
    }
}
