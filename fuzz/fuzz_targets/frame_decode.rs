//! The frame decoder (HTTP, WebSocket and Zenoh frames): any bytes with any camera size must
//! decode or be refused with an error, never panic, hang or allocate beyond the camera's size.
#![no_main]

use libfuzzer_sys::fuzz_target;
use relfusion_server::session::decode::decode_frame;

fuzz_target!(|data: &[u8]| {
    if data.len() < 2 {
        return;
    }
    // The first two bytes pick the camera (16..=271 pixels a side); the rest is the image.
    let width = 16 + u32::from(data[0]);
    let height = 16 + u32::from(data[1]);
    if let Ok(image) = decode_frame(&data[2..], width, height) {
        assert_eq!(image.dimensions(), (width, height));
    }
});
