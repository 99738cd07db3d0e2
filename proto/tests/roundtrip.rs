//! Every v1 message survives encode → decode unchanged, and malformed bytes are rejected with an
//! error rather than a panic.

use relfusion_proto::Message;
use relfusion_proto::v1::{
    BlockIndex, Camera, ClientMessage, CreateSessionReply, DenseMode, Distortion, EndOfStream,
    Error, ErrorCode, Frame, FramePolicy, ImageEncoding, KeyframeDepth, KeyframeUpdate,
    MapSnapshot, MeshBlock, MeshUpdate, PoseUpdate, Quaternion, ServerMessage, SessionConfig,
    SessionFinished, Sim3Pose, StampedPose, TrackingState, Vector3, client_message, server_message,
};

fn roundtrip<M: Message + Default + PartialEq + std::fmt::Debug>(message: &M) {
    let bytes = message.encode_to_vec();
    let decoded = M::decode(bytes.as_slice()).expect("decode what we just encoded");
    assert_eq!(&decoded, message);
    // Length-delimited framing (what a byte stream of several messages uses) must round-trip too.
    let framed = message.encode_length_delimited_to_vec();
    assert_eq!(
        &M::decode_length_delimited(framed.as_slice()).expect("decode framed"),
        message
    );
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn camera() -> Camera {
    Camera {
        fx: 517.3,
        fy: 516.5,
        cx: 318.6,
        cy: 255.3,
        width: 640,
        height: 480,
        distortion: Some(Distortion {
            k1: 0.2624,
            k2: -0.9531,
            p1: -0.0054,
            p2: 0.0026,
            k3: 1.1633,
        }),
    }
}

fn pose() -> Sim3Pose {
    Sim3Pose {
        translation: Some(Vector3 {
            x: 1.5,
            y: -0.25,
            z: 3.0,
        }),
        rotation: Some(Quaternion {
            x: 0.1,
            y: -0.2,
            z: 0.3,
            w: (1.0f64 - 0.14).sqrt(),
        }),
        scale: 0.75,
    }
}

fn pose_update() -> PoseUpdate {
    PoseUpdate {
        session_id: "s-42".into(),
        frame_id: 17,
        timestamp: 1305031229.528748,
        world_from_camera: Some(pose()),
        tracking_state: TrackingState::Tracking as i32,
        is_keyframe: true,
        keyframe_id: 3,
    }
}

fn keyframe_update() -> KeyframeUpdate {
    KeyframeUpdate {
        session_id: "s-42".into(),
        keyframe_id: 3,
        frame_id: 17,
        timestamp: 1305031229.528748,
        world_from_camera: Some(pose()),
        depth: Some(KeyframeDepth {
            width: 2,
            height: 2,
            inverse_depth: f32_bytes(&[0.5, 0.0, 1.25, 2.0]),
            variance: f32_bytes(&[0.01, 0.0, 0.02, 0.03]),
            camera: Some(Camera {
                fx: 2.0,
                fy: 2.0,
                cx: 0.5,
                cy: 0.5,
                width: 2,
                height: 2,
                distortion: None,
            }),
            mode: DenseMode::Prior as i32,
        }),
    }
}

fn mesh_update() -> MeshUpdate {
    MeshUpdate {
        session_id: "s-42".into(),
        revision: 9,
        changed_blocks: vec![MeshBlock {
            index: Some(BlockIndex { x: -1, y: 0, z: 7 }),
            vertices: f32_bytes(&[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]),
            colors: vec![255, 0, 0, 0, 255, 0, 0, 0, 255],
            normals: f32_bytes(&[0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]),
            indices: vec![0, 1, 2],
        }],
        removed_blocks: vec![BlockIndex { x: 3, y: -4, z: 5 }],
        block_size: 0.32,
    }
}

fn error() -> Error {
    Error {
        code: ErrorCode::InvalidArgument as i32,
        message: "unknown config key `foo`".into(),
    }
}

#[test]
fn geometry_messages_roundtrip() {
    roundtrip(&camera());
    roundtrip(&Camera {
        distortion: None,
        ..camera()
    });
    roundtrip(&pose());
    roundtrip(&Distortion {
        k1: 1.0,
        k2: 2.0,
        p1: 3.0,
        p2: 4.0,
        k3: 5.0,
    });
}

#[test]
fn frame_roundtrips_with_and_without_camera() {
    let frame = Frame {
        frame_id: 123,
        timestamp: 12.5,
        image: vec![0xff, 0xd8, 0xff, 0xe0, 1, 2, 3],
        encoding: ImageEncoding::Jpeg as i32,
        camera: Some(camera()),
    };
    roundtrip(&frame);
    roundtrip(&Frame {
        camera: None,
        encoding: ImageEncoding::Png as i32,
        ..frame
    });
}

#[test]
fn update_messages_roundtrip() {
    roundtrip(&pose_update());
    roundtrip(&keyframe_update());
    roundtrip(&KeyframeUpdate {
        depth: None,
        ..keyframe_update()
    });
    roundtrip(&mesh_update());
    roundtrip(&error());
}

#[test]
fn session_config_roundtrips() {
    roundtrip(&SessionConfig {
        camera: Some(camera()),
        config_json: r#"{"tracking":{"affine_lighting":false}}"#.into(),
        model_name: "midas_v21_small_256".into(),
        policy: FramePolicy::Wait as i32,
        map_id: "m-0123456789abcdef01234567".into(),
        map_mode: relfusion_proto::v1::MapMode::Localize as i32,
        ros2: Some(relfusion_proto::v1::Ros2Options {
            publish: true,
            image_topic: "camera/image_raw".into(),
            camera_info_topic: "camera/camera_info".into(),
        }),
    });
    // A config written before `policy` existed decodes to the server default.
    let old = SessionConfig {
        camera: Some(camera()),
        ..Default::default()
    };
    let decoded = SessionConfig::decode(old.encode_to_vec().as_slice()).expect("decode");
    assert_eq!(decoded.policy(), FramePolicy::Unspecified);
    assert!(
        decoded.map_id.is_empty(),
        "no map: an empty one, as before maps existed"
    );
}

#[test]
fn zenoh_messages_roundtrip() {
    roundtrip(&CreateSessionReply {
        session_id: "s-0123456789ab".into(),
        error: None,
    });
    let refused = CreateSessionReply {
        session_id: String::new(),
        error: Some(Error {
            code: ErrorCode::Unauthenticated as i32,
            message: "this server needs a bearer token".into(),
        }),
    };
    roundtrip(&refused);
    let decoded = CreateSessionReply::decode(refused.encode_to_vec().as_slice()).expect("decode");
    assert_eq!(
        decoded.error.expect("error kept").code(),
        ErrorCode::Unauthenticated
    );
    let stamped = |t: f64| StampedPose {
        timestamp: t,
        world_from_camera: Some(pose()),
    };
    let mesh = mesh_update();
    roundtrip(&MapSnapshot {
        session_id: "s-42".into(),
        state: "finished".into(),
        frames_processed: 3,
        trajectory: vec![stamped(0.0), stamped(0.033), stamped(0.066)],
        keyframes: vec![stamped(0.0)],
        mesh_blocks: mesh.changed_blocks,
        block_size: mesh.block_size,
        mesh_revision: mesh.revision,
        frames_received: 4,
        frames_dropped: 1,
    });
    roundtrip(&MapSnapshot::default());
    roundtrip(&SessionFinished {
        session_id: "s-42".into(),
        state: "failed".into(),
        error: "the pipeline failed".into(),
        frames_received: 10,
        frames_processed: 9,
        frames_dropped: 1,
        keyframes: 2,
    });
}

#[test]
fn envelopes_roundtrip_every_variant() {
    let server = [
        server_message::Message::Pose(pose_update()),
        server_message::Message::Keyframe(keyframe_update()),
        server_message::Message::Mesh(mesh_update()),
        server_message::Message::Error(error()),
    ];
    for message in server {
        roundtrip(&ServerMessage {
            message: Some(message),
        });
    }
    let client = [
        client_message::Message::Config(SessionConfig::default()),
        client_message::Message::Frame(Frame {
            frame_id: 1,
            ..Default::default()
        }),
        client_message::Message::EndOfStream(EndOfStream {}),
    ];
    for message in client {
        roundtrip(&ClientMessage {
            message: Some(message),
        });
    }
}

#[test]
fn enums_decode_to_named_values() {
    let decoded = PoseUpdate::decode(pose_update().encode_to_vec().as_slice()).expect("decode");
    assert_eq!(decoded.tracking_state(), TrackingState::Tracking);
    let decoded = Error::decode(error().encode_to_vec().as_slice()).expect("decode");
    assert_eq!(decoded.code(), ErrorCode::InvalidArgument);
}

#[test]
fn garbage_bytes_are_an_error_not_a_panic() {
    // A varint that never ends (overflows 64 bits).
    let overflow = [0xffu8; 16];
    assert!(ServerMessage::decode(overflow.as_slice()).is_err());
    assert!(ClientMessage::decode(overflow.as_slice()).is_err());
    // Field 1 (a message) sent with the varint wire type.
    assert!(ServerMessage::decode([0x08u8, 0x01].as_slice()).is_err());
    // A valid message cut short.
    let bytes = ServerMessage {
        message: Some(server_message::Message::Mesh(mesh_update())),
    }
    .encode_to_vec();
    assert!(ServerMessage::decode(&bytes[..bytes.len() - 3]).is_err());
    // A length prefix larger than the remaining bytes.
    assert!(Frame::decode_length_delimited([0x7fu8, 0x01, 0x02].as_slice()).is_err());
    // Deterministic pseudo-random junk: decoding may succeed or fail, but must never panic.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    for len in 0..256usize {
        let junk: Vec<u8> = (0..len)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                (state >> 24) as u8
            })
            .collect();
        let _ = ServerMessage::decode(junk.as_slice());
        let _ = ClientMessage::decode(junk.as_slice());
    }
}

#[test]
fn proto_sources_are_exported() {
    assert_eq!(relfusion_proto::PROTO_FILES.len(), 4);
    for (path, source) in relfusion_proto::PROTO_FILES {
        assert!(path.starts_with("relfusion/v1/"), "{path}");
        assert!(
            source.contains("package relfusion.v1;"),
            "{path} lacks the package line"
        );
    }
    let all: String = relfusion_proto::PROTO_FILES
        .iter()
        .map(|(_, s)| *s)
        .collect();
    for name in [
        "message ServerMessage",
        "message ClientMessage",
        "message MapSnapshot",
        "message CreateSessionReply",
        "world_from_camera",
    ] {
        assert!(
            all.contains(name),
            "{name} missing from the exported sources"
        );
    }
}
