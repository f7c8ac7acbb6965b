//! Payloads that travel over iceoryx2. Every type is `#[repr(C)]`, `Copy`, fixed size and
//! carries an explicit type name, so any language binding that agrees on the layout can read it.

use iceoryx2_bb_derive_macros::ZeroCopySend;
use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::{ACTION_DIM, MAX_AGENTS, MAX_DELAY_TICKS, MAX_OBS_DIM, MAX_OBSTACLES, NEIGHBOURS};

/// Bumped whenever a payload's layout or meaning changes.
pub const PROTOCOL_VERSION: u32 = 6;

/// `Header::flags`: first tick of an episode (agents reset their history).
pub const FLAG_EPISODE_START: u32 = 1;
/// `Header::flags`: the episode has ended at this tick; no command is expected.
pub const FLAG_EPISODE_END: u32 = 2;
/// `Header::flags`: the run is over; every process finishes and exits.
pub const FLAG_RUN_END: u32 = 4;
/// `Header::flags` on a command: a greeting sent once at start-up, not a command for a tick.
pub const FLAG_HELLO: u32 = 8;
/// `Header::flags`: a train-mode episode the agents play without exploration noise, so the
/// critic can measure the current policy.
pub const FLAG_EVAL_EPISODE: u32 = 16;

/// Common to every payload: who may read it and which tick it belongs to.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
#[type_name("formation::Header")]
pub struct Header {
    /// [`PROTOCOL_VERSION`] of the sender.
    pub protocol_version: u32,
    /// Episode counter, from 0.
    pub episode: u32,
    /// Tick within the episode, from 0.
    pub tick: u32,
    /// `FLAG_*` bits.
    pub flags: u32,
}

impl Header {
    /// A header of this build's protocol version.
    pub fn new(episode: u32, tick: u32, flags: u32) -> Self {
        Self {
            protocol_version: PROTOCOL_VERSION,
            episode,
            tick,
            flags,
        }
    }

    /// True when `flag` is set.
    pub fn has(&self, flag: u32) -> bool {
        self.flags & flag != 0
    }
}

/// sim -> agent i: what robot i sees at a tick, in its own frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
#[type_name("formation::Observation")]
pub struct ObservationMsg {
    /// Episode, tick and flags.
    pub header: Header,
    /// The observing robot.
    pub agent: u32,
    /// Number of robots in the swarm.
    pub n_agents: u32,
    /// Floats of `obs` in use: the run's observation model (`env.observation`).
    pub dim: u32,
    /// The observation, laid out as `formation_core::observation` names it: for each of the 2
    /// neighbours x, y, cos(dtheta), sin(dtheta), desired distance; the goal's x, y; then what
    /// the model adds. Entries past `dim` are zero.
    pub obs: [f32; MAX_OBS_DIM],
}

/// agent i -> sim: the command for one tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
#[type_name("formation::Command")]
pub struct CommandMsg {
    /// Episode and tick of the observation this answers.
    pub header: Header,
    /// The commanding robot.
    pub agent: u32,
    /// Version of the policy weights that produced it (0: scripted or random).
    pub policy_version: u32,
    /// Forward speed, m/s.
    pub v: f32,
    /// Turn rate, rad/s.
    pub w: f32,
    /// Random, non-zero, new for every agent process: a restarted robot greets with a new one.
    pub session: u32,
}

/// `StateMsg::outcome`: the episode goes on.
pub const OUTCOME_RUNNING: u32 = 0;
/// `StateMsg::outcome`: C3 reached (terminal).
pub const OUTCOME_SUCCESS: u32 = 1;
/// `StateMsg::outcome`: C2, two robots collided (terminal).
pub const OUTCOME_COLLISION: u32 = 2;
/// `StateMsg::outcome`: the time limit (a truncation, not terminal).
pub const OUTCOME_TIMEOUT: u32 = 3;
/// `StateMsg::outcome`: the run was stopped mid-episode (a truncation).
pub const OUTCOME_ABORTED: u32 = 4;

/// sim -> critic (and the view): the true world at a tick, plus what led to it.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::State")]
pub struct StateMsg {
    /// Episode, tick and flags.
    pub header: Header,
    /// Number of robots; entries past it are zero.
    pub n_agents: u32,
    /// `OUTCOME_*` of the transition into this tick.
    pub outcome: u32,
    /// Shared reward of the transition into this tick (0 at tick 0).
    pub reward: f32,
    /// How many robots missed the previous tick (nothing new arrived: the command in use stayed).
    pub missed: u32,
    /// Counts every state the sim publishes in this run, from 1 (flow control).
    pub sequence: u64,
    /// Bit i set: robot i's observation of this tick was lost (`observations[i]` is what it
    /// would have been told; it was not published to it).
    pub observation_lost: u64,
    /// World poses (x, y, theta).
    pub poses: [[f32; 3]; MAX_AGENTS],
    /// The command (v, w) in use for the transition into this tick, clamped to the limits: the
    /// one the robot sent for the previous tick when it was on time, else the one the accounting
    /// rule kept or took up late (docs/PROTOCOL.md). The replay's action. Zero at tick 0.
    pub applied: [[f32; ACTION_DIM]; MAX_AGENTS],
    /// The velocity (v, w) that acted on the physics in the transition into this tick: `applied`
    /// after the actuation delay, the motor lag and a dead controller (`[reality]`); equal to
    /// `applied` with the reality model off.
    pub acting: [[f32; ACTION_DIM]; MAX_AGENTS],
    /// The commands queued at each robot's motors after that transition, the next to act first
    /// (`queued_len` of them; the rest zero): with `acting`, what keeps the state Markov under
    /// delay and lag.
    pub queued: [[[f32; ACTION_DIM]; MAX_DELAY_TICKS]; MAX_AGENTS],
    /// How many of `queued` are in use for each robot (its actuation delay, ticks).
    pub queued_len: [u32; MAX_AGENTS],
    /// What each robot was told at this tick (its observation after the sensor noise, as
    /// published on its `obs/i` stream; entries past the observation model's size are zero).
    pub observations: [[f32; MAX_OBS_DIM]; MAX_AGENTS],
    /// Desired distance of each robot's two observed edges (to the robots in the next two
    /// slots), at this tick: a shape change rewrites them.
    pub desired: [[f32; NEIGHBOURS]; MAX_AGENTS],
    /// Each robot's offset from the goal in the formation in force, world frame.
    pub slots: [[f32; 2]; MAX_AGENTS],
    /// Goal of the formation's centroid, world frame.
    pub goal: [f32; 2],
    /// The slot map: robot i holds slot `slot[i]` of the formation in force (i until the
    /// mission planner reassigns the slots at a shape change); robot i observes the robots in
    /// slots `slot[i] + 1` and `slot[i] + 2` mod M, M the robots present; a robot out of the
    /// formation holds [`SLOT_NONE`].
    pub slot: [u32; MAX_AGENTS],
    /// Bit i set: robot i is in the formation at this tick (present). A robot leaves when its
    /// controller fails, when the control service removes it, or after 10 silent ticks in a
    /// row, and comes back after 5 answers in a row or when restored; the slots, edges,
    /// success and formation error are the present robots'.
    pub present: u64,
}

/// `ObstaclesMsg::shapes`: a disc, `values` = centre x, centre y, radius, 0, 0.
pub const OBSTACLE_DISC: u32 = 1;
/// `ObstaclesMsg::shapes`: a wall, `values` = a.x, a.y, b.x, b.y, thickness (a rectangle whose
/// centre line runs from a to b, flat ends).
pub const OBSTACLE_WALL: u32 = 2;

/// sim -> agents, critic and observers, once per episode before its first tick: the episode's
/// obstacles, world frame, metres (none in an open episode: `count` = 0).
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::Obstacles")]
pub struct ObstaclesMsg {
    /// The episode (tick 0, the flags of its first state).
    pub header: Header,
    /// Obstacles in use; entries past it are zero.
    pub count: u32,
    /// The kind the episode drew: 0 none, 1 forest, 2 passage, 3 trap.
    pub kind: u32,
    /// The episode's time limit, steps (it depends on the obstacles and the goal distance).
    pub time_limit: u32,
    /// `OBSTACLE_DISC` or `OBSTACLE_WALL`, per obstacle.
    pub shapes: [u32; MAX_OBSTACLES],
    /// Each obstacle's five numbers (see the shape constants).
    pub values: [[f64; 5]; MAX_OBSTACLES],
}

impl Default for ObstaclesMsg {
    fn default() -> Self {
        Self {
            header: Header::default(),
            count: 0,
            kind: 0,
            time_limit: 0,
            shapes: [0; MAX_OBSTACLES],
            values: [[0.0; 5]; MAX_OBSTACLES],
        }
    }
}

/// sim -> privileged planners (`formation-agent --policy oracle`) and observers, every tick
/// before the observations: the true poses and the formation in force, without the state's
/// training payload.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::Truth")]
pub struct TruthMsg {
    /// Episode, tick and flags (as the tick's observations).
    pub header: Header,
    /// Number of robots; entries past it are zero.
    pub n_agents: u32,
    /// Bit i set: robot i is in the formation (as `StateMsg::present`).
    pub present: u64,
    /// World poses (x, y, theta).
    pub poses: [[f32; 3]; MAX_AGENTS],
    /// Each robot's offset from the goal in the formation in force, world frame.
    pub slots: [[f32; 2]; MAX_AGENTS],
    /// Goal of the formation's centroid, world frame.
    pub goal: [f32; 2],
}

impl Default for TruthMsg {
    fn default() -> Self {
        Self {
            header: Header::default(),
            n_agents: 0,
            present: 0,
            poses: [[0.0; 3]; MAX_AGENTS],
            slots: [[0.0; 2]; MAX_AGENTS],
            goal: [0.0; 2],
        }
    }
}

/// `StateMsg::slot` of a robot out of the formation.
pub const SLOT_NONE: u32 = u32::MAX;

impl Default for StateMsg {
    fn default() -> Self {
        Self {
            header: Header::default(),
            n_agents: 0,
            outcome: OUTCOME_RUNNING,
            reward: 0.0,
            missed: 0,
            sequence: 0,
            observation_lost: 0,
            poses: [[0.0; 3]; MAX_AGENTS],
            applied: [[0.0; ACTION_DIM]; MAX_AGENTS],
            acting: [[0.0; ACTION_DIM]; MAX_AGENTS],
            queued: [[[0.0; ACTION_DIM]; MAX_DELAY_TICKS]; MAX_AGENTS],
            queued_len: [0; MAX_AGENTS],
            observations: [[0.0; MAX_OBS_DIM]; MAX_AGENTS],
            desired: [[0.0; NEIGHBOURS]; MAX_AGENTS],
            slots: [[0.0; 2]; MAX_AGENTS],
            goal: [0.0; 2],
            slot: [0; MAX_AGENTS],
            present: 0,
        }
    }
}

/// critic -> sim: how far the critic has consumed the stream (train-mode flow control).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::CriticProgress")]
pub struct CriticProgressMsg {
    /// Protocol version of the critic.
    pub protocol_version: u32,
    /// Latest published actor weights version.
    pub weights_version: u32,
    /// The critic has processed every state up to this `StateMsg::sequence` (as far as its
    /// gradient updates have paid for them in train mode). States lost on the way do not hold
    /// it back.
    pub acknowledged_sequence: u64,
    /// Gradient updates so far.
    pub updates: u64,
    /// Random, non-zero, new for every critic process: a restarted critic counts from zero.
    pub session: u64,
}

/// critic -> agents: the user header in front of one actor's flat `[f32]` weights.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
#[type_name("formation::WeightsHeader")]
pub struct WeightsHeader {
    /// Protocol version of the critic.
    pub protocol_version: u32,
    /// Which actor (0 for the shared actor, else the robot index).
    pub actor_index: u32,
    /// Increases with every publication, from 1.
    pub version: u32,
    /// Number of f32 values that follow.
    pub len: u32,
}

/// `ControlRequest::kind`: give the swarm a new formation (`shape`, `scale`, `orientation`).
pub const CONTROL_SET_FORMATION: u32 = 1;
/// `ControlRequest::kind`: move the goal to `goal`.
pub const CONTROL_SET_GOAL: u32 = 2;
/// `ControlRequest::kind`: take robot `robot` out of the formation for the rest of the episode.
pub const CONTROL_REMOVE_ROBOT: u32 = 3;
/// `ControlRequest::kind`: bring robot `robot`, removed earlier, back into the formation.
pub const CONTROL_RESTORE_ROBOT: u32 = 4;
/// `ControlReply::status`: the change is in force from `ControlReply::tick`.
pub const CONTROL_OK: u32 = 0;
/// `ControlReply::status`: the request was refused; `ControlReply::message` says why.
pub const CONTROL_REFUSED: u32 = 1;
/// Bytes of `ControlRequest::shape` (a shape's name, NUL-padded UTF-8).
pub const CONTROL_SHAPE_BYTES: usize = 16;
/// Bytes of `ControlReply::message` (NUL-padded UTF-8).
pub const CONTROL_MESSAGE_BYTES: usize = 120;

/// client -> sim (request-response `formation/control`): a live change to the current episode.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::ControlRequest")]
pub struct ControlRequest {
    /// [`PROTOCOL_VERSION`] of the client.
    pub protocol_version: u32,
    /// `CONTROL_SET_*`.
    pub kind: u32,
    /// The new formation's shape name (`random`, `ring`, `line`, `wedge`, `grid`), NUL-padded.
    pub shape: [u8; CONTROL_SHAPE_BYTES],
    /// The new formation's size as a multiple of the shape as drawn.
    pub scale: f32,
    /// The new formation's rotation, radians counter-clockwise in the world frame.
    pub orientation: f32,
    /// The new goal, world frame, metres.
    pub goal: [f32; 2],
    /// The robot to remove or restore.
    pub robot: u32,
}

/// sim -> client: the answer to a [`ControlRequest`], sent at the tick the sim read it.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("formation::ControlReply")]
pub struct ControlReply {
    /// [`PROTOCOL_VERSION`] of the sim.
    pub protocol_version: u32,
    /// `CONTROL_OK` or `CONTROL_REFUSED`.
    pub status: u32,
    /// The episode the change applies to.
    pub episode: u32,
    /// The tick whose observations and state first carry the change.
    pub tick: u32,
    /// Why a request was refused (empty on success), NUL-padded UTF-8.
    pub message: [u8; CONTROL_MESSAGE_BYTES],
}

impl ControlReply {
    /// A reply of this build's protocol version; `message` is cut to fit.
    pub fn new(status: u32, episode: u32, tick: u32, message: &str) -> Self {
        let mut bytes = [0u8; CONTROL_MESSAGE_BYTES];
        let mut len = message.len().min(CONTROL_MESSAGE_BYTES);
        while !message.is_char_boundary(len) {
            len -= 1;
        }
        bytes[..len].copy_from_slice(&message.as_bytes()[..len]);
        Self {
            protocol_version: PROTOCOL_VERSION,
            status,
            episode,
            tick,
            message: bytes,
        }
    }
}
