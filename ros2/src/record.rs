//! A run as an MCAP file of ROS 2 messages (`--record mcap`: `<run dir>/run.mcap`). CDR
//! payloads (`message_encoding` `cdr`), `ros2msg` schemas carrying the full dependent
//! definitions as `ros2 bag` writes them, stamps in sim time (state number x dt, monotonic
//! across episodes). With the range sensor, every robot's scan; with obstacles, each
//! episode's obstacles as markers. The channels are in docs/ROS2.md, "Runs as MCAP".

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Seek, Write};
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use formation_core::obstacles::Obstacle;
use formation_ipc::cli::Mode;
use formation_ipc::services::{self, ProgressPublisher, RunIdentity, SimWatch, Sizing, StreamReader};
use formation_ipc::termination_requested;
use formation_protocol::wire::{
    FLAG_EPISODE_END, FLAG_EPISODE_START, FLAG_EVAL_EPISODE, FLAG_RUN_END, OUTCOME_ABORTED, OUTCOME_COLLISION,
    OUTCOME_SUCCESS, OUTCOME_TIMEOUT, StateMsg,
};
use iceoryx2::prelude::*;
use serde::Serialize;

use crate::side::{Names, odometry_of};
use crate::surroundings::{self, ObstacleFeed, ScanLayout};
use crate::wire::{self, Header, Pose, Quaternion, Time, Twist, Vector3};

/// The file the recorder writes in the run directory.
pub const MCAP_FILE: &str = "run.mcap";
/// The line the recorder prints on stdout once its state subscriber exists (the launcher
/// starts the rest of the run after it).
pub const READY_LINE: &str = "formation-mcap: ready";
/// The longest wait between two looks at the state stream when the critic's wake-up is not rung.
const WAIT_SLICE: Duration = Duration::from_millis(100);

/// The message definitions the recorded types need, as their `.msg` files state them (comments
/// left out): `(package/Name, text)`. A field type without a package is of the same package.
const DEFINITIONS: &[(&str, &str)] = &[
    ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n"),
    ("builtin_interfaces/Duration", "int32 sec\nuint32 nanosec\n"),
    ("std_msgs/ColorRGBA", "float32 r\nfloat32 g\nfloat32 b\nfloat32 a\n"),
    ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id\n"),
    ("std_msgs/Float32", "float32 data\n"),
    ("std_msgs/String", "string data\n"),
    ("std_msgs/UInt32", "uint32 data\n"),
    (
        "std_msgs/MultiArrayDimension",
        "string label\nuint32 size\nuint32 stride\n",
    ),
    (
        "std_msgs/MultiArrayLayout",
        "MultiArrayDimension[] dim\nuint32 data_offset\n",
    ),
    ("std_msgs/UInt32MultiArray", "MultiArrayLayout layout\nuint32[] data\n"),
    ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
    ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n"),
    (
        "geometry_msgs/Quaternion",
        "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    ),
    ("geometry_msgs/Pose", "Point position\nQuaternion orientation\n"),
    (
        "geometry_msgs/PoseWithCovariance",
        "Pose pose\nfloat64[36] covariance\n",
    ),
    ("geometry_msgs/Twist", "Vector3 linear\nVector3 angular\n"),
    (
        "geometry_msgs/TwistWithCovariance",
        "Twist twist\nfloat64[36] covariance\n",
    ),
    ("geometry_msgs/TwistStamped", "std_msgs/Header header\nTwist twist\n"),
    ("geometry_msgs/Transform", "Vector3 translation\nQuaternion rotation\n"),
    (
        "geometry_msgs/TransformStamped",
        "std_msgs/Header header\nstring child_frame_id\nTransform transform\n",
    ),
    ("tf2_msgs/TFMessage", "geometry_msgs/TransformStamped[] transforms\n"),
    ("geometry_msgs/PoseArray", "std_msgs/Header header\nPose[] poses\n"),
    (
        "sensor_msgs/LaserScan",
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\nfloat32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\nfloat32[] ranges\nfloat32[] intensities\n",
    ),
    (
        "sensor_msgs/CompressedImage",
        "std_msgs/Header header\nstring format\nuint8[] data\n",
    ),
    ("visualization_msgs/UVCoordinate", "float32 u\nfloat32 v\n"),
    ("visualization_msgs/MeshFile", "string filename\nuint8[] data\n"),
    (
        "visualization_msgs/Marker",
        "int32 ARROW=0\nint32 CUBE=1\nint32 SPHERE=2\nint32 CYLINDER=3\nint32 LINE_STRIP=4\nint32 LINE_LIST=5\nint32 CUBE_LIST=6\nint32 SPHERE_LIST=7\nint32 POINTS=8\nint32 TEXT_VIEW_FACING=9\nint32 MESH_RESOURCE=10\nint32 TRIANGLE_LIST=11\nint32 ARROW_STRIP=12\n\
         int32 ADD=0\nint32 MODIFY=0\nint32 DELETE=2\nint32 DELETEALL=3\n\
         std_msgs/Header header\nstring ns\nint32 id\nint32 type\nint32 action\ngeometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nstd_msgs/ColorRGBA color\nbuiltin_interfaces/Duration lifetime\nbool frame_locked\n\
         geometry_msgs/Point[] points\nstd_msgs/ColorRGBA[] colors\nstring texture_resource\nsensor_msgs/CompressedImage texture\nUVCoordinate[] uv_coordinates\nstring text\nstring mesh_resource\nMeshFile mesh_file\nbool mesh_use_embedded_materials\n",
    ),
    ("visualization_msgs/MarkerArray", "Marker[] markers\n"),
    (
        "nav_msgs/Odometry",
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist\n",
    ),
];

/// The separator `ros2 bag` puts before each dependent definition.
const SEPARATOR: &str = "================================================================================";

/// The primitive field types of the ROS 2 IDL (`.msg` files).
const PRIMITIVES: &[&str] = &[
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64",
    "uint64", "string", "wstring",
];

/// `package/Name` of `pkg/msg/Name` or `pkg/Name`.
fn short_name(name: &str) -> String {
    let mut parts = name.split('/');
    let package = parts.next().unwrap_or_default();
    let leaf = parts.next_back().unwrap_or_default();
    format!("{package}/{leaf}")
}

fn definition(short: &str) -> Result<&'static str> {
    DEFINITIONS
        .iter()
        .find(|(name, _)| *name == short)
        .map(|(_, text)| *text)
        .ok_or_else(|| anyhow!("no message definition of {short}"))
}

/// The message types a definition's fields use, in field order (`package/Name`).
fn field_types(package: &str, text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|line| line.split_whitespace().next())
        .map(|ty| ty.split(['[', '<']).next().unwrap_or(ty))
        .filter(|ty| !PRIMITIVES.contains(ty))
        .map(|ty| match ty.contains('/') {
            true => short_name(ty),
            false => format!("{package}/{ty}"),
        })
        .collect()
}

/// The `ros2msg` schema of `name` (`pkg/msg/Name`) as `ros2 bag` writes it: its definition,
/// then each type it depends on (depth first, once each) after a line of 80 `=` and
/// `MSG: package/Name`.
pub fn schema_text(name: &str) -> Result<String> {
    let root = short_name(name);
    let mut text = definition(&root)?.to_string();
    let mut seen = vec![root.clone()];
    let mut pending = field_types(root.split('/').next().unwrap_or_default(), definition(&root)?);
    pending.reverse();
    while let Some(dependency) = pending.pop() {
        if seen.contains(&dependency) {
            continue;
        }
        let body = definition(&dependency)?;
        text.push_str(&format!("{SEPARATOR}\nMSG: {dependency}\n{body}"));
        let package = dependency.split('/').next().unwrap_or_default().to_string();
        let mut inner = field_types(&package, body);
        inner.reverse();
        pending.extend(inner);
        seen.push(dependency);
    }
    Ok(text)
}

/// `geometry_msgs/msg/TwistStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TwistStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The twist.
    pub twist: Twist,
}

/// `geometry_msgs/msg/PoseArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct PoseArray {
    /// Stamp and frame.
    pub header: Header,
    /// The poses.
    pub poses: Vec<Pose>,
}

/// `geometry_msgs/msg/Transform`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Transform {
    /// Where the child frame's origin is.
    pub translation: Vector3,
    /// How it is turned.
    pub rotation: Quaternion,
}

/// `geometry_msgs/msg/TransformStamped`: `header.frame_id` -> `child_frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TransformStamped {
    /// Stamp and the parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// The child frame in the parent's.
    pub transform: Transform,
}

/// `tf2_msgs/msg/TFMessage`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// `std_msgs/msg/UInt32MultiArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct UInt32MultiArray {
    /// The layout.
    pub layout: wire::MultiArrayLayout,
    /// The values.
    pub data: Vec<u32>,
}

/// One recorded topic: its name and ROS 2 type.
#[derive(Debug, Clone, Copy)]
enum Topic {
    Odometry(usize),
    Command(usize),
    Scan(usize),
    Obstacles,
    Tf,
    Goal,
    Target,
    Slot,
    Reward,
    Outcome,
    Episode,
}

impl Topic {
    fn ty(self) -> &'static str {
        match self {
            Topic::Odometry(_) => "nav_msgs/msg/Odometry",
            Topic::Command(_) => "geometry_msgs/msg/TwistStamped",
            Topic::Scan(_) => "sensor_msgs/msg/LaserScan",
            Topic::Obstacles => "visualization_msgs/msg/MarkerArray",
            Topic::Tf => "tf2_msgs/msg/TFMessage",
            Topic::Goal | Topic::Target => "geometry_msgs/msg/PoseArray",
            Topic::Slot => "std_msgs/msg/UInt32MultiArray",
            Topic::Reward => "std_msgs/msg/Float32",
            Topic::Outcome => "std_msgs/msg/String",
            Topic::Episode => "std_msgs/msg/UInt32",
        }
    }

    fn name(self, names: &Names) -> String {
        let ns = names.namespace();
        match self {
            Topic::Odometry(robot) => names.topic(robot, "odom"),
            Topic::Command(robot) => names.topic(robot, "cmd_applied"),
            Topic::Scan(robot) => names.topic(robot, "scan"),
            Topic::Obstacles => surroundings::obstacles_topic(ns),
            Topic::Tf => "/tf".into(),
            Topic::Goal => format!("/{ns}/goal"),
            Topic::Target => format!("/{ns}/target"),
            Topic::Slot => format!("/{ns}/slot"),
            Topic::Reward => format!("/{ns}/reward"),
            Topic::Outcome => format!("/{ns}/outcome"),
            Topic::Episode => format!("/{ns}/episode"),
        }
    }
}

/// The name of a state's `OUTCOME_*` code, as `episodes.csv` writes it.
fn outcome_name(code: u32) -> &'static str {
    match code {
        OUTCOME_SUCCESS => "success",
        OUTCOME_COLLISION => "collision",
        OUTCOME_TIMEOUT => "timeout",
        OUTCOME_ABORTED => "aborted",
        _ => "running",
    }
}

/// Sim time of the state numbered `sequence` (from 1), nanoseconds: `(sequence - 1) * dt`
/// (the stamps of `formation-ros2`'s odometry).
fn sim_nanos(sequence: u64, dt_s: f64) -> u64 {
    (sequence.saturating_sub(1) as f64 * dt_s * 1e9).round() as u64
}

/// What the recorder wrote.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct Recorded {
    /// States written.
    pub states: u64,
    /// Episodes begun in the file.
    pub episodes: u64,
    /// States missing from the stream (a gap in their numbers): the recorder fell behind.
    pub lost: u64,
}

/// Writes states of one swarm as ROS 2 messages into an MCAP file.
pub struct Recorder<W: Write + Seek> {
    writer: mcap::Writer<W>,
    names: Names,
    n_agents: usize,
    dt_s: f64,
    /// The range sensor in the observations, if the model has one.
    scan: Option<ScanLayout>,
    /// Train mode: only evaluation episodes are written.
    eval_only: bool,
    channels: BTreeMap<String, u16>,
    sequences: BTreeMap<u16, u32>,
    /// The formation last written (goal, targets, slot map) and its episode.
    last_formation: Option<(u32, Vec<[f32; 2]>, Vec<u32>)>,
    last_sequence: u64,
    recorded: Recorded,
}

impl<W: Write + Seek> Recorder<W> {
    /// A recorder of an `n_agents` swarm writing to `out`; in train mode (`mode`) only the
    /// evaluation episodes are recorded. With `scan`, each robot's scan is recorded; with
    /// `obstacles`, the channel of the episodes' obstacles is opened.
    pub fn new(
        out: W,
        names: Names,
        n_agents: usize,
        dt_s: f64,
        mode: Mode,
        scan: Option<ScanLayout>,
        obstacles: bool,
    ) -> Result<Self> {
        let writer = mcap::WriteOptions::new()
            .profile("ros2")
            .create(out)
            .context("cannot start the MCAP file")?;
        let mut recorder = Self {
            writer,
            names,
            n_agents,
            dt_s,
            scan,
            eval_only: mode == Mode::Train,
            channels: BTreeMap::new(),
            sequences: BTreeMap::new(),
            last_formation: None,
            last_sequence: 0,
            recorded: Recorded::default(),
        };
        let mut topics = vec![
            Topic::Tf,
            Topic::Episode,
            Topic::Goal,
            Topic::Target,
            Topic::Slot,
            Topic::Reward,
            Topic::Outcome,
        ];
        if obstacles {
            topics.push(Topic::Obstacles);
        }
        for robot in 0..n_agents {
            topics.extend([Topic::Odometry(robot), Topic::Command(robot)]);
            if scan.is_some() {
                topics.push(Topic::Scan(robot));
            }
        }
        for topic in topics {
            recorder.channel(topic)?;
        }
        Ok(recorder)
    }

    fn channel(&mut self, topic: Topic) -> Result<u16> {
        let name = topic.name(&self.names);
        if let Some(&id) = self.channels.get(&name) {
            return Ok(id);
        }
        let schema = schema_text(topic.ty())?;
        let schema_id = self
            .writer
            .add_schema(topic.ty(), "ros2msg", schema.as_bytes())
            .context("MCAP schema")?;
        let id = self
            .writer
            .add_channel(schema_id, &name, "cdr", &BTreeMap::new())
            .context("MCAP channel")?;
        self.channels.insert(name, id);
        Ok(id)
    }

    fn write<T: Serialize>(&mut self, topic: Topic, nanos: u64, msg: &T) -> Result<()> {
        let channel_id = self.channel(topic)?;
        let sequence = self.sequences.entry(channel_id).or_insert(0);
        *sequence += 1;
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: *sequence,
            log_time: nanos,
            publish_time: nanos,
        };
        self.writer
            .write_to_known_channel(&header, &wire::encode(msg)?)
            .context("MCAP message")
    }

    /// Whether a state is left out: a training episode's in train mode.
    fn skips(&self, state: &StateMsg) -> bool {
        self.eval_only && !state.header.has(FLAG_EVAL_EPISODE)
    }

    /// Writes an episode's obstacles as markers, stamped at its first state `state` (or
    /// skips them with the episode).
    pub fn obstacles(&mut self, state: &StateMsg, obstacles: &[Obstacle]) -> Result<()> {
        if self.skips(state) {
            return Ok(());
        }
        let nanos = sim_nanos(state.sequence, self.dt_s);
        let markers = surroundings::obstacle_markers(obstacles, Time::from_nanos(nanos));
        self.write(Topic::Obstacles, nanos, &markers)
    }

    /// Writes one state of the sim (or skips it: a training episode in train mode).
    pub fn state(&mut self, state: &StateMsg) -> Result<()> {
        if self.last_sequence != 0 && state.sequence > self.last_sequence + 1 {
            self.recorded.lost += state.sequence - self.last_sequence - 1;
        }
        self.last_sequence = state.sequence;
        let header = state.header;
        if self.skips(state) {
            return Ok(());
        }
        let nanos = sim_nanos(state.sequence, self.dt_s);
        let stamp = Header {
            stamp: Time::from_nanos(nanos),
            frame_id: "world".into(),
        };
        let n = (state.n_agents as usize).min(self.n_agents);
        if header.has(FLAG_EPISODE_START) {
            self.write(Topic::Episode, nanos, &header.episode)?;
            self.recorded.episodes += 1;
        }
        self.formation(state, n, nanos, &stamp)?;
        let tf = TfMessage {
            transforms: (0..n)
                .map(|robot| {
                    let pose = odometry_of(state, robot, stamp.stamp).pose.pose;
                    TransformStamped {
                        header: stamp.clone(),
                        child_frame_id: format!("robot_{robot}/base_link"),
                        transform: Transform {
                            translation: pose.position,
                            rotation: pose.orientation,
                        },
                    }
                })
                .collect(),
        };
        self.write(Topic::Tf, nanos, &tf)?;
        for robot in 0..n {
            self.write(Topic::Odometry(robot), nanos, &odometry_of(state, robot, stamp.stamp))?;
            let scan = self
                .scan
                .and_then(|layout| layout.of_state(state, robot, stamp.stamp, self.dt_s));
            if let Some(scan) = scan {
                self.write(Topic::Scan(robot), nanos, &scan)?;
            }
        }
        if header.tick > 0 {
            // The command in use over the transition into this state: stamped when it began.
            let began = sim_nanos(state.sequence.saturating_sub(1), self.dt_s);
            for robot in 0..n {
                let [v, w] = state.applied[robot].map(f64::from);
                let command = TwistStamped {
                    header: Header {
                        stamp: Time::from_nanos(began),
                        frame_id: format!("robot_{robot}/base_link"),
                    },
                    twist: Twist {
                        linear: Vector3 { x: v, y: 0.0, z: 0.0 },
                        angular: Vector3 { x: 0.0, y: 0.0, z: w },
                    },
                };
                self.write(Topic::Command(robot), began, &command)?;
            }
            self.write(Topic::Reward, nanos, &state.reward)?;
        }
        if header.has(FLAG_EPISODE_END) {
            self.write(Topic::Outcome, nanos, &outcome_name(state.outcome).to_string())?;
        }
        self.recorded.states += 1;
        Ok(())
    }

    /// The goal, each robot's target (goal + its slot's offset) and the slot map, at an
    /// episode's first state and whenever they change (a shape change).
    fn formation(&mut self, state: &StateMsg, n: usize, nanos: u64, stamp: &Header) -> Result<()> {
        let goal = state.goal;
        let targets: Vec<[f32; 2]> = (0..n)
            .map(|robot| [goal[0] + state.slots[robot][0], goal[1] + state.slots[robot][1]])
            .chain(std::iter::once(goal))
            .collect();
        let slots = state.slot[..n].to_vec();
        let current = (state.header.episode, targets, slots);
        if self.last_formation.as_ref() == Some(&current) {
            return Ok(());
        }
        let (_, targets, slots) = &current;
        let pose_at = |[x, y]: [f32; 2]| Pose {
            position: Vector3 {
                x: f64::from(x),
                y: f64::from(y),
                z: 0.0,
            },
            orientation: Quaternion::from_yaw(0.0),
        };
        let goal_msg = PoseArray {
            header: stamp.clone(),
            poses: vec![pose_at(goal)],
        };
        let target_msg = PoseArray {
            header: stamp.clone(),
            poses: targets[..n].iter().copied().map(pose_at).collect(),
        };
        let slot_msg = UInt32MultiArray {
            layout: wire::MultiArrayLayout {
                dim: vec![wire::MultiArrayDimension {
                    label: "slot_of_robot".into(),
                    size: n as u32,
                    stride: n as u32,
                }],
                data_offset: 0,
            },
            data: slots.clone(),
        };
        self.write(Topic::Goal, nanos, &goal_msg)?;
        self.write(Topic::Target, nanos, &target_msg)?;
        self.write(Topic::Slot, nanos, &slot_msg)?;
        self.last_formation = Some(current);
        Ok(())
    }

    /// Writes the MCAP summary and index; returns what was recorded.
    pub fn finish(mut self) -> Result<Recorded> {
        self.writer.finish().context("cannot finish the MCAP file")?;
        Ok(self.recorded)
    }
}

/// What the recorder records, and the run it belongs to.
#[derive(Debug, Clone)]
pub struct Options {
    /// The run's iceoryx2 identity.
    pub identity: RunIdentity,
    /// Where `run.mcap` goes.
    pub run_dir: PathBuf,
    /// Robots of the swarm.
    pub n_agents: usize,
    /// train (only evaluation episodes) or eval (every episode).
    pub mode: Mode,
    /// The services' sizing and contract.
    pub sizing: Sizing,
    /// Topic names.
    pub names: Names,
    /// The range sensor in the observations (`None`: the model has none, no scans).
    pub scan: Option<ScanLayout>,
    /// The run has obstacles: each episode's are recorded.
    pub obstacles: bool,
    /// One tick of sim time, seconds.
    pub dt_s: f64,
    /// How long a sim may be silent before its process is checked.
    pub sim_silence: Duration,
    /// How long a sim may be away at all.
    pub startup_timeout: Duration,
}

/// Subscribes to the sim's state stream, calls `ready` once the subscriber exists, and records
/// every state into `<run dir>/run.mcap` until the run ends (or the sim is gone, or Ctrl-C:
/// the file is finished either way).
pub fn run(options: &Options, ready: impl FnOnce() -> Result<()>) -> Result<Recorded> {
    let node = services::create_node::<ipc::Service>(&options.identity, "mcap")?;
    let sizing = &options.sizing;
    let states = services::state_stream(&node, sizing)?
        .subscriber_builder()
        .buffer_size(sizing.stream_buffer)
        .create()
        .context("mcap: state subscriber")?;
    // The sim rings the readers' wake-up every half window and at each episode's end, and
    // never runs more than a window ahead of what `progress` acknowledges; the stream holds
    // two windows, so nothing is lost.
    let wake = services::critic_wake_event(&node, sizing)?
        .listener_builder()
        .create()
        .context("mcap: wake-up listener")?;
    let progress = ProgressPublisher::open(&node, sizing, StreamReader::Recorder)?;
    progress.publish(0, 0, 0)?;
    let path = options.run_dir.join(MCAP_FILE);
    let file = File::create(&path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut obstacles = match options.obstacles {
        true => Some(ObstacleFeed::new(&node, sizing).context("mcap")?),
        false => None,
    };
    let mut recorder = Recorder::new(
        BufWriter::new(file),
        options.names.clone(),
        options.n_agents,
        options.dt_s,
        options.mode,
        options.scan,
        options.obstacles,
    )?;
    ready()?;
    let mut sim_watch = SimWatch::new(options.sim_silence, options.startup_timeout);
    let outcome = record(
        options,
        &states,
        obstacles.as_mut(),
        (&wake, &progress),
        &mut recorder,
        &mut sim_watch,
    );
    let recorded = recorder.finish()?;
    outcome.map(|()| recorded)
}

fn record(
    options: &Options,
    states: &iceoryx2::port::subscriber::Subscriber<ipc::Service, StateMsg, ()>,
    mut obstacles: Option<&mut ObstacleFeed>,
    (wake, progress): (
        &iceoryx2::port::listener::Listener<ipc::Service>,
        &ProgressPublisher<ipc::Service>,
    ),
    recorder: &mut Recorder<BufWriter<File>>,
    sim_watch: &mut SimWatch,
) -> Result<()> {
    let mut acknowledged = 0;
    loop {
        services::wait_for_event(wake, WAIT_SLICE)?;
        while let Some(sample) = states.receive().context("mcap: receive state")? {
            let state = sample.payload();
            services::check_sim_protocol(&state.header, "mcap", "recorder")?;
            sim_watch.heard();
            acknowledged = state.sequence;
            if state.header.has(FLAG_RUN_END) {
                return Ok(());
            }
            if state.header.has(FLAG_EPISODE_START)
                && let Some(feed) = obstacles.as_deref_mut()
                && let Some(list) = feed.of_episode(state.header.episode)?
            {
                recorder.obstacles(state, &list)?;
            }
            recorder.state(state)?;
        }
        // Also when nothing came: the sim hears the recorder is alive.
        progress.publish(acknowledged, 0, 0)?;
        if termination_requested() {
            return Ok(());
        }
        if let Some(quiet) = sim_watch.gone::<ipc::Service>(&options.identity, "mcap")? {
            bail!(
                "mcap: no state from the sim for {:.1} s; is it alive?",
                quiet.as_secs_f64()
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_twist_stamped_schema_is_its_definition_then_each_dependency_once() {
        let text = schema_text("geometry_msgs/msg/TwistStamped").expect("schema");
        let bar = "=".repeat(80);
        let expected = format!(
            "std_msgs/Header header\nTwist twist\n\
             {bar}\nMSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n\
             {bar}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n\
             {bar}\nMSG: geometry_msgs/Twist\nVector3 linear\nVector3 angular\n\
             {bar}\nMSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
        );
        assert_eq!(text, expected);
    }

    #[test]
    fn every_schema_defines_every_type_it_names_exactly_once() {
        for ty in [
            "nav_msgs/msg/Odometry",
            "geometry_msgs/msg/TwistStamped",
            "geometry_msgs/msg/PoseArray",
            "std_msgs/msg/UInt32MultiArray",
            "std_msgs/msg/Float32",
            "std_msgs/msg/String",
            "std_msgs/msg/UInt32",
            "sensor_msgs/msg/LaserScan",
            "visualization_msgs/msg/MarkerArray",
            "tf2_msgs/msg/TFMessage",
        ] {
            let text = schema_text(ty).expect("schema");
            let sections: Vec<&str> = text.split(&format!("{SEPARATOR}\n")).collect();
            let mut defined = vec![short_name(ty)];
            for section in &sections[1..] {
                let name = section
                    .lines()
                    .next()
                    .and_then(|l| l.strip_prefix("MSG: "))
                    .expect("MSG line");
                assert!(!defined.contains(&name.to_string()), "{ty}: {name} twice");
                defined.push(name.to_string());
            }
            for (k, section) in sections.iter().enumerate() {
                let (package, body) = match k {
                    0 => (
                        short_name(ty).split('/').next().map(str::to_string).expect("pkg"),
                        *section,
                    ),
                    _ => {
                        let (first, body) = section.split_once('\n').expect("body");
                        let name = first.trim_start_matches("MSG: ");
                        (name.split('/').next().expect("pkg").to_string(), body)
                    }
                };
                for used in field_types(&package, body) {
                    assert!(defined.contains(&used), "{ty}: {used} used but not defined");
                }
            }
        }
        let odometry = schema_text("nav_msgs/msg/Odometry").expect("odometry");
        assert_eq!(odometry.matches("\nMSG: ").count(), 9, "{odometry}");
        assert!(odometry.starts_with("std_msgs/Header header\nstring child_frame_id\n"));
        assert!(
            odometry.contains("MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n")
        );
    }

    /// The states of one 2-tick episode of 3 robots numbered from `first`, flagged `extra`.
    fn episode(episode: u32, first: u64, extra: u32) -> Vec<StateMsg> {
        (0..3)
            .map(|tick| {
                let mut flags = extra;
                if tick == 0 {
                    flags |= FLAG_EPISODE_START;
                }
                if tick == 2 {
                    flags |= FLAG_EPISODE_END;
                }
                let mut state = StateMsg {
                    header: formation_protocol::wire::Header::new(episode, tick, flags),
                    n_agents: 3,
                    sequence: first + u64::from(tick),
                    outcome: if tick == 2 { OUTCOME_SUCCESS } else { 0 },
                    ..StateMsg::default()
                };
                state.slot[..3].copy_from_slice(&[0, 1, 2]);
                state
            })
            .collect()
    }

    /// (topic, log time) of every message of an MCAP file.
    fn messages(bytes: &[u8]) -> Vec<(String, u64)> {
        mcap::MessageStream::new(bytes)
            .expect("stream")
            .map(|m| m.expect("message"))
            .map(|m| (m.channel.topic.clone(), m.log_time))
            .collect()
    }

    fn record(mode: Mode, states: &[StateMsg]) -> (Vec<(String, u64)>, Recorded) {
        let names = Names::new(0, "formation").expect("names");
        let mut out = std::io::Cursor::new(Vec::new());
        let mut recorder = Recorder::new(&mut out, names, 3, 0.1, mode, None, false).expect("recorder");
        for state in states {
            recorder.state(state).expect("state");
        }
        let recorded = recorder.finish().expect("finish");
        (messages(out.get_ref()), recorded)
    }

    #[test]
    fn training_records_only_its_evaluation_episodes_and_eval_every_episode() {
        let mut states = episode(0, 1, 0);
        states.extend(episode(1, 4, FLAG_EVAL_EPISODE));
        states.extend(episode(2, 7, 0));
        let (train, recorded) = record(Mode::Train, &states);
        assert_eq!((recorded.states, recorded.episodes, recorded.lost), (3, 1, 0));
        let odometry: Vec<u64> = train
            .iter()
            .filter(|(topic, _)| topic == "/formation/robot_0/odom")
            .map(|(_, t)| *t)
            .collect();
        assert_eq!(
            odometry,
            [300_000_000, 400_000_000, 500_000_000],
            "sim time of states 4-6"
        );
        let count = |messages: &[(String, u64)], topic: &str| messages.iter().filter(|(t, _)| t == topic).count();
        assert_eq!(count(&train, "/formation/outcome"), 1);
        assert_eq!(count(&train, "/formation/robot_2/cmd_applied"), 2, "one per step");
        let (eval, recorded) = record(Mode::Eval, &states);
        assert_eq!((recorded.states, recorded.episodes), (9, 3));
        assert_eq!(count(&eval, "/formation/robot_1/odom"), 9);
        assert_eq!(count(&eval, "/formation/target"), 3, "once an episode: no shape change");
        let (_, gap) = record(Mode::Eval, &[states[0], states[1], states[5]]);
        assert_eq!(gap.lost, 3, "states 3-5 never read");
    }

    #[test]
    fn scans_follow_the_odometry_but_for_lost_observations_and_obstacles_come_once_an_episode() {
        let names = Names::new(0, "formation").expect("names");
        let mut out = std::io::Cursor::new(Vec::new());
        let scan = ScanLayout {
            offset: 16,
            rays: 16,
            range_m: 2.0,
        };
        let mut recorder = Recorder::new(&mut out, names, 3, 0.1, Mode::Eval, Some(scan), true).expect("recorder");
        let wall = Obstacle::Wall {
            a: [1.0, 1.0],
            b: [1.0, 3.0],
            thickness: 0.1,
        };
        let mut states = episode(0, 1, 0);
        states[1].observation_lost = 1 << 1;
        for state in &states {
            if state.header.has(FLAG_EPISODE_START) {
                recorder.obstacles(state, &[wall]).expect("obstacles");
            }
            recorder.state(state).expect("state");
        }
        recorder.finish().expect("finish");
        let messages = messages(out.get_ref());
        let times = |topic: &str| -> Vec<u64> {
            messages
                .iter()
                .filter(|(t, _)| t == topic)
                .map(|(_, time)| *time)
                .collect()
        };
        assert_eq!(times("/formation/robot_0/scan"), times("/formation/robot_0/odom"));
        assert_eq!(times("/formation/robot_1/scan"), [0, 200_000_000], "tick 1 was lost");
        assert_eq!(times("/formation/obstacles"), [0], "at the episode's first state");
        assert_eq!(times("/tf"), [0, 100_000_000, 200_000_000], "every state");
    }

    #[test]
    fn a_missing_definition_is_an_error_not_a_short_schema() {
        let err = schema_text("sensor_msgs/msg/Imu").expect_err("unknown");
        assert!(err.to_string().contains("sensor_msgs/Imu"), "{err}");
    }
}
