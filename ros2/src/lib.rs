//! The ROS 2 face of the swarm: `formation-ros2` plays robot slots as ROS 2 topics over
//! rmw_zenoh's wire format ([`side`], [`wire`]); `formation-mcap` writes a run as an MCAP file
//! of ROS 2 messages ([`record`]); both carry the range sensor and the obstacles
//! ([`surroundings`]). docs/ROS2.md.

pub mod record;
pub mod side;
pub mod surroundings;
pub mod wire;
