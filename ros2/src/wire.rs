//! rmw_zenoh's wire format for the message types the ROS 2 side carries, as rmw_zenoh_cpp
//! writes it on the Jazzy and Kilted branches (docs/ROS2.md names the releases): the data key
//! `<domain>/<topic>/<DDS type name>/<RIHS01 hash>`, the CDR payload with its 4-byte
//! encapsulation header, the 33-byte attachment (sequence number, source timestamp, publisher
//! GID) and the liveliness tokens of nodes, publishers and subscriptions.

use byteorder::{BigEndian, LittleEndian};
use serde::de::{self, SeqAccess, Visitor};
use serde::ser::SerializeTuple;
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A ROS 2 message type: its ROS name, its DDS name (the key's type chunk) and its RIHS01 hash
/// (REP-2016; the tests check each against `rosbags`' `hash_rihs01`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RosType {
    /// e.g. `nav_msgs/msg/Odometry`.
    pub name: &'static str,
    /// e.g. `nav_msgs::msg::dds_::Odometry_`.
    pub dds: &'static str,
    /// `RIHS01_` and 64 hex digits.
    pub hash: &'static str,
}

/// `nav_msgs/msg/Odometry`.
pub const ODOMETRY: RosType = RosType {
    name: "nav_msgs/msg/Odometry",
    dds: "nav_msgs::msg::dds_::Odometry_",
    hash: "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
};

/// `std_msgs/msg/Float32MultiArray`.
pub const FLOAT32_MULTI_ARRAY: RosType = RosType {
    name: "std_msgs/msg/Float32MultiArray",
    dds: "std_msgs::msg::dds_::Float32MultiArray_",
    hash: "RIHS01_0599f6f85b4bfca379873a0b4375a0aca022156bd2d7021275d116ed1fa8bfe0",
};

/// `rosgraph_msgs/msg/Clock`.
pub const CLOCK: RosType = RosType {
    name: "rosgraph_msgs/msg/Clock",
    dds: "rosgraph_msgs::msg::dds_::Clock_",
    hash: "RIHS01_692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564",
};

/// `geometry_msgs/msg/Twist`.
pub const TWIST: RosType = RosType {
    name: "geometry_msgs/msg/Twist",
    dds: "geometry_msgs::msg::dds_::Twist_",
    hash: "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
};

/// `sensor_msgs/msg/LaserScan`.
pub const LASER_SCAN: RosType = RosType {
    name: "sensor_msgs/msg/LaserScan",
    dds: "sensor_msgs::msg::dds_::LaserScan_",
    hash: "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
};

/// `visualization_msgs/msg/MarkerArray`.
pub const MARKER_ARRAY: RosType = RosType {
    name: "visualization_msgs/msg/MarkerArray",
    dds: "visualization_msgs::msg::dds_::MarkerArray_",
    hash: "RIHS01_86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf",
};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds past `sec`.
    pub nanosec: u32,
}

impl Time {
    /// The time `nanoseconds` after zero (sim time; saturates at `i32::MAX` seconds).
    pub fn from_nanos(nanoseconds: u64) -> Self {
        Self {
            sec: i32::try_from(nanoseconds / 1_000_000_000).unwrap_or(i32::MAX),
            nanosec: (nanoseconds % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// When.
    pub stamp: Time,
    /// In which frame.
    pub frame_id: String,
}

/// `geometry_msgs/msg/Vector3` (also `Point`: the same three doubles).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Quaternion {
    /// A rotation by `yaw` about z.
    pub fn from_yaw(yaw: f64) -> Self {
        let half = 0.5 * yaw;
        Self {
            x: 0.0,
            y: 0.0,
            z: half.sin(),
            w: half.cos(),
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// `geometry_msgs/msg/Point`.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/Twist`: linear.x = v, angular.z = w for a unicycle.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// m/s.
    pub linear: Vector3,
    /// rad/s.
    pub angular: Vector3,
}

/// A `float64[36]` covariance (a fixed array: no length on the wire).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Default for Covariance {
    fn default() -> Self {
        Self([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        let mut tuple = serializer.serialize_tuple(36)?;
        for value in &self.0 {
            tuple.serialize_element(value)?;
        }
        tuple.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Values;
        impl<'de> Visitor<'de> for Values {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 doubles")
            }
            fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut out = [0.0; 36];
                for (k, slot) in out.iter_mut().enumerate() {
                    *slot = seq.next_element()?.ok_or_else(|| de::Error::invalid_length(k, &self))?;
                }
                Ok(Covariance(out))
            }
        }
        deserializer.deserialize_tuple(36, Values)
    }
}

/// `geometry_msgs/msg/PoseWithCovariance`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Row-major 6x6 (zero: unknown).
    pub covariance: Covariance,
}

/// `geometry_msgs/msg/TwistWithCovariance`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Row-major 6x6 (zero: unknown).
    pub covariance: Covariance,
}

/// `nav_msgs/msg/Odometry`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Stamp and the pose's frame.
    pub header: Header,
    /// The twist's frame.
    pub child_frame_id: String,
    /// Pose in `header.frame_id`.
    pub pose: PoseWithCovariance,
    /// Twist in `child_frame_id`.
    pub twist: TwistWithCovariance,
}

/// `std_msgs/msg/MultiArrayDimension`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiArrayDimension {
    /// What the dimension is.
    pub label: String,
    /// Its length.
    pub size: u32,
    /// Its stride.
    pub stride: u32,
}

/// `std_msgs/msg/MultiArrayLayout`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MultiArrayLayout {
    /// The dimensions.
    pub dim: Vec<MultiArrayDimension>,
    /// Floats before the first element.
    pub data_offset: u32,
}

/// `std_msgs/msg/Float32MultiArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Float32MultiArray {
    /// The layout.
    pub layout: MultiArrayLayout,
    /// The values.
    pub data: Vec<f32>,
}

/// `rosgraph_msgs/msg/Clock`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Clock {
    /// The current time.
    pub clock: Time,
}

/// `builtin_interfaces/msg/Duration`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Duration {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds past `sec`.
    pub nanosec: u32,
}

/// `sensor_msgs/msg/LaserScan`: `ranges[k]` is read at `angle_min + k * angle_increment`
/// counter-clockwise from the x axis of `header.frame_id`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LaserScan {
    /// Acquisition time and the scanner's frame.
    pub header: Header,
    /// The first ray's angle, rad.
    pub angle_min: f32,
    /// The last ray's angle, rad.
    pub angle_max: f32,
    /// Between two rays, rad.
    pub angle_increment: f32,
    /// Between two measurements, s.
    pub time_increment: f32,
    /// Between two scans, s.
    pub scan_time: f32,
    /// The shortest range read, m.
    pub range_min: f32,
    /// The longest range read, m.
    pub range_max: f32,
    /// One range per ray, m.
    pub ranges: Vec<f32>,
    /// Per ray (empty: none).
    pub intensities: Vec<f32>,
}

/// `std_msgs/msg/ColorRGBA`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ColorRgba {
    /// Red, 0-1.
    pub r: f32,
    /// Green, 0-1.
    pub g: f32,
    /// Blue, 0-1.
    pub b: f32,
    /// Opacity, 0-1.
    pub a: f32,
}

/// `sensor_msgs/msg/CompressedImage` (a marker's texture).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and frame.
    pub header: Header,
    /// `jpeg` or `png`.
    pub format: String,
    /// The compressed bytes.
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/UVCoordinate`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct UvCoordinate {
    /// u.
    pub u: f32,
    /// v.
    pub v: f32,
}

/// `visualization_msgs/msg/MeshFile`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshFile {
    /// The file's name.
    pub filename: String,
    /// Its bytes.
    pub data: Vec<u8>,
}

/// `visualization_msgs/msg/Marker` as Jazzy and Kilted define it (with the texture and mesh
/// fields added in Iron).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Marker {
    /// Stamp and the frame of `pose`.
    pub header: Header,
    /// Namespace: with `id`, names the marker.
    pub ns: String,
    /// Its id within `ns`.
    pub id: i32,
    /// The shape ([`Marker::CUBE`], [`Marker::CYLINDER`], ...).
    pub r#type: i32,
    /// [`Marker::ADD`] or [`Marker::DELETEALL`], ...
    pub action: i32,
    /// The shape's centre and orientation.
    pub pose: Pose,
    /// The shape's size along its axes, m (a cylinder's x and y: its diameter).
    pub scale: Vector3,
    /// Its colour.
    pub color: ColorRgba,
    /// How long it stays (zero: until deleted).
    pub lifetime: Duration,
    /// Whether it follows its frame after it was placed.
    pub frame_locked: bool,
    /// Points of the list types.
    pub points: Vec<Vector3>,
    /// Per point colours.
    pub colors: Vec<ColorRgba>,
    /// Texture URI.
    pub texture_resource: String,
    /// Texture image.
    pub texture: CompressedImage,
    /// Texture coordinates.
    pub uv_coordinates: Vec<UvCoordinate>,
    /// Text of a text marker.
    pub text: String,
    /// Mesh URI.
    pub mesh_resource: String,
    /// Mesh bytes.
    pub mesh_file: MeshFile,
    /// Whether the mesh's own materials are used.
    pub mesh_use_embedded_materials: bool,
}

impl Marker {
    /// `type`: a box.
    pub const CUBE: i32 = 1;
    /// `type`: an upright cylinder.
    pub const CYLINDER: i32 = 3;
    /// `action`: add or replace.
    pub const ADD: i32 = 0;
    /// `action`: delete every marker.
    pub const DELETEALL: i32 = 3;
}

/// `visualization_msgs/msg/MarkerArray`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerArray {
    /// The markers, applied in order.
    pub markers: Vec<Marker>,
}

/// The encapsulation header of little-endian plain CDR (what rmw_zenoh_cpp writes).
pub const CDR_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
/// The encapsulation header of big-endian plain CDR.
const CDR_BE: [u8; 4] = [0x00, 0x00, 0x00, 0x00];
/// A Twist's CDR payload: the header and six doubles (alignment is counted after the header).
pub const TWIST_CDR_LEN: usize = 4 + 6 * 8;

/// `msg` as little-endian CDR with its encapsulation header.
pub fn encode<T: Serialize>(msg: &T) -> anyhow::Result<Vec<u8>> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(msg).map_err(|err| anyhow::anyhow!("CDR: {err}"))?;
    let mut out = Vec::with_capacity(4 + body.len());
    out.extend_from_slice(&CDR_LE);
    out.extend_from_slice(&body);
    Ok(out)
}

/// Why a Twist is refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Malformed {
    /// Not plain CDR (little or big endian).
    Header,
    /// Not 52 bytes.
    Length,
    /// A value is NaN or infinite.
    NonFinite,
    /// No rmw_zenoh attachment (or not 33 bytes with a 16-byte GID).
    Attachment,
}

impl std::fmt::Display for Malformed {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str(match self {
            Malformed::Header => "bad CDR encapsulation header",
            Malformed::Length => "wrong length",
            Malformed::NonFinite => "non-finite value",
            Malformed::Attachment => "no rmw_zenoh attachment",
        })
    }
}

/// A Twist from its CDR payload: plain CDR of either byte order, exactly 52 bytes, every value
/// finite.
pub fn decode_twist(payload: &[u8]) -> Result<Twist, Malformed> {
    let header = payload.get(..4).ok_or(Malformed::Length)?;
    let big_endian = if header == CDR_LE {
        false
    } else if header == CDR_BE {
        true
    } else {
        return Err(Malformed::Header);
    };
    if payload.len() != TWIST_CDR_LEN {
        return Err(Malformed::Length);
    }
    let body = &payload[4..];
    let decoded = if big_endian {
        cdr_encoding::from_bytes::<Twist, BigEndian>(body)
    } else {
        cdr_encoding::from_bytes::<Twist, LittleEndian>(body)
    };
    let (twist, _) = decoded.map_err(|_| Malformed::Length)?;
    let values = [twist.linear, twist.angular].into_iter().flat_map(|v| [v.x, v.y, v.z]);
    if values.into_iter().all(f64::is_finite) {
        Ok(twist)
    } else {
        Err(Malformed::NonFinite)
    }
}

/// The attachment rmw_zenoh puts on every sample (docs/design.md, "Publishers"): the sequence
/// number and the source timestamp (ns since the UNIX epoch) as little-endian int64, then the
/// GID's length (one byte, 16) and the 16-byte publisher GID.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Attachment {
    /// Counts the publisher's messages from 1.
    pub sequence_number: i64,
    /// When the message was published, ns since the UNIX epoch.
    pub source_timestamp_ns: i64,
    /// The publisher's GID.
    pub gid: [u8; 16],
}

/// An attachment's size.
pub const ATTACHMENT_LEN: usize = 8 + 8 + 1 + 16;

impl Attachment {
    /// Its 33 bytes.
    pub fn to_bytes(self) -> [u8; ATTACHMENT_LEN] {
        let mut out = [0u8; ATTACHMENT_LEN];
        out[..8].copy_from_slice(&self.sequence_number.to_le_bytes());
        out[8..16].copy_from_slice(&self.source_timestamp_ns.to_le_bytes());
        out[16] = 16;
        out[17..].copy_from_slice(&self.gid);
        out
    }

    /// Reads 33 bytes whose GID length is 16.
    pub fn from_bytes(bytes: &[u8]) -> Option<Self> {
        if bytes.len() != ATTACHMENT_LEN || bytes[16] != 16 {
            return None;
        }
        let int = |range: std::ops::Range<usize>| bytes.get(range)?.try_into().ok().map(i64::from_le_bytes);
        Some(Self {
            sequence_number: int(0..8)?,
            source_timestamp_ns: int(8..16)?,
            gid: bytes[17..].try_into().ok()?,
        })
    }
}

/// The GID rmw_zenoh gives an entity: XXH3-128 of its liveliness key, low then high 64 bits,
/// each little-endian (`liveliness_utils.cpp`).
pub fn gid_of(liveliness_key: &str) -> [u8; 16] {
    xxhash_rust::xxh3::xxh3_128(liveliness_key.as_bytes()).to_le_bytes()
}

/// A name with every `/` replaced by `%` (rmw_zenoh's `mangle_name`).
pub fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

/// The key a topic's samples travel on: `<domain>/<topic without its leading slash>/<DDS type
/// name>/<type hash>`.
pub fn data_key(domain: u32, topic: &str, ty: &RosType) -> String {
    format!("{domain}/{}/{}/{}", topic.trim_matches('/'), ty.dds, ty.hash)
}

/// The compact QoS of a liveliness token (`qos_to_keyexpr`) for reliable, volatile, keep last
/// `depth` (rmw_zenoh's defaults but for the depth, 42, which is left out when it is 42).
pub fn qos_keep_last(depth: usize) -> String {
    let depth = if depth == 42 { String::new() } else { depth.to_string() };
    format!("::,{depth}:,:,:,,")
}

/// What a liveliness token announces.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntityKind {
    /// `NN`.
    Node,
    /// `MP`.
    Publisher,
    /// `MS`.
    Subscription,
}

impl EntityKind {
    /// Its two letters.
    pub fn as_str(self) -> &'static str {
        match self {
            EntityKind::Node => "NN",
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        }
    }
}

/// A ROS 2 node's place on the graph: domain, Zenoh session id, node id, namespace, name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeIdentity {
    /// `ROS_DOMAIN_ID`.
    pub domain: u32,
    /// The Zenoh session id, as Zenoh prints it.
    pub zid: String,
    /// The node's id within its session.
    pub node_id: u32,
    /// `/` or `/formation`.
    pub namespace: String,
    /// The node's name.
    pub name: String,
}

impl NodeIdentity {
    fn prefix(&self, entity_id: u32, kind: EntityKind) -> String {
        format!(
            "@ros2_lv/{}/{}/{}/{entity_id}/{}/%/{}/{}",
            self.domain,
            self.zid,
            self.node_id,
            kind.as_str(),
            mangle(&self.namespace),
            self.name
        )
    }

    /// The node's liveliness token (its entity id is its node id; the enclave is unset, `%`).
    pub fn node_token(&self) -> String {
        self.prefix(self.node_id, EntityKind::Node)
    }

    /// The liveliness token of the node's publisher or subscription `entity_id` on `topic`.
    pub fn entity_token(&self, entity_id: u32, kind: EntityKind, topic: &str, ty: &RosType, qos: &str) -> String {
        format!(
            "{}/{}/{}/{}/{qos}",
            self.prefix(entity_id, kind),
            mangle(topic),
            ty.dds,
            ty.hash
        )
    }
}

/// The parts of an entity's liveliness token this side reads: kind and topic (unmangled).
pub fn parse_entity_token(key: &str) -> Option<(&str, String)> {
    let parts: Vec<&str> = key.split('/').collect();
    if parts.first() != Some(&"@ros2_lv") || parts.len() < 13 {
        return None;
    }
    Some((parts[5], parts[9].replace('%', "/")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `std_msgs/msg/String`, the type of design.md's examples.
    const STRING: RosType = RosType {
        name: "std_msgs/msg/String",
        dds: "std_msgs::msg::dds_::String_",
        hash: "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    };

    #[test]
    fn keys_and_tokens_match_the_examples_of_rmw_zenohs_design_document() {
        // docs/design.md, "Topic and Service name mapping to Zenoh key expressions".
        assert_eq!(
            data_key(0, "/chatter", &STRING),
            "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        assert_eq!(
            data_key(0, "/robot1/chatter", &STRING),
            "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        // "Graph Cache": the listener node, its subscription and the talker's publisher.
        let listener = NodeIdentity {
            domain: 2,
            zid: "aac3178e146ba6f1fc6e6a4085e77f21".into(),
            node_id: 0,
            namespace: "/".into(),
            name: "listener".into(),
        };
        assert_eq!(
            listener.node_token(),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
        );
        assert_eq!(
            listener.entity_token(10, EntityKind::Subscription, "/chatter", &STRING, &qos_keep_last(10)),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,"
        );
        let talker = NodeIdentity {
            zid: "8b20917502ee955ac4476e0266340d5c".into(),
            name: "talker".into(),
            ..listener
        };
        let token = talker.entity_token(10, EntityKind::Publisher, "/chatter", &STRING, &qos_keep_last(7));
        assert_eq!(
            token,
            "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
        );
        assert_eq!(parse_entity_token(&token), Some(("MP", "/chatter".to_string())));
        assert_eq!(parse_entity_token(&talker.node_token()), None);
        assert_eq!(qos_keep_last(42), "::,:,:,:,,", "the default depth is left out");
    }

    #[test]
    fn an_attachment_is_33_bytes_little_endian_with_the_gid_length() {
        let attachment = Attachment {
            sequence_number: 1,
            source_timestamp_ns: 0x0102_0304_0506_0708,
            gid: [0xAB; 16],
        };
        let bytes = attachment.to_bytes();
        assert_eq!(&bytes[..8], &[1, 0, 0, 0, 0, 0, 0, 0]);
        assert_eq!(&bytes[8..16], &[8, 7, 6, 5, 4, 3, 2, 1]);
        assert_eq!(bytes[16], 16);
        assert_eq!(Attachment::from_bytes(&bytes), Some(attachment));
        assert_eq!(Attachment::from_bytes(&bytes[..32]), None);
        let mut wrong_length = bytes;
        wrong_length[16] = 15;
        assert_eq!(Attachment::from_bytes(&wrong_length), None);
    }

    #[test]
    fn the_gid_is_the_xxh3_128_of_the_token_low_half_first() {
        // XXH3-128 of the empty input is 99aa06d3014798d86001c324468d497f (high, low halves).
        let gid = gid_of("");
        assert_eq!(&gid[..8], &0x6001_c324_468d_497f_u64.to_le_bytes());
        assert_eq!(&gid[8..], &0x99aa_06d3_0147_98d8_u64.to_le_bytes());
    }

    /// The golden CDR files written by `rosbags` (python/tests/ros2_golden.py).
    fn golden(name: &str) -> Vec<u8> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(name);
        std::fs::read(&path).unwrap_or_else(|err| panic!("{}: {err}", path.display()))
    }

    /// The messages of the golden files, as python/tests/ros2_golden.py builds them.
    fn golden_odometry() -> Odometry {
        let mut pose_cov = [0.0; 36];
        pose_cov[0] = 0.01;
        pose_cov[35] = 0.02;
        Odometry {
            header: Header {
                stamp: Time {
                    sec: 12,
                    nanosec: 300_000_000,
                },
                frame_id: "world".into(),
            },
            child_frame_id: "robot_2/base_link".into(),
            pose: PoseWithCovariance {
                pose: Pose {
                    position: Vector3 {
                        x: 1.5,
                        y: -2.25,
                        z: 0.0,
                    },
                    orientation: Quaternion::from_yaw(0.5),
                },
                covariance: Covariance(pose_cov),
            },
            twist: TwistWithCovariance {
                twist: Twist {
                    linear: Vector3 { x: 0.4, y: 0.0, z: 0.0 },
                    angular: Vector3 {
                        x: 0.0,
                        y: 0.0,
                        z: -0.7,
                    },
                },
                covariance: Covariance::default(),
            },
        }
    }

    #[test]
    fn cdr_bytes_equal_the_golden_files_written_by_rosbags() {
        assert_eq!(encode(&golden_odometry()).expect("odometry"), golden("odometry.cdr"));
        let observation = Float32MultiArray {
            layout: MultiArrayLayout {
                dim: vec![MultiArrayDimension {
                    label: "relative".into(),
                    size: 3,
                    stride: 3,
                }],
                data_offset: 0,
            },
            data: vec![0.25, -1.0, 3.5],
        };
        assert_eq!(encode(&observation).expect("array"), golden("float32_multi_array.cdr"));
        let clock = Clock {
            clock: Time {
                sec: 7,
                nanosec: 100_000_000,
            },
        };
        assert_eq!(encode(&clock).expect("clock"), golden("clock.cdr"));
        let twist = Twist {
            linear: Vector3 { x: 0.3, y: 0.0, z: 0.0 },
            angular: Vector3 { x: 0.0, y: 0.0, z: 0.8 },
        };
        assert_eq!(encode(&twist).expect("twist"), golden("twist.cdr"));
        assert_eq!(decode_twist(&golden("twist.cdr")), Ok(twist));
        assert_eq!(decode_twist(&golden("twist_be.cdr")), Ok(twist), "big-endian CDR too");
    }

    #[test]
    fn a_laser_scan_and_a_marker_array_are_the_bytes_rosbags_writes() {
        let scan = LaserScan {
            header: Header {
                stamp: Time {
                    sec: 3,
                    nanosec: 250_000_000,
                },
                frame_id: "robot_1/base_link".into(),
            },
            angle_min: 0.0,
            angle_max: (std::f64::consts::TAU * 15.0 / 16.0) as f32,
            angle_increment: (std::f64::consts::TAU / 16.0) as f32,
            time_increment: 0.0,
            scan_time: 0.1,
            range_min: 0.0,
            range_max: 2.0,
            ranges: vec![0.5, 2.0, 1.25],
            intensities: Vec::new(),
        };
        assert_eq!(encode(&scan).expect("scan"), golden("laser_scan.cdr"));
        let header = Header {
            stamp: Time { sec: 3, nanosec: 0 },
            frame_id: "world".into(),
        };
        let delete_all = Marker {
            header: header.clone(),
            ns: "obstacles".into(),
            action: Marker::DELETEALL,
            ..Marker::default()
        };
        let rgba = |r, g, b, a| ColorRgba { r, g, b, a };
        let wall = Marker {
            header,
            ns: "obstacles".into(),
            id: 7,
            r#type: Marker::CUBE,
            action: Marker::ADD,
            pose: Pose {
                position: Vector3 {
                    x: 2.0,
                    y: 3.5,
                    z: 0.15,
                },
                orientation: Quaternion::from_yaw(1.0),
            },
            scale: Vector3 { x: 3.0, y: 0.1, z: 0.3 },
            color: rgba(0.5, 0.25, 0.125, 1.0),
            lifetime: Duration::default(),
            frame_locked: true,
            points: vec![Vector3 { x: 1.0, y: 2.0, z: 3.0 }],
            colors: vec![rgba(1.0, 0.0, 0.0, 1.0)],
            texture_resource: "t".into(),
            texture: CompressedImage {
                header: Header {
                    stamp: Time { sec: 1, nanosec: 2 },
                    frame_id: "cam".into(),
                },
                format: "png".into(),
                data: vec![1, 2, 3],
            },
            uv_coordinates: vec![UvCoordinate { u: 0.25, v: 0.75 }],
            text: "wall".into(),
            mesh_resource: "m".into(),
            mesh_file: MeshFile {
                filename: "f".into(),
                data: vec![9],
            },
            mesh_use_embedded_materials: true,
        };
        let markers = MarkerArray {
            markers: vec![delete_all, wall],
        };
        assert_eq!(encode(&markers).expect("markers"), golden("marker_array.cdr"));
    }

    #[test]
    fn a_malformed_twist_is_refused_with_its_reason() {
        let good = encode(&Twist::default()).expect("twist");
        assert_eq!(good.len(), TWIST_CDR_LEN);
        assert!(decode_twist(&good).is_ok());
        let mut header = good.clone();
        header[1] = 0x07;
        assert_eq!(decode_twist(&header), Err(Malformed::Header));
        assert_eq!(decode_twist(&good[..40]), Err(Malformed::Length));
        assert_eq!(decode_twist(&[0, 1]), Err(Malformed::Length));
        let mut long = good.clone();
        long.extend_from_slice(&[0; 8]);
        assert_eq!(decode_twist(&long), Err(Malformed::Length));
        let nan = Twist {
            angular: Vector3 {
                z: f64::NAN,
                ..Vector3::default()
            },
            ..Twist::default()
        };
        assert_eq!(decode_twist(&encode(&nan).expect("nan")), Err(Malformed::NonFinite));
    }
}
