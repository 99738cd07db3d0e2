//! Every protobuf message a peer can send (WebSocket `ClientMessage`, Zenoh `Frame`,
//! `SessionConfig`, `EndOfStream`) and those clients decode (`ServerMessage`, `MapSnapshot`,
//! `CreateSessionReply`): decoding arbitrary bytes returns a message or an error, and a
//! decoded message re-encodes to bytes that decode to the same encoding (bytes, not values:
//! a NaN float is not equal to itself).
#![no_main]

use libfuzzer_sys::fuzz_target;
use relfusion_proto::Message;
use relfusion_proto::v1;

fn round_trip<M: Message + Default>(data: &[u8]) {
    if let Ok(message) = M::decode(data) {
        let bytes = message.encode_to_vec();
        let again = M::decode(bytes.as_slice()).expect("re-decodes");
        assert_eq!(again.encode_to_vec(), bytes);
    }
}

fuzz_target!(|data: &[u8]| {
    round_trip::<v1::ClientMessage>(data);
    round_trip::<v1::Frame>(data);
    round_trip::<v1::SessionConfig>(data);
    round_trip::<v1::EndOfStream>(data);
    round_trip::<v1::ServerMessage>(data);
    round_trip::<v1::MapSnapshot>(data);
    round_trip::<v1::CreateSessionReply>(data);
    if let Ok(config) = v1::SessionConfig::decode(data) {
        // What the Zenoh create queryable does next with it.
        let _ = relfusion_server::zenoh_api::create::create_request(&config);
    }
});
