//! Keyframe graph, Sim(3) constraints, pose-graph optimisation (being written).
