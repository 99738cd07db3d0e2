//! The HTTP API of a real `relfusiond` process, through a real HTTP client (ureq) and a real
//! WebSocket client (tungstenite): a live session fed over HTTP and WebSocket reports a pose
//! for every frame over SSE and WebSocket and its trajectory holds every frame; every kind of
//! bad input gets its 4xx JSON error and the server keeps answering; tokens scope sessions.

mod auth;
mod bad_input;
mod client;
mod cluster;
mod live;
mod map;
mod uploads;
