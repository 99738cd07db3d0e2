//! The ROS 2 message types relfusion speaks, with their type hashes (REP-2011 `RIHS01`).
//!
//! A hash is the SHA-256 of the type's description — its fields' names and types and those of
//! every type it references, sorted by name — written as JSON exactly as
//! `rosidl_generator_type_description` writes it (default values left out). It is computed
//! here from the field lists below rather than pasted, so a wrong field cannot hide behind a
//! right-looking constant; the tests compare the results with the values that Kilted Kaiju's
//! generated `*__description.c` files publish (and `std_msgs/String`'s, which the rmw_zenoh
//! design document quotes). These definitions are unchanged from Jazzy to Kilted.

use std::collections::{BTreeSet, HashMap};
use std::sync::OnceLock;

use sha2::{Digest as _, Sha256};

/// One ROS 2 message type, by its full name (`package/msg/Name`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct RosType(pub &'static str);

pub const POSE_STAMPED: RosType = RosType("geometry_msgs/msg/PoseStamped");
pub const PATH: RosType = RosType("nav_msgs/msg/Path");
pub const TF_MESSAGE: RosType = RosType("tf2_msgs/msg/TFMessage");
pub const POINT_CLOUD2: RosType = RosType("sensor_msgs/msg/PointCloud2");
pub const MARKER_ARRAY: RosType = RosType("visualization_msgs/msg/MarkerArray");
pub const IMAGE: RosType = RosType("sensor_msgs/msg/Image");
pub const COMPRESSED_IMAGE: RosType = RosType("sensor_msgs/msg/CompressedImage");
pub const CAMERA_INFO: RosType = RosType("sensor_msgs/msg/CameraInfo");

/// Field lists (`name`, `type`) of every type above and of the types they reference. A type
/// is a primitive, a full type name, either followed by `[]` (sequence) or `[N]` (array).
#[rustfmt::skip]
const DESCRIPTIONS: &[(&str, &[(&str, &str)])] = &[
    ("builtin_interfaces/msg/Time", &[("sec", "int32"), ("nanosec", "uint32")]),
    ("builtin_interfaces/msg/Duration", &[("sec", "int32"), ("nanosec", "uint32")]),
    ("std_msgs/msg/Header", &[("stamp", "builtin_interfaces/msg/Time"), ("frame_id", "string")]),
    ("std_msgs/msg/String", &[("data", "string")]),
    ("std_msgs/msg/ColorRGBA", &[("r", "float32"), ("g", "float32"), ("b", "float32"), ("a", "float32")]),
    ("geometry_msgs/msg/Point", &[("x", "float64"), ("y", "float64"), ("z", "float64")]),
    ("geometry_msgs/msg/Vector3", &[("x", "float64"), ("y", "float64"), ("z", "float64")]),
    ("geometry_msgs/msg/Quaternion", &[("x", "float64"), ("y", "float64"), ("z", "float64"), ("w", "float64")]),
    ("geometry_msgs/msg/Pose", &[("position", "geometry_msgs/msg/Point"), ("orientation", "geometry_msgs/msg/Quaternion")]),
    ("geometry_msgs/msg/PoseStamped", &[("header", "std_msgs/msg/Header"), ("pose", "geometry_msgs/msg/Pose")]),
    ("geometry_msgs/msg/Transform", &[("translation", "geometry_msgs/msg/Vector3"), ("rotation", "geometry_msgs/msg/Quaternion")]),
    ("geometry_msgs/msg/TransformStamped", &[("header", "std_msgs/msg/Header"), ("child_frame_id", "string"), ("transform", "geometry_msgs/msg/Transform")]),
    ("tf2_msgs/msg/TFMessage", &[("transforms", "geometry_msgs/msg/TransformStamped[]")]),
    ("nav_msgs/msg/Path", &[("header", "std_msgs/msg/Header"), ("poses", "geometry_msgs/msg/PoseStamped[]")]),
    ("sensor_msgs/msg/CompressedImage", &[("header", "std_msgs/msg/Header"), ("format", "string"), ("data", "uint8[]")]),
    ("sensor_msgs/msg/Image", &[("header", "std_msgs/msg/Header"), ("height", "uint32"), ("width", "uint32"), ("encoding", "string"), ("is_bigendian", "uint8"), ("step", "uint32"), ("data", "uint8[]")]),
    ("sensor_msgs/msg/RegionOfInterest", &[("x_offset", "uint32"), ("y_offset", "uint32"), ("height", "uint32"), ("width", "uint32"), ("do_rectify", "boolean")]),
    ("sensor_msgs/msg/CameraInfo", &[("header", "std_msgs/msg/Header"), ("height", "uint32"), ("width", "uint32"), ("distortion_model", "string"), ("d", "float64[]"), ("k", "float64[9]"), ("r", "float64[9]"), ("p", "float64[12]"), ("binning_x", "uint32"), ("binning_y", "uint32"), ("roi", "sensor_msgs/msg/RegionOfInterest")]),
    ("sensor_msgs/msg/PointField", &[("name", "string"), ("offset", "uint32"), ("datatype", "uint8"), ("count", "uint32")]),
    ("sensor_msgs/msg/PointCloud2", &[("header", "std_msgs/msg/Header"), ("height", "uint32"), ("width", "uint32"), ("fields", "sensor_msgs/msg/PointField[]"), ("is_bigendian", "boolean"), ("point_step", "uint32"), ("row_step", "uint32"), ("data", "uint8[]"), ("is_dense", "boolean")]),
    ("visualization_msgs/msg/UVCoordinate", &[("u", "float32"), ("v", "float32")]),
    ("visualization_msgs/msg/MeshFile", &[("filename", "string"), ("data", "uint8[]")]),
    ("visualization_msgs/msg/Marker", &[("header", "std_msgs/msg/Header"), ("ns", "string"), ("id", "int32"), ("type", "int32"), ("action", "int32"), ("pose", "geometry_msgs/msg/Pose"), ("scale", "geometry_msgs/msg/Vector3"), ("color", "std_msgs/msg/ColorRGBA"), ("lifetime", "builtin_interfaces/msg/Duration"), ("frame_locked", "boolean"), ("points", "geometry_msgs/msg/Point[]"), ("colors", "std_msgs/msg/ColorRGBA[]"), ("texture_resource", "string"), ("texture", "sensor_msgs/msg/CompressedImage"), ("uv_coordinates", "visualization_msgs/msg/UVCoordinate[]"), ("text", "string"), ("mesh_resource", "string"), ("mesh_file", "visualization_msgs/msg/MeshFile"), ("mesh_use_embedded_materials", "boolean")]),
    ("visualization_msgs/msg/MarkerArray", &[("markers", "visualization_msgs/msg/Marker[]")]),
];

/// `type_description_interfaces/msg/FieldType` ids of the primitives used above.
fn primitive_id(name: &str) -> Option<u8> {
    Some(match name {
        "int8" => 2,
        "uint8" => 3,
        "int16" => 4,
        "uint16" => 5,
        "int32" => 6,
        "uint32" => 7,
        "int64" => 8,
        "uint64" => 9,
        "float32" => 10,
        "float64" => 11,
        "boolean" => 15,
        "string" => 17,
        _ => return None,
    })
}

/// The id of a nested type (`FIELD_TYPE_NESTED_TYPE`).
const NESTED: u8 = 1;
/// Added to an element's id for a fixed array, and for an unbounded sequence.
const ARRAY: u8 = 48;
const SEQUENCE: u8 = 144;

struct FieldType<'a> {
    id: u8,
    capacity: usize,
    nested: &'a str,
}

fn field_type(spec: &str) -> FieldType<'_> {
    let (element, offset, capacity) = if let Some(e) = spec.strip_suffix("[]") {
        (e, SEQUENCE, 0)
    } else if let Some((e, n)) = spec.strip_suffix(']').and_then(|s| s.split_once('[')) {
        (e, ARRAY, n.parse().unwrap_or(0))
    } else {
        (spec, 0, 0)
    };
    match primitive_id(element) {
        Some(id) => FieldType {
            id: id + offset,
            capacity,
            nested: "",
        },
        None => FieldType {
            id: NESTED + offset,
            capacity,
            nested: element,
        },
    }
}

fn fields_of(name: &str) -> &'static [(&'static str, &'static str)] {
    DESCRIPTIONS
        .iter()
        .find(|(n, _)| *n == name)
        .map_or(&[], |(_, fields)| *fields)
}

/// `{"type_name": ..., "fields": [...]}` as rosidl writes it (separators `", "` and `": "`).
fn individual_json(name: &str) -> String {
    let fields: Vec<String> = fields_of(name)
        .iter()
        .map(|(field, spec)| {
            let t = field_type(spec);
            format!(
                "{{\"name\": \"{field}\", \"type\": {{\"type_id\": {}, \"capacity\": {}, \
                 \"string_capacity\": 0, \"nested_type_name\": \"{}\"}}}}",
                t.id, t.capacity, t.nested
            )
        })
        .collect();
    format!(
        "{{\"type_name\": \"{name}\", \"fields\": [{}]}}",
        fields.join(", ")
    )
}

/// Every type `name` references, directly or not, sorted by name.
fn referenced(name: &str) -> BTreeSet<&'static str> {
    let mut found = BTreeSet::new();
    let mut todo = vec![name];
    while let Some(next) = todo.pop() {
        for (_, spec) in fields_of(next) {
            let nested = field_type(spec).nested;
            if let Some((n, _)) = DESCRIPTIONS.iter().find(|(n, _)| *n == nested)
                && found.insert(*n)
            {
                todo.push(n);
            }
        }
    }
    found
}

fn compute_hash(name: &str) -> String {
    let refs: Vec<String> = referenced(name).into_iter().map(individual_json).collect();
    let json = format!(
        "{{\"type_description\": {}, \"referenced_type_descriptions\": [{}]}}",
        individual_json(name),
        refs.join(", ")
    );
    let digest = Sha256::digest(json.as_bytes());
    let hex: String = digest.iter().map(|b| format!("{b:02x}")).collect();
    format!("RIHS01_{hex}")
}

impl RosType {
    /// `RIHS01_<64 hex digits>`.
    pub fn hash(self) -> &'static str {
        static HASHES: OnceLock<HashMap<&'static str, String>> = OnceLock::new();
        let hashes = HASHES.get_or_init(|| {
            DESCRIPTIONS
                .iter()
                .map(|(name, _)| (*name, compute_hash(name)))
                .collect()
        });
        hashes.get(self.0).map_or("", String::as_str)
    }

    /// The DDS name rmw implementations put in keys: `geometry_msgs::msg::dds_::PoseStamped_`.
    pub fn dds_name(self) -> String {
        let (package, name) = self.0.rsplit_once('/').unwrap_or(("", self.0));
        format!("{}::dds_::{name}_", package.replace('/', "::"))
    }

    /// `geometry_msgs/msg/PoseStamped`: the name MCAP's `ros2msg` schemas go by.
    pub fn name(self) -> &'static str {
        self.0
    }

    /// The type's definition as `ros2 bag` writes it into MCAP (`ros2msg` schema encoding):
    /// its fields, then each referenced type after a line of `=` and `MSG: package/Name`.
    /// Constants and comments are left out: they are not part of the wire format.
    pub fn msg_definition(self) -> String {
        let fields = |name: &str| -> String {
            fields_of(name)
                .iter()
                .map(|(field, spec)| {
                    let spec = spec.replace("/msg/", "/").replace("boolean", "bool");
                    format!("{spec} {field}\n")
                })
                .collect()
        };
        let mut text = fields(self.0);
        for referenced in referenced(self.0) {
            text.push_str(&"=".repeat(80));
            text.push_str(&format!("\nMSG: {}\n", referenced.replace("/msg/", "/")));
            text.push_str(&fields(referenced));
        }
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hashes_are_the_published_ones() {
        #[rustfmt::skip]
        let published = [
            ("std_msgs/msg/String", "df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"),
            ("std_msgs/msg/Header", "f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01"),
            ("geometry_msgs/msg/PoseStamped", "10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"),
            ("nav_msgs/msg/Path", "1957a5bb3cee5da65c4e52e52b65a93df227efce4c20f8458b36e73066ca334b"),
            ("tf2_msgs/msg/TFMessage", "e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"),
            ("sensor_msgs/msg/PointCloud2", "9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"),
            ("visualization_msgs/msg/Marker", "45b13ccf791f225962bf74e746f9644518855d783a6f42ba0cc14fde2b4f3ce0"),
            ("sensor_msgs/msg/Image", "d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47"),
            ("sensor_msgs/msg/CompressedImage", "15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a"),
            ("sensor_msgs/msg/CameraInfo", "b3dfd68ff46c9d56c80fd3bd4ed22c7a4ddce8c8348f2f59c299e73118e7e275"),
        ];
        for (name, hex) in published {
            assert_eq!(RosType(name).hash(), format!("RIHS01_{hex}"), "{name}");
        }
        // MarkerArray's value is not among the files at hand; it is one more level over the
        // verified Marker.
        assert_eq!(MARKER_ARRAY.hash().len(), 71);
        assert_eq!(RosType("unknown/msg/X").hash(), "");
    }

    #[test]
    fn msg_definitions_carry_every_referenced_type() {
        let path = PATH.msg_definition();
        assert!(path.starts_with("std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n"));
        for dependency in [
            "MSG: std_msgs/Header\n",
            "MSG: builtin_interfaces/Time\n",
            "MSG: geometry_msgs/Quaternion\n",
        ] {
            assert!(path.contains(dependency), "{dependency} in {path}");
        }
        assert!(CAMERA_INFO.msg_definition().contains("float64[9] k\n"));
        assert!(POINT_CLOUD2.msg_definition().contains("bool is_dense\n"));
    }

    #[test]
    fn dds_names_are_what_rmw_zenoh_puts_in_keys() {
        assert_eq!(
            POSE_STAMPED.dds_name(),
            "geometry_msgs::msg::dds_::PoseStamped_"
        );
        assert_eq!(TF_MESSAGE.dds_name(), "tf2_msgs::msg::dds_::TFMessage_");
    }
}
