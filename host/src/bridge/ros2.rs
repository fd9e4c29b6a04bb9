//! rmw_zenoh's wire format (ros2/rmw_zenoh `docs/design.md`), pure: the key
//! expression of a topic, the liveliness tokens of a node and of its
//! publishers and subscriptions under `@ros2_lv`, the attachment every
//! publication carries, and the message types the ROS 2 face supports with
//! their DDS names and REP-2016 `RIHS01_` type hashes.
//!
//! The hashes are the ones `rosidl` generates for ROS 2 Jazzy/Kilted; the
//! tests check them against `rosbags`' own computation from the message
//! definitions (`tests/all/ros2.rs`) and against the examples of the design
//! document. Humble has no type hashes: its key expressions carry
//! `TypeHashNotSupported`.

use std::fmt;

/// A message type the ROS 2 face speaks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MessageType {
    Twist,
    Odometry,
    LaserScan,
    Log,
    Bool,
}

impl MessageType {
    /// Every supported type, with its parameter spelling.
    pub const ALL: &'static [(&'static str, MessageType)] = &[
        ("geometry_msgs/msg/Twist", MessageType::Twist),
        ("nav_msgs/msg/Odometry", MessageType::Odometry),
        ("sensor_msgs/msg/LaserScan", MessageType::LaserScan),
        ("rcl_interfaces/msg/Log", MessageType::Log),
        ("std_msgs/msg/Bool", MessageType::Bool),
    ];

    /// The names a `type` parameter accepts.
    pub const NAMES: &'static [&'static str] = &[
        "geometry_msgs/msg/Twist",
        "nav_msgs/msg/Odometry",
        "sensor_msgs/msg/LaserScan",
        "rcl_interfaces/msg/Log",
        "std_msgs/msg/Bool",
    ];

    pub fn parse(name: &str) -> Option<MessageType> {
        MessageType::ALL.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
    }

    /// `package/msg/Name`.
    pub fn ros_name(self) -> &'static str {
        MessageType::ALL.iter().find(|(_, t)| *t == self).map(|(n, _)| *n).unwrap_or("")
    }

    /// The type's name as declared in DDS (`package::msg::dds_::Name_`).
    pub fn dds_name(self) -> &'static str {
        match self {
            MessageType::Twist => "geometry_msgs::msg::dds_::Twist_",
            MessageType::Odometry => "nav_msgs::msg::dds_::Odometry_",
            MessageType::LaserScan => "sensor_msgs::msg::dds_::LaserScan_",
            MessageType::Log => "rcl_interfaces::msg::dds_::Log_",
            MessageType::Bool => "std_msgs::msg::dds_::Bool_",
        }
    }

    /// The REP-2016 type hash rosidl generates (Jazzy, Kilted).
    pub fn rihs01(self) -> &'static str {
        match self {
            MessageType::Twist => "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
            MessageType::Odometry => "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
            MessageType::LaserScan => "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
            MessageType::Log => "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac",
            MessageType::Bool => "RIHS01_feb91e995ff9ebd09c0cb3d2aed18b11077585839fb5db80193b62d74528f6c9",
        }
    }
}

/// Which ROS 2 distribution's naming the peers expect.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Distro {
    /// Jazzy and later: real type hashes.
    Jazzy,
    /// Humble: `TypeHashNotSupported`.
    Humble,
}

impl Distro {
    pub const NAMES: &'static [&'static str] = &["jazzy", "kilted", "humble"];

    pub fn parse(name: &str) -> Option<Distro> {
        match name {
            "jazzy" | "kilted" => Some(Distro::Jazzy),
            "humble" => Some(Distro::Humble),
            _ => None,
        }
    }

    pub fn type_hash(self, ty: MessageType) -> &'static str {
        match self {
            Distro::Jazzy => ty.rihs01(),
            Distro::Humble => "TypeHashNotSupported",
        }
    }
}

/// Why a topic or node name is not one ROS 2 accepts.
#[derive(Clone, Debug, thiserror::Error, PartialEq, Eq)]
#[error("{0}")]
pub struct NameError(pub String);

/// Checks a topic name (`/cmd_vel`, `robot1/scan`): tokens of letters,
/// digits and underscores separated by single slashes, not starting with a
/// digit; returns it without its leading slash.
pub fn topic_path(topic: &str) -> Result<&str, NameError> {
    let path = topic.strip_prefix('/').unwrap_or(topic);
    if path.is_empty() {
        return Err(NameError("a topic needs a name after '/'".into()));
    }
    for token in path.split('/') {
        check_token(token, "topic")?;
    }
    Ok(path)
}

/// Checks a node name: one token.
pub fn check_node_name(name: &str) -> Result<(), NameError> {
    check_token(name, "node name")
}

fn check_token(token: &str, what: &str) -> Result<(), NameError> {
    let mut chars = token.chars();
    match chars.next() {
        None => Err(NameError(format!("a {what} has an empty part (two slashes, or a slash at the end)"))),
        Some(c) if c.is_ascii_digit() => Err(NameError(format!("a {what} part may not start with a digit: '{token}'"))),
        Some(_) if !token.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') => Err(NameError(format!(
            "a {what} may only hold letters, digits, '_' and '/': '{}'",
            crate::contract::clip(token)
        ))),
        Some(_) => Ok(()),
    }
}

/// The key expression data travels on:
/// `<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>`.
pub fn topic_key(domain: u32, topic_path: &str, ty: MessageType, distro: Distro) -> String {
    format!("{domain}/{topic_path}/{}/{}", ty.dds_name(), distro.type_hash(ty))
}

/// A name with each `/` replaced by `%` (how names sit in one chunk of a
/// liveliness token).
pub fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

/// Publisher or subscription.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EntityKind {
    Publisher,
    Subscription,
}

impl fmt::Display for EntityKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        })
    }
}

/// The QoS chunk of a token: default reliability and durability, keep-last
/// 10 (what the design document's examples of a default subscription show).
pub const DEFAULT_QOS: &str = "::,10:,:,:,,";

/// `@ros2_lv/<domain_id>/<session_id>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>`
/// (enclave and namespace empty: `%`).
pub fn node_token(domain: u32, session_id: &str, node_id: u32, node: &str) -> String {
    format!("@ros2_lv/{domain}/{session_id}/{node_id}/{node_id}/NN/%/%/{node}")
}

/// The token of a publisher or subscription:
/// `@ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/<MP|MS>/%/%/<node_name>/<mangled_topic>/<type_name>/<type_hash>/<qos>`.
#[allow(clippy::too_many_arguments)]
pub fn entity_token(
    domain: u32,
    session_id: &str,
    node_id: u32,
    entity_id: u32,
    kind: EntityKind,
    node: &str,
    topic_path: &str,
    ty: MessageType,
    distro: Distro,
) -> String {
    format!(
        "@ros2_lv/{domain}/{session_id}/{node_id}/{entity_id}/{kind}/%/%/{node}/{}/{}/{}/{DEFAULT_QOS}",
        mangle(&format!("/{topic_path}")),
        ty.dds_name(),
        distro.type_hash(ty)
    )
}

/// Length of an attachment: sequence number, timestamp, GID length, GID.
pub const ATTACHMENT_LEN: usize = 8 + 8 + 1 + 16;

/// What every publication carries beside its payload.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attachment {
    pub sequence: i64,
    /// Nanoseconds since the UNIX epoch.
    pub timestamp_ns: i64,
    pub gid: [u8; 16],
}

impl Attachment {
    /// 8 bytes sequence number (LE), 8 bytes timestamp (LE), 1 byte GID
    /// length (16), the 16 GID bytes.
    pub fn encode(&self) -> [u8; ATTACHMENT_LEN] {
        let mut out = [0u8; ATTACHMENT_LEN];
        out[..8].copy_from_slice(&self.sequence.to_le_bytes());
        out[8..16].copy_from_slice(&self.timestamp_ns.to_le_bytes());
        out[16] = 16;
        out[17..].copy_from_slice(&self.gid);
        out
    }

    pub fn decode(bytes: &[u8]) -> Option<Attachment> {
        if bytes.len() != ATTACHMENT_LEN || bytes[16] != 16 {
            return None;
        }
        let mut gid = [0u8; 16];
        gid.copy_from_slice(&bytes[17..]);
        Some(Attachment {
            sequence: i64::from_le_bytes(bytes[..8].try_into().ok()?),
            timestamp_ns: i64::from_le_bytes(bytes[8..16].try_into().ok()?),
            gid,
        })
    }
}

/// A publisher's GID: a digest of its session id and entity id, so two
/// entities never share one.
pub fn gid(session_id: &str, entity_id: u32) -> [u8; 16] {
    use sha2::Digest;
    let digest = sha2::Sha256::digest(format!("{session_id}/{entity_id}").as_bytes());
    let mut out = [0u8; 16];
    out.copy_from_slice(&digest[..16]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    // Fixtures from ros2/rmw_zenoh docs/design.md, "Topic and Service name
    // mapping to Zenoh key expressions" and "Graph Cache": the `chatter`
    // examples use std_msgs/String, whose hash the document gives; the
    // shapes are the same for every type.
    #[test]
    fn key_expressions_and_tokens_follow_the_design_document() {
        let chatter = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18";
        assert_eq!(
            format!("0/{}/std_msgs::msg::dds_::String_/{chatter}", topic_path("/robot1/chatter").unwrap_or("")),
            "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        assert_eq!(
            node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "listener"),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
        );
        // The subscription example with our type in place of String.
        assert_eq!(
            entity_token(
                2,
                "aac3178e146ba6f1fc6e6a4085e77f21",
                0,
                10,
                EntityKind::Subscription,
                "listener",
                "cmd_vel",
                MessageType::Twist,
                Distro::Jazzy
            ),
            "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a/::,10:,:,:,,"
        );
        assert_eq!(
            topic_key(0, "cmd_vel", MessageType::Twist, Distro::Humble),
            "0/cmd_vel/geometry_msgs::msg::dds_::Twist_/TypeHashNotSupported"
        );
        assert_eq!(mangle("/robot1/scan"), "%robot1%scan");
    }

    #[test]
    fn topic_names_are_checked() {
        assert_eq!(topic_path("/cmd_vel"), Ok("cmd_vel"));
        assert_eq!(topic_path("robot1/scan"), Ok("robot1/scan"));
        for bad in ["/", "//x", "/x/", "/1x", "/a b", "/a*", "/a$"] {
            assert!(topic_path(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_attachment_is_33_bytes_little_endian() {
        let a = Attachment { sequence: 1, timestamp_ns: 0x0102, gid: [7; 16] };
        let bytes = a.encode();
        assert_eq!(bytes.len(), 33);
        assert_eq!(&bytes[..9], &[1, 0, 0, 0, 0, 0, 0, 0, 2]);
        assert_eq!(bytes[16], 16);
        assert_eq!(Attachment::decode(&bytes), Some(a));
        assert_eq!(Attachment::decode(&bytes[..32]), None);
    }

    #[test]
    fn every_type_name_parses_back() {
        for (name, ty) in MessageType::ALL {
            assert_eq!(MessageType::parse(name), Some(*ty));
            assert_eq!(ty.ros_name(), *name);
            assert!(MessageType::NAMES.contains(name));
        }
    }
}
