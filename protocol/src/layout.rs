//! The memory layout of every payload in [`crate::wire`], as JSON: size, alignment, iceoryx2
//! type name and each field's offset, size and element type, plus the protocol's constants.
//!
//! Bindings in other languages mirror the payloads by hand (`python/formation_swarm/wire.py`).
//! `formation_core::layout` adds the observation models to this JSON and keeps
//! `python/formation_swarm/layout.json` equal to it (a unit test there), so a layout change in
//! Rust fails `cargo test` until the file is regenerated, and then the Python conformance test
//! fails until the mirrors follow. `formation-layout` (in `core/`) prints the same JSON.

use std::fmt::Write as _;
use std::mem::{align_of, offset_of, size_of};

use iceoryx2_bb_elementary_traits::zero_copy_send::ZeroCopySend;

use crate::wire::*;
use crate::{ACTION_DIM, MAX_AGENTS, MAX_DELAY_TICKS, MAX_OBS_DIM, MAX_OBSTACLES, MIN_AGENTS, NEIGHBOURS};

/// One field: name, byte offset, byte size and element type (`u32`, `f32[16]`, `f32[64][3]`, or
/// another payload's type name).
struct Field(&'static str, usize, usize, &'static str);

fn type_name<T: ZeroCopySend>() -> &'static str {
    // SAFETY: only reads the name the payload declares with `#[type_name]`.
    unsafe { <T as ZeroCopySend>::type_name() }
}

fn payload<T: ZeroCopySend>(out: &mut String, rust_name: &str, fields: &[Field]) {
    let _ = write!(
        out,
        "    {{\"rust\": \"{rust_name}\", \"type_name\": \"{}\", \"size\": {}, \"align\": {}, \"fields\": [",
        type_name::<T>(),
        size_of::<T>(),
        align_of::<T>()
    );
    for (i, Field(name, offset, size, ty)) in fields.iter().enumerate() {
        let sep = if i == 0 { "" } else { "," };
        let _ = write!(
            out,
            "{sep}\n      {{\"name\": \"{name}\", \"offset\": {offset}, \"size\": {size}, \"type\": \"{ty}\"}}"
        );
    }
    out.push_str("\n    ]}");
}

macro_rules! field {
    ($t:ty, $f:ident, $ty:expr) => {
        Field(stringify!($f), offset_of!($t, $f), size_of_field(|v: &$t| &v.$f), $ty)
    };
}

fn size_of_field<T, F>(_: impl Fn(&T) -> &F) -> usize {
    size_of::<F>()
}

/// The layout of every payload and the protocol's constants, as pretty-printed JSON, followed
/// by `more`: further members of the top-level object (`  "key": value`, comma-separated, no
/// trailing comma), or nothing when empty.
pub fn layout_json_with(more: &str) -> String {
    let mut out = String::from("{\n");
    let _ = writeln!(out, "  \"protocol_version\": {PROTOCOL_VERSION},");
    write_constants(&mut out);
    out.push_str(",\n  \"payloads\": [\n");
    write_payloads(&mut out);
    out.push_str("\n  ]");
    if !more.is_empty() {
        out.push_str(",\n");
        out.push_str(more);
    }
    out.push_str("\n}\n");
    out
}

/// The `"constants"` object.
fn write_constants(out: &mut String) {
    let constants: [(&str, u64); 21] = [
        ("PROTOCOL_VERSION", u64::from(PROTOCOL_VERSION)),
        ("FLAG_EPISODE_START", u64::from(FLAG_EPISODE_START)),
        ("FLAG_EPISODE_END", u64::from(FLAG_EPISODE_END)),
        ("FLAG_RUN_END", u64::from(FLAG_RUN_END)),
        ("FLAG_HELLO", u64::from(FLAG_HELLO)),
        ("FLAG_EVAL_EPISODE", u64::from(FLAG_EVAL_EPISODE)),
        ("OUTCOME_RUNNING", u64::from(OUTCOME_RUNNING)),
        ("OUTCOME_SUCCESS", u64::from(OUTCOME_SUCCESS)),
        ("OUTCOME_COLLISION", u64::from(OUTCOME_COLLISION)),
        ("OUTCOME_TIMEOUT", u64::from(OUTCOME_TIMEOUT)),
        ("OUTCOME_ABORTED", u64::from(OUTCOME_ABORTED)),
        ("MAX_AGENTS", MAX_AGENTS as u64),
        ("MIN_AGENTS", MIN_AGENTS as u64),
        ("NEIGHBOURS", NEIGHBOURS as u64),
        ("MAX_OBS_DIM", MAX_OBS_DIM as u64),
        ("ACTION_DIM", ACTION_DIM as u64),
        ("MAX_DELAY_TICKS", MAX_DELAY_TICKS as u64),
        ("SPARE_PORTS", crate::SPARE_PORTS as u64),
        ("MAX_OBSTACLES", MAX_OBSTACLES as u64),
        ("OBSTACLE_DISC", u64::from(OBSTACLE_DISC)),
        ("OBSTACLE_WALL", u64::from(OBSTACLE_WALL)),
    ];
    out.push_str("  \"constants\": {");
    for (i, (name, value)) in constants.iter().enumerate() {
        let sep = if i == 0 { "" } else { "," };
        let _ = write!(out, "{sep}\n    \"{name}\": {value}");
    }
    out.push_str("\n  }");
}

/// The entries of the `"payloads"` array, comma-separated: what sim and agents exchange every
/// tick, the sim's state, the critic's messages, then the control service's.
fn write_payloads(out: &mut String) {
    write_tick_payloads(out);
    out.push_str(",\n");
    write_state_payload(out);
    out.push_str(",\n");
    write_critic_payloads(out);
    out.push_str(",\n");
    write_control_payloads(out);
}

/// The common header, then sim -> agent (the observation) and agent -> sim (the command).
fn write_tick_payloads(out: &mut String) {
    payload::<Header>(
        out,
        "Header",
        &[
            field!(Header, protocol_version, "u32"),
            field!(Header, episode, "u32"),
            field!(Header, tick, "u32"),
            field!(Header, flags, "u32"),
        ],
    );
    out.push_str(",\n");
    payload::<ObservationMsg>(
        out,
        "ObservationMsg",
        &[
            field!(ObservationMsg, header, "formation::Header"),
            field!(ObservationMsg, agent, "u32"),
            field!(ObservationMsg, n_agents, "u32"),
            field!(ObservationMsg, dim, "u32"),
            field!(ObservationMsg, obs, "f32[32]"),
        ],
    );
    out.push_str(",\n");
    payload::<CommandMsg>(
        out,
        "CommandMsg",
        &[
            field!(CommandMsg, header, "formation::Header"),
            field!(CommandMsg, agent, "u32"),
            field!(CommandMsg, policy_version, "u32"),
            field!(CommandMsg, v, "f32"),
            field!(CommandMsg, w, "f32"),
            field!(CommandMsg, session, "u32"),
        ],
    );
}

/// sim -> critic and the view: the true world at a tick.
fn write_state_payload(out: &mut String) {
    payload::<StateMsg>(
        out,
        "StateMsg",
        &[
            field!(StateMsg, header, "formation::Header"),
            field!(StateMsg, n_agents, "u32"),
            field!(StateMsg, outcome, "u32"),
            field!(StateMsg, reward, "f32"),
            field!(StateMsg, missed, "u32"),
            field!(StateMsg, sequence, "u64"),
            field!(StateMsg, observation_lost, "u64"),
            field!(StateMsg, poses, "f32[64][3]"),
            field!(StateMsg, applied, "f32[64][2]"),
            field!(StateMsg, acting, "f32[64][2]"),
            field!(StateMsg, queued, "f32[64][10][2]"),
            field!(StateMsg, queued_len, "u32[64]"),
            field!(StateMsg, observations, "f32[64][32]"),
            field!(StateMsg, desired, "f32[64][2]"),
            field!(StateMsg, slots, "f32[64][2]"),
            field!(StateMsg, goal, "f32[2]"),
            field!(StateMsg, slot, "u32[64]"),
            field!(StateMsg, present, "u64"),
        ],
    );
    out.push_str(",\n");
    payload::<ObstaclesMsg>(
        out,
        "ObstaclesMsg",
        &[
            field!(ObstaclesMsg, header, "formation::Header"),
            field!(ObstaclesMsg, count, "u32"),
            field!(ObstaclesMsg, kind, "u32"),
            field!(ObstaclesMsg, time_limit, "u32"),
            field!(ObstaclesMsg, shapes, "u32[128]"),
            field!(ObstaclesMsg, values, "f64[128][5]"),
        ],
    );
    out.push_str(",\n");
    payload::<TruthMsg>(
        out,
        "TruthMsg",
        &[
            field!(TruthMsg, header, "formation::Header"),
            field!(TruthMsg, n_agents, "u32"),
            field!(TruthMsg, present, "u64"),
            field!(TruthMsg, poses, "f32[64][3]"),
            field!(TruthMsg, slots, "f32[64][2]"),
            field!(TruthMsg, goal, "f32[2]"),
        ],
    );
}

/// critic -> sim (its progress, for train-mode flow control) and critic -> agents (the header
/// in front of an actor's weights).
fn write_critic_payloads(out: &mut String) {
    payload::<CriticProgressMsg>(
        out,
        "CriticProgressMsg",
        &[
            field!(CriticProgressMsg, protocol_version, "u32"),
            field!(CriticProgressMsg, weights_version, "u32"),
            field!(CriticProgressMsg, acknowledged_sequence, "u64"),
            field!(CriticProgressMsg, updates, "u64"),
            field!(CriticProgressMsg, session, "u64"),
        ],
    );
    out.push_str(",\n");
    payload::<WeightsHeader>(
        out,
        "WeightsHeader",
        &[
            field!(WeightsHeader, protocol_version, "u32"),
            field!(WeightsHeader, actor_index, "u32"),
            field!(WeightsHeader, version, "u32"),
            field!(WeightsHeader, len, "u32"),
        ],
    );
}

/// The control service's request (client -> sim) and reply (sim -> client).
fn write_control_payloads(out: &mut String) {
    payload::<ControlRequest>(
        out,
        "ControlRequest",
        &[
            field!(ControlRequest, protocol_version, "u32"),
            field!(ControlRequest, kind, "u32"),
            field!(ControlRequest, shape, "u8[16]"),
            field!(ControlRequest, scale, "f32"),
            field!(ControlRequest, orientation, "f32"),
            field!(ControlRequest, goal, "f32[2]"),
            field!(ControlRequest, robot, "u32"),
        ],
    );
    out.push_str(",\n");
    payload::<ControlReply>(
        out,
        "ControlReply",
        &[
            field!(ControlReply, protocol_version, "u32"),
            field!(ControlReply, status, "u32"),
            field!(ControlReply, episode, "u32"),
            field!(ControlReply, tick, "u32"),
            field!(ControlReply, message, "u8[120]"),
        ],
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The array dimensions the field types spell out are the build's constants.
    #[test]
    fn spelled_dimensions_match_the_constants() {
        assert_eq!((MAX_OBS_DIM, MAX_OBSTACLES), (32, 128));
        assert_eq!(MAX_AGENTS, 64);
        assert_eq!((NEIGHBOURS, ACTION_DIM, MAX_DELAY_TICKS), (2, 2, 10));
    }
}
