//! The TUM text parsers an upload feeds: `rgb.txt`/`depth.txt` lists, `calibration.txt` and
//! `groundtruth.txt` (any text parses to values or an error naming its line, never a panic),
//! and the confinement of listed names to the dataset folder.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relfusion_slam::dataset::trajectory::parse_tum_trajectory;
use relfusion_slam::dataset::tum::{parse_calibration, parse_file_list};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(list) = parse_file_list(text, "rgb.txt", 1 << 16) {
        for (t, name) in list {
            assert!(t.is_finite() && !name.is_empty());
        }
    }
    if let Ok(camera) = parse_calibration(text, 640, 480) {
        assert!(camera.fx > 0.0 && camera.fy > 0.0);
    }
    if let Ok(poses) = parse_tum_trajectory(text, "groundtruth.txt") {
        for p in poses {
            assert!(p.timestamp.is_finite());
        }
    }
});
