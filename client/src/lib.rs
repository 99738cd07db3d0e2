//! relfusion client library (being written).
