//! The ROS 2 message types Twinswarm speaks, as their type descriptions, and their RIHS01
//! type hashes computed from those the way ROS 2 Jazzy does (rosidl
//! `rosidl_generator_type_description`, `calculate_type_hash`): the JSON of the type's
//! description and of every type it refers to (sorted by name, default values left out),
//! written with `", "` and `": "` separators, hashed with SHA-256.
//!
//! The field lists are Jazzy's (`ros2/common_interfaces`, `ros2/rcl_interfaces`,
//! `ros2/geometry2` at their Jazzy releases; the same as rosbags' `ROS2_JAZZY` type store).
//! A test compares every hash with the values rosbags computes, and the Python tests ask
//! rosbags itself.

use sha2::{Digest, Sha256};

/// A field's element type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Elem {
    /// `int32`.
    Int32,
    /// `uint32`.
    Uint32,
    /// `uint8`.
    Uint8,
    /// `float32`.
    Float32,
    /// `float64`.
    Float64,
    /// `bool`.
    Bool,
    /// `string` (unbounded).
    Str,
    /// Another message, by its full name (`pkg/msg/Name`).
    Nested(&'static str),
}

impl Elem {
    /// rosidl's `FieldType` id of the element.
    fn type_id(self) -> u32 {
        match self {
            Elem::Nested(_) => 1,
            Elem::Uint8 => 3,
            Elem::Int32 => 6,
            Elem::Uint32 => 7,
            Elem::Float32 => 10,
            Elem::Float64 => 11,
            Elem::Bool => 15,
            Elem::Str => 17,
        }
    }
}

/// One field: a name, an element, and whether it is one, a fixed array or a sequence.
#[derive(Clone, Copy, Debug)]
pub struct Field {
    /// Its name.
    pub name: &'static str,
    /// Its element type.
    pub elem: Elem,
    /// `Some(n)`: a fixed array of `n`; `Some(0)`: an unbounded sequence; `None`: one.
    pub array: Option<u32>,
}

const fn one(name: &'static str, elem: Elem) -> Field {
    Field { name, elem, array: None }
}

const fn fixed(name: &'static str, elem: Elem, n: u32) -> Field {
    Field { name, elem, array: Some(n) }
}

const fn seq(name: &'static str, elem: Elem) -> Field {
    Field { name, elem, array: Some(0) }
}

use Elem::*;

/// Every type: full name and fields, in wire order.
pub const TYPES: &[(&str, &[Field])] = &[
    ("builtin_interfaces/msg/Time", &[one("sec", Int32), one("nanosec", Uint32)]),
    ("builtin_interfaces/msg/Duration", &[one("sec", Int32), one("nanosec", Uint32)]),
    ("std_msgs/msg/Header", &[one("stamp", Nested("builtin_interfaces/msg/Time")), one("frame_id", Str)]),
    ("std_msgs/msg/ColorRGBA", &[one("r", Float32), one("g", Float32), one("b", Float32), one("a", Float32)]),
    ("geometry_msgs/msg/Point", &[one("x", Float64), one("y", Float64), one("z", Float64)]),
    ("geometry_msgs/msg/Vector3", &[one("x", Float64), one("y", Float64), one("z", Float64)]),
    ("geometry_msgs/msg/Quaternion", &[one("x", Float64), one("y", Float64), one("z", Float64), one("w", Float64)]),
    (
        "geometry_msgs/msg/Pose",
        &[
            one("position", Nested("geometry_msgs/msg/Point")),
            one("orientation", Nested("geometry_msgs/msg/Quaternion")),
        ],
    ),
    (
        "geometry_msgs/msg/PoseStamped",
        &[one("header", Nested("std_msgs/msg/Header")), one("pose", Nested("geometry_msgs/msg/Pose"))],
    ),
    (
        "geometry_msgs/msg/Twist",
        &[one("linear", Nested("geometry_msgs/msg/Vector3")), one("angular", Nested("geometry_msgs/msg/Vector3"))],
    ),
    (
        "geometry_msgs/msg/PoseWithCovariance",
        &[one("pose", Nested("geometry_msgs/msg/Pose")), fixed("covariance", Float64, 36)],
    ),
    (
        "geometry_msgs/msg/TwistWithCovariance",
        &[one("twist", Nested("geometry_msgs/msg/Twist")), fixed("covariance", Float64, 36)],
    ),
    (
        "geometry_msgs/msg/Transform",
        &[
            one("translation", Nested("geometry_msgs/msg/Vector3")),
            one("rotation", Nested("geometry_msgs/msg/Quaternion")),
        ],
    ),
    (
        "geometry_msgs/msg/TransformStamped",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("child_frame_id", Str),
            one("transform", Nested("geometry_msgs/msg/Transform")),
        ],
    ),
    (
        "nav_msgs/msg/Odometry",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("child_frame_id", Str),
            one("pose", Nested("geometry_msgs/msg/PoseWithCovariance")),
            one("twist", Nested("geometry_msgs/msg/TwistWithCovariance")),
        ],
    ),
    (
        "sensor_msgs/msg/Imu",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("orientation", Nested("geometry_msgs/msg/Quaternion")),
            fixed("orientation_covariance", Float64, 9),
            one("angular_velocity", Nested("geometry_msgs/msg/Vector3")),
            fixed("angular_velocity_covariance", Float64, 9),
            one("linear_acceleration", Nested("geometry_msgs/msg/Vector3")),
            fixed("linear_acceleration_covariance", Float64, 9),
        ],
    ),
    (
        "sensor_msgs/msg/Range",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("radiation_type", Uint8),
            one("field_of_view", Float32),
            one("min_range", Float32),
            one("max_range", Float32),
            one("range", Float32),
            one("variance", Float32),
        ],
    ),
    (
        "sensor_msgs/msg/BatteryState",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("voltage", Float32),
            one("temperature", Float32),
            one("current", Float32),
            one("charge", Float32),
            one("capacity", Float32),
            one("design_capacity", Float32),
            one("percentage", Float32),
            one("power_supply_status", Uint8),
            one("power_supply_health", Uint8),
            one("power_supply_technology", Uint8),
            one("present", Bool),
            seq("cell_voltage", Float32),
            seq("cell_temperature", Float32),
            one("location", Str),
            one("serial_number", Str),
        ],
    ),
    ("tf2_msgs/msg/TFMessage", &[seq("transforms", Nested("geometry_msgs/msg/TransformStamped"))]),
    ("rosgraph_msgs/msg/Clock", &[one("clock", Nested("builtin_interfaces/msg/Time"))]),
    (
        "sensor_msgs/msg/CompressedImage",
        &[one("header", Nested("std_msgs/msg/Header")), one("format", Str), seq("data", Uint8)],
    ),
    ("visualization_msgs/msg/UVCoordinate", &[one("u", Float32), one("v", Float32)]),
    ("visualization_msgs/msg/MeshFile", &[one("filename", Str), seq("data", Uint8)]),
    (
        "visualization_msgs/msg/Marker",
        &[
            one("header", Nested("std_msgs/msg/Header")),
            one("ns", Str),
            one("id", Int32),
            one("type", Int32),
            one("action", Int32),
            one("pose", Nested("geometry_msgs/msg/Pose")),
            one("scale", Nested("geometry_msgs/msg/Vector3")),
            one("color", Nested("std_msgs/msg/ColorRGBA")),
            one("lifetime", Nested("builtin_interfaces/msg/Duration")),
            one("frame_locked", Bool),
            seq("points", Nested("geometry_msgs/msg/Point")),
            seq("colors", Nested("std_msgs/msg/ColorRGBA")),
            one("texture_resource", Str),
            one("texture", Nested("sensor_msgs/msg/CompressedImage")),
            seq("uv_coordinates", Nested("visualization_msgs/msg/UVCoordinate")),
            one("text", Str),
            one("mesh_resource", Str),
            one("mesh_file", Nested("visualization_msgs/msg/MeshFile")),
            one("mesh_use_embedded_materials", Bool),
        ],
    ),
    ("visualization_msgs/msg/MarkerArray", &[seq("markers", Nested("visualization_msgs/msg/Marker"))]),
];

/// The fields of type `name` (`pkg/msg/Name`), if it is one of [`TYPES`].
pub fn fields(name: &str) -> Option<&'static [Field]> {
    TYPES.iter().find(|(n, _)| *n == name).map(|(_, f)| *f)
}

/// The DDS name of a type, as rmw_zenoh puts it in keys: `pkg::msg::dds_::Name_`.
pub fn dds_name(name: &str) -> String {
    let mut parts = name.splitn(3, '/');
    let (pkg, kind, ty) = (parts.next().unwrap_or(""), parts.next().unwrap_or(""), parts.next().unwrap_or(""));
    format!("{pkg}::{kind}::dds_::{ty}_")
}

fn description_json(name: &str, out: &mut String) {
    out.push_str(&format!("{{\"type_name\": \"{name}\", \"fields\": ["));
    for (k, f) in fields(name).unwrap_or(&[]).iter().enumerate() {
        if k > 0 {
            out.push_str(", ");
        }
        let (container, capacity) = match f.array {
            None => (0, 0),
            Some(0) => (144, 0),
            Some(n) => (48, n),
        };
        let nested = if let Nested(t) = f.elem { t } else { "" };
        out.push_str(&format!(
            "{{\"name\": \"{}\", \"type\": {{\"type_id\": {}, \"capacity\": {capacity}, \"string_capacity\": 0, \
             \"nested_type_name\": \"{nested}\"}}}}",
            f.name,
            f.elem.type_id() + container,
        ));
    }
    out.push_str("]}");
}

/// Every type `name` refers to, transitively, sorted by name, without `name`.
fn referenced(name: &str) -> Vec<&'static str> {
    let mut found: Vec<&'static str> = Vec::new();
    let mut todo = vec![name.to_owned()];
    while let Some(t) = todo.pop() {
        for f in fields(&t).unwrap_or(&[]) {
            if let Nested(n) = f.elem
                && n != name
                && !found.contains(&n)
            {
                found.push(n);
                todo.push(n.to_owned());
            }
        }
    }
    found.sort_unstable();
    found
}

/// The JSON that RIHS01 hashes for type `name`.
pub fn hashed_json(name: &str) -> String {
    let mut out = String::from("{\"type_description\": ");
    description_json(name, &mut out);
    out.push_str(", \"referenced_type_descriptions\": [");
    for (k, r) in referenced(name).iter().enumerate() {
        if k > 0 {
            out.push_str(", ");
        }
        description_json(r, &mut out);
    }
    out.push_str("]}");
    out
}

/// The RIHS01 type hash of type `name` (`RIHS01_` and 64 lowercase hex digits).
pub fn type_hash(name: &str) -> String {
    // Memoised: the node names every topic's type hash in two keys, 9 topics per copter.
    static KNOWN: std::sync::LazyLock<std::sync::Mutex<std::collections::HashMap<String, String>>> =
        std::sync::LazyLock::new(Default::default);
    let mut known = crate::lock(&KNOWN);
    if let Some(h) = known.get(name) {
        return h.clone();
    }
    let digest = Sha256::digest(hashed_json(name).as_bytes());
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    let hash = format!("RIHS01_{hex}");
    known.insert(name.to_owned(), hash.clone());
    hash
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Jazzy's hashes, as rosbags 0.11.9 computes them (`get_typestore(Stores.ROS2_JAZZY)
    /// .hash_rihs01(t)`); PoseStamped, Twist, Imu, Odometry, TFMessage and Marker also appear
    /// in code that talks to rmw_zenoh.
    const JAZZY: &[(&str, &str)] = &[
        ("builtin_interfaces/msg/Time", "b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197"),
        ("std_msgs/msg/Header", "f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01"),
        ("geometry_msgs/msg/PoseStamped", "10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"),
        ("geometry_msgs/msg/Twist", "9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"),
        ("nav_msgs/msg/Odometry", "3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"),
        ("sensor_msgs/msg/Imu", "7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b"),
        ("sensor_msgs/msg/Range", "b42b62562e93cbfe9d42b82fe5994dfa3d63d7d5c90a317981703f7388adff3a"),
        ("sensor_msgs/msg/BatteryState", "4bee5dfce981c98faa6828b868307a0a73f992ed0789f374ee96c8f840e69741"),
        ("tf2_msgs/msg/TFMessage", "e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"),
        ("rosgraph_msgs/msg/Clock", "692f7a66e93a3c83e71765d033b60349ba68023a8c689a79e48078bcb5c58564"),
        ("visualization_msgs/msg/Marker", "45b13ccf791f225962bf74e746f9644518855d783a6f42ba0cc14fde2b4f3ce0"),
        ("visualization_msgs/msg/MarkerArray", "86cb8800b6fb05b5eff1abd7a56f62a5641d3ae9a1c29e78e67e704f1d067dcf"),
    ];

    #[test]
    fn hashes_equal_jazzy_s() {
        for (name, hex) in JAZZY {
            assert_eq!(type_hash(name), format!("RIHS01_{hex}"), "{name}");
        }
    }

    #[test]
    fn the_hashed_text_of_time_is_rosidl_s() {
        assert_eq!(
            hashed_json("builtin_interfaces/msg/Time"),
            "{\"type_description\": {\"type_name\": \"builtin_interfaces/msg/Time\", \"fields\": [{\"name\": \
             \"sec\", \"type\": {\"type_id\": 6, \"capacity\": 0, \"string_capacity\": 0, \"nested_type_name\": \
             \"\"}}, {\"name\": \"nanosec\", \"type\": {\"type_id\": 7, \"capacity\": 0, \"string_capacity\": 0, \
             \"nested_type_name\": \"\"}}]}, \"referenced_type_descriptions\": []}"
        );
        assert_eq!(dds_name("geometry_msgs/msg/PoseStamped"), "geometry_msgs::msg::dds_::PoseStamped_");
    }

    #[test]
    fn every_nested_type_is_described() {
        for (name, fields) in TYPES {
            for f in *fields {
                if let Nested(n) = f.elem {
                    assert!(super::fields(n).is_some(), "{name}.{} refers to {n}", f.name);
                }
            }
        }
    }
}
