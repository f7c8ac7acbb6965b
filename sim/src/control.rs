//! The live control service: the sim serves `formation/control` (iceoryx2 request-response,
//! [`ControlRequest`] -> [`ControlReply`]) once per tick, after the step, without waiting. A
//! change is applied through the episode's [`Mission`] (the same slot assignment as a
//! scheduled change) and is in force from the tick told next, which the reply names; it lasts
//! for the current episode. Removing robot k takes it out of the formation (the others re-form
//! the same formation for one robot fewer) and it stands still until restored or the episode
//! ends; restoring brings a removed robot back. A request the sim cannot obey gets a refusal
//! saying why. After a
//! tick that answered anything the sim raises `formation/control/answered`, so a client waits
//! on an event rather than polling.

use anyhow::{Context, Result};
use formation_core::config::FormationShape;
use formation_core::formation::FormationSpec;
use formation_core::mission::{Attendance, Away, Mission, fits_arena, live_formation};
use formation_core::world::World;
use formation_ipc::services::{self, Sizing};
use formation_protocol::wire::*;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::server::Server;
use iceoryx2::prelude::*;

/// Mixed into a live formation's seed (run seed, episode, tick), apart from the other streams.
const LIVE_STREAM: u64 = 0x6C69_7665_5F66_6F72;

/// The sim's end of the control service.
pub struct ControlServer<S: Service> {
    server: Server<S, ControlRequest, (), ControlReply, ()>,
    answered: Notifier<S>,
}

impl<S: Service> ControlServer<S> {
    /// Creates the service's server and the answered event's notifier.
    pub fn open(node: &Node<S>, sizing: &Sizing) -> Result<Self> {
        Ok(Self {
            server: services::control_service(node, sizing)?
                .server_builder()
                .create()
                .context("sim cannot create the control server")?,
            answered: services::control_answered_event(node, sizing)?
                .notifier_builder()
                .create()
                .context("sim cannot create the control notifier")?,
        })
    }

    /// Answers every request waiting (never blocks), applying each accepted one to `world`
    /// through `mission` (and `attendance`, for removals); `seed` is the run's.
    pub fn serve(
        &self,
        world: &mut World,
        mission: &mut Mission,
        attendance: &mut Attendance,
        seed: u64,
        episode: u32,
    ) -> Result<()> {
        let mut answered = false;
        while let Some(active) = self.server.receive().context("control receive")? {
            let live_seed = seed ^ LIVE_STREAM ^ (u64::from(episode) << 32) ^ u64::from(world.steps);
            let reply = match apply(active.payload(), world, mission, attendance, live_seed) {
                Ok(()) => ControlReply::new(CONTROL_OK, episode, world.steps, ""),
                Err(why) => ControlReply::new(CONTROL_REFUSED, episode, world.steps, &why),
            };
            // A client that gave up on its request is no reason to stop the run.
            let _gone = active.send_copy(reply);
            answered = true;
        }
        if answered {
            self.answered.notify().context("control answered")?;
        }
        Ok(())
    }
}

/// Applies one request, or says why not.
fn apply(
    request: &ControlRequest,
    world: &mut World,
    mission: &mut Mission,
    attendance: &mut Attendance,
    seed: u64,
) -> Result<(), String> {
    if request.protocol_version != PROTOCOL_VERSION {
        return Err(format!(
            "protocol {} (the sim speaks {PROTOCOL_VERSION})",
            request.protocol_version
        ));
    }
    match request.kind {
        CONTROL_SET_FORMATION => {
            let kind = shape_named(&request.shape)?;
            let spec = FormationSpec {
                kind,
                orientation: f64::from(request.orientation),
                scale: f64::from(request.scale),
            };
            let offsets = live_formation(world, kind, spec.scale, spec.orientation, seed)?;
            mission.reform(world, &offsets, spec);
            Ok(())
        }
        CONTROL_SET_GOAL => {
            let goal = request.goal.map(f64::from);
            if !goal.iter().all(|v| v.is_finite()) {
                return Err(format!("goal {goal:?} is not a point"));
            }
            let offsets: Vec<[f64; 2]> = world.slots.clone();
            if !fits_arena(world, goal, &offsets) {
                return Err(format!(
                    "goal ({}, {}): the formation around it leaves the arena [0, {:.2}] m",
                    goal[0], goal[1], world.arena_m
                ));
            }
            mission.move_goal(world, goal);
            Ok(())
        }
        CONTROL_REMOVE_ROBOT => {
            let robot = request.robot as usize;
            mission.leave(world, robot)?;
            attendance.set_away(robot, Some(Away::Removed));
            Ok(())
        }
        CONTROL_RESTORE_ROBOT => {
            let robot = request.robot as usize;
            match (robot < world.n_agents()).then(|| attendance.away(robot)) {
                Some(Some(Away::Removed)) => {
                    mission.rejoin(world, robot)?;
                    attendance.set_away(robot, None);
                    Ok(())
                }
                Some(Some(Away::Failed)) => Err(format!(
                    "robot {robot}'s controller failed: it stays out for the episode"
                )),
                Some(Some(Away::Silent)) => Err(format!(
                    "robot {robot} is silent: it comes back after answering 5 ticks in a row"
                )),
                Some(None) => Err(format!("robot {robot} is already in the formation")),
                None => Err(format!("no robot {robot} (robots 0 to {})", world.n_agents() - 1)),
            }
        }
        kind => Err(format!(
            "unknown request kind {kind} (set formation {CONTROL_SET_FORMATION}, set goal {CONTROL_SET_GOAL}, \
             remove robot {CONTROL_REMOVE_ROBOT}, restore robot {CONTROL_RESTORE_ROBOT})"
        )),
    }
}

/// The shape a request names.
fn shape_named(bytes: &[u8]) -> Result<FormationShape, String> {
    let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
    let name = std::str::from_utf8(&bytes[..end]).map_err(|_| "the shape's name is not UTF-8".to_string())?;
    FormationShape::KINDS
        .into_iter()
        .chain([FormationShape::Mixed])
        .find(|kind| kind.as_str() == name)
        .ok_or_else(|| format!("unknown shape {name:?} (random, ring, line, wedge, grid)"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_are_read_by_name_and_an_unknown_one_is_refused() {
        let mut bytes = [0u8; CONTROL_SHAPE_BYTES];
        bytes[..4].copy_from_slice(b"ring");
        assert_eq!(shape_named(&bytes), Ok(FormationShape::Ring));
        bytes[..4].copy_from_slice(b"hexa");
        assert!(shape_named(&bytes).is_err_and(|why| why.contains("unknown shape \"hexa\"")));
    }
}
