//! What a robot senses around it and what stands in its way, as ROS 2 messages: each robot's
//! range sensor as a `sensor_msgs/msg/LaserScan` in its body frame, and the episode's
//! obstacles as a `visualization_msgs/msg/MarkerArray` in `world` (used by `formation-ros2`
//! and `formation-mcap`; docs/ROS2.md).

use anyhow::{Context, Result};
use formation_core::config::EnvConfig;
use formation_core::observation::{Layout, SCAN_RAYS};
use formation_core::obstacles::{Obstacle, Obstacles};
use formation_ipc::services::{self, Sizing};
use formation_protocol::wire::{ObstaclesMsg, StateMsg};
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

use crate::wire::{ColorRgba, Header, LaserScan, Marker, MarkerArray, Pose, Quaternion, Time, Vector3};

/// The markers' namespace.
pub const MARKER_NS: &str = "obstacles";
/// The height obstacles are drawn with, m (the world is planar).
pub const OBSTACLE_HEIGHT_M: f64 = 0.3;
/// The obstacles' colour: opaque grey.
const OBSTACLE_COLOUR: ColorRgba = ColorRgba {
    r: 0.55,
    g: 0.55,
    b: 0.6,
    a: 1.0,
};

/// Where an observation of the run's model holds the range sensor's rays, and what they mean.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScanLayout {
    /// The first ray's float.
    pub offset: usize,
    /// Rays, ray k at 2 pi k / rays counter-clockwise from the heading.
    pub rays: usize,
    /// The range a float of 1 reads, m (`env.scan_range_m`).
    pub range_m: f64,
}

impl ScanLayout {
    /// The rays of the run's observation model (`None`: the model has no range sensor).
    pub fn of(env: &EnvConfig) -> Option<Self> {
        Layout::of(env.observation).scan().map(|offset| Self {
            offset,
            rays: SCAN_RAYS,
            range_m: env.scan_range_m,
        })
    }

    /// The scan in `observation` (one robot's floats) as a LaserScan of `robot`'s body frame,
    /// ranges in metres; `scan_time` is the time between two scans, one tick.
    pub fn laser_scan(&self, observation: &[f32], robot: usize, stamp: Time, dt_s: f64) -> LaserScan {
        let increment = std::f64::consts::TAU / self.rays as f64;
        LaserScan {
            header: Header {
                stamp,
                frame_id: format!("robot_{robot}/base_link"),
            },
            angle_min: 0.0,
            angle_max: (increment * (self.rays - 1) as f64) as f32,
            angle_increment: increment as f32,
            time_increment: 0.0,
            scan_time: dt_s as f32,
            range_min: 0.0,
            range_max: self.range_m as f32,
            ranges: observation[self.offset..self.offset + self.rays]
                .iter()
                .map(|&value| (f64::from(value) * self.range_m) as f32)
                .collect(),
            intensities: Vec::new(),
        }
    }

    /// Robot `robot`'s scan at `state`: what its observation of that tick told it (with the
    /// sensor noise of `[reality]`), or `None` when that observation was lost.
    pub fn of_state(&self, state: &StateMsg, robot: usize, stamp: Time, dt_s: f64) -> Option<LaserScan> {
        let lost = state.observation_lost & (1 << robot) != 0;
        (!lost).then(|| self.laser_scan(&state.observations[robot], robot, stamp, dt_s))
    }
}

/// The episode's obstacles as markers in `world` stamped `stamp`: first a DELETEALL (the
/// previous episode's markers go), then obstacle k as marker id k of namespace
/// [`MARKER_NS`]: a disc as an upright cylinder, a wall as a box along its centre line, both
/// [`OBSTACLE_HEIGHT_M`] tall standing on the ground.
pub fn obstacle_markers(obstacles: &[Obstacle], stamp: Time) -> MarkerArray {
    let header = Header {
        stamp,
        frame_id: "world".into(),
    };
    let delete_all = Marker {
        header: header.clone(),
        ns: MARKER_NS.into(),
        action: Marker::DELETEALL,
        ..Marker::default()
    };
    let shape = |(id, obstacle): (usize, &Obstacle)| {
        let (kind, [x, y], yaw, [length, width]) = match *obstacle {
            Obstacle::Disc { centre, radius } => (Marker::CYLINDER, centre, 0.0, [2.0 * radius; 2]),
            Obstacle::Wall { a, b, thickness } => {
                let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
                let middle = [0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1])];
                (Marker::CUBE, middle, dy.atan2(dx), [dx.hypot(dy), thickness])
            }
        };
        Marker {
            header: header.clone(),
            ns: MARKER_NS.into(),
            id: i32::try_from(id).unwrap_or(i32::MAX),
            r#type: kind,
            action: Marker::ADD,
            pose: Pose {
                position: Vector3 {
                    x,
                    y,
                    z: 0.5 * OBSTACLE_HEIGHT_M,
                },
                orientation: Quaternion::from_yaw(yaw),
            },
            scale: Vector3 {
                x: length,
                y: width,
                z: OBSTACLE_HEIGHT_M,
            },
            color: OBSTACLE_COLOUR,
            ..Marker::default()
        }
    };
    MarkerArray {
        markers: std::iter::once(delete_all)
            .chain(obstacles.iter().enumerate().map(shape))
            .collect(),
    }
}

/// The sim's `formation/obstacles` stream (once per episode, before its first tick), read when
/// an episode's first state is handled.
pub struct ObstacleFeed {
    subscriber: Subscriber<ipc::Service, ObstaclesMsg, ()>,
    /// Episodes whose obstacles came before their first state was handled.
    pending: Vec<(u32, Vec<Obstacle>)>,
}

impl ObstacleFeed {
    /// Subscribes to the run's obstacles.
    pub fn new(node: &Node<ipc::Service>, sizing: &Sizing) -> Result<Self> {
        let subscriber = services::obstacles_stream(node, sizing)?
            .subscriber_builder()
            .create()
            .context("obstacles subscriber")?;
        Ok(Self {
            subscriber,
            pending: Vec::new(),
        })
    }

    /// Episode `episode`'s obstacles, if they came (the stream keeps the last two episodes';
    /// older episodes' are dropped).
    pub fn of_episode(&mut self, episode: u32) -> Result<Option<Vec<Obstacle>>> {
        while let Some(sample) = self.subscriber.receive().context("receive obstacles")? {
            let msg = sample.payload();
            self.pending
                .push((msg.header.episode, Obstacles::from_wire(msg).list().to_vec()));
        }
        self.pending.retain(|(of, _)| *of >= episode);
        Ok(self
            .pending
            .iter()
            .position(|(of, _)| *of == episode)
            .map(|at| self.pending.remove(at).1))
    }
}

/// The topic the obstacles go on: `/<namespace>/obstacles`.
pub fn obstacles_topic(namespace: &str) -> String {
    format!("/{namespace}/obstacles")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scan_is_the_observations_rays_in_metres_around_the_body_frame() {
        let layout = ScanLayout {
            offset: 16,
            rays: 16,
            range_m: 2.0,
        };
        let mut state = StateMsg::default();
        state.observations[2][16..32].copy_from_slice(&[1.0; 16]);
        state.observations[2][16 + 4] = 0.25;
        let stamp = Time { sec: 4, nanosec: 5 };
        let scan = layout.of_state(&state, 2, stamp, 0.1).expect("not lost");
        assert_eq!(scan.header.frame_id, "robot_2/base_link");
        assert_eq!(scan.header.stamp, stamp);
        assert_eq!(scan.ranges.len(), 16);
        assert_eq!(
            scan.ranges[4], 0.5,
            "ray 4 (a quarter turn to the left) reads a quarter of 2 m"
        );
        assert!(scan.ranges.iter().enumerate().all(|(k, &r)| k == 4 || r == 2.0));
        assert_eq!((scan.range_min, scan.range_max), (0.0, 2.0));
        let quarter = scan.angle_min + 4.0 * scan.angle_increment;
        assert!((f64::from(quarter) - std::f64::consts::FRAC_PI_2).abs() < 1e-6);
        assert!((f64::from(scan.angle_max) - std::f64::consts::TAU * 15.0 / 16.0).abs() < 1e-6);
        state.observation_lost = 1 << 2;
        assert_eq!(
            layout.of_state(&state, 2, stamp, 0.1),
            None,
            "a lost observation has no scan"
        );
        assert!(layout.of_state(&state, 1, stamp, 0.1).is_some());
    }

    #[test]
    fn discs_are_cylinders_and_walls_boxes_along_their_centre_line_after_a_delete_all() {
        let obstacles = [
            Obstacle::Disc {
                centre: [1.0, 2.0],
                radius: 0.25,
            },
            Obstacle::Wall {
                a: [0.0, 3.0],
                b: [0.0, 5.0],
                thickness: 0.1,
            },
        ];
        let array = obstacle_markers(&obstacles, Time::default());
        let [clear, disc, wall] = array.markers.as_slice() else {
            panic!("{} markers", array.markers.len());
        };
        assert_eq!(clear.action, Marker::DELETEALL);
        assert_eq!((disc.r#type, disc.id, disc.action), (Marker::CYLINDER, 0, Marker::ADD));
        assert_eq!(
            disc.scale,
            Vector3 {
                x: 0.5,
                y: 0.5,
                z: OBSTACLE_HEIGHT_M
            }
        );
        assert_eq!((disc.pose.position.x, disc.pose.position.y), (1.0, 2.0));
        assert_eq!((wall.r#type, wall.id), (Marker::CUBE, 1));
        assert_eq!((wall.pose.position.x, wall.pose.position.y), (0.0, 4.0));
        assert_eq!(
            (wall.scale.x, wall.scale.y),
            (2.0, 0.1),
            "length along a to b, thickness across"
        );
        let q = wall.pose.orientation;
        assert!(
            (2.0 * q.z.atan2(q.w) - std::f64::consts::FRAC_PI_2).abs() < 1e-12,
            "along +y"
        );
        assert!(
            array
                .markers
                .iter()
                .all(|m| m.header.frame_id == "world" && m.ns == MARKER_NS)
        );
        assert_eq!(
            obstacle_markers(&[], Time::default()).markers.len(),
            1,
            "none: only the clear"
        );
    }
}
