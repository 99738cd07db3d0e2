//! Decoding an incoming frame: JPEG or PNG recognised from the magic bytes, its size checked
//! against the session's camera before the pixels are decoded (a 100-megapixel PNG must not be
//! decoded only to be refused), every failure a 400 that says what was wrong.

use image::ImageFormat;
use relfusion_slam::dataset::tum::{SizedDecodeError, decode_sized};

use crate::ApiError;

const JPEG_MAGIC: &[u8] = &[0xFF, 0xD8, 0xFF];
const PNG_MAGIC: &[u8] = &[0x89, b'P', b'N', b'G', 0x0D, 0x0A, 0x1A, 0x0A];

/// The format of an encoded frame, from its first bytes.
pub fn sniff(bytes: &[u8]) -> Result<ImageFormat, ApiError> {
    if bytes.starts_with(JPEG_MAGIC) {
        Ok(ImageFormat::Jpeg)
    } else if bytes.starts_with(PNG_MAGIC) {
        Ok(ImageFormat::Png)
    } else if bytes.is_empty() {
        Err(ApiError::bad_request(
            "empty frame: expected a JPEG or PNG image",
        ))
    } else {
        Err(ApiError::bad_request(
            "frame is neither a JPEG nor a PNG (unrecognised first bytes)",
        ))
    }
}

/// Decodes `bytes` into RGB, requiring `width`×`height` (checked from the header before any
/// pixel is decoded; the decoder may allocate no more than that size needs).
pub fn decode_frame(bytes: &[u8], width: u32, height: u32) -> Result<image::RgbImage, ApiError> {
    let name = match sniff(bytes)? {
        ImageFormat::Jpeg => "JPEG",
        _ => "PNG",
    };
    match decode_sized(bytes, width, height) {
        Ok(image) => Ok(image.into_rgb8()),
        Err(SizedDecodeError::Size(w, h)) => Err(ApiError::bad_request(format!(
            "frame is {w}x{h} but the session camera is {width}x{height}"
        ))),
        Err(SizedDecodeError::Image(e)) => {
            Err(ApiError::bad_request(format!("corrupt {name}: {e}")))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn encode(format: ImageFormat, w: u32, h: u32) -> Vec<u8> {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 7]));
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, format).expect("encode");
        out.into_inner()
    }

    #[test]
    fn decodes_jpeg_and_png_of_the_right_size() {
        for f in [ImageFormat::Jpeg, ImageFormat::Png] {
            let img = decode_frame(&encode(f, 32, 24), 32, 24).expect("decode");
            assert_eq!(img.dimensions(), (32, 24));
        }
    }

    #[test]
    fn rejects_garbage_truncation_and_size_mismatch() {
        let e = decode_frame(b"hello", 32, 24).expect_err("garbage");
        assert!(e.message.contains("neither"), "{e}");
        let png = encode(ImageFormat::Png, 32, 24);
        let e = decode_frame(&png[..png.len() / 2], 32, 24).expect_err("truncated");
        assert_eq!(e.status, 400);
        assert!(e.message.contains("PNG"), "{e}");
        let e = decode_frame(&encode(ImageFormat::Jpeg, 32, 24), 64, 48).expect_err("size");
        assert!(
            e.message.contains("32x24") && e.message.contains("64x48"),
            "{e}"
        );
        let mut jpeg = encode(ImageFormat::Jpeg, 32, 24);
        jpeg.truncate(40);
        assert_eq!(
            decode_frame(&jpeg, 32, 24).expect_err("corrupt").status,
            400
        );
    }
}
