//! The messages, CDR-encoded from the simulator's values (and the two it reads, decoded).
//! Field order and types are those of [`super::types::TYPES`]; a test per type checks the
//! bytes against that description, and the Python tests decode them with rosbags.

use super::cdr::{CdrError, CdrReader, CdrWriter};

/// A ROS time stamp (`builtin_interfaces/Time`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stamp {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds, below 10⁹.
    pub nanosec: u32,
}

impl Stamp {
    /// The stamp of a time in seconds (non-negative, exact to the nanosecond).
    pub fn from_secs(t: f64) -> Self {
        let ns = (t.max(0.0) * 1e9).round() as u64;
        Self { sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32, nanosec: (ns % 1_000_000_000) as u32 }
    }

    fn write(self, w: &mut CdrWriter) {
        w.i32(self.sec);
        w.u32(self.nanosec);
    }
}

fn header(w: &mut CdrWriter, stamp: Stamp, frame_id: &str) {
    stamp.write(w);
    w.string(frame_id);
}

/// A pose: position (m) and orientation (x, y, z, w).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    /// Position, m.
    pub pos: [f64; 3],
    /// Orientation quaternion (x, y, z, w).
    pub quat: [f64; 4],
}

impl Pose {
    fn write(&self, w: &mut CdrWriter) {
        w.f64s(&self.pos);
        w.f64s(&self.quat);
    }
}

/// `geometry_msgs/PoseStamped`.
pub fn pose_stamped(stamp: Stamp, frame_id: &str, pose: &Pose) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    pose.write(&mut w);
    w.into_bytes()
}

/// `nav_msgs/Odometry`: the pose in `frame_id`, the twist (m/s, rad/s) in `child_frame_id`
/// (the body), covariances unknown (zeros).
pub fn odometry(
    stamp: Stamp,
    frame_id: &str,
    child_frame_id: &str,
    pose: &Pose,
    linear: [f64; 3],
    angular: [f64; 3],
) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    w.string(child_frame_id);
    pose.write(&mut w);
    w.f64s(&[0.0; 36]);
    w.f64s(&linear);
    w.f64s(&angular);
    w.f64s(&[0.0; 36]);
    w.into_bytes()
}

/// `sensor_msgs/Imu`: orientation (x, y, z, w), body rates (rad/s) and specific force (m/s²),
/// each with the diagonal variance given.
pub fn imu(
    stamp: Stamp,
    frame_id: &str,
    quat: [f64; 4],
    gyro: [f64; 3],
    accel: [f64; 3],
    variances: [f64; 3],
) -> Vec<u8> {
    let diag = |v: f64| [v, 0.0, 0.0, 0.0, v, 0.0, 0.0, 0.0, v];
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    w.f64s(&quat);
    w.f64s(&diag(variances[0]));
    w.f64s(&gyro);
    w.f64s(&diag(variances[1]));
    w.f64s(&accel);
    w.f64s(&diag(variances[2]));
    w.into_bytes()
}

/// What a range sensor is (`sensor_msgs/Range` less the reading).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeSensor {
    /// 0: ultrasound, 1: infrared.
    pub radiation_type: u8,
    /// Full cone angle, rad.
    pub field_of_view: f32,
    /// Minimum and maximum range, m.
    pub min_range: f32,
    /// Maximum range, m.
    pub max_range: f32,
}

/// `sensor_msgs/Range`. Out of range: +∞ (beyond `max_range`, ROS's convention).
pub fn range(stamp: Stamp, frame_id: &str, sensor: &RangeSensor, range: f32, variance: f32) -> Vec<u8> {
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    w.u8(sensor.radiation_type);
    w.f32(sensor.field_of_view);
    w.f32(sensor.min_range);
    w.f32(sensor.max_range);
    w.f32(range);
    w.f32(variance);
    w.into_bytes()
}

/// `sensor_msgs/BatteryState` of a LiPo being discharged: voltage (V) and charge left (0–1);
/// what the model does not know is NaN, as the message asks.
pub fn battery(stamp: Stamp, frame_id: &str, voltage: f32, percentage: f32) -> Vec<u8> {
    const DISCHARGING: u8 = 2;
    const GOOD: u8 = 1;
    const LIPO: u8 = 3;
    let mut w = CdrWriter::new();
    header(&mut w, stamp, frame_id);
    for v in [voltage, f32::NAN, f32::NAN, f32::NAN, f32::NAN, f32::NAN, percentage] {
        w.f32(v);
    }
    w.u8(DISCHARGING);
    w.u8(GOOD);
    w.u8(LIPO);
    w.bool(true);
    w.seq(0); // cell_voltage
    w.seq(0); // cell_temperature
    w.string("");
    w.string("");
    w.into_bytes()
}

/// `tf2_msgs/TFMessage`: each (child frame, pose) relative to `parent`.
pub fn tf<'a>(stamp: Stamp, parent: &str, transforms: impl ExactSizeIterator<Item = (&'a str, Pose)>) -> Vec<u8> {
    let mut w = CdrWriter::new();
    w.seq(transforms.len());
    for (child, pose) in transforms {
        header(&mut w, stamp, parent);
        w.string(child);
        pose.write(&mut w);
    }
    w.into_bytes()
}

/// `rosgraph_msgs/Clock`.
pub fn clock(stamp: Stamp) -> Vec<u8> {
    let mut w = CdrWriter::new();
    stamp.write(&mut w);
    w.into_bytes()
}

/// A box drawn as a `CUBE` marker.
#[derive(Clone, Debug, PartialEq)]
pub struct Cube {
    /// Marker namespace.
    pub ns: String,
    /// Marker id (unique in its namespace).
    pub id: i32,
    /// Centre and orientation.
    pub pose: Pose,
    /// Size along its axes, m.
    pub size: [f64; 3],
    /// Colour (r, g, b, a), 0–1.
    pub rgba: [f32; 4],
}

/// `visualization_msgs/MarkerArray` of `ADD` cube markers that never expire.
pub fn marker_array(stamp: Stamp, frame_id: &str, cubes: &[Cube]) -> Vec<u8> {
    const CUBE: i32 = 1;
    const ADD: i32 = 0;
    let mut w = CdrWriter::new();
    w.seq(cubes.len());
    for c in cubes {
        header(&mut w, stamp, frame_id);
        w.string(&c.ns);
        w.i32(c.id);
        w.i32(CUBE);
        w.i32(ADD);
        c.pose.write(&mut w);
        w.f64s(&c.size);
        for v in c.rgba {
            w.f32(v);
        }
        Stamp::default().write(&mut w); // lifetime 0: forever
        w.bool(false); // frame_locked
        w.seq(0); // points
        w.seq(0); // colors
        w.string(""); // texture_resource
        header(&mut w, Stamp::default(), ""); // texture: an empty CompressedImage
        w.string("");
        w.seq(0);
        w.seq(0); // uv_coordinates
        w.string(""); // text
        w.string(""); // mesh_resource
        w.string(""); // mesh_file: an empty MeshFile
        w.seq(0);
        w.bool(false); // mesh_use_embedded_materials
    }
    w.into_bytes()
}

/// A `geometry_msgs/Twist`: (linear, angular).
pub fn decode_twist(data: &[u8]) -> Result<([f64; 3], [f64; 3]), CdrError> {
    let mut r = CdrReader::new(data)?;
    let mut v = [0.0; 6];
    for (x, what) in v.iter_mut().zip(["linear.x", "linear.y", "linear.z", "angular.x", "angular.y", "angular.z"]) {
        *x = r.f64(what)?;
    }
    Ok(([v[0], v[1], v[2]], [v[3], v[4], v[5]]))
}

/// A `geometry_msgs/PoseStamped`: its frame id and pose.
pub fn decode_pose_stamped(data: &[u8]) -> Result<(String, Pose), CdrError> {
    let mut r = CdrReader::new(data)?;
    r.i32("header.stamp.sec")?;
    r.u32("header.stamp.nanosec")?;
    let frame = r.string("header.frame_id")?.to_owned();
    let mut v = [0.0; 7];
    for (x, what) in v.iter_mut().zip(["x", "y", "z", "qx", "qy", "qz", "qw"]) {
        *x = r.f64(what)?;
    }
    Ok((frame, Pose { pos: [v[0], v[1], v[2]], quat: [v[3], v[4], v[5], v[6]] }))
}

#[cfg(test)]
mod tests {
    use super::super::types::{Elem, fields};
    use super::*;

    /// Walks `data` as type `name` says, with default field contents (strings empty,
    /// sequences as long as their count says): the number of bytes that makes.
    fn walk(name: &str, r: &mut Walker<'_>) {
        for f in fields(name).unwrap() {
            let n = match f.array {
                None => 1,
                Some(0) => r.u32() as usize,
                Some(n) => n as usize,
            };
            for _ in 0..n {
                match f.elem {
                    Elem::Nested(t) => walk(t, r),
                    Elem::Str => {
                        let len = r.u32() as usize;
                        r.pos += len;
                    }
                    Elem::Float64 => r.skip(8),
                    Elem::Int32 | Elem::Uint32 | Elem::Float32 => r.skip(4),
                    Elem::Uint8 | Elem::Bool => r.skip(1),
                }
            }
        }
    }

    struct Walker<'a> {
        data: &'a [u8],
        pos: usize,
    }

    impl Walker<'_> {
        fn skip(&mut self, n: usize) {
            self.pos += (n - (self.pos - 4) % n) % n + n;
        }
        fn u32(&mut self) -> u32 {
            self.pos += (4 - (self.pos - 4) % 4) % 4;
            let v = u32::from_le_bytes(self.data[self.pos..self.pos + 4].try_into().unwrap());
            self.pos += 4;
            v
        }
    }

    fn length_as_described(name: &str, data: &[u8]) -> usize {
        let mut w = Walker { data, pos: 4 };
        walk(name, &mut w);
        w.pos
    }

    #[test]
    fn every_message_is_as_long_as_its_type_says() {
        let s = Stamp::from_secs(12.345);
        let p = Pose { pos: [1.0, 2.0, 3.0], quat: [0.0, 0.0, 0.0, 1.0] };
        let sonar = RangeSensor { radiation_type: 0, field_of_view: 0.5, min_range: 0.2, max_range: 3.0 };
        let cube = Cube { ns: "arena".into(), id: 3, pose: p, size: [1.0, 1.0, 1.0], rgba: [1.0; 4] };
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("geometry_msgs/msg/PoseStamped", pose_stamped(s, "world", &p)),
            ("nav_msgs/msg/Odometry", odometry(s, "world", "c/base_link", &p, [1.0; 3], [0.5; 3])),
            ("sensor_msgs/msg/Imu", imu(s, "c/base_link", p.quat, [0.1; 3], [9.8; 3], [0.0; 3])),
            ("sensor_msgs/msg/Range", range(s, "c/sonar_front", &sonar, 1.5, 0.0)),
            ("sensor_msgs/msg/BatteryState", battery(s, "c/base_link", 11.1, 0.9)),
            ("tf2_msgs/msg/TFMessage", tf(s, "world", [("a/base_link", p), ("bb/base_link", p)].into_iter())),
            ("rosgraph_msgs/msg/Clock", clock(s)),
            ("visualization_msgs/msg/MarkerArray", marker_array(s, "world", &[cube.clone(), cube])),
        ];
        for (name, data) in cases {
            assert_eq!(length_as_described(name, &data), data.len(), "{name}");
        }
    }

    #[test]
    fn stamps_and_decoders_round_trip() {
        assert_eq!(Stamp::from_secs(12.345), Stamp { sec: 12, nanosec: 345_000_000 });
        let p = Pose { pos: [1.0, -2.0, 0.5], quat: [0.0, 0.0, 0.6, 0.8] };
        assert_eq!(decode_pose_stamped(&pose_stamped(Stamp::from_secs(1.0), "world", &p)), Ok(("world".into(), p)));
        let mut w = CdrWriter::new();
        w.f64s(&[0.3, -0.1, 0.2, 0.0, 0.0, 0.5]);
        assert_eq!(decode_twist(&w.into_bytes()), Ok(([0.3, -0.1, 0.2], [0.0, 0.0, 0.5])));
        assert!(decode_twist(&[0, 1, 0, 0, 1, 2]).is_err());
    }
}
