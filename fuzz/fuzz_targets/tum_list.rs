//! The TUM list parser with the association an upload runs on it: the input is split at the
//! first NUL into an `rgb.txt` and a `depth.txt`; both parse within an entry cap or fail with
//! an error, and the association is one-to-one, within its time window, and linear in cost
//! (repeated stamps included: the hardening issue's quadratic association).
#![no_main]

use libfuzzer_sys::fuzz_target;
use relfusion_slam::dataset::tum::{MAX_ASSOCIATION_DT, associate, parse_file_list};

/// Entries per list: enough for long lists, small enough to keep every run fast.
const MAX_ENTRIES: usize = 4096;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let (rgb_text, depth_text) = text.split_once('\0').unwrap_or((text, text));
    let (Ok(rgb), Ok(depth)) = (
        parse_file_list(rgb_text, "rgb.txt", MAX_ENTRIES),
        parse_file_list(depth_text, "depth.txt", MAX_ENTRIES),
    ) else {
        return;
    };
    assert!(rgb.len() <= MAX_ENTRIES && depth.len() <= MAX_ENTRIES);
    let a: Vec<f64> = rgb.iter().map(|(t, _)| *t).collect();
    let b: Vec<f64> = depth.iter().map(|(t, _)| *t).collect();
    let pairs = associate(&a, &b, MAX_ASSOCIATION_DT);
    assert_eq!(pairs.len(), a.len());
    let mut used = vec![false; b.len()];
    for (i, partner) in pairs.iter().enumerate() {
        if let Some(j) = *partner {
            assert!(!used[j], "depth {j} associated twice");
            used[j] = true;
            assert!((a[i] - b[j]).abs() < MAX_ASSOCIATION_DT);
        }
    }
});
