//! The ROS 2 messages a robot sends a session (`sensor_msgs/Image`, `CompressedImage`,
//! `CameraInfo`, CDR from any rmw_zenoh peer of the tenant): reading arbitrary bytes returns
//! a message or an error, never panics, and never allocates more than the input holds (counts
//! are checked against the bytes left). The first byte picks the type.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relfusion_viz::ros2::msgs;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, cdr)) = data.split_first() else {
        return;
    };
    match kind % 3 {
        0 => {
            if let Ok(image) = msgs::read_image(cdr) {
                assert!(image.data.len() <= cdr.len());
            }
        }
        1 => {
            if let Ok(image) = msgs::read_compressed_image(cdr) {
                assert!(image.data.len() <= cdr.len());
            }
        }
        _ => {
            if let Ok(info) = msgs::read_camera_info(cdr) {
                assert!(info.d.len() * 8 <= cdr.len());
            }
        }
    }
});
