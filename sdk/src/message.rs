//! The protobuf messages a client sends on a live session, and the image encodings it tells
//! apart (below every transport: HTTP uploads frames with the same sniffing).

use relfusion_proto::v1::{ClientMessage, EndOfStream, Frame, ImageEncoding, client_message};

/// Image formats the server accepts, told apart by their magic bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Encoding {
    Jpeg,
    Png,
    Unknown,
}

/// The encoding of `bytes` from its first bytes (what the server does too: file names and
/// extensions are not trusted).
pub fn sniff_encoding(bytes: &[u8]) -> Encoding {
    if bytes.starts_with(&[0xff, 0xd8, 0xff]) {
        Encoding::Jpeg
    } else if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        Encoding::Png
    } else {
        Encoding::Unknown
    }
}

/// A protobuf `Frame` message for an encoded image.
pub fn frame_message(frame_id: u64, timestamp: f64, image: Vec<u8>) -> ClientMessage {
    let encoding = match sniff_encoding(&image) {
        Encoding::Jpeg => ImageEncoding::Jpeg,
        Encoding::Png => ImageEncoding::Png,
        Encoding::Unknown => ImageEncoding::Unspecified,
    };
    ClientMessage {
        message: Some(client_message::Message::Frame(Frame {
            frame_id,
            timestamp,
            image,
            encoding: encoding as i32,
            camera: None,
        })),
    }
}

/// The protobuf end-of-stream marker.
pub fn end_of_stream() -> ClientMessage {
    ClientMessage {
        message: Some(client_message::Message::EndOfStream(EndOfStream {})),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encodings_are_sniffed_from_magic_bytes() {
        assert_eq!(sniff_encoding(&[0xff, 0xd8, 0xff, 0xe0]), Encoding::Jpeg);
        assert_eq!(sniff_encoding(b"\x89PNG\r\n\x1a\n...."), Encoding::Png);
        assert_eq!(sniff_encoding(b"GIF89a"), Encoding::Unknown);
        assert_eq!(sniff_encoding(b""), Encoding::Unknown);
        let m = frame_message(7, 1.5, b"\x89PNG\r\n\x1a\nxx".to_vec());
        let Some(client_message::Message::Frame(f)) = m.message else {
            panic!("a frame message")
        };
        assert_eq!((f.frame_id, f.timestamp), (7, 1.5));
        assert_eq!(f.encoding, ImageEncoding::Png as i32);
    }
}
